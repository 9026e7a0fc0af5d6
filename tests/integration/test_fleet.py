"""The fleet as real processes on loopback: router, map server, two simulated agents.

One run (module fixture) checks what a user of the service relies on: a subscriber started
mid-run gets the current fused map at once (query) and then every update; the map server killed
with SIGKILL and restarted on the same ``--state`` comes back with everything it had and goes on
fusing; every process is stopped by its own handle.
"""

from __future__ import annotations

import numpy as np
import pytest

from fleet_slam.procs import ProcGroup, python_module
from fleet_slam.watch import FusedWatcher
from map_server.store import Store
from shared.bus import Bus, BusConfig
from shared.keys import Keys
from shared.messages import FusedMap
from tests.netutil import loopback_endpoint, wait_for

pytestmark = pytest.mark.integration

STARTUP_S = 30.0
SIM_S = 40.0  # simulated seconds per agent, run at 1x


def agent_argv(i: int, endpoint: str) -> list[str]:
    prior = "9.0,4.5,0.0" if i == 0 else "15.0,5.5,-1.5707963267948966"
    args = ["--robot", f"robot{i + 1}", "--world", "office", "--route", i, "--prior", prior]
    args += ["--duration", SIM_S, "--particles", 10, "--connect", endpoint]
    return python_module("robot_agent", *args)


def restored_from(state) -> FusedMap | None:
    """The fused map a server restarted on ``state`` begins with (before any new input)."""
    from map_server.server import MapServer

    class NoBus:  # MapServer only touches the bus in start() and tick()
        pass

    return MapServer(NoBus(), Keys(), store=Store(state)).fleet.latest()


def start_server(group: ProcGroup, endpoint: str, state, name: str = "server"):
    proc = group.start(name, python_module("map_server", "--connect", endpoint, "--state", state))
    assert proc.wait_for("running", STARTUP_S), proc.output()
    return proc


def segments_covered(old: np.ndarray, new: np.ndarray, tol_m: float = 1e-4) -> bool:
    """Every segment of ``old`` is in ``new`` (same endpoints within ``tol_m``)."""
    if len(old) == 0:
        return True
    d = np.abs(old.reshape(-1, 1, 4) - new.reshape(1, -1, 4)).max(axis=2)
    return bool(np.all(d.min(axis=1) <= tol_m))


@pytest.fixture(scope="module")
def fleet(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("fleet")
    endpoint = loopback_endpoint()
    with ProcGroup(tmp / "logs") as group:
        router = group.start("router", python_module("shared.bus", "router", "--listen", endpoint))
        assert router.wait_for("listening", STARTUP_S), router.output()
        server = start_server(group, endpoint, tmp / "state")
        agents = [group.start(f"robot{i + 1}", agent_argv(i, endpoint)) for i in range(2)]
        yield {
            "group": group,
            "endpoint": endpoint,
            "server": server,
            "agents": agents,
            "state": tmp / "state",
        }
    assert all(not p.running for p in group.procs)  # every process stopped by its handle


def test_late_subscriber_gets_the_map_at_once_then_every_update_and_survives_a_server_crash(fleet):
    keys = Keys()
    with Bus(BusConfig(connect=(fleet["endpoint"],))) as bus:
        # wait until the fleet has a fused map with both robots in it
        probe = FusedWatcher(bus, keys)

        def has_both() -> bool:
            f = probe.fetch(0.5)
            return f is not None and len(f.seg) > 10 and sum(r.merged for r in f.robots) == 2

        assert wait_for(has_both, STARTUP_S)

        # 1. a subscriber started mid-run: the current map by query at once, then the puts.
        # "At once" is what start() returns: the query's answer, not a later put, and no older
        # than the map the fleet already had before this subscriber existed.
        current = probe.latest
        late = FusedWatcher(bus, keys)
        first = late.start(query_timeout_s=2.0)
        assert first is not None and late.updates[0].via == "query" and len(first.seg) > 0
        assert late.updates[0].fused.version >= current.version
        assert wait_for(lambda: sum(u.via == "put" for u in late.updates) >= 3, 15.0)
        versions = [u.fused.version for u in late.updates]
        assert versions == sorted(set(versions))  # every update newer than the last

        # 2. kill -9 the server; restart it on the same state: nothing it had is lost
        before = late.latest
        fleet["server"].kill()
        restored = restored_from(fleet["state"])  # persisted before it was published
        assert restored is not None and restored.version >= before.version
        if restored.version == before.version:
            assert restored.seg.shape == before.seg.shape  # the same map (the wire carries float32)
            assert np.allclose(restored.seg, before.seg, atol=1e-4)
        assert segments_covered(before.seg, restored.seg) or restored.version > before.version
        assert {r.robot for r in restored.robots} == {"robot1", "robot2"}
        start_server(fleet["group"], fleet["endpoint"], fleet["state"], name="server-restarted")
        fresh = FusedWatcher(bus, keys)
        assert wait_for(lambda: fresh.fetch(0.5) is not None, STARTUP_S)
        assert fresh.latest.version >= restored.version

        # 3. and updates continue: the agents' next maps are fused by the restarted server
        n = len(late.updates)
        assert wait_for(lambda: len(late.updates) >= n + 2, 20.0)
        assert late.latest.version > restored.version
        assert len(late.latest.seg) >= 0.8 * len(before.seg)


def test_agents_finish_cleanly(fleet):
    for a in fleet["agents"]:
        a.popen.wait(SIM_S * 3)
        assert a.popen.returncode == 0, a.output()[-2000:]
