"""The message bus: the only module of fleet-slam that imports zenoh.

Payloads are opaque ``bytes`` here (``shared/codec.py`` gives them meaning); keys come from
``shared/keys.py``. The whole API::

    cfg = BusConfig(mode="client", connect=("tcp/127.0.0.1:7447",))
    with Bus(cfg) as bus:                              # one zenoh session
        bus.put(key, payload, reliable=True)           # True: block if congested (maps); False: drop (poses)
        bus.delete(key)                                # subscribers' on_delete(key)
        h = bus.subscribe(key_expr, on_sample, on_delete)  # on_sample(key, payload), on_delete(key)
        h = bus.serve(key_expr, answer)                # queryable: answer(query_key_expr) -> [(key, payload)]
        replies = bus.get(key_expr, timeout_s=2.0)     # [(key, payload)]: ok replies only, [] if none
        h = bus.declare_alive(key)                     # liveliness token: gone when the bus closes or dies
        h = bus.watch_alive(key_expr, on_change)       # on_change(key, alive): current members first
        h.close()                                      # undeclare one; bus.close() undeclares all

    run_router(listen=("tcp/127.0.0.1:7447",), stop=event)  # a router in this process, until stop is set
    router_main(["tcp/127.0.0.1:7447"])                     # the same for a CLI: signals, one status line
    python -m shared.bus router --listen tcp/127.0.0.1:7447 [--bus-config deploy/router.json5]

Security (``deploy/README.md``): ``BusConfig.config_file`` names a zenoh JSON5 configuration file —
TLS certificates (mutual TLS), user/password, access control — read before the fields are applied;
every file it names is checked before zenoh sees it, so a missing certificate is an error that
names it instead of a client silently waiting for a router that refuses it.

Threads: callbacks run on zenoh's callback threads — one per declaration, so several of them run
concurrently with each other and with the caller. State shared between callbacks and the rest of
the program needs a lock. An exception raised by a callback is logged (logger ``fleet_slam.bus``)
and the declaration goes on. Do not close the bus or a handle from inside one of its callbacks.

Callbacks must return quickly (store the payload, signal a worker): one slow callback stalls every
delivery to its session — poses, liveliness and all — and pushes back to the publishers; after a
stall of about 5 s zenoh closes the link, and what was queued is lost (measured: 337 of 2000 maps
arrived, and the stalled session saw every token go and come back). Decoding and fusing belong in
a worker thread; the same holds for ``serve`` answers, which should return a ready payload.

Network facts the callers rely on (measured, see ``notes/zenoh.md``):

- Nothing listens or connects anywhere the caller did not name: listen/connect endpoints are
  explicit (zenoh's defaults are ``tcp/[::]`` on every interface) and multicast scouting is off.
- A client whose router is absent waits for it (``connect_timeout_s=None``) or raises
  :class:`BusError` after ``connect_timeout_s``. After a router restart clients reconnect on their
  own (every ``retry_ms``) and their subscriptions, queryables and tokens come back; while the
  router is down ``put`` is dropped silently and ``get`` returns ``[]``. Watchers see a router
  restart as every token going (``False``) and coming back (``True``).
- ``reliable=True`` puts block the caller when the link is congested, so nothing is lost between
  two live ends whose callbacks keep up; ``reliable=False`` puts vanish under load (a burst of
  200 × 50 KB lost 33 with a subscriber that did nothing) — right for poses, never for maps.
- A closed or killed process's tokens vanish within milliseconds; a hung process's only after the
  lease (``lease_s``, zenoh default 10 s).
"""

from __future__ import annotations

import argparse
import json
import logging
import re
import signal
import sys
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import zenoh

log = logging.getLogger("fleet_slam.bus")

MODES = ("client", "peer", "router")
DEFAULT_ENDPOINT = "tcp/127.0.0.1:7447"
OPEN_SLICE_S = 0.5  # a client waiting for its router retries zenoh.open() this often (see _open)
ROUTER_POLL_S = 0.1  # how often a router's wait loop looks at its stop event
BUS_CONFIG_HELP = "zenoh JSON5 config file: TLS certificates, user/password, access control (deploy/)"
OPEN_WARN_S = 10.0  # a client still waiting for its router after this long says so, once


class BusError(RuntimeError):
    """A bus that cannot be configured, opened or used (bad config, no router, closed bus)."""


