"""Pose-graph back end: the graph (chain, loops, robust kernel), the verified scan match, jumps."""

import numpy as np
import pytest

from robot_agent.slam import backend as be
from robot_agent.slam.posegraph import ChainNoise, chain_edges, optimize
from shared.geometry import apply_points, compose, inverse, relative
from shared.scanmatch import match_covariance, window_surface


def _square(drift_rad: float) -> tuple[np.ndarray, np.ndarray]:
    u = np.array(([[0.1, 0.0, 0.0]] * 100 + [[0.0, 0.0, np.pi / 2]]) * 4)
    true, drifted = [np.zeros(3)], [np.zeros(3)]
    for d in u:
        true.append(compose(true[-1], d))
        drifted.append(compose(drifted[-1], d + np.array([0.0, 0.0, drift_rad])))
    return np.array(true), np.array(drifted)


def test_pose_graph_closes_a_drifted_square():
    true, drifted = _square(0.002)
    a, b, z, info = chain_edges(drifted, ChainNoise())
    loop_z = relative(true[0], true[-1])
    x = optimize(
        drifted,
        np.append(a, 0),
        np.append(b, len(drifted) - 1),
        np.vstack([z, loop_z]),
        np.vstack([info, [1e4, 1e4, 1e5]]),
    )
    before = np.max(np.hypot(*(drifted[:, :2] - true[:, :2]).T))
    after = np.max(np.hypot(*(x[:, :2] - true[:, :2]).T))
    assert before > 4.0
    assert after < 0.7  # the loop is closed; a uniform heading bias is only partly recovered
    np.testing.assert_allclose(relative(x[0], x[-1]), loop_z, atol=0.01)
    np.testing.assert_allclose(x[0], drifted[0])  # node 0 holds the map frame


def test_pose_graph_without_loops_keeps_the_chain():
    _, drifted = _square(0.002)
    a, b, z, info = chain_edges(drifted, ChainNoise())
    np.testing.assert_allclose(optimize(drifted, a, b, z, info), drifted, atol=1e-9)


def test_backend_optimize_drops_a_false_loop():
    true, drifted = _square(0.002)
    kf = np.arange(0, len(true), 5)
    info = np.diag([400.0, 400.0, 3283.0])  # 5 cm, 1°
    good = [be.Loop(0, len(kf) - 1, relative(true[kf[0]], true[kf[-1]]), 1.0, info, 1.0)]
    good += [be.Loop(2, len(kf) - 3, relative(true[kf[2]], true[kf[-3]]), 1.0, info, 1.0)]
    false = be.Loop(10, 50, relative(true[kf[10]], true[kf[50]]) + np.array([1.5, -0.8, 0.3]), 1.0, info, 1.0)
    stats: dict = {}
    cfg = be.BackendConfig()
    x = be.optimize(drifted[kf], [*good, false], cfg, stats)
    assert stats["loops_kept"] == 2
    honest = be.optimize(drifted[kf], good, cfg, {})
    np.testing.assert_allclose(x, honest, atol=1e-3)  # the false loop left no trace
    assert np.max(np.hypot(*(x[:, :2] - true[kf, :2]).T)) < 0.7


def test_a_warm_start_with_agreeing_loops_needs_only_the_narrow_kernel():
    """An online update: the last solution, and a new loop that agrees with it. The narrow kernel
    alone from there lands where the whole wide-to-narrow schedule does."""
    true, drifted = _square(0.002)
    kf = np.arange(0, len(true), 5)
    info = np.diag([400.0, 400.0, 3283.0])
    loops = [be.Loop(0, len(kf) - 1, relative(true[kf[0]], true[kf[-1]]), 1.0, info, 1.0)]
    cfg = be.BackendConfig()
    last = be.optimize(drifted[kf], loops, cfg, {})
    loops.append(
        be.Loop(2, len(kf) - 3, relative(last[2], last[-3]) + np.array([0.02, -0.01, 0.005]), 1.0, info, 1.0)
    )
    cold = be.optimize(drifted[kf], loops, cfg, {}, x0=last)
    warm = be.optimize(drifted[kf], loops, cfg, {}, x0=last, warm=True)
    assert np.max(np.abs(warm - last)) > 0.005  # the new loop moved it
    np.testing.assert_allclose(warm, cold, atol=2e-3)


