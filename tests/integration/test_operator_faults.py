"""Faults an unlucky or hostile operator hits, each as the operator hit it (issue 24's table):
real processes on loopback where the fault needs them."""

from __future__ import annotations

import time

import numpy as np
import pytest

from fleet_slam.procs import ProcGroup, python_module
from tests.netutil import loopback_endpoint

pytestmark = pytest.mark.integration

STARTUP_S = 30.0


def test_row2_a_second_server_on_the_same_state_exits_2_at_once_naming_the_holder(tmp_path):
    """Two servers on one ``--state``: the second exits 2 at once with a message naming the
    directory and the holder; the first keeps running and saving."""
    endpoint = loopback_endpoint()
    state = tmp_path / "state"
    with ProcGroup(tmp_path / "logs") as group:
        router = group.start("router", python_module("shared.bus", "router", "--listen", endpoint))
        assert router.wait_for("listening", STARTUP_S), router.output()
        argv = ["--connect", endpoint, "--state", state]
        first = group.start("server1", python_module("map_server", *argv))
        assert first.wait_for("running", STARTUP_S), first.output()
        t0 = time.monotonic()
        second = group.start("server2", python_module("map_server", *argv))
        code = second.popen.wait(timeout=STARTUP_S)
        took = time.monotonic() - t0
        out = second.output()
        assert code == 2, out
        assert str(state) in out and "in use" in out and f"pid {first.popen.pid}" in out, out
        assert took < 10.0  # at once: before it connects anywhere (the interpreter's start-up)
        time.sleep(1.0)
        assert first.running, first.output()


def test_row1_an_odometry_jump_in_a_robots_log_is_reported_and_the_fused_map_stays_sane(tmp_path):
    """Router, server and an agent on 700 scans of the Intel excerpt whose odometry jumps 1 km
    at one line (as the operator edited it): the agent says so and exits 0; no segment of the
    fused map is more than 5 m from the building (the map of the unedited scans). Before: 32 of
    78 segments ~1 km away, and not a word."""

    from shared.geometry import point_segment_distance
    from tests.slam.test_odometry_jump import SCANS, _edited, reference_map

    log = _edited(tmp_path, persistent=False)
    building = reference_map()
    out, _, ends = _agent_on_log(tmp_path, log, "--to", SCANS)
    assert "warning: odometry jumped 100" in out, out[-3000:]
    far = point_segment_distance(ends[:, None, :], building[None, :, :, :]).min(axis=1)
    assert far.max() < 5.0, f"{int((far > 5).sum())} segment ends more than 5 m from the building"


def _agent_on_log(tmp_path, log, *extra) -> tuple[str, object, np.ndarray]:
    """Router, server and one agent (10 particles, as fast as it goes, ``extra`` arguments) on
    ``log``: the agent's output (it exited 0), the fused map after it and its segment ends (N,2)."""
    from fleet_slam.watch import FusedWatcher
    from shared.bus import Bus, BusConfig
    from shared.keys import Keys

    endpoint = loopback_endpoint()
    with ProcGroup(tmp_path / "logs") as group:
        router = group.start("router", python_module("shared.bus", "router", "--listen", endpoint))
        assert router.wait_for("listening", STARTUP_S), router.output()
        server = group.start("server", python_module("map_server", "--connect", endpoint))
        assert server.wait_for("running", STARTUP_S), server.output()
        argv = ["--robot", "robot1", "--log", log, "--particles", 10, "--speed", 0, *extra]
        agent = group.start("robot1", python_module("robot_agent", *argv, "--connect", endpoint))
        code = agent.popen.wait(timeout=300)
        out = agent.output()
        assert code == 0, out[-3000:]
        with Bus(BusConfig(connect=(endpoint,))) as bus:
            fused = FusedWatcher(bus, Keys()).fetch(timeout_s=10.0)
    assert fused is not None and len(fused.seg) > 20
    return out, fused, fused.seg.astype(float).reshape(-1, 2)