class BusConfigError(BusError, ValueError):
    """A configuration that cannot work: a bad field or endpoint, a zenoh config file that does not
    parse or sets what the fields set, a certificate, key or password file missing or unreadable.
    A ``ValueError`` too, so that the CLI reports it as an error rather than a crash."""


@dataclass(frozen=True)
class BusConfig:
    """One zenoh session.

    ``mode``: ``client`` (agents, server, tools: everything goes through a router), ``router``, or
    ``peer``. ``connect`` / ``listen``: zenoh endpoints such as ``tcp/127.0.0.1:7447``; a router
    needs ``listen``, a client ``connect``. ``connect_timeout_s``: how long opening waits for a
    ``connect`` endpoint, ``None`` = forever. ``retry_ms``: reconnect period after a lost link.
    ``lease_s``: how long others wait before declaring this session dead when it stops answering
    (zenoh default 10 s); it only matters for hung processes, killed ones are noticed at once.
    ``shm``: zenoh shared memory between local processes (off: slower for our message sizes).
    ``config_file``: a zenoh JSON5 configuration file (what ``zenohd -c`` reads) applied first:
    the place for security — TLS certificates, user/password, access control (``deploy/``). It
    may not set differently what the fields set (mode, endpoints, scouting, ...): those come from
    the command line. ``overrides``: raw ``(config path, JSON5 value)`` pairs applied last.
    """

    mode: str = "client"
    connect: tuple[str, ...] = (DEFAULT_ENDPOINT,)
    listen: tuple[str, ...] = ()
    connect_timeout_s: float | None = None
    retry_ms: int = 200
    lease_s: float | None = None
    shm: bool = False
    config_file: str | None = None
    overrides: tuple[tuple[str, str], ...] = ()

    def __post_init__(self):
        if self.mode not in MODES:
            raise BusConfigError(f"mode: expected one of {MODES}, got {self.mode!r}")
        for name in ("connect", "listen"):
            endpoints = getattr(self, name)
            if isinstance(endpoints, str) or not all(isinstance(e, str) and e for e in endpoints):
                raise BusConfigError(f"{name}: expected a tuple of endpoint strings, got {endpoints!r}")
            object.__setattr__(self, name, tuple(endpoints))  # a list from a CLI stays hashable
        if self.mode == "client" and not self.connect:
            raise BusConfigError("connect: a client needs at least one endpoint (multicast scouting is off)")
        if self.mode == "router" and not self.listen:
            raise BusConfigError("listen: a router needs at least one endpoint")
        if self.connect_timeout_s is not None and not self.connect_timeout_s > 0:
            raise BusConfigError(f"connect_timeout_s: expected > 0 or None, got {self.connect_timeout_s!r}")
        if not (isinstance(self.retry_ms, int) and self.retry_ms > 0):
            raise BusConfigError(f"retry_ms: expected a positive integer, got {self.retry_ms!r}")
        if self.lease_s is not None and not self.lease_s > 0:
            raise BusConfigError(f"lease_s: expected > 0 or None, got {self.lease_s!r}")
        if self.config_file is not None:
            object.__setattr__(self, "config_file", str(self.config_file))  # a Path stays hashable too


def client_config(connect: Sequence[str] | None = None, config_file: str | None = None) -> BusConfig:
    """A client's configuration from command-line values: ``connect`` endpoints (``None``: the
    default endpoint) and an optional zenoh config file (``--bus-config``)."""
    return BusConfig(connect=tuple(connect or (DEFAULT_ENDPOINT,)), config_file=config_file)


def zenoh_config(cfg: BusConfig) -> zenoh.Config:
    """The zenoh configuration of ``cfg``: explicit endpoints only, multicast scouting off; its
    config file first, its overrides last; raises :class:`BusConfigError` naming what is wrong."""
    timeout_ms = -1 if cfg.connect_timeout_s is None else max(1, round(cfg.connect_timeout_s * 1000))
    retry = cfg.retry_ms
    entries: list[tuple[str, object]] = [
        ("mode", cfg.mode),
        ("connect/endpoints", list(cfg.connect)),
        ("connect/timeout_ms", timeout_ms),
        # a fixed period: zenoh's default backs off from 1 s to 4 s, i.e. seconds of outage per restart
        ("connect/retry", {"period_init_ms": retry, "period_max_ms": retry, "period_increase_factor": 1}),
        # [] replaces zenoh's defaults tcp/[::]:0 (peer) and tcp/[::]:7447 (router): every interface
        ("listen/endpoints", list(cfg.listen)),
        ("scouting/multicast/enabled", False),
        ("scouting/delay", 0),  # routers and peers would wait 500 ms in open() for scouting that is off
        # gossip tells routers and peers about each other's (explicit) listen endpoints; one hop is enough
        ("scouting/gossip/enabled", True),
        ("scouting/gossip/multihop", False),
        ("transport/shared_memory/enabled", cfg.shm),
    ]
    if cfg.lease_s is not None:
        entries.append(("transport/link/tx/lease", max(1, round(cfg.lease_s * 1000))))
    conf = zenoh.Config() if cfg.config_file is None else _load_file(cfg.config_file, entries)
    for path, value in entries:
        _insert(conf, path, json.dumps(value))
    for path, value in cfg.overrides:
        _insert(conf, path, value)
    check_security(conf, cfg, where=f"{cfg.config_file}: " if cfg.config_file else "")
    return conf