def test_an_optimization_past_its_deadline_returns_what_it_has():
    true, drifted = _square(0.002)
    a, b, z, info = chain_edges(drifted, ChainNoise())
    args = (drifted, np.append(a, 0), np.append(b, len(drifted) - 1))
    args += (np.vstack([z, relative(true[0], true[-1])]), np.vstack([info, [1e4, 1e4, 1e5]]))
    one = optimize(*args, iterations=1)
    np.testing.assert_allclose(optimize(*args, stop=lambda: True), one)  # one iteration, then stop
    assert np.max(np.abs(optimize(*args) - one)) > 1e-4  # (the full run goes further)
    kf = np.arange(0, len(true), 5)
    loops = [
        be.Loop(
            0, len(kf) - 1, relative(true[kf[0]], true[kf[-1]]), 1.0, np.diag([400.0, 400.0, 3283.0]), 1.0
        )
    ]
    stats: dict = {}
    be.optimize(drifted[kf], loops, be.BackendConfig(), stats, stop=lambda: True)
    assert stats["optimize_cut"] == 1


def _room_points(pose: np.ndarray, rng: np.random.Generator, walls: np.ndarray) -> np.ndarray:
    """Points on ``walls (W,2,2)`` seen from ``pose`` (no occlusion), in the robot frame."""
    pts = []
    for p, q in walls:
        n = int(np.hypot(*(q - p)) / 0.05)
        t = rng.uniform(0, 1, n)[:, None]
        pts.append(p + t * (q - p))
    world = np.vstack(pts) + rng.normal(0, 0.01, (sum(len(p) for p in pts), 2))
    return apply_points(inverse(pose), world)


ROOM = np.array(
    [
        [[0, 0], [6, 0]],
        [[6, 0], [6, 4]],
        [[6, 4], [0, 4]],
        [[0, 4], [0, 0]],
        [[2, 2], [3.5, 2]],
        [[3.5, 2], [3.5, 3]],
    ],
    float,
)
CORRIDOR = np.array([[[-20, 0], [20, 0]], [[-20, 2], [20, 2]]], float)


def _match(walls: np.ndarray, error: np.ndarray):
    rng = np.random.default_rng(1)
    true = np.array([[1.0, 1.0, 0.1], [4.5, 1.2, 2.0]])
    est = true.copy()
    est[1] = compose(true[1], error)  # the estimate of the new keyframe is off by ``error``
    points = [_room_points(p, rng, walls) for p in true]
    stats: dict = {}
    loop = be.match_loop(est, points, 0, 1, be.BackendConfig(cloud_neighbours=0, query_neighbours=0), stats)
    return loop, relative(true[0], true[1]), stats


def test_match_loop_finds_a_known_offset():
    loop, z_true, _ = _match(ROOM, np.array([0.35, -0.25, np.radians(5.0)]))
    assert loop is not None
    assert np.hypot(*(loop.z[:2] - z_true[:2])) < 0.02
    assert abs(loop.z[2] - z_true[2]) < np.radians(0.5)


def test_a_featureless_corridor_constrains_only_across_it():
    """In a corridor every shift along it scores alike: the loop says where the robot is across
    the corridor and how it is turned, and nothing about where along it (its information there
    is next to none, not a false certainty)."""
    loop, z_true, stats = _match(CORRIDOR, np.array([0.3, 0.12, np.radians(4.0)]))
    assert loop is not None and stats.get("ambiguous", 0) == 0
    cov = np.linalg.inv(loop.info)
    along = np.array([np.cos(-0.1), np.sin(-0.1)])  # the corridor's direction in keyframe 0's frame
    across = np.array([-along[1], along[0]])
    assert np.sqrt(along @ cov[:2, :2] @ along) > 2.0
    assert np.sqrt(across @ cov[:2, :2] @ across) < 0.08 and np.sqrt(cov[2, 2]) < np.radians(1.5)
    assert abs(across @ (loop.z[:2] - z_true[:2])) < 0.03 and abs(loop.z[2] - z_true[2]) < np.radians(0.5)


def _surface(peaks):
    """A score surface over the default window: ``peaks`` of (x, y, θ, height, width_x, width_y)."""
    cfg = be.BackendConfig()
    n_xy = round(cfg.search_xy_m / cfg.search_step_m)
    n_th = round(cfg.search_theta_rad / cfg.search_step_rad)
    angles = cfg.search_step_rad * np.arange(-n_th, n_th + 1)
    o = cfg.search_step_m * np.arange(-n_xy, n_xy + 1)
    offs = np.array([(x, y) for x in o for y in o])
    scores = np.zeros((len(angles), len(offs)))
    for x, y, th, h, wx, wy in peaks:
        g = np.exp(-0.5 * (((offs[:, 0] - x) / wx) ** 2 + ((offs[:, 1] - y) / wy) ** 2))
        scores = np.maximum(scores, h * g[None, :] * np.exp(-0.5 * ((angles - th) / 0.02) ** 2)[:, None])
    _, d, edge = window_surface(scores, angles, offs, cfg.search_xy_m, cfg.search_theta_rad)
    floor = np.array([cfg.loop_sigma_xy_m**2] * 2 + [cfg.loop_sigma_theta_rad**2])
    return match_covariance(d, scores.ravel(), scores.max(), edge, floor, cfg.surface)


