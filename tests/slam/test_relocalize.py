"""Relocalization at loop closure (report §6): hypotheses from the global map, particle injection."""

import numpy as np
import pytest

from robot_agent.sim.lidar import cast_rays
from robot_agent.slam.consensus import GlobalMap
from robot_agent.slam.extraction import extract_segments
from robot_agent.slam.lines import fit_lines, moments_of
from robot_agent.slam.particles import ParticleSet
from robot_agent.slam.relocalize import (
    Pending,
    Relocalization,
    RelocalizationConfig,
    ScanRays,
    confirm,
    inject,
    relocalize,
    through_counts,
)
from shared.geometry import apply_points, compose, inverse, wrap_angle
from tests.rooms import ANGLES, L_FACING, L_ROOM, TRUE_POSE

STEP = 300  # a multiple of RelocalizationConfig.every
LOG_WEIGHTS = np.log([0.1, 0.05, 0.4, 0.02, 0.08, 0.35])  # best: 2; weakest others: 3, then 1
BEST = 2


def global_map(born=0, hits=10, trust=0.9, walls=L_ROOM, facing=L_FACING):
    """An old, reliable global map of the room (one column per wall)."""
    g = len(walls)
    moments = np.array([moments_of(np.linspace(a, b, 41)) for a, b in walls])
    alpha, rho, _ = fit_lines(moments)
    full = np.ones(g)
    return GlobalMap(
        step=STEP,
        cols=np.arange(g),
        seg=np.array(walls, float),
        alpha=alpha,
        rho=rho,
        facing=np.array(facing, float),
        moments=moments,
        hits=np.full(g, hits),
        born=np.full(g, born),
        last_seen=np.full(g, born),
        trust=full * trust,
        support=full,
        source=np.zeros(g, int),
    )


def scan_at(pose, noise_m=0.01, seed=0):
    ranges = cast_rays(pose[None, :2], (pose[2] + ANGLES)[None], L_ROOM, 30.0)[0]
    ranges = ranges + np.random.default_rng(seed).normal(0.0, noise_m, ranges.shape)
    segs = extract_segments(ranges, ANGLES)  # laser = robot frame
    return segs, wrap_angle(segs.alpha + np.pi)


def particles(best_pose):
    """Six particles with distinct maps, slips and poses; the best one at ``best_pose``."""
    rng = np.random.default_rng(4)
    ps = ParticleSet.create(6)
    ps.poses = best_pose + rng.normal(0.0, [0.2, 0.2, 0.05], (6, 3))
    ps.poses[BEST] = best_pose
    ps.log_weights = LOG_WEIGHTS.copy()
    ps.slip = rng.normal(0.0, 0.01, (6, 2))
    ps.slip_cov = np.einsum("p,ij->pij", rng.uniform(1e-5, 1e-4, 6), np.eye(2))
    m = ps.maps
    m.valid[:, :8] = rng.random((6, 8)) < 0.7
    m.seg[:, :8] = rng.normal(size=(6, 8, 2, 2))
    m.rho[:, :8] = rng.random((6, 8))
    m.hits[:, :8] = rng.integers(1, 20, (6, 8))
    return ps


# 0.8 m and 8° off the truth
OFF_POSE = TRUE_POSE + np.array([0.8 * np.cos(2.0), 0.8 * np.sin(2.0), np.radians(8.0)])


def test_relocalize_finds_the_true_pose_when_the_best_particle_is_off():
    segs, facing = scan_at(TRUE_POSE)
    cfg = RelocalizationConfig()
    res = relocalize(particles(OFF_POSE), global_map(), segs, facing, STEP, cfg)
    assert res is not None
    assert 1 <= len(res.poses) <= cfg.inject and res.poses.shape[1] == 3
    best = res.poses[0]
    assert np.hypot(*(best[:2] - TRUE_POSE[:2])) < 0.05
    assert abs(wrap_angle(best[2] - TRUE_POSE[2])) < np.radians(1.0)
    # it explains clearly more of the scan than the current estimate, and is listed best first
    assert res.scores[0] >= cfg.min_score_m
    assert res.scores[0] >= res.current_score + cfg.score_gain_m
    assert np.all(np.diff(res.scores) <= 0)
    assert res.scores[0] > 0.9 * segs.lengths_m.sum()


def test_no_relocalization_when_the_estimate_is_already_right():
    segs, facing = scan_at(TRUE_POSE)
    assert relocalize(particles(TRUE_POSE), global_map(), segs, facing, STEP, RelocalizationConfig()) is None