def _insert(conf: zenoh.Config, path: str, value_json5: str) -> None:
    try:
        conf.insert_json5(path, value_json5)
    except (zenoh.ZError, ValueError) as e:
        raise BusConfigError(f"zenoh config {path}: cannot set {value_json5[:200]!r}: {_z(e)}") from e


def _z(e: Exception) -> str:
    """A zenoh error's text without the Rust source location zenoh appends."""
    return re.sub(r"\s+at \S+\.rs:\d+\.?$", "", str(e).strip())


def _json(conf: zenoh.Config, path: str):
    return json.loads(conf.get_json(path))


def _load_file(path: str, entries: list[tuple[str, object]]) -> zenoh.Config:
    """The zenoh config in the file ``path``; it must leave what ``entries`` set to them."""
    if not Path(path).is_file():
        raise BusConfigError(f"bus config {path!r}: no such file")
    try:
        conf = zenoh.Config.from_file(path)
    except (zenoh.ZError, ValueError) as e:
        raise BusConfigError(f"bus config {path}: {_z(e)}") from e
    default = zenoh.Config()
    for key, value in entries:
        mine = _json(conf, key)
        if mine != _json(default, key) and mine != value:
            raise BusConfigError(
                f"bus config {path}: sets {key} = {json.dumps(mine)}, which fleet-slam sets itself "
                f"({json.dumps(value)}): give endpoints with --listen/--connect, drop {key} from the file"
            )
    return conf


# Every file a zenoh config may name for authentication, and whether it must be PEM.
SECURITY_FILES = {
    "transport/link/tls/root_ca_certificate": True,
    "transport/link/tls/listen_certificate": True,
    "transport/link/tls/listen_private_key": True,
    "transport/link/tls/connect_certificate": True,
    "transport/link/tls/connect_private_key": True,
    "transport/auth/usrpwd/dictionary_file": False,
    "transport/auth/pubkey/public_key_file": True,
    "transport/auth/pubkey/private_key_file": True,
    "transport/auth/pubkey/known_keys_file": False,
}


def check_security(conf: zenoh.Config, cfg: BusConfig, where: str = "") -> None:
    """Raise :class:`BusConfigError` for what would fail later and obscurely: a named certificate,
    key or dictionary file that is missing, unreadable or not PEM; TLS endpoints without the
    certificates they need. (zenoh itself reports a bad certificate only as a connection that
    never opens.)"""
    for path, pem in SECURITY_FILES.items():
        name = _json(conf, path)
        if name is None:
            continue
        try:
            head = Path(name).read_bytes()[:65536]
        except OSError as e:
            raise BusConfigError(f"{where}{path}: cannot read {name!r}: {e.strerror}") from e
        if pem and b"-----BEGIN " not in head:
            raise BusConfigError(f"{where}{path}: {name!r} is not a PEM file")
    tls = _json(conf, "transport/link/tls")
    mtls = bool(tls.get("enable_mtls"))
    need: list[str] = []
    if cfg.mode != "client" and any(e.startswith("tls/") for e in cfg.listen):
        need += ["listen_certificate", "listen_private_key"] + (["root_ca_certificate"] if mtls else [])
    if cfg.mode != "router" and mtls and any(e.startswith("tls/") for e in cfg.connect):
        need += ["connect_certificate", "connect_private_key"]
    missing = [f"transport/link/tls/{k}" for k in need if not tls.get(k)]
    if missing:
        tls_eps = [e for e in (*cfg.listen, *cfg.connect) if e.startswith("tls/")]
        raise BusConfigError(f"{where}TLS endpoint {tls_eps[0]} needs {', '.join(missing)}")


