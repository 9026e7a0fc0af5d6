"""What a robot says it saw free: one scan's region keeps off every wall it saw (also at a grazing
angle and behind a depth step), a beam without return counts only so far, an unusable one not at
all; views are kept by the area they add, forgotten when odometry is in doubt, and anchored to the
published path; the agent's free space stays compact beside its map and true to the world."""

from __future__ import annotations

import numpy as np
import pytest
import shapely
from shapely.geometry import LineString, Polygon

from robot_agent.agent import AgentConfig, AgentCore
from robot_agent.freespace import FreeSpaceConfig, FreeSpaceViews, scan_region
from robot_agent.sim import LiveSim, builtin_world
from robot_agent.sim.lidar import cast_rays
from robot_agent.sim.world import free_space
from robot_agent.slam.fastslam import FastSLAM, SlamConfig
from shared import codec
from shared.geometry import compose
from shared.occupancy import place, union, view_rings

CFG = FreeSpaceConfig()
ANGLES = np.linspace(-np.pi / 2, np.pi / 2, 181)
ROOM = np.array([[[-1, -3], [5, -3]], [[5, -3], [5, 3]], [[5, 3], [-1, 3]], [[-1, 3], [-1, -3]]], float)


def scan(walls, pose=(0.0, 0.0, 0.0), range_max=30.0):
    pose = np.asarray(pose, float)
    r = cast_rays(pose[None, :2], pose[2] + ANGLES[None, :], walls, range_max)[0]
    return r


def region(ranges, cfg=CFG, range_max=30.0):
    return union([v for v, _ in scan_region(ranges, ANGLES, np.zeros(3), range_max, cfg)])


def wall_distance(geom, walls) -> float:
    return float(min(geom.distance(LineString(w)) for w in walls))


def test_a_room_seen_from_inside_is_free_up_to_its_walls_and_says_which_edges_are_walls():
    ((ring, wall),) = scan_region(scan(ROOM), ANGLES, np.zeros(3), 30.0)
    g = Polygon(ring)
    seen = Polygon([[0, -3], [5, -3], [5, 3], [0, 3]])  # the half in front of the laser
    assert g.area == pytest.approx(seen.area, rel=0.02)
    assert g.difference(seen.buffer(CFG.tolerance_m)).area < 1e-6  # no farther than the walls
    nxt = np.roll(ring, -1, axis=0)
    on_wall = [max(LineString(w).distance(shapely.Point(p)) for p in (a, b)) < 0.05
               and any(LineString(w).distance(shapely.Point((a + b) / 2)) < 0.05 for w in ROOM)
               for a, b in zip(ring, nxt, strict=True) for w in ROOM[:1]]  # fmt: skip
    assert wall.sum() >= 3 and not wall.all()  # the three walls in front; the two beams at the sides not
    for a, b, is_wall in zip(ring, nxt, wall, strict=True):
        mid = shapely.Point((a + b) / 2)
        assert is_wall == (min(LineString(w).distance(mid) for w in ROOM) < 0.05)
    assert on_wall is not None


def test_behind_a_depth_step_nothing_is_free():
    """A short wall in front (its end a depth step): the space behind it stays out, although the
    beams on both sides of its end reach far."""
    near = np.array([[[2.0, -0.6], [2.0, 3.0]]])
    g = region(scan(np.concatenate([ROOM, near])))
    shadow = Polygon([[2.0, 0.0], [5, 0.0], [5, 3], [2.0, 3]]).intersection(
        Polygon([[0, 0], [2.0, -0.6], [10, -3.0], [10, 10], [0, 10]])  # behind the near wall's end
    )
    assert g.intersection(shadow.buffer(-0.02)).area < 0.01


def test_no_return_counts_only_so_far_and_an_unusable_reading_not_at_all():
    r = np.full(181, 30.0)  # nothing hit at all: open space, or glass
    g = region(r)
    assert g.bounds[2] <= CFG.no_return_m and 0.97 < g.area / (np.pi * CFG.no_return_m**2 / 2) < 1.0
    ((_, wall),) = scan_region(r, ANGLES, np.zeros(3), 30.0)
    assert not wall.any()  # nothing hit: no wall
    r = scan(ROOM)
    blind = r.copy()
    blind[:90] = np.nan  # half the laser blind
    assert region(blind).area < 0.6 * region(r).area
    assert scan_region(np.full(181, np.nan), ANGLES, np.zeros(3), 30.0) == []


