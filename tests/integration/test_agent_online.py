"""A deployed agent (no end to its source) with its online back end, as real processes on
loopback: it closes loops and publishes corrected maps while it runs, and on SIGTERM it makes
its last back-end update, publishes the final corrected map and exits 0 within 10 s — and that
map is the one the server fuses."""

from __future__ import annotations

import json
import time

import pytest

from fleet_slam.procs import ProcGroup, python_module
from fleet_slam.watch import FusedWatcher
from shared.bus import Bus, BusConfig
from shared.keys import Keys
from tests.netutil import loopback_endpoint, start_router_and_server, wait_for

pytestmark = pytest.mark.integration

STARTUP_S = 30.0


def test_sigterm_publishes_the_final_corrected_map_and_exits_0_within_10_s(tmp_path):
    endpoint = loopback_endpoint()
    with ProcGroup(tmp_path / "logs") as group:
        _router, _server = start_router_and_server(group, endpoint, tmp_path / "s", STARTUP_S)
        # the office route comes back to its start after ~60 s of simulated time: at 4x, 15 s
        argv = ["--robot", "robot1", "--world", "office", "--particles", 10, "--speed", 4]
        argv += ["--connect", endpoint, "--out", tmp_path / "out"]
        agent = group.start("robot1", python_module("robot_agent", *argv))
        # loops found and closed while it runs (the line comes when the loop count changes)
        assert agent.wait_for("online back end:", 120.0), agent.output()
        with Bus(BusConfig(connect=(endpoint,))) as bus:
            watch = FusedWatcher(bus, Keys())
            watch.start()
            assert wait_for(lambda: watch.latest is not None and len(watch.latest.seg) > 10, 20.0)
            t0 = time.monotonic()
            code = agent.stop(grace_s=15.0)
            took = time.monotonic() - t0
            out = agent.output()
            assert code == 0, out[-2000:]
            assert took < 10.0, f"exit took {took:.1f} s"
            assert "published the corrected map" in out and "last update not in time" not in out
            summary = json.loads((tmp_path / "out" / "robot1.agent.json").read_text())
            assert summary["backend"]["loops"] > 0 and summary["backend"]["final_update_in_time"]
            last_seq = summary["map_seq"] - 1  # the seq of the last map it published

            def fused_has_last() -> bool:
                f = watch.latest
                return f is not None and any(r.robot == "robot1" and r.map_seq == last_seq for r in f.robots)

            assert wait_for(fused_has_last, 10.0), [(r.robot, r.map_seq) for r in watch.latest.robots]
    assert all(not p.running for p in group.procs)
