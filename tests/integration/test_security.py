"""The secure deployment (deploy/): a router process running deploy/router.json5 — mutual TLS for
fleet members, access control, anonymous read-only TCP — with certificates made at test time by
deploy/make-certs.sh.

Denied messages give their sender no error (zenoh drops them at the router), so every denial is
shown by what a legitimate receiver did *not* get while a legitimate message sent after it by the
same session *did* arrive (reliable messages of one session keep their order).
"""

from __future__ import annotations

import re
import shutil
import subprocess
import time
from pathlib import Path

import pytest

from fleet_slam.procs import ProcGroup, python_module
from shared.bus import Bus, BusConfig, BusConfigError, BusError, zenoh_config
from shared.keys import Keys
from tests.netutil import Inbox, loopback_endpoint, wait_for

pytestmark = [
    pytest.mark.integration,
    pytest.mark.timeout(180),
    pytest.mark.skipif(shutil.which("openssl") is None, reason="deploy/make-certs.sh needs openssl"),
]

ROOT = Path(__file__).resolve().parents[2]
DEPLOY = ROOT / "deploy"
SECRETS = "/run/secrets/"  # where the deploy configs expect the files (compose secrets)
STARTUP_S = 20.0
DELIVERY_S = 10.0
GRACE_S = 0.5  # after the proof message arrived, time left for anything denied to show up anyway
REFUSED_S = 3.0  # how long a refused client tries before giving up
E2E_S = 60.0  # a first fused map with walls: a few seconds of simulated driving
KEYS = Keys("secure")


def make_certs(out: Path, *ids: str) -> None:
    run = subprocess.run(
        ["sh", DEPLOY / "make-certs.sh", out, *ids], capture_output=True, text=True, timeout=60
    )
    assert run.returncode == 0, run.stderr


def deploy_copy(name: str, path: Path, replacements: dict[str, str]) -> Path:
    """deploy/<name> written to ``path`` with its secret paths pointed at the test's files (the
    rest unchanged: the access control under test is the one in deploy/)."""
    text = (DEPLOY / name).read_text()
    for old, new in replacements.items():
        assert old in text, f"{name} no longer names {old}"
        text = text.replace(old, new)
    path.write_text(text)
    return path


@pytest.fixture(scope="module")
def fleet(tmp_path_factory):
    """A secure router process; ``fleet["member"](id)`` is a member's BusConfig over TLS,
    ``fleet["anonymous"]()`` a client with no credentials on the plain TCP port."""
    tmp = tmp_path_factory.mktemp("secure")
    pki = tmp / "pki"
    make_certs(pki)  # ca, router, server, robot1..3
    config = deploy_copy("router.json5", tmp / "router.json5", {SECRETS: f"{pki}/"})
    clients = {
        member: deploy_copy(
            "client.json5",
            tmp / f"{member}.json5",
            {
                f"{SECRETS}ca.pem": str(pki / "ca.pem"),
                f"{SECRETS}client.pem": str(pki / f"{member}.pem"),
                f"{SECRETS}client.key": str(pki / f"{member}.key"),
            },
        )
        for member in ("server", "robot1", "robot2")
    }
    tls, tcp = loopback_endpoint().replace("tcp/", "tls/"), loopback_endpoint()
    with ProcGroup(tmp / "logs") as group:
        argv = python_module(
            "fleet_slam.cli", "router", "--bus-config", config, "--listen", tls, "--listen", tcp
        )
        router = group.start("router", argv)
        assert router.wait_for("router listening on", STARTUP_S), router.output()

        def member(name: str, **kw) -> BusConfig:
            return BusConfig(
                connect=(tls,), config_file=str(clients[name]), connect_timeout_s=STARTUP_S, **kw
            )

        def anonymous() -> BusConfig:
            return BusConfig(connect=(tcp,), connect_timeout_s=STARTUP_S)

        yield {
            "tmp": tmp, "pki": pki, "tls": tls, "tcp": tcp, "clients": clients, "group": group,
            "member": member, "anonymous": anonymous,
        }  # fmt: skip
    assert all(not p.running for p in group.procs)


def keep_putting(bus: Bus, key: str, payload: bytes, inbox: Inbox) -> bool:
    """Put ``payload`` on ``key`` until ``inbox`` has it (the link may still be settling)."""

    def attempt() -> bool:
        bus.put(key, payload)
        return inbox.has((key, payload))

    return wait_for(attempt, DELIVERY_S)


