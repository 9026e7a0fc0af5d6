"""Exploration controller: kernels on hand-made cases, the controller on small scenes, and one
seeded closed loop in the office driven only by the filter's estimate and map."""

from __future__ import annotations

import numpy as np
import pytest
import shapely
from shapely.geometry import box

from robot_agent.explore import (
    ExploreConfig,
    ExploreInputError,
    Explorer,
    clearance_grid,
    frontier_mask,
    ray_lengths,
    safe_command,
    shortest_paths,
)
from robot_agent.sim.lidar import LidarConfig, beam_angles, cast_rays
from robot_agent.sim.simulate import LiveSim
from robot_agent.sim.world import free_space, make_world
from robot_agent.sim.worlds import builtin_world
from robot_agent.slam.fastslam import FastSLAM, SlamConfig
from shared.geometry import point_segment_distance

CFG = ExploreConfig()
LIDAR = LidarConfig()
ANGLES = beam_angles(LIDAR)


def scan(pose, walls) -> np.ndarray:
    """Noise-free ranges (B,) of the default lidar at ``pose`` (laser at the robot centre)."""
    return cast_rays(pose[None, :2], pose[2] + ANGLES[None], np.asarray(walls, float), LIDAR.range_max_m)[0]


def rectangle(x0, y0, x1, y1) -> np.ndarray:
    c = np.array([(x0, y0), (x1, y0), (x1, y1), (x0, y1)], float)
    return np.stack([c, np.roll(c, -1, axis=0)], axis=1)


def command(ex, stamp_s, pose, map_walls, scan_walls=None):
    pose = np.asarray(pose, float)
    ranges = scan(pose, map_walls if scan_walls is None else scan_walls)
    return ex.command(stamp_s, pose, map_walls, ranges, ANGLES, np.zeros(3), LIDAR.range_max_m)


# --- kernels ------------------------------------------------------------------------------------


def test_clearance_error_bounds_and_blocking_hold_for_random_walls():
    rng = np.random.default_rng(3)
    seg = rng.uniform(0.5, 9.5, size=(12, 2, 2))
    cell = CFG.cell_m
    clear = clearance_grid(seg, np.zeros(2), (40, 40), cell)
    ii, jj = np.mgrid[:40, :40]
    centres = (np.stack([ii, jj], -1) + 0.5) * cell
    exact = point_segment_distance(centres[:, :, None, :], seg).min(axis=-1)
    err = clear - exact
    assert err.max() <= (np.sqrt(2) / 2 - 0.5 + 0.125) * cell + 1e-9  # documented bounds
    assert err.min() >= -(np.sqrt(2) / 2 + 0.5) * cell - 1e-9
    blocked = clear < CFG.robot_radius_m + CFG.block_margin_m
    assert np.all(blocked[exact < CFG.robot_radius_m])  # never plan through the robot's footprint
    assert not np.any(blocked[exact > 0.65])
    assert np.all(np.isinf(clearance_grid(np.zeros((0, 2, 2)), np.zeros(2), (5, 5), cell)))


def test_cells_next_to_a_wall_are_blocked_and_cells_a_metre_off_are_free():
    wall = np.array([[[2.0, 5.0], [8.0, 5.0]]])
    clear = clearance_grid(wall, np.zeros(2), (40, 40), 0.25)
    blocked = clear < CFG.robot_radius_m + CFG.block_margin_m
    # column x = 5.125 m: rows at y = 4.875 and 5.125 touch the wall, 4.0 and 6.0 are 1 m off
    col = int(5.125 / 0.25)
    assert blocked[col, int(4.875 / 0.25)] and blocked[col, int(5.125 / 0.25)]
    assert not blocked[col, int(4.125 / 0.25)] and not blocked[col, int(6.125 / 0.25)]
    # beyond the wall's end, the blocked band stops within a cell of radius + margin
    assert not blocked[int(8.625 / 0.25), int(5.125 / 0.25)]


def test_ray_lengths_hand_cases():
    seg = np.array([[[2.0, -1.0], [2.0, 1.0]]])
    dirs = np.array([0.0, np.pi, np.pi / 2, np.arctan2(0.5, 2.0)])
    got = ray_lengths(np.zeros(2), dirs, seg, np.full(4, 5.0))
    np.testing.assert_allclose(got, [2.0, 5.0, 5.0, np.hypot(2.0, 0.5)])
    np.testing.assert_allclose(ray_lengths(np.zeros(2), dirs, seg, np.full(4, 1.5)), 1.5)