def test_no_relocalization_among_young_or_unreliable_elements_or_off_schedule():
    segs, facing = scan_at(TRUE_POSE)
    cfg = RelocalizationConfig()
    ps = particles(OFF_POSE)
    assert relocalize(ps, global_map(born=STEP - 50), segs, facing, STEP, cfg) is None  # not a revisit
    assert relocalize(ps, global_map(hits=2), segs, facing, STEP, cfg) is None  # too few updates
    assert relocalize(ps, global_map(trust=0.1), segs, facing, STEP, cfg) is None
    assert relocalize(ps, global_map(), segs, facing, STEP + 1, cfg) is None  # every 5 steps
    assert relocalize(ps, global_map(), segs, facing, STEP, cfg) is not None  # the control


def test_no_relocalization_beyond_the_plausible_jump():
    segs, facing = scan_at(TRUE_POSE)
    cfg = RelocalizationConfig(max_jump_m=0.5)  # the truth is 0.8 m away
    assert relocalize(particles(OFF_POSE), global_map(), segs, facing, STEP, cfg) is None


def test_inject_replaces_the_weakest_particles_with_the_best_ones_map_and_weight():
    ps = particles(OFF_POSE)
    before = ps.take(np.arange(6))
    hyp = np.array([TRUE_POSE, compose(TRUE_POSE, [0.3, 0.0, 0.1])])
    targets, sources = inject(ps, Relocalization(hyp, np.array([20.0, 15.0]), 3.0))
    np.testing.assert_array_equal(targets, [3, 1])  # the two lightest, the best one never
    np.testing.assert_array_equal(sources, [BEST, BEST])
    np.testing.assert_allclose(ps.poses[targets], hyp)
    np.testing.assert_allclose(ps.slip[targets], before.slip[[BEST, BEST]])
    np.testing.assert_allclose(ps.slip_cov[targets], before.slip_cov[[BEST, BEST]])
    for k, v in ps.maps.arrays().items():
        np.testing.assert_array_equal(v[targets], before.maps.arrays()[k][[BEST, BEST]], err_msg=k)
    # the injected particles carry the best one's log-weight; weights stay normalized
    np.testing.assert_allclose(ps.log_weights[targets], ps.log_weights[BEST])
    assert np.exp(ps.log_weights).sum() == pytest.approx(1.0)
    others = [0, 2, 4, 5]
    np.testing.assert_allclose(
        ps.log_weights[others] - ps.log_weights[BEST], before.log_weights[others] - before.log_weights[BEST]
    )
    np.testing.assert_allclose(ps.poses[others], before.poses[others])
    for k, v in ps.maps.arrays().items():
        np.testing.assert_array_equal(v[others], before.maps.arrays()[k][others], err_msg=k)


def test_inject_never_replaces_the_best_even_when_asked_for_more():
    ps = ParticleSet.create(2)
    ps.log_weights = np.log([0.9, 0.1])
    ps.poses[:] = [[1.0, 1.0, 0.0], [2.0, 2.0, 0.0]]
    targets, _ = inject(ps, Relocalization(np.array([TRUE_POSE, TRUE_POSE]), np.array([9.0, 9.0]), 1.0))
    np.testing.assert_array_equal(targets, [1])
    np.testing.assert_allclose(ps.poses, [[1.0, 1.0, 0.0], TRUE_POSE])
    np.testing.assert_allclose(np.exp(ps.log_weights), [0.5, 0.5])


def test_relocalize_then_inject_puts_a_particle_at_the_truth():
    segs, facing = scan_at(TRUE_POSE, seed=1)
    ps = particles(OFF_POSE)
    res = relocalize(ps, global_map(), segs, facing, STEP, RelocalizationConfig())
    targets, _ = inject(ps, res)
    assert BEST not in targets
    err = ps.poses[targets[0]] - TRUE_POSE
    assert np.hypot(err[0], err[1]) < 0.05 and abs(wrap_angle(err[2])) < np.radians(1.0)