class _Gate:
    """What a declaration's callbacks pass through: once its handle is closed none is delivered,
    and the close waits for one being delivered (zenoh may still run a callback it had begun, or
    one for a sample already received, after ``undeclare``: a closed subscription's inbox grew by
    one in a CI run). Re-entrant: a callback may close its own handle."""

    __slots__ = ("closed", "lock")

    def __init__(self) -> None:
        self.lock = threading.RLock()
        self.closed = False


class Handle:
    """One declaration on a bus (subscription, queryable, liveliness token or watch).

    ``close()`` undeclares it; it is idempotent, and ``Bus.close`` closes every handle left.
    """

    def __init__(self, bus: Bus, entity, what: str, gate: _Gate | None = None):
        self._bus = bus
        self._entity = entity
        self.what = what
        self._gate = gate

    def close(self) -> None:
        entity, self._entity = self._entity, None
        if entity is None:
            return
        if self._gate is not None:  # waits for a callback being delivered; none after it
            with self._gate.lock:
                self._gate.closed = True
        self._bus._forget(self)
        try:
            entity.undeclare()
        except zenoh.ZError as e:  # the session is already closed: nothing left to undeclare
            log.debug("undeclare %s: %s", self.what, e)

    @property
    def closed(self) -> bool:
        return self._entity is None

    def __enter__(self) -> Handle:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"Handle({self.what!r}, closed={self.closed})"