def test_frontier_is_the_seen_free_border_towards_unseen_free_cells():
    seen = np.zeros((10, 10), bool)
    seen[:5] = True
    blocked = np.zeros((10, 10), bool)
    blocked[:, 7:] = True  # a wall band: unseen but not "unknown free"
    front = frontier_mask(seen, blocked, min_cells=1)
    expected = np.zeros((10, 10), bool)
    expected[4, :7] = True
    np.testing.assert_array_equal(front, expected)
    lone = np.zeros((10, 10), bool)
    lone[5, 5] = True  # one seen cell: a frontier speck, dropped by the cluster size
    assert frontier_mask(lone, np.zeros_like(lone), 1)[5, 5]
    assert not frontier_mask(lone, np.zeros_like(lone), 3).any()


def test_planner_goes_round_a_wall_through_its_gap():
    cell = 0.25
    wall = np.array([[[5.0, 0.0], [5.0, 7.5]]])  # 10 m × 10 m area, gap above y = 7.5
    clear = clearance_grid(wall, np.zeros(2), (40, 40), cell)
    free = clear >= CFG.robot_radius_m + CFG.block_margin_m
    dist, pred = shortest_paths(np.ones((40, 40)), free, (8, 8))  # from (2.125, 2.125)
    goal = (32, 8)  # (8.125, 2.125): 6 m away in a straight line, through the wall
    assert np.isfinite(dist[goal])
    cells = [np.ravel_multi_index(goal, (40, 40))]
    while pred.flat[cells[-1]] >= 0:
        cells.append(pred.flat[cells[-1]])
    xy = (np.stack(np.unravel_index(cells[::-1], (40, 40)), -1) + 0.5) * cell
    np.testing.assert_allclose(xy[0], [2.125, 2.125])
    length = np.sum(np.hypot(*np.diff(xy, axis=0).T))
    assert xy[:, 1].max() > 7.5 + CFG.robot_radius_m  # over the wall's end
    assert length > 2 * np.hypot(3.0, 5.6) - 0.5 and dist[goal] * cell == pytest.approx(length)
    assert point_segment_distance(xy[:, None], wall).min() >= CFG.robot_radius_m
    # a wall without a gap: unreachable
    closed = clearance_grid(np.array([[[5.0, -1.0], [5.0, 11.0]]]), np.zeros(2), (40, 40), cell)
    dist2, _ = shortest_paths(np.ones((40, 40)), closed >= 0.3, (8, 8))
    assert np.isinf(dist2[goal]) and np.isfinite(dist2[12, 30])


def test_safety_stops_before_a_close_wall_and_lets_a_far_one_be():
    wall = np.array([[[0.4, -2.0], [0.4, 2.0]]])  # robot frame: 0.4 m ahead
    v, w, refused = safe_command(0.6, 0.0, 0.1, np.zeros((0, 2)), wall, CFG)
    assert v == 0.0 and refused
    far = wall + np.array([2.6, 0.0])
    assert safe_command(0.6, 0.0, 0.1, np.zeros((0, 2)), far, CFG) == (0.6, 0.0, False)
    # scan points instead of segments; moving at full speed, no stop in 0.6 m is possible:
    # the command that keeps the most clearance is a turn, not straight on
    pts = np.c_[np.full(41, 0.6), np.linspace(-2, 2, 41)]
    v, w, refused = safe_command(0.6, 0.0, 0.6, pts, np.zeros((0, 2, 2)), CFG)
    assert refused and v == 0.0 and abs(w) == CFG.max_w_radps
    # already too close, but driving away from the wall is allowed
    behind = np.array([[[-0.25, -2.0], [-0.25, 2.0]]])
    assert safe_command(0.3, 0.0, 0.0, np.zeros((0, 2)), behind, CFG)[0] == 0.3


# --- the controller on small scenes ---------------------------------------------------------------


def test_in_an_open_room_the_nearest_frontier_is_behind_so_it_turns_first():
    room = rectangle(0, 0, 8, 8)
    ex = Explorer()
    v, w = command(ex, 0.0, [4.0, 4.0, 0.0], room)
    assert ex.mode == "frontier" and ex.frontier.any()
    # nearest frontier: on the border of the unseen half (x < 4), not ahead in the seen one
    assert ex.goal[0] <= 4.0 + CFG.cell_m
    bearing = np.arctan2(ex.goal[1] - 4.0, ex.goal[0] - 4.0)
    assert abs(bearing) > 1.2
    assert v == 0.0 and abs(w) > 0.5 and np.sign(w) == np.sign(bearing)  # turn in place towards it
    fx = ex.centre_of(np.argwhere(ex.frontier))
    assert np.all(point_segment_distance(fx[:, None], room).min(axis=1) >= 0.3)  # none in a wall