def test_views_are_kept_by_the_area_they_add_and_forgotten_from_a_doubt():
    views = FreeSpaceViews(CFG)
    r = scan(ROOM)
    assert views.add(0, np.zeros(3), r, ANGLES, np.zeros(3), 30.0)
    assert not views.add(1, np.array([0.1, 0, 0]), r, ANGLES, np.zeros(3), 30.0)  # not moved enough
    r2 = scan(ROOM, (1.0, 0.0, 0.0))
    assert not views.add(2, np.array([1.0, 0, 0]), r2, ANGLES, np.zeros(3), 30.0)  # nothing new
    back = scan(ROOM, (1.0, 0.0, np.pi))
    assert views.add(3, np.array([1.0, 0, np.pi]), back, ANGLES, np.zeros(3), 30.0)  # the other half
    assert len(views) == 2 and views.scan == [0, 3]
    path = np.array([[0.0, 0.0, 0.0]] * 3 + [[1.2, 0.1, np.pi]])
    np.testing.assert_allclose(views.refresh(path), [[0, 0, 0], [1.2, 0.1, np.pi]])
    assert views.drop_from(3) == 1 and views.scan == [0]
    assert views.add(4, np.array([1.0, 0, np.pi]), back, ANGLES, np.zeros(3), 30.0)  # again new


@pytest.fixture(scope="module")
def office_run():
    """60 s of robot 0 in the office (10 particles), as the agent publishes it."""
    world = builtin_world("office")
    sim = LiveSim(world, 0, seed=0)
    core = AgentCore("robot1", FastSLAM(SlamConfig(particles=10), np.random.default_rng(0)), AgentConfig())
    truth, map_bytes, free = [], 0, []
    for s in sim.scans(60.0):
        truth.append(sim.truth.copy())
        core.step(s)
        if (m := core.map_messages()) is not None:
            map_bytes += sum(len(codec.encode(c)) for c in m)
        if (f := core.free_message()) is not None:
            free.append(f)
    return world, core, np.array(truth), map_bytes, free


def test_the_agent_sends_its_views_compactly_every_period(office_run):
    _, core, _, map_bytes, free = office_run
    assert [f.seq for f in free] == list(range(len(free))) and len(free) >= 5
    assert np.all(np.diff([f.stamp_s for f in free]) >= AgentConfig().free_period_s - 1e-9)
    sizes = [len(codec.encode(f)) for f in free]
    whole = core.free_whole
    assert len(codec.encode(whole)) / len(whole.view_pose) < 300  # bytes per view: a few hundred at most
    assert sum(sizes) <= 0.3 * map_bytes  # beside the map: at most 30 % more (issue 23)
    assert core.free_message() is None  # not due yet


def test_the_free_space_sent_lies_in_the_worlds_free_space(office_run):
    world, core, truth, *_ = office_run
    last = core.free_whole
    rings = view_rings(last, truth[0])  # the map frame is the start frame
    g = union(rings)
    inside = free_space(world)
    assert g.area > 60.0  # m²: what the robot saw of the office in a minute
    assert g.difference(inside.buffer(0.05)).area < 0.01 * g.area  # up to the walls, not through
    assert last.wall.mean() > 0.3  # most edges run along walls
    # each view where the robot was when it saw it (the published path: the filter's)
    err = np.hypot(*(compose(truth[0], last.view_pose)[:, :2] - truth[core.free.scan][:, :2]).T)
    assert err.max() < 0.1
    assert shapely.is_valid(g) and all(len(v) >= 3 for v in place(rings, np.zeros(3)))


def test_each_view_goes_out_once_then_only_its_pose(office_run):
    """Every message carries every view's pose but only the rings of views not sent before; put
    together in order they are the whole free space the agent holds."""
    _, core, _, _, free = office_run
    assert free[0].rings_from == 0 and all(f.rings_from > 0 for f in free[1:])
    whole = free[0]
    for f in free[1:]:
        assert set(f.ring_view.tolist()) <= set(range(f.rings_from, len(f.view_pose)))
        whole = f.merged_onto(whole)
        assert whole is not None and whole.rings_from == 0
    last = core.free_whole
    assert whole.seq == last.seq and np.array_equal(whole.ring_view, last.ring_view)
    np.testing.assert_array_equal(whole.vertices, last.vertices)
    np.testing.assert_array_equal(whole.wall, last.wall)
    assert free[-1].merged_onto(free[-3]) is None  # not the one before: refused
    sizes = [len(codec.encode(f)) for f in free]
    assert max(sizes[1:]) < len(codec.encode(last)) / 2  # increments are small