class Bus:
    """A context manager around one zenoh session; see the module docstring for the API.

    Opening a client blocks until its router answers, or raises :class:`BusError` when
    ``cfg.connect_timeout_s`` passes or ``cancel`` is set (e.g. by :func:`stop_on_signals`).
    All methods may be called from any thread, callbacks included.
    """

    def __init__(self, cfg: BusConfig | None = None, *, cancel: threading.Event | None = None):
        self.cfg = cfg if cfg is not None else BusConfig()
        self._session = _open(self.cfg, cancel)
        self._lock = threading.Lock()
        self._handles: list[Handle] = []
        self._closed = False

    # -- lifecycle ------------------------------------------------------------------------------

    def close(self) -> None:
        """Undeclare every handle and close the session; idempotent."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            handles, self._handles = self._handles, []
        for handle in reversed(handles):
            handle.close()
        self._session.close()

    @property
    def closed(self) -> bool:
        return self._closed

    def __enter__(self) -> Bus:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _check_open(self) -> None:
        if self._closed:
            raise BusError("the bus is closed")

    def _keep(self, entity, what: str, gate: _Gate | None = None) -> Handle:
        handle = Handle(self, entity, what, gate)
        with self._lock:
            if self._closed:  # closed while declaring: do not leak the declaration
                entity.undeclare()
                raise BusError("the bus is closed")
            self._handles.append(handle)
        return handle

    def _forget(self, handle: Handle) -> None:
        with self._lock:
            if handle in self._handles:
                self._handles.remove(handle)

    def _guarded(self, what: str, fn: Callable, gate: _Gate) -> Callable:
        """``fn`` wrapped so that an exception is logged instead of reaching zenoh, and nothing is
        delivered once ``gate`` is closed."""

        def call(*args):
            with gate.lock:
                if gate.closed:
                    return
                try:
                    fn(*args)
                except Exception:
                    if self._closed:  # e.g. a callback that puts while the bus shuts down
                        log.debug("callback of %s failed after close", what, exc_info=True)
                    else:
                        log.exception("callback of %s failed; the declaration goes on", what)

        return call

    # -- publish / subscribe --------------------------------------------------------------------

    def put(self, key: str, payload: bytes, *, reliable: bool = True) -> None:
        """Publish ``payload`` on the concrete ``key``.

        ``reliable=True`` blocks while the link is congested (maps: nothing lost);
        ``reliable=False`` drops under congestion and skips batching (poses: latest wins).
        Without a router the sample is dropped silently.
        """
        self._check_open()
        cc = zenoh.CongestionControl.BLOCK if reliable else zenoh.CongestionControl.DROP
        try:
            self._session.put(key, bytes(payload), congestion_control=cc, express=not reliable)
        except zenoh.ZError as e:
            raise BusError(f"put on {key!r}: {e}") from e

    def delete(self, key: str) -> None:
        """Publish a deletion of ``key`` (subscribers' ``on_delete``), e.g. a robot that left."""
        self._check_open()
        try:
            self._session.delete(key, congestion_control=zenoh.CongestionControl.BLOCK)
        except zenoh.ZError as e:
            raise BusError(f"delete {key!r}: {e}") from e

    def subscribe(
        self,
        key_expr: str,
        on_sample: Callable[[str, bytes], None],
        on_delete: Callable[[str], None] | None = None,
    ) -> Handle:
        """Call ``on_sample(key, payload)`` for every put on a key matching ``key_expr`` and
        ``on_delete(key)`` for every delete (ignored when ``on_delete`` is None)."""
        self._check_open()

        def on_zenoh_sample(sample: zenoh.Sample) -> None:
            key = str(sample.key_expr)
            if sample.kind == zenoh.SampleKind.PUT:
                on_sample(key, sample.payload.to_bytes())
            elif on_delete is not None:
                on_delete(key)

        what = f"subscriber {key_expr}"
        entity, gate = self._declare(what, self._session.declare_subscriber, key_expr, on_zenoh_sample)
        return self._keep(entity, what, gate)

    # -- query / reply --------------------------------------------------------------------------

    def serve(self, key_expr: str, answer: Callable[[str], list[tuple[str, bytes]]]) -> Handle:
        """Answer queries on ``key_expr``: ``answer(query_key_expr)`` returns ``(key, payload)``
        pairs, each on a concrete key that intersects the query (others are logged and skipped)."""
        self._check_open()
        what = f"queryable {key_expr}"

        def on_query(query: zenoh.Query) -> None:
            with query:  # dropping the query finalizes it: without this the querier waits for its timeout
                for key, payload in answer(str(query.key_expr)):
                    try:
                        query.reply(key, bytes(payload))
                    except zenoh.ZError as e:
                        log.error("%s: cannot reply on %r to %s: %s", what, key, query.key_expr, e)

        entity, gate = self._declare(what, self._session.declare_queryable, key_expr, on_query)
        return self._keep(entity, what, gate)

    def get(self, key_expr: str, timeout_s: float = 2.0) -> list[tuple[str, bytes]]:
        """Query every queryable matching ``key_expr``; the ``(key, payload)`` replies received
        within ``timeout_s``. Errors and timeouts are not replies: no answer gives ``[]``."""
        self._check_open()
        try:
            replies = self._session.get(key_expr, target=zenoh.QueryTarget.ALL, timeout=timeout_s)
            out = []
            for reply in replies:  # ends when every queryable has finished or the timeout fired
                sample = reply.ok
                if sample is None:
                    log.debug("get %s: %s", key_expr, _err_text(reply.err))
                elif sample.kind == zenoh.SampleKind.PUT:
                    out.append((str(sample.key_expr), sample.payload.to_bytes()))
            return out
        except zenoh.ZError as e:
            raise BusError(f"get {key_expr!r}: {e}") from e

    # -- liveliness -----------------------------------------------------------------------------

    def declare_alive(self, key: str) -> Handle:
        """A liveliness token on ``key``: watchers see it until the handle or bus closes or the
        process dies (lease)."""
        self._check_open()
        what = f"liveliness token {key}"
        try:
            entity = self._session.liveliness().declare_token(key)
        except zenoh.ZError as e:
            raise BusError(f"{what}: {e}") from e
        return self._keep(entity, what)

    def watch_alive(self, key_expr: str, on_change: Callable[[str, bool], None]) -> Handle:
        """``on_change(key, alive)`` for every token matching ``key_expr``: first ``True`` for
        each token present now, then ``True`` when one appears and ``False`` when it goes."""
        self._check_open()

        def on_zenoh_sample(sample: zenoh.Sample) -> None:
            on_change(str(sample.key_expr), sample.kind == zenoh.SampleKind.PUT)

        what = f"liveliness watch {key_expr}"
        declare = self._session.liveliness().declare_subscriber
        entity, gate = self._declare(what, declare, key_expr, on_zenoh_sample, history=True)
        return self._keep(entity, what, gate)

    def _declare(
        self, what: str, declare: Callable, key_expr: str, callback: Callable, **kwargs
    ) -> tuple[object, _Gate]:
        """The declaration of ``callback`` (guarded, and gated by its handle's close)."""
        gate = _Gate()
        try:
            return declare(
                key_expr, zenoh.handlers.Callback(self._guarded(what, callback, gate)), **kwargs
            ), gate
        except zenoh.ZError as e:
            raise BusError(f"{what}: {e}") from e


def _open(cfg: BusConfig, cancel: threading.Event | None) -> zenoh.Session:
    """``zenoh.open`` in slices of at most ``OPEN_SLICE_S``: zenoh holds the thread (not the GIL)
    while it waits for a router, so one long wait would delay signal handlers and ``cancel``."""
    where = ", ".join(cfg.connect if cfg.mode == "client" else cfg.listen)
    deadline = None if cfg.connect_timeout_s is None else time.monotonic() + cfg.connect_timeout_s
    warn_at = time.monotonic() + OPEN_WARN_S
    while True:
        left_s = OPEN_SLICE_S if deadline is None else min(OPEN_SLICE_S, deadline - time.monotonic())
        started = time.monotonic()
        try:
            return zenoh.open(zenoh_config(replace(cfg, connect_timeout_s=max(left_s, 0.001))))
        except zenoh.ZError as e:
            failed_fast = time.monotonic() - started < left_s / 2  # not a timeout: a real error
            timed_out = deadline is not None and time.monotonic() >= deadline
            if failed_fast or timed_out:
                raise BusError(f"cannot open a zenoh {cfg.mode} session on {where}: {_z(e)}") from e
            log.debug("still waiting for %s: %s", where, e)
            if time.monotonic() > warn_at:  # a router that refuses our certificate looks like no router
                warn_at = float("inf")
                secured = ", and does it accept this client's credentials" if cfg.config_file else ""
                log.warning("no session on %s after %.0f s: is the router up%s?", where, OPEN_WARN_S, secured)
        if cancel is not None and cancel.is_set():
            raise BusError(f"cancelled while waiting for a zenoh {cfg.mode} session on {where}")


def _err_text(err) -> str:
    try:
        return err.payload.to_string()
    except Exception:
        return repr(err)


# -- router ---------------------------------------------------------------------------------------


def run_router(
    listen: Sequence[str] = (DEFAULT_ENDPOINT,),
    stop: threading.Event | None = None,
    *,
    on_ready: Callable[[Bus], None] | None = None,
    config_file: str | None = None,
) -> None:
    """Run a zenoh router listening on ``listen`` in this process until ``stop`` is set (forever
    when None), with the zenoh config file ``config_file`` if given (TLS, access control).
    ``on_ready(bus)`` is called once the router listens. Raises :class:`BusError` when it cannot
    listen (e.g. the port is taken), :class:`BusConfigError` for a bad config."""
    stop = stop if stop is not None else threading.Event()
    cfg = BusConfig(mode="router", connect=(), listen=tuple(listen), config_file=config_file)
    with Bus(cfg) as bus:
        if on_ready is not None:
            on_ready(bus)
        while not stop.wait(ROUTER_POLL_S):  # a bounded wait keeps the main thread responsive to signals
            pass


def stop_on_signals(stop: threading.Event) -> None:
    """Make SIGINT and SIGTERM set ``stop`` (call from the main thread). A process that is PID 1 in
    a container would otherwise ignore SIGTERM."""
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())