def corridor():
    walls = np.array([[[-0.5, -1.0], [20.0, -1.0]], [[-0.5, 1.0], [20.0, 1.0]], [[-0.5, -1.0], [-0.5, 1.0]]])
    box_ahead = rectangle(0.4, -0.9, 0.6, 0.9)  # unmapped, seen by the scan only
    return walls, box_ahead


def test_drives_down_a_corridor_but_stops_and_turns_for_an_unmapped_obstacle_in_the_scan():
    walls, box_ahead = corridor()
    clear, blocked = Explorer(), Explorer()
    for ex in (clear, blocked):
        v, _ = command(ex, 0.0, [0.0, 0.0, 0.0], walls)
        assert v > 0.0 and ex.goal[0] > 1.0  # the frontier ahead, down the corridor
    v, w = command(clear, 0.2, [0.0, 0.0, 0.0], walls)
    assert v > 0.3 and clear.stats["safety_stops"] == 0
    v, w = command(blocked, 0.2, [0.0, 0.0, 0.0], walls, np.concatenate([walls, box_ahead]))
    assert v == 0.0 and abs(w) > 0.0 and blocked.stats["safety_stops"] == 1
    assert blocked.memory_s[tuple(blocked.cell_of([0.4, 0.0]))] > 0.2  # remembered for planning


def test_grid_grows_with_the_map_and_keeps_what_was_seen():
    ex = Explorer()
    command(ex, 0.0, [0.0, 0.0, 0.0], np.zeros((0, 2, 2)))
    assert ex.seen[tuple(ex.cell_of([2.0, 0.0]))] and not ex.seen[tuple(ex.cell_of([-2.0, 0.0]))]
    origin, shape = ex.origin.copy(), ex.seen.shape
    command(ex, 0.2, [0.0, 0.0, 0.0], np.array([[[30.0, -2.0], [30.0, 2.0]]]))
    assert ex.seen.shape[0] > shape[0] and np.all(ex.origin <= origin)
    assert ex.seen[tuple(ex.cell_of([2.0, 0.0]))] and not ex.seen[tuple(ex.cell_of([-2.0, 0.0]))]
    assert ex.seen.sum() >= 1


@pytest.mark.parametrize(
    ("field", "value", "needle"),
    [
        ("pose", np.zeros(2), "pose: expected shape (3)"),
        ("pose", np.array([0.0, np.nan, 0.0]), "pose: contains non-finite"),
        ("map_segments", np.zeros((4, 2)), "map_segments: expected shape (N, 2, 2)"),
        ("map_segments", np.full((1, 2, 2), np.inf), "map_segments: contains non-finite"),
        ("ranges_m", np.zeros((2, 181)), "ranges_m: expected shape (N)"),
        ("angles_rad", np.zeros(180), "angles_rad: expected shape (181)"),
        ("laser_offset", np.zeros(4), "laser_offset: expected shape (3)"),
        ("stamp_s", np.nan, "stamp_s: contains non-finite"),
    ],
)
def test_bad_inputs_name_the_field(field, value, needle):
    args = {
        "stamp_s": 0.0,
        "pose": np.zeros(3),
        "map_segments": np.zeros((0, 2, 2)),
        "ranges_m": np.full(181, 5.0),
        "angles_rad": ANGLES,
        "laser_offset": np.zeros(3),
    }
    args[field] = value
    with pytest.raises(ExploreInputError, match=needle.replace("(", r"\(").replace(")", r"\)")):
        Explorer().command(**args)
    assert issubclass(ExploreInputError, ValueError)


def test_config_rejects_bad_values():
    with pytest.raises(ValueError, match="cell_m"):
        ExploreConfig(cell_m=0.0)
    with pytest.raises(ValueError, match="grid_chunk_m"):
        ExploreConfig(cell_m=0.3, grid_chunk_m=1.0)


