"""The fleet's free space at the server: each robot session's views placed where its map is, united,
re-fused only when something changed (and not more often than min_gap_s), bounded to the sessions
the fleet keeps, persisted and restored with the state, published and answered on map/free."""

from __future__ import annotations

import numpy as np
import pytest
from shapely.geometry import Polygon

from map_server.freespace import FreeFusionConfig, FreeSpaces
from map_server.server import MapServer
from map_server.store import Store
from shared import codec
from shared.keys import Keys
from shared.messages import FreeSpace, FusedFree
from shared.occupancy import fused_geometry
from tests.map_server.test_server_faults import PullBus, room_chunks
from tests.netutil import wait_for

KEYS = Keys()
SQUARE = np.array([[0.0, 0.0], [2.0, 0.0], [2.0, 2.0], [0.0, 2.0]])


def views(robot="robot1", session="s1", seq=0, at=(1.0, 1.0)) -> FreeSpace:
    """One view: a 2 m square in front of the robot at ``at``."""
    pose = np.array([[*at, 0.0]])
    wall = np.array([1, 1, 1, 0], bool)  # three edges along hits, the fourth along beams
    return FreeSpace(robot, session, seq, 5.0, pose, np.array([0, 4]), np.array([0]), SQUARE, wall)


M = FreeFusionConfig().wall_margin_m
SIDE = 2.0 - 2 * M  # a 2 m square kept M off its edges


def test_free_space_is_placed_united_and_refused_when_stale():
    fs = FreeSpaces(FreeFusionConfig(min_gap_s=2.0))
    assert fs.put(views(seq=1)) == "kept" and fs.put(views(seq=1)) == fs.put(views(seq=0)) == "stale"
    assert fs.put(views("robot2", "s9", 0)) == "kept"
    placements = {("robot1", "s1"): np.zeros(3), ("robot2", "s9"): np.array([1.0, 0.0, 0.0])}
    assert fs.due(placements, 0.0)
    f = fs.fuse(placements, "server", 4, 0.0)
    assert f.map_version == 4 and f.version == 1
    geom = fused_geometry(f)
    assert geom.area == pytest.approx((3 - 2 * M) * SIDE, abs=0.01)  # [1,4] x [1,3], kept off the edges
    # no segment map given: the wall edges outside the free space — robot1's edge at x = 3 lies in
    # robot2's free space (as someone walking by would): gone
    w = f.walls
    x, y = w[..., 0], w[..., 1]
    on_outer = np.isclose(y, 1.0).all(1) | np.isclose(y, 3.0).all(1) | np.isclose(x, 4.0).all(1)
    assert len(w) >= 4 and on_outer.all()
    assert not fs.due(placements, 1.0)  # nothing changed
    moved = {**placements, ("robot2", "s9"): np.array([3.0, 0.0, 0.0])}
    assert not fs.due(moved, 1.0) and fs.due(moved, 2.5)  # a move re-fuses, after min_gap_s
    fs.cost_s = 0.9  # ... or, after a fusion that took 0.9 s, 5 times that (the loop is the maps')
    assert fs.cfg.gap_per_cost == 5.0 and not fs.due(moved, 4.4) and fs.due(moved, 4.6)
    f = fs.fuse(moved, "server", 5, 2.5)
    assert fused_geometry(f).area == pytest.approx(2 * SIDE**2, abs=0.01)  # apart now
    f = fs.fuse({("robot1", "s1"): np.zeros(3)}, "server", 6, 5.0)  # robot2 not placed: not in it
    assert fused_geometry(f).area == pytest.approx(SIDE**2, abs=0.01)
    seg = np.array([[[1.0, 1.0], [3.0, 1.0]], [[3.0, 1.0], [3.0, 3.0]]])  # the map has two of its walls
    f = fs.fuse({("robot1", "s1"): np.zeros(3)}, "server", 7, 7.5, seg)
    assert len(f.walls) == 1 and np.allclose(np.sort(f.walls[0, :, 1]), [3.0, 3.0])  # the third: y = 3
    fs.keep_only({("robot1", "s1")})
    assert set(fs.latest) == {("robot1", "s1")} and fs.changed


def test_a_message_that_adds_views_is_put_together_with_the_one_before_or_asks_for_the_whole():
    fs = FreeSpaces()
    first = views(seq=0)
    assert fs.put(first) == "kept"
    two = np.array([[1.0, 1.0, 0.0], [5.0, 1.0, 0.0]])
    adds = FreeSpace("robot1", "s1", 1, 6.0, two, np.array([0, 4]), np.array([1]), SQUARE,
                     np.ones(4, bool), rings_from=1)  # fmt: skip
    assert fs.put(adds) == "kept"
    whole = fs.latest[("robot1", "s1")]
    assert whole.rings_from == 0 and whole.ring_view.tolist() == [0, 1] and len(whole.vertices) == 8
    later = FreeSpace("robot1", "s1", 3, 7.0, two, np.array([0]), np.zeros(0, int), np.zeros((0, 2)),
                      np.zeros(0, bool), rings_from=2)  # fmt: skip
    assert fs.put(later) == "gap"  # seq 2 missed
    assert fs.latest[("robot1", "s1")].seq == 1


