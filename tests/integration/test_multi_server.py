"""A fleet larger than one server serves, split by fleet id over two servers on one zenoh network.

Every key lives under ``fleet/<fleet-id>/`` (shared/keys.py): a map server started with
``--fleet east`` subscribes to, fuses, persists and answers for the robots started with
``--fleet east`` only, in its own ``--state``. Two servers on one router, one robot each: each
fused map holds its own robot and none of the other's, each state directory its own robot, and
one server killed leaves the other fusing (README, "A fleet larger than one server").
"""

from __future__ import annotations

import pytest

from fleet_slam.procs import ProcGroup, python_module
from fleet_slam.watch import FusedWatcher
from map_server.store import Store
from shared.bus import Bus, BusConfig
from shared.keys import Keys
from tests.netutil import loopback_endpoint, wait_for

pytestmark = pytest.mark.integration

STARTUP_S = 30.0
SIM_S = 40.0  # simulated seconds per agent, run at 1x
FLEETS = ("east", "west")


def agent_argv(i: int, fleet: str, endpoint: str) -> list[str]:
    prior = "9.0,4.5,0.0" if i == 0 else "15.0,5.5,-1.5707963267948966"
    args = ["--robot", f"robot{i + 1}", "--fleet", fleet, "--world", "office", "--route", i]
    args += ["--prior", prior, "--duration", SIM_S, "--particles", 10, "--connect", endpoint]
    return python_module("robot_agent", *args)


def stored_robots(state) -> set[str]:
    """The robots a server's state directory holds (what a restart would resume with)."""
    from map_server.server import MapServer

    class NoBus:  # MapServer only touches the bus in start() and tick()
        pass

    fused = MapServer(NoBus(), Keys(), store=Store(state)).fleet.latest()
    return set() if fused is None else {r.robot for r in fused.robots}


def test_two_servers_split_the_fleet_by_id_each_with_its_own_state(tmp_path):
    endpoint = loopback_endpoint()
    with ProcGroup(tmp_path / "logs") as group:
        router = group.start("router", python_module("shared.bus", "router", "--listen", endpoint))
        assert router.wait_for("listening", STARTUP_S), router.output()
        servers = {}
        for fleet in FLEETS:
            state = tmp_path / f"state-{fleet}"
            argv = python_module(
                "map_server",
                "--connect",
                endpoint,
                "--fleet",
                fleet,
                "--id",
                f"server-{fleet}",
                "--state",
                state,
            )
            servers[fleet] = group.start(f"server-{fleet}", argv)
            assert servers[fleet].wait_for("running", STARTUP_S), servers[fleet].output()
        agents = [group.start(f"robot{i + 1}", agent_argv(i, f, endpoint)) for i, f in enumerate(FLEETS)]

        with Bus(BusConfig(connect=(endpoint,))) as bus:
            watchers = {f: FusedWatcher(bus, Keys(f)) for f in FLEETS}
            for w in watchers.values():
                w.start(query_timeout_s=2.0)

            def each_has_its_robot() -> bool:
                return all(
                    (m := w.latest) is not None and len(m.seg) > 10 and any(r.merged for r in m.robots)
                    for w in watchers.values()
                )

            assert wait_for(each_has_its_robot, STARTUP_S + 20.0)
            for i, fleet in enumerate(FLEETS):
                fused = watchers[fleet].latest
                assert fused.server == f"server-{fleet}"
                assert {r.robot for r in fused.robots} == {f"robot{i + 1}"}  # its own robot, only
                assert stored_robots(tmp_path / f"state-{fleet}") == {f"robot{i + 1}"}

            # one server down: the other fleet goes on being fused and published
            servers["east"].kill()
            west = watchers["west"]
            n = len(west.updates)
            assert wait_for(lambda: len(west.updates) >= n + 2, 20.0), servers["west"].output()[-2000:]
            assert {r.robot for r in west.latest.robots} == {"robot2"}
            assert stored_robots(tmp_path / "state-east") == {"robot1"}  # kept for its restart
        for a in agents:
            a.popen.wait(SIM_S * 3)
            assert a.popen.returncode == 0, a.output()[-2000:]
    assert all(not p.running for p in group.procs)  # every process stopped by its handle