def test_when_nothing_is_left_to_explore_it_keeps_revisiting():
    # a 5 m × 4 m room, perfect pose and map: the frontier runs out, and the robot keeps moving
    world = make_world("room", [box(0, 0, 5, 4).exterior.buffer(0.05)], routes=[[(1.0, 2.0), (4.0, 2.0)]])
    sim = LiveSim(world, 0, seed=0)
    ex = Explorer()
    modes, xy = [], []
    for _ in range(int(80 * LIDAR.rate_hz)):
        s = sim.scan()
        v, w = ex.command(s.stamp_s, sim.truth, world.walls, s.ranges_m, s.angles_rad, s.laser_offset, 30.0)
        sim.set_velocity(v, w)
        for _ in range(sim.cfg.steps_per_scan):
            sim.step()
            assert not sim.bumped
        modes.append(ex.mode)
        xy.append(sim.truth[:2])
    first = modes.index("revisit")  # measured: 3 s in (one look round the small room)
    assert first < 20 * LIDAR.rate_hz
    after = np.array(xy[first:])
    assert np.sum(np.hypot(*np.diff(after, axis=0).T)) > 10.0  # drives on: measured 27 m in 77 s
    assert np.ptp(after, axis=0).max() > 1.5  # and goes places (measured 3.0 m), not circles on the spot


# --- closed loop ----------------------------------------------------------------------------------


def sensor_coverage(world, truth, ranges, radius_m=3.0, spacing_m=0.5) -> float:
    """Share of free-space sample points that a TRUE beam reached within ``radius_m``: per scan,
    a point counts when it is in the field of view, within the radius and not behind the beam's
    measured range."""
    fs = free_space(world)
    b = world.bounds
    gx, gy = np.meshgrid(np.arange(b[0], b[2], spacing_m) + spacing_m / 2, np.arange(b[1], b[3], spacing_m))
    pts = np.c_[gx.ravel(), gy.ravel() + spacing_m / 2]
    pts = pts[shapely.contains_xy(fs, pts[:, 0], pts[:, 1])]
    seen = np.zeros(len(pts), bool)
    step = ANGLES[1] - ANGLES[0]
    for pose, r in zip(truth, ranges, strict=True):
        d = pts - pose[:2]
        dist = np.hypot(d[:, 0], d[:, 1])
        bearing = (np.arctan2(d[:, 1], d[:, 0]) - pose[2] + np.pi) % (2 * np.pi) - np.pi
        beam = np.round((bearing - ANGLES[0]) / step).astype(int)
        look = np.flatnonzero((beam >= 0) & (beam < len(ANGLES)) & (dist <= radius_m))
        seen[look[r[beam[look]] >= dist[look]]] = True
    return float(seen.mean())


@pytest.mark.slow
def test_closed_loop_office_explores_from_the_filter_estimate_without_bumping():
    """LiveSim driven only by the Explorer, fed by FastSLAM's pose and global map (never the truth);
    the truth is used here only to score. Measured (seed 0, 300 s, filter as of 7078964): coverage
    0.67, 0 bump steps, ~115 m driven, 14 s wall on a 2-core machine."""
    world = builtin_world("office")
    sim = LiveSim(world, 0, seed=0)
    slam = FastSLAM(SlamConfig(particles=10), np.random.default_rng(0))
    ex = Explorer()
    truth, ranges, bumps = [], [], 0
    for _ in range(int(300 * LIDAR.rate_hz)):
        s = sim.scan()
        est = slam.step(s.stamp_s, s.odometry, s.ranges_m, s.angles_rad, s.laser_offset, s.range_max_m)
        gm, _ = slam.published_map()  # rebuilt now: FastSLAM.global_map lags by consensus.every steps
        v, w = ex.command(
            s.stamp_s, est.pose, gm.seg, s.ranges_m, s.angles_rad, s.laser_offset, s.range_max_m
        )
        sim.set_velocity(v, w)
        truth.append(sim.truth)
        ranges.append(s.ranges_m)
        for _ in range(sim.cfg.steps_per_scan):
            sim.step()
            bumps += sim.bumped
    truth = np.array(truth)
    assert bumps == 0
    driven = np.sum(np.hypot(*np.diff(truth[:, :2], axis=0).T))
    assert driven > 70.0  # measured ~115 m
    coverage = sensor_coverage(world, truth, np.array(ranges))
    # measured 0.67 (seeds 1, 2: 0.73, 0.70; with the filter's uncommitted point proposal 0.70-0.72);
    # spinning in place scores 0.03, and patrolling robot 0's route for the same 300 s scores 0.43
    assert coverage > 0.55
    assert ex.stats["replans"] > 100
