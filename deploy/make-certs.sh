#!/bin/sh
# Make a fleet's TLS material with openssl: a CA, the router's server certificate, and one client
# certificate per fleet member whose common name (CN) is the member's id — the access-control rules
# of router.json5 match robots and the server by that CN.
#
#   deploy/make-certs.sh DIR [ID ...]      # default ids: server robot1 robot2 robot3
#
# Writes DIR/ca.pem, DIR/ca.key (keep the CA key offline: it can mint any identity), DIR/router.pem,
# DIR/router.key, and DIR/<id>.pem, DIR/<id>.key per id. An existing CA in DIR is reused, so running
# it again with a new id adds a robot. ROUTER_NAMES lists the names clients may reach the router by
# (default "router localhost 127.0.0.1"); CERT_DAYS the validity (default 365).
set -eu

if [ $# -lt 1 ]; then
    echo "usage: $0 DIR [ID ...]" >&2
    exit 2
fi
out=$1
shift
[ $# -gt 0 ] || set -- server robot1 robot2 robot3
days=${CERT_DAYS:-365}
names=${ROUTER_NAMES:-router localhost 127.0.0.1}
command -v openssl >/dev/null || { echo "$0: openssl not found" >&2; exit 1; }
for id in "$@"; do  # the same id rule as the fleet (shared/messages.py ID_PATTERN)
    case $id in
        *[!A-Za-z0-9_-]* | "" | router | ca) echo "$0: bad id '$id'" >&2; exit 2 ;;
    esac
done

umask 077  # private keys readable by their owner only
mkdir -p "$out"
ext=$(mktemp)
trap 'rm -f "$ext" "$out"/*.csr' EXIT

key() { openssl genpkey -algorithm EC -pkeyopt ec_paramgen_curve:P-256 -out "$1" 2>/dev/null; }

if [ ! -f "$out/ca.key" ]; then
    key "$out/ca.key"
    openssl req -x509 -new -key "$out/ca.key" -subj "/CN=fleet-slam CA" -days "$days" -out "$out/ca.pem" \
        -addext "basicConstraints=critical,CA:TRUE" -addext "keyUsage=critical,keyCertSign,cRLSign"
fi

# issue NAME CN EXTENSIONS: a key and a certificate signed by the CA
issue() {
    key "$out/$1.key"
    openssl req -new -key "$out/$1.key" -subj "/CN=$2" -out "$out/$1.csr"
    printf '%s\n' "basicConstraints=critical,CA:FALSE" "keyUsage=critical,digitalSignature" "$3" >"$ext"
    openssl x509 -req -in "$out/$1.csr" -CA "$out/ca.pem" -CAkey "$out/ca.key" -CAcreateserial \
        -days "$days" -extfile "$ext" -out "$out/$1.pem" 2>/dev/null
}

san=""
for n in $names; do
    case $n in
        *[!0-9.]*) san="$san,DNS:$n" ;;
        *) san="$san,IP:$n" ;;
    esac
done
issue router router "extendedKeyUsage=serverAuth
subjectAltName=${san#,}"
for id in "$@"; do
    issue "$id" "$id" "extendedKeyUsage=clientAuth
subjectAltName=DNS:$id"
done
chmod 644 "$out"/*.pem  # certificates are public; keys stay 600
echo "wrote $out: ca.pem router.pem/.key $(printf '%s.pem/.key ' "$@")"