def test_no_relocalization_where_places_repeat():
    """Two identical rooms 12 m apart (a row of doors, warehouse aisles): the scan fits both, so
    no hypothesis is unique and none is injected — an alias would be a wrong loop closure."""
    twin = np.concatenate([L_ROOM, L_ROOM + np.array([12.0, 0.0])])
    twin_map = global_map(walls=twin, facing=np.concatenate([L_FACING, L_FACING]))
    segs, facing = scan_at(TRUE_POSE)
    cfg = RelocalizationConfig(search_radius_m=25.0)  # both rooms in view of the search
    assert relocalize(particles(OFF_POSE), twin_map, segs, facing, STEP, cfg) is None
    # the uniqueness test is what refuses it: without it the (right) room would be injected
    loose = RelocalizationConfig(search_radius_m=25.0, unique_ratio=0.0)
    assert relocalize(particles(OFF_POSE), twin_map, segs, facing, STEP, loose) is not None


# --- negative evidence and confirmation ------------------------------------------------------


def rays_at(pose):
    """The raw scan from ``pose`` in L_ROOM (laser = robot frame)."""
    ranges = cast_rays(pose[None, :2], (pose[2] + ANGLES)[None], L_ROOM, 30.0)[0]
    return ScanRays(ranges, ANGLES, np.zeros(3), 20.0)


def element(a, b, facing):
    seg = np.array([[a, b]], float)
    d = seg[0, 1] - seg[0, 0]
    return seg, np.array([np.arctan2(d[0], -d[1])]), np.array([facing])


def test_through_counts_the_elements_the_beams_pass_from_each_pose():
    rays = rays_at(TRUE_POSE)
    # 0.8 m below the truth, 1.2 m short of the wall there: the true pose's beams cross it
    seg, alpha, facing = element((2.5, -2.2), (3.5, -2.2), np.pi / 2)
    np.testing.assert_array_equal(
        through_counts(np.array([TRUE_POSE, OFF_POSE]), seg, alpha, facing, rays), [1, 0]
    )
    # the room's own walls stop the beams: never seen through from the pose the scan was taken at
    walls = global_map()
    assert through_counts(TRUE_POSE[None], walls.seg, walls.alpha, walls.facing, rays)[0] == 0
    assert through_counts(TRUE_POSE[None], seg[:0], alpha[:0], facing[:0], rays).shape == (1,)


def test_a_hypothesis_whose_beams_cross_old_walls_is_not_injected():
    """Old elements in the true pose's free space: the true pose is refuted by the scan (its
    beams run through 4 of them, the current estimate's through 2 of the room's walls), so
    nothing is injected; the controls without the rays, or with a looser tolerance, inject it."""
    segs, facing = scan_at(TRUE_POSE)
    ghosts = [
        ((-0.5, 0.0), (0.5, 0.0)),
        ((2.0, 2.5), (3.0, 2.5)),
        ((3.0, -2.5), (4.0, -2.5)),
        ((0.0, -2.5), (1.0, -2.5)),
    ]
    gm = global_map(
        walls=np.concatenate([L_ROOM, np.array(ghosts, float)]),
        facing=np.concatenate([L_FACING, np.full(len(ghosts), np.pi / 2)]),
    )
    rays = rays_at(TRUE_POSE)
    counts = through_counts(np.array([OFF_POSE, TRUE_POSE]), gm.seg, gm.alpha, gm.facing, rays)
    np.testing.assert_array_equal(counts, [2, 4])
    cfg = RelocalizationConfig()  # at most 1 more than the current estimate
    assert relocalize(particles(OFF_POSE), gm, segs, facing, STEP, cfg, rays) is None
    assert relocalize(particles(OFF_POSE), gm, segs, facing, STEP, cfg) is not None
    loose = RelocalizationConfig(max_extra_through=2)
    res = relocalize(particles(OFF_POSE), gm, segs, facing, STEP, loose, rays)
    assert res is not None and np.hypot(*(res.poses[0, :2] - TRUE_POSE[:2])) < 0.05


def result_at(*poses):
    poses = np.array(poses, float)
    return Relocalization(poses, np.full(len(poses), 10.0), 2.0)


def test_confirm_small_corrections_at_once_large_ones_when_found_again():
    cfg = RelocalizationConfig()
    pose = np.array([1.0, 2.0, 0.3])
    small = compose(pose, np.array([0.5, 0.3, np.radians(4.0)]))
    ok, pending = confirm(None, result_at(small), pose, 100, cfg)
    assert ok and isinstance(pending, Pending) and pending.step == 100
    # 4.2 m along a corridor: an alias as often as a loop closure, so it waits for a repeat
    big = compose(pose, np.array([4.2, 0.0, 0.0]))
    ok, pending = confirm(None, result_at(big), pose, 100, cfg)
    assert not ok
    # 5 steps later the robot moved 0.6 m ahead; the same correction is found again: injected
    moved = compose(pose, np.array([0.6, 0.0, 0.0]))
    again = compose(pending.correction, moved) + np.array([0.05, -0.05, 0.01])
    other = compose(moved, np.array([-4.2, 0.0, 0.0]))  # listed too: any agreeing hypothesis counts
    assert confirm(pending, result_at(other, again), moved, 105, cfg)[0]
    # a different correction the second time, or the same one too late, is not a confirmation
    assert not confirm(pending, result_at(other), moved, 105, cfg)[0]
    assert not confirm(pending, result_at(again), moved, 100 + cfg.confirm_steps + 5, cfg)[0]
    # confirm_steps=0: every correction at once
    assert confirm(None, result_at(big), pose, 100, RelocalizationConfig(confirm_steps=0))[0]