def keys_seen(inbox: Inbox) -> set[str]:
    return {item[0] for item in inbox.snapshot()}


# -- (a) a robot writes only its own keys -------------------------------------------------------------


def test_a_robot_cannot_write_another_robots_keys_or_the_fused_map(fleet):
    member, anonymous = fleet["member"], fleet["anonymous"]
    with (
        Bus(member("server")) as server,
        Bus(member("robot1")) as robot1,
        Bus(member("robot2")) as robot2,
        Bus(anonymous()) as reader,
    ):
        maps, poses, alive, fused = Inbox(), Inbox(), Inbox(), Inbox()
        frees, fused_free = Inbox(), Inbox()
        server.subscribe(KEYS.all_maps, maps)
        server.subscribe(KEYS.all_poses, poses)
        server.subscribe(KEYS.all_free, frees)
        server.watch_alive(KEYS.all_alive, alive)
        reader.subscribe(KEYS.fused, fused)
        reader.subscribe(KEYS.fused_free, fused_free)
        seen_by_robot1 = Inbox()
        robot1.subscribe(KEYS.all_poses, seen_by_robot1)  # reading the others is not for robots either

        # robot1 pretends to be robot2 and the server, then does its own job
        robot1.declare_alive(KEYS.robot_alive("robot2"))
        robot1.put(KEYS.robot_map("robot2"), b"forged map")
        robot1.put(KEYS.robot_pose("robot2"), b"forged pose")
        robot1.delete(KEYS.robot_map("robot2"))
        robot1.put(KEYS.fused, b"forged fused")
        robot1.put(KEYS.robot_free("robot2"), b"forged free")
        robot1.put(KEYS.fused_free, b"forged fused free")
        robot1.declare_alive(KEYS.robot_alive("robot1"))
        assert keep_putting(robot1, KEYS.robot_map("robot1"), b"robot1 map", maps)
        assert keep_putting(robot1, KEYS.robot_pose("robot1"), b"robot1 pose", poses)
        # robot2 writes its own keys; the server writes the fused map
        assert keep_putting(robot2, KEYS.robot_pose("robot2"), b"robot2 pose", poses)
        assert keep_putting(server, KEYS.fused, b"fused v1", fused)
        assert keep_putting(robot1, KEYS.robot_free("robot1"), b"robot1 free", frees)
        assert keep_putting(server, KEYS.fused_free, b"free v1", fused_free)  # anyone reads it
        assert wait_for(lambda: alive.has((KEYS.robot_alive("robot1"), True)), DELIVERY_S)
        time.sleep(GRACE_S)

        assert keys_seen(maps) == {KEYS.robot_map("robot1")}
        assert (KEYS.robot_pose("robot2"), b"forged pose") not in poses.snapshot()
        assert alive.snapshot() == [(KEYS.robot_alive("robot1"), True)]  # no token for robot2
        assert (KEYS.fused, b"forged fused") not in fused.snapshot()
        assert keys_seen(frees) == {KEYS.robot_free("robot1")}
        assert (KEYS.fused_free, b"forged fused free") not in fused_free.snapshot()
        # (a session hears its own puts locally, forged ones included: only robot2's real pose counts)
        assert (KEYS.robot_pose("robot2"), b"robot2 pose") not in seen_by_robot1.snapshot()

        # the server's pull of every map: robot1 answers for robot2 too, only its own answer arrives
        def answer(_query: str) -> list[tuple[str, bytes]]:
            return [(KEYS.robot_map("robot2"), b"forged reply"), (KEYS.robot_map("robot1"), b"robot1 reply")]

        robot1.serve(KEYS.robot_map("robot1"), answer)
        replies: list = []  # the queryable's declaration reaches the router a moment after serve()

        def pulled() -> bool:
            replies[:] = server.get(KEYS.all_maps, timeout_s=2.0)
            return bool(replies)

        assert wait_for(pulled, DELIVERY_S)
        assert replies == [(KEYS.robot_map("robot1"), b"robot1 reply")]


# -- (b) no credentials, no writing -------------------------------------------------------------------