def test_a_robot_carried_elsewhere_in_its_map_is_reported_and_the_fused_map_stays_sane(tmp_path):
    """Issue 24 item 1, a teleport, as an operator runs it: router, server and an agent (with
    its online back end and the map rebuilt at the end) on the Intel excerpt carried at scan
    1000 back to where scan 150 was, odometry none the wiser. The agent says the robot was moved
    and where it was found, and exits 0; the fused map's segments lie on the building's walls
    (the map of the intact excerpt): measured 84 ends, 0.053 m from them on average, and each
    end within 0.50 m of them or of the intact excerpt's scan points (one wall's end 1.9 m past
    the intact map's: a stretch of it seen 151 times in those scans, on its line, which the
    intact map did not trust yet — the map rebuilt along the corrected path has it). Before: 21
    m off for good, the corridor mapped over."""
    from scipy.spatial import cKDTree

    from shared.geometry import point_segment_distance
    from tests.slam.test_kidnap import INTEL, building_map, building_points, teleported

    log = teleported(tmp_path, 1000, INTEL, 150, 150)
    building = building_map(1000)
    out, _, ends = _agent_on_log(tmp_path, log)
    assert "warning: from scan 1000 the scans disagree with odometry" in out, out[-3000:]
    assert "warning: the robot was moved: found at scan 10" in out, out[-3000:]
    far = point_segment_distance(ends[:, None, :], building[None, :, :, :]).min(axis=1)
    # an end beyond the walls the intact map trusts may still be on the building: on its points
    off = np.minimum(far, cKDTree(building_points(1000)).query(ends)[0])
    assert far.mean() < 0.1 and off.max() < 0.8, (
        f"{int((far > 0.3).sum())} of {len(far)} segment ends more than 0.3 m off the building's walls, "
        f"{far.max():.2f} m at most; {off.max():.2f} m from the walls and the scan points"
    )


def test_a_robot_carried_where_its_map_does_not_reach_gets_a_new_session_and_its_old_map_stays(tmp_path):
    """The Intel excerpt's first 700 scans, then ACES's (the robot carried into another
    building), as an operator runs it: the agent says it lost the robot and begins a new
    session, exits 0, writes the ended session's path beside the new one's; the fused map keeps
    the ended session's map where it was — the Intel walls, nothing of ACES bent onto them: each
    end on the intact excerpt's walls or on its scan points (a wall the intact map does not trust
    yet; the online back end's timing decides whether the last map before the teleport trusts it).
    Measured on 39 runs, 4-6 at once (2026-12-05): 0.031 m from them on average at most, 0.091 m
    at most. In 3 of 55 runs the map published at scan 695 trusted a wall 3.4 m from the intact
    map's walls and 0.01-0.05 m from its scan points (CI failed on one: the check counted only the
    walls). While the agent still published during the doubt, the back end's corrections (its
    keyframes followed the robot into ACES) had moved one segment 3.4 m."""
    import json

    from scipy.spatial import cKDTree

    from shared.geometry import point_segment_distance
    from tests.slam.test_kidnap import ACES, building_map, building_points, teleported

    log = teleported(tmp_path, 700, ACES, 0, 250)
    building = building_map(700)
    out_dir = tmp_path / "out"
    out, _, ends = _agent_on_log(tmp_path, log, "--out", out_dir)
    assert "warning: lost at scan" in out and "a new one begins" in out, out[-3000:]
    summary = json.loads((out_dir / "robot1.agent.json").read_text())
    (ended,) = summary["sessions_ended"]
    old = (out_dir / f"robot1.{ended['session']}.poses.txt").read_text().splitlines()
    new = (out_dir / "robot1.poses.txt").read_text().splitlines()
    assert len(old) == ended["last_scan"] + 1 and len(new) == 950 - len(old)
    far = point_segment_distance(ends[:, None, :], building[None, :, :, :]).min(axis=1)
    off = np.minimum(far, cKDTree(building_points(700)).query(ends)[0])
    assert off.mean() < 0.06 and off.max() < 0.3, (
        f"{int((off > 0.3).sum())} of {len(off)} fused segment ends more than 0.3 m off the Intel walls "
        f"and scan points, {off.max():.2f} m at most ({far.max():.2f} m from the walls)"
    )