def test_match_covariance_of_a_sharp_peak_a_ridge_and_two_places():
    sharp = _surface([(0.1, -0.2, 0.0, 0.9, 0.05, 0.05)])
    assert sharp is not None and np.sqrt(sharp[0, 0]) < 0.08 and np.sqrt(sharp[2, 2]) < np.radians(1.5)
    ridge = _surface([(0.0, 0.0, 0.0, 0.9, 10.0, 0.05)])  # alike all along x, to the window's edges
    assert ridge is not None and np.sqrt(ridge[0, 0]) >= 4.9 and np.sqrt(ridge[1, 1]) < 0.08
    # two places 0.9 m apart along y that fit alike: x and the heading are still known, y is not
    apart = _surface([(0.0, -0.4, 0.0, 0.9, 0.05, 0.05), (0.0, 0.5, 0.0, 0.88, 0.05, 0.05)])
    assert apart is not None and np.sqrt(apart[1, 1]) > 0.4 and np.sqrt(apart[0, 0]) < 0.08
    # three that do not lie on a line, or two headings: nothing is known — refused
    assert _surface([(0.0, -0.4, 0.0, 0.9, 0.05, 0.05), (0.5, 0.4, 0.0, 0.88, 0.05, 0.05),
                     (-0.5, 0.4, 0.0, 0.88, 0.05, 0.05)]) is None  # fmt: skip
    assert _surface([(0.0, 0.0, -0.1, 0.9, 0.05, 0.05), (0.0, 0.0, 0.1, 0.9, 0.05, 0.05)]) is None
    near = _surface([(0.0, 0.0, 0.0, 0.9, 0.05, 0.05), (0.0, 0.5, 0.0, 0.6, 0.05, 0.05)])
    assert near is not None  # a far weaker second peak costs nothing


def test_a_jump_starts_a_keyframe():
    odo = np.column_stack([np.arange(50) * 0.05, np.zeros(50), np.zeros(50)])
    poses = odo.copy()
    poses[33:, 1] += 0.02  # a relocalization moved the filter by 2 cm at scan 33: no motion keyframe
    jumps = np.arange(50) == 33
    cfg = be.BackendConfig()
    assert 33 not in be.select_keyframes(poses, cfg)
    assert 33 in be.select_keyframes(poses, cfg, jumps)


def test_a_jump_without_loops_is_bridged_by_odometry():
    odo = np.column_stack([np.arange(50) * 0.05, np.zeros(50), np.zeros(50)])
    poses = odo.copy()
    poses[30:, 1] += 1.0
    points = lambda i: np.zeros((0, 2))  # noqa: E731 — no scan: no loop can be found
    jumps = np.arange(50) == 30  # the filter says where it jumped (FastSLAM.best_jumps)
    out, stats = be.run_backend(np.arange(50.0), poses, odo, points, be.BackendConfig(), jumps=jumps)
    assert stats["jumps"] == 1 and stats["loops"] == 0
    np.testing.assert_allclose(relative(out[29], out[30]), relative(odo[29], odo[30]), atol=1e-6)


def test_odometry_that_disagrees_with_the_path_is_no_jump():
    """MIT-CSAIL's odometry turns 30° in a step where the robot turned 17°: a path that
    follows the scans is not a relocalization, and its chain edges keep the path's motion."""
    odo = np.column_stack([np.arange(50) * 0.05, np.zeros(50), np.zeros(50)])
    odo[30:, 2] += np.radians(13.0)  # a spike the scans did not see
    poses = np.column_stack([np.arange(50) * 0.05, np.zeros(50), np.zeros(50)])
    points = lambda i: np.zeros((0, 2))  # noqa: E731
    out, stats = be.run_backend(np.arange(50.0), poses, odo, points, be.BackendConfig())
    assert stats["jumps"] == 0
    np.testing.assert_allclose(out, poses, atol=1e-9)