def test_a_robot_that_fits_the_old_map_only_jumps_by_drift_sized_amounts():
    """The estimate 0.8 m off still explains part of the scan with old elements: the truth is
    injected only if 0.8 m is drift the distance driven since the last relocalization allows
    (1 m + 3 % of it); an estimate that explains nothing old may jump up to max_jump_m."""
    segs, facing = scan_at(TRUE_POSE)
    cfg = RelocalizationConfig(jump_base_m=0.5, anchored_m=0.0)  # 0.5 m + 3 % of the distance
    assert relocalize(particles(OFF_POSE), global_map(), segs, facing, STEP, cfg, None, 5.0) is None
    res = relocalize(particles(OFF_POSE), global_map(), segs, facing, STEP, cfg, None, 15.0)
    assert res is not None and np.hypot(*(res.poses[0, :2] - TRUE_POSE[:2])) < 0.05
    # anchored only when the estimate explains anchored_m of old elements
    current = res.current_score
    lost = RelocalizationConfig(jump_base_m=0.5, anchored_m=current + 0.5)
    assert relocalize(particles(OFF_POSE), global_map(), segs, facing, STEP, lost, None, 5.0) is not None


def test_inject_after_a_large_correction_moves_the_young_part_of_the_map_with_the_pose():
    ps = ParticleSet.create(2)
    ps.log_weights = np.log([0.9, 0.1])
    drifted = np.array([2.0, 1.0, 0.3])
    ps.poses[:] = [drifted, drifted]
    walls = np.array([[[0.0, 0.0], [4.0, 0.0]], [[3.0, 1.0], [3.0, 3.0]]])  # old, then young
    for p in range(2):
        for c, (a, b) in enumerate(walls):
            ps.maps.valid[p, c] = True
            ps.maps.seg[p, c] = [a, b]
            ps.maps.moments[p, c] = moments_of(np.linspace(a, b, 21))
            ps.maps.born[p, c] = [10, 250][c]
            ps.maps.facing[p, c] = [np.pi / 2, np.pi][c]
        ps.maps.alpha[p, :2], ps.maps.rho[p, :2], _ = fit_lines(ps.maps.moments[p, :2])
    before = ps.maps.take(np.arange(2))
    truth = np.array([1.0, 2.5, 0.1])  # the hypothesis: 1.8 m and 11 degrees away
    targets, _ = inject(ps, Relocalization(truth[None], np.array([9.0]), 1.0), young_since=200)
    assert targets.tolist() == [1]
    correction = compose(truth, inverse(drifted))
    maps = ps.maps
    # the injected particle: the old wall stays, the young one moved exactly with the pose
    np.testing.assert_allclose(maps.seg[1, 0], walls[0])
    np.testing.assert_allclose(maps.seg[1, 1], apply_points(correction, walls[1]), atol=1e-12)
    np.testing.assert_allclose(
        maps.moments[1, 1], moments_of(apply_points(correction, np.linspace(*walls[1], 21)))
    )
    alpha, rho, _ = fit_lines(maps.moments[1, :2])
    np.testing.assert_allclose(wrap_angle(maps.alpha[1, :2] - alpha), 0.0, atol=1e-9)
    np.testing.assert_allclose(maps.rho[1, :2], rho, atol=1e-9)
    assert maps.facing[1, 1] == pytest.approx(wrap_angle(np.pi + correction[2]))
    # the young wall keeps its place relative to the robot; the best particle's map is untouched
    np.testing.assert_allclose(
        apply_points(inverse(truth), maps.seg[1, 1]), apply_points(inverse(drifted), walls[1]), atol=1e-12
    )
    for k, v in maps.arrays().items():
        np.testing.assert_array_equal(v[0], before.arrays()[k][0], err_msg=k)