def test_the_server_publishes_persists_and_restores_the_free_space(tmp_path):
    bus = PullBus([])
    server = MapServer(bus, KEYS, store=Store(tmp_path))
    for c in room_chunks():  # robot1, session s1, placed by its prior
        server.on_map(KEYS.robot_map("robot1"), codec.encode(c))
    server.on_free(KEYS.robot_free("robot1"), codec.encode(views(seq=3)))
    server.on_free(KEYS.robot_free("robot1"), codec.encode(views(robot="robot2")))  # wrong key
    assert server.rejected["free"] == 1 and "free: robot" in next(iter(server.reasons))
    nothing = (np.array([0]), np.zeros(0, int), np.zeros((0, 2)), np.zeros(0, bool))
    gap = FreeSpace("robot1", "s1", 9, 6.0, np.zeros((1, 3)), *nothing, rings_from=1)
    server.on_free(KEYS.robot_free("robot1"), codec.encode(gap))  # adds to seq 8, never received
    server.free.cost_s = 0.5  # as after a fusion of 0.5 s (free_thread_above_s: a short one stays inline)
    assert server.tick() is not None
    assert wait_for(lambda: KEYS.robot_free("robot1") in bus.queries)  # the whole is asked for
    job = server._free_job  # fused on a thread of its own, out at a later tick
    assert job is not None and not any(k == KEYS.fused_free for k, _ in bus.puts)
    job.thread.join(10.0)
    server.tick()
    assert server._free_job is None
    puts = [codec.decode(p) for k, p in bus.puts if k == KEYS.fused_free]
    assert len(puts) == 1 and isinstance(puts[0], FusedFree) and puts[0].session == server.session
    assert len(server.free_ms) == 1 and server.status()["free_ms"]["max"] > 0.0  # (timed: the status line)
    assert server.free.cost_s < server.cfg.free_thread_above_s  # (this one was short: the next inline)
    kept = Polygon(SQUARE + 1.0).buffer(-M, join_style="mitre")
    assert fused_geometry(puts[0]).symmetric_difference(kept).area < 1e-3
    ((_, answer),) = server.answer_free(KEYS.fused_free)
    assert codec.decode(answer).version == puts[0].version
    again = MapServer(PullBus([]), KEYS, store=Store(tmp_path))  # a restart: nothing lost
    assert again.free.latest[("robot1", "s1")].seq == 3
    ((_, answer),) = again.answer_free(KEYS.fused_free)
    assert fused_geometry(codec.decode(answer)).area == pytest.approx(SIDE**2, abs=0.01)


def test_a_free_space_fusion_that_fails_is_reported_and_tried_again(tmp_path, caplog):
    """The free space's fusion runs on its own thread: one that raises is logged by the loop, the
    messages stay, and the next tick fuses them again (in the loop here: ``free_thread_above_s``
    infinite)."""
    from map_server.server import ServerConfig

    bus = PullBus([])
    server = MapServer(bus, KEYS, ServerConfig(free_thread_above_s=float("inf")), store=Store(tmp_path))
    for c in room_chunks():
        server.on_map(KEYS.robot_map("robot1"), codec.encode(c))
    server.on_free(KEYS.robot_free("robot1"), codec.encode(views(seq=3)))
    real = server.free.compute
    server.free.compute = lambda *a: 1 / 0
    server.tick()
    assert "fusing the free space failed: division by zero" in caplog.text and server.free.changed
    assert not any(k == KEYS.fused_free for k, _ in bus.puts) and server._free_job is None
    server.free.compute = real
    server.free._last_fuse_s = -np.inf  # (past min_gap_s)
    server.tick()
    puts = [codec.decode(p) for k, p in bus.puts if k == KEYS.fused_free]
    assert len(puts) == 1 and fused_geometry(puts[0]).area > 0.0


def test_a_short_free_space_fusion_stays_in_the_loop(tmp_path):
    """While the last fusion took less than ``free_thread_above_s`` (a few robots' free space) the
    next runs in the loop and goes out at the same tick: a thread would only contend for the GIL
    with the maps' fusions (bench_fleet's latency at 8 and 16 agents)."""
    bus = PullBus([])
    server = MapServer(bus, KEYS, store=Store(tmp_path))
    for c in room_chunks():
        server.on_map(KEYS.robot_map("robot1"), codec.encode(c))
    server.on_free(KEYS.robot_free("robot1"), codec.encode(views(seq=3)))
    assert server.cfg.free_thread_above_s == 0.1 and server.free.cost_s == 0.0
    server.tick()
    assert server._free_job is None and sum(k == KEYS.fused_free for k, _ in bus.puts) == 1