def router_main(listen: Sequence[str] | None = None, config_file: str | None = None) -> int:
    """The ``router`` command: run a router until SIGINT/SIGTERM; 0 on a clean stop, 1 when it
    cannot listen or its config is bad. Prints one line ``router listening on <endpoints>`` once
    it listens (followed by `` with <config_file>`` when given)."""
    listen = tuple(listen) if listen else (DEFAULT_ENDPOINT,)
    stop = threading.Event()
    stop_on_signals(stop)

    def ready(_bus: Bus) -> None:
        with_file = f" with {config_file}" if config_file else ""
        print(f"router listening on {' '.join(listen)}{with_file}", flush=True)

    try:
        run_router(listen, stop, on_ready=ready, config_file=config_file)
    except BusError as e:
        print(f"router: {e}", file=sys.stderr, flush=True)
        return 1
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m shared.bus", description="fleet-slam bus tools")
    commands = parser.add_subparsers(dest="command", required=True)
    router = commands.add_parser("router", help="run a zenoh router")
    router.add_argument(
        "--listen",
        action="append",
        metavar="ENDPOINT",
        help=f"endpoint to listen on, repeatable (default {DEFAULT_ENDPOINT})",
    )
    router.add_argument("--bus-config", metavar="FILE", help=BUS_CONFIG_HELP)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    return router_main(args.listen, args.bus_config)


if __name__ == "__main__":
    sys.exit(main())