def test_a_relocalization_hint_finds_a_loop_beyond_the_search_window():
    rng = np.random.default_rng(2)
    true = np.array([[1.0, 1.0, 0.1], [2.5, 1.5, 2.0]])
    path = true.copy()
    path[1] = compose(true[1], np.array([1.5, -1.2, np.radians(12.0)]))  # drifted far beyond the window
    points = [_room_points(p, rng, ROOM) for p in true]
    cfg = be.BackendConfig(cloud_neighbours=0, query_neighbours=0, min_gap_keyframes=1)
    z_true = relative(true[0], true[1])
    stamps = np.array([0.0, 100.0])
    plain = be.match_loop(path, points, 0, 1, cfg, {})
    assert plain is None or np.hypot(*(plain.z[:2] - z_true[:2])) > 0.5  # the window misses it
    hint = compose(true[1], np.array([0.1, -0.05, np.radians(1.5)]))  # the filter's hypothesis
    stats: dict = {}
    loops = be.hinted_loops(stamps, path, points, np.array([0, 1]), path, [(1, hint)], cfg, stats)
    assert stats["loops_hinted"] == 1 and (loops[0].old, loops[0].new) == (0, 1)
    assert np.hypot(*(loops[0].z[:2] - z_true[:2])) < 0.02
    assert abs(loops[0].z[2] - z_true[2]) < np.radians(0.5)
    wrong = compose(true[1], np.array([0.0, 1.5, 0.0]))  # a hint the scans do not support
    assert be.hinted_loops(stamps, path, points, np.array([0, 1]), path, [(1, wrong)], cfg, {}) == []


def test_the_first_pass_searches_as_wide_as_the_path_may_have_drifted():
    """The simulated office round (100 m) along a path drifted 0.2°/m and 2 % long — where it
    comes back it is 1.5 m and 20° off: the search window around the path (0.8 m, 8°) finds no
    loop at all, the window widened by the drift the path may hold (branch and bound) closes it."""
    from shared.metrics import ate
    from tests.rooms import drifted_office

    sim, log, drifted, points = drifted_office(200.0)
    truth = sim.truth

    def corrected(cfg):
        out, stats = be.run_backend(log.stamps_s, drifted, log.odometry, points, cfg)
        return ate(log.stamps_s, out, sim.stamps_s, truth).rmse_m, stats["loops"]

    before = ate(log.stamps_s, drifted, sim.stamps_s, truth).rmse_m
    narrow, narrow_loops = corrected(be.BackendConfig(drift_xy_per_m=0.0, drift_theta_rad_per_m=0.0))
    wide, wide_loops = corrected(be.BackendConfig())
    assert before > 0.8 and narrow_loops == 0 and narrow == pytest.approx(before)  # measured 0.89
    assert wide_loops >= 20 and wide < 0.3  # measured 40 loops, 0.19 m


@pytest.fixture(scope="module")
def office_keyframes():
    """Robot 0's first 40 s in the simulated office: its keyframes' true poses in its start frame
    (``(K,3)``, the first at the origin) and their thinned scan points (robot frame)."""
    from robot_agent.backend import scan_points_robot
    from robot_agent.sim import SimConfig, builtin_world, simulate_robot
    from robot_agent.slam.fastslam import SlamConfig
    from shared.scanmatch import voxel_thin

    sim = simulate_robot(builtin_world("office"), 0, 40.0, 0, SimConfig())
    log, cfg = sim.to_log(), SlamConfig()
    kf = be.select_keyframes(sim.truth, cfg.backend)
    x = relative(sim.truth[kf[0]], sim.truth[kf])
    return x, [voxel_thin(scan_points_robot(log, int(i), cfg), cfg.backend.voxel_m) for i in kf]


def test_the_first_keyframes_own_scan_gauges_a_map_turned_against_it(office_keyframes):
    x, points = office_keyframes
    cfg = be.BackendConfig()
    # a map right about its first keyframe: the gauge leaves it where it is
    at = be.start_gauge(x, points, cfg)
    assert at is not None
    assert np.hypot(at[0], at[1]) < 0.005 and abs(np.degrees(at[2])) < 0.02  # measured 3.4 mm, 0.014°
    # every keyframe but the first turned 0.3° about it and shifted 2 cm (the filter's heading
    # drifted in the first keyframes): the first scan says where the start is on that map
    turn = np.array([0.02, -0.01, np.radians(0.3)])
    turned = np.vstack([x[:1], compose(turn, x[1:])])
    at = be.start_gauge(turned, points, cfg)
    assert at is not None
    e = relative(turn, at)  # (where the turned map puts the start)
    assert np.hypot(e[0], e[1]) < 0.012 and abs(np.degrees(e[2])) < 0.01  # measured 8.6 mm, 0.002°
    gauge = compose(turned[0], inverse(at))  # the map moved by it comes back to the truth
    back = compose(gauge, turned[1:])
    assert np.max(np.hypot(*(back[:, :2] - x[1:, :2]).T)) < 0.012
    assert np.max(np.abs(np.degrees(back[:, 2] - x[1:, 2]))) < 0.01
    # a start the map does not hold (its scan 2 m off and half turned): none
    far = np.vstack([compose(np.array([2.0, 0.0, np.pi]), x[:1]), x[1:]])
    assert be.start_gauge(far, points, cfg) is None
    # turned beyond what the gauge takes: none
    big = np.vstack([x[:1], compose(np.array([0.0, 0.0, np.radians(3.0)]), x[1:])])
    assert be.start_gauge(big, points, cfg) is None