def test_an_anonymous_client_can_neither_publish_nor_read_robot_data(fleet):
    member, anonymous = fleet["member"], fleet["anonymous"]
    with (
        Bus(member("server")) as server,
        Bus(member("robot1")) as robot1,
        Bus(anonymous()) as intruder,
        Bus(anonymous()) as reader,
    ):
        maps, alive, fused, stolen = Inbox(), Inbox(), Inbox(), Inbox()
        server.subscribe(KEYS.all_maps, maps)
        server.watch_alive(KEYS.all_alive, alive)
        reader.subscribe(KEYS.fused, fused)
        intruder.subscribe(KEYS.all_maps, stolen)
        robot1.serve(KEYS.robot_map("robot1"), lambda _q: [(KEYS.robot_map("robot1"), b"robot1 latest")])

        intruder.declare_alive(KEYS.robot_alive("robot1"))
        intruder.put(KEYS.robot_map("robot1"), b"intruder map")
        intruder.put(KEYS.fused, b"intruder fused")
        assert keep_putting(robot1, KEYS.robot_map("robot1"), b"robot1 map", maps)
        assert keep_putting(server, KEYS.fused, b"fused v1", fused)
        time.sleep(GRACE_S)

        assert maps.snapshot() and set(maps.snapshot()) == {(KEYS.robot_map("robot1"), b"robot1 map")}
        assert alive.snapshot() == []
        assert (KEYS.fused, b"intruder fused") not in fused.snapshot()
        assert (KEYS.robot_map("robot1"), b"robot1 map") not in stolen.snapshot()
        # queries: the server may pull a robot's map, an anonymous client may not
        assert server.get(KEYS.all_maps, timeout_s=2.0) == [(KEYS.robot_map("robot1"), b"robot1 latest")]
        assert intruder.get(KEYS.all_maps, timeout_s=1.0) == []


def test_the_tls_port_refuses_clients_without_a_certificate_of_the_fleet(fleet):
    pki, tls = fleet["pki"], fleet["tls"]
    no_cert = BusConfig(
        connect=(tls,),
        connect_timeout_s=REFUSED_S,
        overrides=(("transport/link/tls/root_ca_certificate", f'"{pki / "ca.pem"}"'),),
    )
    with pytest.raises(BusError, match="cannot open"):
        Bus(no_cert)
    # a certificate that says robot1, signed by another CA
    impostor = fleet["tmp"] / "impostor"
    make_certs(impostor, "robot1")
    forged = replace_tls(fleet["member"]("robot1"), impostor / "robot1.pem", impostor / "robot1.key")
    with pytest.raises(BusError, match="cannot open"):
        Bus(forged)


def replace_tls(cfg: BusConfig, cert: Path, key: Path) -> BusConfig:
    return BusConfig(
        connect=cfg.connect,
        config_file=cfg.config_file,
        connect_timeout_s=REFUSED_S,
        overrides=(
            ("transport/link/tls/connect_certificate", f'"{cert}"'),
            ("transport/link/tls/connect_private_key", f'"{key}"'),
        ),
    )


def test_clients_cannot_read_the_routers_admin_space(fleet):
    # zenohd (the compose router) enables its admin space, which lists sessions, addresses and
    # identities; the library router here does only when asked
    tls, tcp = loopback_endpoint().replace("tcp/", "tls/"), loopback_endpoint()
    admin = BusConfig(
        mode="router",
        connect=(),
        listen=(tls, tcp),
        config_file=str(fleet["tmp"] / "router.json5"),
        overrides=(("adminspace/enabled", "true"),),
    )
    with Bus(admin), Bus(BusConfig(connect=(tcp,), connect_timeout_s=STARTUP_S)) as anonymous:
        member = fleet["member"]("server")
        with Bus(
            BusConfig(connect=(tls,), config_file=member.config_file, connect_timeout_s=STARTUP_S)
        ) as server:
            for bus in (anonymous, server):
                keys = [key for key, _ in bus.get("@/**", timeout_s=1.0)]
                # a session sees its own admin entries (local), never the router's
                assert keys and all("/session/" in k for k in keys), keys
                assert len({k.split("/")[1] for k in keys}) == 1, keys  # one zid: its own


# -- (c) anyone reads the fused map -------------------------------------------------------------------


def test_an_anonymous_reader_gets_the_fused_map_by_subscription_and_by_query(fleet):
    with Bus(fleet["member"]("server")) as server, Bus(fleet["anonymous"]()) as reader:
        server.serve(KEYS.fused, lambda _q: [(KEYS.fused, b"fused latest")])
        fused = Inbox()
        reader.subscribe(KEYS.fused, fused)
        assert keep_putting(server, KEYS.fused, b"fused v2", fused)
        assert reader.get(KEYS.fused, timeout_s=2.0) == [(KEYS.fused, b"fused latest")]


# -- the real services under the secure config --------------------------------------------------------


