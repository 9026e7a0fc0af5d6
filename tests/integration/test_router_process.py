"""The router as a real process (``python -m shared.bus router``): clients that wait for it, survive
its kill -9 and reconnect to its restart; clean exit on SIGTERM; a clear failure on a taken port."""

from __future__ import annotations

import os
import select
import signal
import subprocess
import sys
import threading
from pathlib import Path

import pytest

from shared.bus import Bus, BusConfig
from tests.netutil import Inbox, loopback_endpoint, wait_for

pytestmark = pytest.mark.integration

ROOT = Path(__file__).resolve().parents[2]
STARTUP_S = 15.0  # generous: a loaded CI machine imports zenoh slowly
RECONNECT_S = 10.0


def start_router(endpoint: str) -> subprocess.Popen:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    return subprocess.Popen(
        [sys.executable, "-m", "shared.bus", "router", "--listen", endpoint],
        cwd=ROOT,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def read_line(proc: subprocess.Popen, timeout_s: float = STARTUP_S) -> str:
    """The router's next stdout line ('' if none within ``timeout_s`` or the process ended)."""
    ready, _, _ = select.select([proc.stdout], [], [], timeout_s)
    return proc.stdout.readline().strip() if ready else ""


def stop(proc: subprocess.Popen) -> None:
    if proc.poll() is None:
        proc.kill()
    proc.wait()
    proc.stdout.close()
    proc.stderr.close()


@pytest.fixture
def routers():
    """Start routers through ``routers.append(start_router(...))``; every one is killed at the end."""
    procs: list[subprocess.Popen] = []
    yield procs
    for proc in procs:
        stop(proc)


def delivers(pub: Bus, received: Inbox, key: str, payload: bytes, timeout_s: float) -> bool:
    """Put ``payload`` on ``key`` until the subscriber has it (puts during an outage are dropped)."""

    def attempt() -> bool:
        pub.put(key, payload)
        return received.has((key, payload))

    return wait_for(attempt, timeout_s)


def test_clients_wait_for_the_router_and_survive_its_kill_and_restart(routers):
    endpoint = loopback_endpoint()
    cfg = BusConfig(connect=(endpoint,), connect_timeout_s=STARTUP_S + 5.0, retry_ms=100)
    opened: dict[str, Bus] = {}
    early = threading.Thread(target=lambda: opened.setdefault("early", Bus(cfg)))
    early.start()  # a client started before its router: opening waits
    try:
        early.join(0.3)
        assert early.is_alive(), "the client opened without a router"
        routers.append(start_router(endpoint))
        assert read_line(routers[-1]) == f"router listening on {endpoint}"
        early.join(STARTUP_S)
        assert "early" in opened, "the early client did not connect"
        with opened["early"] as pub, Bus(cfg) as sub:
            received, presence = Inbox(), Inbox()
            sub.subscribe("restart/*", received)
            sub.watch_alive("restart/alive/*", presence)
            pub.declare_alive("restart/alive/pub")
            assert delivers(pub, received, "restart/x", b"before", RECONNECT_S)
            assert wait_for(lambda: presence.has(("restart/alive/pub", True)))

            routers[-1].kill()  # kill -9: no goodbye to the clients
            routers[-1].wait()
            assert wait_for(lambda: presence.has(("restart/alive/pub", False)), RECONNECT_S)
            routers.append(start_router(endpoint))
            assert read_line(routers[-1]) == f"router listening on {endpoint}"

            # the clients reconnect by themselves and re-declare subscription and token
            assert delivers(pub, received, "restart/x", b"after", RECONNECT_S)
            # a router restart looks like every token leaving and coming back
            states = [True, False, True]
            assert wait_for(lambda: presence.states("restart/alive/pub") == states, RECONNECT_S)
    finally:
        early.join(STARTUP_S)  # with the router never up, the client gives up after its timeout
        if "early" in opened:
            opened["early"].close()


def test_router_exits_cleanly_on_sigterm(routers):
    endpoint = loopback_endpoint()
    routers.append(start_router(endpoint))
    assert read_line(routers[-1]) == f"router listening on {endpoint}"
    routers[-1].send_signal(signal.SIGTERM)
    assert routers[-1].wait(STARTUP_S) == 0


def test_router_on_a_taken_port_fails_with_a_message(routers):
    endpoint = loopback_endpoint()
    routers.append(start_router(endpoint))
    assert read_line(routers[-1]) == f"router listening on {endpoint}"
    routers.append(start_router(endpoint))
    assert routers[-1].wait(STARTUP_S) == 1
    assert "Address already in use" in routers[-1].stderr.read()
