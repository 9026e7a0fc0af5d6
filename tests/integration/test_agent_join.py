"""`fleet-slam agent --join` as real processes on loopback (issue 21, item 3).

robot1 maps part of the simulated office (no prior: its frame is the fused map's) and ends; then
robot2 starts elsewhere in the office with ``--join``: it takes the fused map by query, finds
itself in it, and sends its map with that place. The server checks the claim and places it at
once — within 10 s of its start, where the truth says — and the walls robot2 sees that robot1
never saw join the fused map, on the office's true walls.
"""

from __future__ import annotations

import time

import numpy as np
import pytest

from fleet_slam.procs import ProcGroup, python_module
from fleet_slam.watch import FusedWatcher
from robot_agent.sim import builtin_world
from shared.bus import Bus, BusConfig
from shared.geometry import apply_segments, point_segment_distance, relative, segment_lengths
from shared.keys import Keys
from shared.metrics import map_quality
from tests.netutil import loopback_endpoint, start_router_and_server, wait_for

pytestmark = pytest.mark.integration

STARTUP_S = 30.0
FIRST_S = 60.0  # robot1's simulated seconds (route 0), run at 3x
JOIN_S = 40.0  # robot2's (route 1), run at 1x


def agent_argv(robot: str, route: int, endpoint: str, duration_s: float, speed: float, *extra) -> list:
    args = ["--robot", robot, "--world", "office", "--route", route, "--duration", duration_s]
    args += ["--speed", speed, "--particles", 10, "--seed", route, "--connect", endpoint, *extra]
    return python_module("robot_agent", *args)


def own_new_walls(fused, before: np.ndarray, robot: str) -> np.ndarray:
    """The fused map's segments that only ``robot`` contributed and that lie off every segment of
    ``before`` (the fused map before it came): the walls it brought."""
    mine = np.array([fused.provenance(i) == [robot] for i in range(len(fused.seg))], bool)
    seg = fused.seg[mine]
    if not len(seg) or not len(before):
        return seg
    mid = 0.5 * (seg[:, 0] + seg[:, 1])
    d = point_segment_distance(mid[:, None, :], before[None]).min(axis=1)
    return seg[d > 0.3]


def test_a_robot_that_joins_is_placed_within_seconds_and_its_new_walls_join_the_fused_map(tmp_path):
    world = builtin_world("office")
    truth = relative(world.starts[0], world.starts[1])  # robot2's map frame in robot1's (the global)
    endpoint = loopback_endpoint()
    with ProcGroup(tmp_path / "logs") as group:
        _router, server = start_router_and_server(group, endpoint, tmp_path / "s", STARTUP_S)
        first = group.start("robot1", agent_argv("robot1", 0, endpoint, FIRST_S, 3.0))
        with Bus(BusConfig(connect=(endpoint,))) as bus:
            watcher = FusedWatcher(bus, Keys())
            watcher.start(query_timeout_s=2.0)
            ended = first.wait_for("rebuilt along the corrected path", STARTUP_S + FIRST_S)
            assert ended, first.output()[-3000:]
            assert wait_for(lambda: not first.running, 30.0), first.output()[-3000:]

            def robot1_final(f) -> bool:
                s = None if f is None else f.robot("robot1")
                return s is not None and s.status == "reference" and s.map_seq >= 1 and len(f.seg) >= 40

            assert wait_for(lambda: robot1_final(watcher.fetch(0.5)), 20.0)
            time.sleep(2.0)  # the final map's fusion settled
            before = watcher.fetch(1.0)
            start_s = time.monotonic()
            second = group.start("robot2", agent_argv("robot2", 1, endpoint, JOIN_S, 1.0, "--join"))
            assert second.wait_for("connected", STARTUP_S), second.output()
            connected_s = time.monotonic()

            def placed(f) -> bool:
                s = None if f is None else f.robot("robot2")
                return s is not None and s.status != "unaligned"

            assert wait_for(lambda: placed(watcher.latest), 30.0), (
                second.output()[-3000:] + server.output()[-3000:]
            )
            placed_s = time.monotonic()
            f = watcher.latest
            s = f.robot("robot2")
            out = second.output()
            assert "joined the fused map" in out, out[-3000:]
            assert s.status == "aligned"
            e = relative(truth, s.transform)
            print(
                f"robot2 placed {placed_s - connected_s:.1f} s after it connected, "
                f"{placed_s - start_s:.1f} s after it started: "
                f"{np.hypot(e[0], e[1]):.3f} m, {np.degrees(e[2]):.2f} deg off"
            )
            assert placed_s - connected_s <= 10.0
            assert np.hypot(e[0], e[1]) <= 0.15 and abs(e[2]) <= np.radians(1.5)
            # robot2 maps on: its walls that robot1 never saw join the fused map, on true walls
            assert second.wait_for("done", JOIN_S + 60.0), out[-3000:]
            assert wait_for(lambda: watcher.fetch(0.5).robot("robot2").map_seq >= 30, 20.0)
            time.sleep(2.0)
            after = watcher.fetch(1.0)
        assert after.robot("robot2").status == "aligned"
        new = own_new_walls(after, before.seg, "robot2")
        new_m = float(segment_lengths(new).sum())
        on_walls = map_quality(apply_segments(world.starts[0], new), world.walls).precision
        print(
            f"robot2's new walls in the fused map: {len(new)} segments, {new_m:.1f} m, "
            f"{on_walls:.0%} on the office's walls"
        )
        assert new_m >= 10.0 and on_walls >= 0.9
        assert "Traceback" not in server.output() + out