def test_secure_fleet_server_and_agent_make_a_map_an_anonymous_subscriber_receives(fleet):
    group, tls, tcp, clients = fleet["group"], fleet["tls"], fleet["tcp"], fleet["clients"]
    fleet_id = ["--fleet", "e2e"]
    server_argv = ["server", "--connect", tls, "--bus-config", clients["server"], *fleet_id]
    server = group.start("server", python_module("fleet_slam.cli", *server_argv))
    assert server.wait_for("running", STARTUP_S), server.output()
    robot = ["--robot", "robot1", "--world", "office", "--prior", "9.0,4.5,0.0", "--duration", 60]
    robot += ["--particles", 10, "--connect", tls, "--bus-config", clients["robot1"], *fleet_id]
    agent = group.start("robot1", python_module("fleet_slam.cli", "agent", *robot))
    reader = group.start(
        "subscribe", python_module("fleet_slam.cli", "subscribe", "--connect", tcp, *fleet_id)
    )
    placed = re.compile(r"v\d+ [1-9]\d* segments, 1 robots \[robot1:prior\]")  # walls, robot1 placed
    try:
        assert wait_for(lambda: placed.search(reader.output()), E2E_S), "\n".join(
            p.output() for p in (reader, server, agent)
        )
        assert agent.running and server.running  # neither was refused nor crashed
        assert not re.search(r"rejected \w+ on", server.output())  # every message it got was valid
    finally:
        for proc in (reader, agent, server):
            assert proc.stop() == 0, proc.output()


# -- bad configs are named ----------------------------------------------------------------------------


def test_a_missing_certificate_is_an_error_that_names_it(fleet, tmp_path):
    cfg = fleet["member"]("robot1")
    gone = tmp_path / "robot9.pem"
    with pytest.raises(BusConfigError, match=r"connect_certificate: cannot read .*robot9\.pem"):
        zenoh_config(replace_tls(cfg, gone, fleet["pki"] / "robot1.key"))
    not_pem = tmp_path / "robot1.pem"
    not_pem.write_text("hello")
    with pytest.raises(BusConfigError, match="is not a PEM file"):
        zenoh_config(replace_tls(cfg, not_pem, fleet["pki"] / "robot1.key"))


def test_the_deploy_configs_name_the_compose_secrets_and_fail_clearly_without_them():
    # outside compose the files are absent: the error names the first one, and is a ValueError (CLI)
    with pytest.raises(BusConfigError, match=r"root_ca_certificate: cannot read '/run/secrets/ca\.pem'"):
        zenoh_config(BusConfig(connect=("tls/router:7448",), config_file=str(DEPLOY / "client.json5")))
    assert issubclass(BusConfigError, ValueError)


def test_bad_bus_config_files_are_errors_that_name_the_problem(tmp_path):
    with pytest.raises(BusConfigError, match="no such file"):
        zenoh_config(BusConfig(config_file=str(tmp_path / "nope.json5")))
    typo = tmp_path / "typo.json5"
    typo.write_text("{ transport: { link: { tls: { enable_mlts: true } } } }")
    with pytest.raises(BusConfigError, match="enable_mlts"):
        zenoh_config(BusConfig(config_file=str(typo)))
    endpoints = tmp_path / "endpoints.json5"
    endpoints.write_text('{ connect: { endpoints: ["tcp/10.0.0.1:7447"] } }')
    with pytest.raises(BusConfigError, match="connect/endpoints"):
        zenoh_config(BusConfig(config_file=str(endpoints)))
    with pytest.raises(BusConfigError, match="needs transport/link/tls/connect_certificate"):
        zenoh_config(
            BusConfig(
                connect=("tls/127.0.0.1:7448",), overrides=(("transport/link/tls/enable_mtls", "true"),)
            )
        )


def test_cli_reports_a_bad_bus_config_without_a_traceback(tmp_path):
    missing = str(tmp_path / "nope.json5")
    # the router: exit 1 and a message; a client command: exit 2 and a message (own processes:
    # the commands install signal handlers)
    for command, code in ((["router", "--listen", loopback_endpoint()], 1), (["subscribe", "--once"], 2)):
        run = subprocess.run(
            python_module("fleet_slam.cli", *command, "--bus-config", missing),
            capture_output=True, text=True, timeout=60, cwd=ROOT,
        )  # fmt: skip
        assert run.returncode == code, run.stderr
        assert "nope.json5': no such file" in run.stderr and "Traceback" not in run.stderr
