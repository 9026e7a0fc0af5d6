"""Improved proposal: point-to-line alignment of the scan (its points, or its segments' moments)
to each particle's map."""

import numpy as np
import pytest

from robot_agent.slam.association import AssociationConfig
from robot_agent.slam.lines import fit_lines
from robot_agent.slam.particles import SegmentMaps
from robot_agent.slam.proposal import (
    MeasuredOdometry,
    ProposalConfig,
    _rotate,
    align,
    associate_points,
    draw_covariance,
)
from shared.geometry import apply_points, inverse, wrap_angle
from tests.maps import put_element, seen_from, wall_points

POINTS_PER_M = 20
TRUE_POSE = np.array([2.5, 2.0, 0.4])
PRIOR_OFFSETS = np.array([[0.15, -0.1, np.radians(3.0)], [-0.1, -0.12, np.radians(-2.0)]])
PRIOR_SIGMA_XY_M = 0.15
PRIOR_SIGMA_THETA_RAD = np.radians(3.0)

# a room corner (map frame): floor wall y = 0, wall x = 0 perpendicular to it, third wall x = 6;
# facing = the normal toward the room's inside, the side the sensor sees
CORNER_ROOM = [
    (((0.0, 0.0), (6.0, 0.0)), np.pi / 2),
    (((0.0, 5.0), (0.0, 0.0)), 0.0),
    (((6.0, 0.0), (6.0, 5.0)), np.pi),
]
# one wall along 30° through (0, -1): the robot at TRUE_POSE is 1.35 m on its normal's side
DIR_30 = np.array([np.cos(np.radians(30.0)), np.sin(np.radians(30.0))])
NORMAL_30 = np.array([-DIR_30[1], DIR_30[0]])
ONE_WALL = [(((0.0, -1.0), tuple(np.array([0.0, -1.0]) + 8.0 * DIR_30)), np.radians(120.0))]


def build_maps(walls, n_particles):
    """Every particle holds the same walls (exact TLS lines from their points)."""
    maps = SegmentMaps.empty(n_particles, 4)
    for col, ((a, b), facing) in enumerate(walls):
        put_element(maps, col, wall_points(a, b, POINTS_PER_M), facing, ends=[a, b], hits=10)
    return maps


def scan(walls, pose):
    """Robot-frame segments of the walls seen from ``pose``: moments, ends, facing, covariance."""
    moments, ends, _, cov = seen_from([ab for ab, _ in walls], pose, 0.02, POINTS_PER_M)
    facing = np.array([wrap_angle(f - pose[2]) for _, f in walls])
    return moments, ends, facing, cov


def prior():
    mean = TRUE_POSE + PRIOR_OFFSETS
    cov = np.tile(
        np.diag([PRIOR_SIGMA_XY_M**2, PRIOR_SIGMA_XY_M**2, PRIOR_SIGMA_THETA_RAD**2]), (len(mean), 1, 1)
    )
    return mean, cov


def scan_points(walls, pose):
    """Every point of the walls in the robot frame ``(N,2)``: the scan the segments came from."""
    return np.vstack([apply_points(inverse(pose), wall_points(a, b, POINTS_PER_M)) for (a, b), _ in walls])


MODES = ["points", "segments"]


def run(walls, mode="points", cfg=None, maps=None):
    """Align the scan of ``walls`` from TRUE_POSE, starting at the offset prior, to ``maps``
    (default: the same walls)."""
    mean, cov = prior()
    m, ends, facing, seg_cov = scan(walls, TRUE_POSE)
    res = align(
        mean,
        cov,
        m,
        ends,
        facing,
        seg_cov,
        build_maps(walls, len(mean)) if maps is None else maps,
        AssociationConfig(),
        cfg or ProposalConfig(measurement=mode),
        scan_points(walls, TRUE_POSE),
    )
    return mean, cov, res


def test_scan_helper_puts_the_walls_back_at_the_true_pose():
    m, ends, facing, _ = scan(CORNER_ROOM, TRUE_POSE)
    back = apply_points(TRUE_POSE, ends)
    np.testing.assert_allclose(back, np.array([w for w, _ in CORNER_ROOM]), atol=1e-12)
    # robot-frame facing points back to the sensor: alpha + pi for a line with rho >= 0
    alpha, _, _ = fit_lines(m)
    np.testing.assert_allclose(wrap_angle(facing - alpha - np.pi), 0.0, atol=1e-9)


@pytest.mark.parametrize("mode", MODES)
def test_corner_room_aligns_to_the_truth(mode):
    _, _, res = run(CORNER_ROOM, mode)
    # every point (thinned to max_points) or every segment is associated
    n_points = min(len(scan_points(CORNER_ROOM, TRUE_POSE)), ProposalConfig().max_points)
    np.testing.assert_array_equal(res.n_matched, [n_points if mode == "points" else 3] * 2)
    err = res.mean - TRUE_POSE
    assert np.all(np.hypot(err[:, 0], err[:, 1]) < 0.01)
    assert np.all(np.abs(wrap_angle(err[:, 2])) < np.radians(0.2))


@pytest.mark.parametrize("mode", MODES)
def test_corner_room_shrinks_the_covariance_in_every_direction(mode):
    _, prior_cov, res = run(CORNER_ROOM, mode)
    assert res.cov.shape == (2, 3, 3)
    np.testing.assert_allclose(res.cov, np.transpose(res.cov, (0, 2, 1)))
    assert np.all(np.linalg.eigvalsh(res.cov) > 0)
    # all three directions are constrained: variances 100× below the prior's
    ratio = np.diagonal(res.cov, axis1=1, axis2=2) / np.diagonal(prior_cov, axis1=1, axis2=2)
    assert np.all(ratio < 0.01), ratio
    # the largest variance of the posterior in any direction too
    assert np.all(np.linalg.eigvalsh(res.cov[:, :2, :2]).max(axis=1) < 0.01 * PRIOR_SIGMA_XY_M**2)


@pytest.mark.parametrize("mode", MODES)
def test_one_wall_corrects_the_across_offset_and_heading_but_not_the_along_offset(mode):
    prior_mean, prior_cov, res = run(ONE_WALL, mode)
    assert np.all(res.n_matched >= (100 if mode == "points" else 1))
    err = res.mean[:, :2] - TRUE_POSE[:2]
    assert np.all(np.abs(err @ NORMAL_30) < 0.01)  # across the wall: corrected
    assert np.all(np.abs(wrap_angle(res.mean[:, 2] - TRUE_POSE[2])) < np.radians(0.2))
    # along the wall: no information; the mean stays at the prior's and so does the variance
    np.testing.assert_allclose((res.mean[:, :2] - prior_mean[:, :2]) @ DIR_30, 0.0, atol=0.01)
    assert np.all(np.abs((prior_mean[:, :2] - TRUE_POSE[:2]) @ DIR_30) > 0.05)  # so it was off
    var_along = np.einsum("i,pij,j->p", DIR_30, res.cov[:, :2, :2], DIR_30)
    var_across = np.einsum("i,pij,j->p", NORMAL_30, res.cov[:, :2, :2], NORMAL_30)
    np.testing.assert_allclose(var_along, PRIOR_SIGMA_XY_M**2, rtol=0.05)
    assert np.all(var_across < 0.01 * PRIOR_SIGMA_XY_M**2)
    assert np.all(res.cov[:, 2, 2] < 0.01 * prior_cov[:, 2, 2])


@pytest.mark.parametrize("mode", MODES)
def test_empty_map_returns_the_prior(mode):
    mean, cov, res = run(CORNER_ROOM, mode, maps=SegmentMaps.empty(2, 4))
    np.testing.assert_array_equal(res.n_matched, 0)
    np.testing.assert_allclose(res.mean, mean, atol=1e-12)
    np.testing.assert_allclose(res.cov, cov, rtol=1e-9)


@pytest.mark.parametrize("mode", MODES)
def test_the_proposal_is_the_posterior_whatever_the_sample_scale(mode):
    """``sample_scale`` acts where the particles are drawn, not on the proposal itself."""
    _, _, base = run(CORNER_ROOM, cfg=ProposalConfig(measurement=mode, sample_scale=1.0))
    _, _, scaled = run(CORNER_ROOM, cfg=ProposalConfig(measurement=mode, sample_scale=0.5))
    np.testing.assert_allclose(scaled.mean, base.mean, atol=1e-12)
    np.testing.assert_allclose(scaled.cov, base.cov, rtol=1e-12)


def test_the_particles_are_drawn_from_the_proposal_scaled():
    """FastSLAM draws each particle from its proposal's covariance times ``sample_scale``: with the
    same random stream, each particle's offset from its proposal's mean grows as its square root
    (the draws at scales 1, 1/4 and 9/16 lie on one line, at 1, 1/2 and 3/4 of the way)."""
    from pathlib import Path

    from robot_agent.backend import feed
    from robot_agent.slam.fastslam import FastSLAM, SlamConfig
    from robot_agent.sources import read_log

    log = read_log(Path(__file__).parents[1] / "data" / "intel_head.clf.gz")
    poses = {}
    for scale in (1.0, 0.25, 0.5625):
        cfg = SlamConfig(particles=8, proposal=ProposalConfig(sample_scale=scale))
        slam = FastSLAM(cfg, np.random.default_rng(3))
        for i in range(200):  # up to the first draw: the particles start at one pose, exactly
            feed(slam, log, i)
            if np.ptp(slam.particles.poses, axis=0).max() > 0.0:
                break
        poses[scale] = (i, slam.particles.poses.copy())
    assert poses[1.0][0] == poses[0.25][0] == poses[0.5625][0] < 199  # the same scan drew them
    poses = {scale: p for scale, (_, p) in poses.items()}
    offset = 2.0 * (poses[1.0] - poses[0.25])  # sqrt(1) - sqrt(1/4) = 1/2 of the offset
    assert np.abs(offset).max() > 1e-4  # the particles were drawn apart
    np.testing.assert_allclose(poses[0.5625], poses[1.0] - 0.25 * offset, atol=1e-9)


def test_points_behind_an_element_or_beyond_its_extent_are_not_associated():
    """A point is matched only to an element whose free side faces the sensor and whose extent
    (plus the margin) it falls in: the back of a thin wall and the wall's continuation past a
    doorway are not evidence. Points exactly on the line: only those two tests can refuse them."""
    wall = [(((0.0, 0.0), (6.0, 0.0)), np.pi / 2)]
    maps = build_maps(wall, 2)
    cfg = ProposalConfig()

    def matches(pose, walls_seen):
        poses = np.tile(pose, (2, 1))
        idx = associate_points(
            poses, scan_points(walls_seen, pose), maps, cfg.point_gate_m, cfg.extent_margin_m
        )
        assert idx.shape == (2, len(scan_points(walls_seen, pose)))
        return idx

    # the wall's back: the same line seen from below (the robot mirrored across it)
    np.testing.assert_array_equal(matches(TRUE_POSE * np.array([1.0, -1.0, -1.0]), wall), -1)
    # points on the line but 1 m past the wall's end (beyond the 0.2 m margin)
    np.testing.assert_array_equal(matches(TRUE_POSE, [(((7.0, 0.0), (9.0, 0.0)), np.pi / 2)]), -1)
    # ... and the ones within the margin are, like the wall's own points
    np.testing.assert_array_equal(matches(TRUE_POSE, [(((6.0, 0.0), (6.15, 0.0)), np.pi / 2)]), 0)
    np.testing.assert_array_equal(matches(TRUE_POSE, wall), 0)


def _associate_points_dense(
    poses: np.ndarray, points: np.ndarray, maps: SegmentMaps, gate_m: np.ndarray | float, margin_m: float
) -> np.ndarray:
    """:func:`associate_points` by testing every (particle, point, element) triple — the kernel
    as it was before candidate pairs: the reference it is tested against."""
    qx, qy = _rotate(poses, points)
    wx, wy = (qx + poses[:, None, 0])[..., None], (qy + poses[:, None, 1])[..., None]  # map frame
    nx, ny = np.cos(maps.alpha)[:, None, :], np.sin(maps.alpha)[:, None, :]  # (P,1,C)
    perp = np.abs(nx * wx + ny * wy - maps.rho[:, None, :])  # (P,N,C)
    t_pt = ny * wx - nx * wy
    t0 = ny * maps.seg[:, None, :, 0, 0] - nx * maps.seg[:, None, :, 0, 1]
    t1 = ny * maps.seg[:, None, :, 1, 0] - nx * maps.seg[:, None, :, 1, 1]
    inside = (t_pt > np.minimum(t0, t1) - margin_m) & (t_pt < np.maximum(t0, t1) + margin_m)
    front = (
        np.cos(maps.facing)[:, None, :] * qx[..., None] + np.sin(maps.facing)[:, None, :] * qy[..., None] < 0
    )
    gate = np.reshape(gate_m, (-1, 1, 1)) if np.ndim(gate_m) else gate_m
    cost = np.where(maps.valid[:, None, :] & inside & front & (perp < gate), perp, np.inf)
    idx = np.argmin(cost, axis=2)
    matched = np.isfinite(np.take_along_axis(cost, idx[..., None], axis=2)[..., 0])
    return np.where(matched, idx, -1)


@pytest.mark.parametrize("seed", range(6))
def test_point_association_by_candidate_pairs_equals_every_pair(seed):
    """associate_points tests only the (point, element) pairs a box around every particle's copy
    of each element admits; the result must be the dense test's, element for element — with
    particles spread by up to 0.3 m / 10°, per-particle gates, elements valid in some particles
    only, and elements that differ between particles."""
    rng = np.random.default_rng(seed)
    n_p, n_c = 7, 40
    maps = SegmentMaps.empty(n_p, n_c)
    for col in range(n_c):
        a = rng.uniform(-6, 6, 2)
        b = a + rng.uniform(0.3, 4.0) * np.array([np.cos(t := rng.uniform(0, np.pi)), np.sin(t)])
        rows = rng.random(n_p) < 0.8
        put_element(maps, col, wall_points(a, b, POINTS_PER_M), rng.uniform(-np.pi, np.pi), rows, ends=[a, b])
        jitter = rng.normal(0.0, 0.05, (n_p, 2, 2))  # each particle's copy a little different
        maps.seg[:, col] += np.where(rows[:, None, None], jitter, 0.0)
    poses = np.array([0.5, -0.3, 0.2]) + rng.uniform(-1, 1, (n_p, 3)) * np.array([0.3, 0.3, 0.17])
    points = rng.uniform(-7, 7, (300, 2))
    gates = rng.uniform(0.1, 0.6, n_p)
    for gate in (0.25, gates):
        fast = associate_points(poses, points, maps, gate, 0.2)
        dense = _associate_points_dense(poses, points, maps, gate, 0.2)
        np.testing.assert_array_equal(fast, dense)
        assert (fast >= 0).sum() > 50  # the case is not vacuous


@pytest.mark.parametrize("chunk", [1, 7 * 5, 7 * 23])
def test_point_association_in_chunks_of_pairs_is_the_same(monkeypatch, chunk):
    """Wide gates make many (point, element) pairs: they are evaluated in runs of whole points
    (bounded memory); any run length gives the result of one run — down to a point a run."""
    import robot_agent.slam.proposal as proposal

    rng = np.random.default_rng(11)
    n_p, n_c = 7, 30
    maps = SegmentMaps.empty(n_p, n_c)
    for col in range(n_c):
        a = rng.uniform(-4, 4, 2)
        b = a + rng.uniform(0.3, 4.0) * np.array([np.cos(t := rng.uniform(0, np.pi)), np.sin(t)])
        put_element(
            maps,
            col,
            wall_points(a, b, POINTS_PER_M),
            rng.uniform(-np.pi, np.pi),
            rng.random(n_p) < 0.8,
            ends=[a, b],
        )
    poses = rng.uniform(-1, 1, (n_p, 3)) * np.array([0.3, 0.3, 0.17])
    points = rng.uniform(-5, 5, (200, 2))
    whole = associate_points(poses, points, maps, 1.5, 0.2)  # wide: several elements a point
    monkeypatch.setattr(proposal, "ASSOCIATION_CHUNK", chunk)
    np.testing.assert_array_equal(associate_points(poses, points, maps, 1.5, 0.2), whole)
    assert (whole >= 0).sum() > 100


def test_a_point_pairs_only_with_an_element_along_its_own_line():
    """A pillar's side, a face too short to be kept as a segment, stands 0.05-0.18 m off the wall
    it juts from, within the point gate of the wall's line: unchecked, its points pair with the
    wall and pull the pose one way (the simulated warehouse's robots turned 0.19 deg in 30 s
    along a wall with pillars). With each point's own line (``point_alpha``: at right angles to
    the wall here) they pair with nothing; the wall's own points still pair with the wall, and a
    point with no line of its own (NaN) is not checked."""
    wall = [(((0.0, 0.0), (6.0, 0.0)), np.pi / 2)]
    maps = build_maps(wall, 2)
    cfg = ProposalConfig()
    side = apply_points(inverse(TRUE_POSE), wall_points((4.0, 0.05), (4.0, 0.18), POINTS_PER_M))
    on_wall = scan_points(wall, TRUE_POSE)
    pts = np.vstack([on_wall, side])
    across = np.full(len(side), 0.0 - TRUE_POSE[2])  # normal along x (map frame), in the robot's
    along = np.full(len(on_wall), np.pi / 2 - TRUE_POSE[2])
    poses = np.tile(TRUE_POSE, (2, 1))

    def pairs(point_alpha, gate=cfg.point_angle_gate_rad):
        return associate_points(poses, pts, maps, cfg.point_gate_m, cfg.extent_margin_m, point_alpha, gate)

    np.testing.assert_array_equal(pairs(None), 0)  # unchecked: the side's points on the wall
    lines = np.concatenate([along, across])
    np.testing.assert_array_equal(pairs(lines)[:, : len(on_wall)], 0)
    np.testing.assert_array_equal(pairs(lines)[:, len(on_wall) :], -1)
    np.testing.assert_array_equal(pairs(lines, np.pi / 2), 0)  # (no gate)
    np.testing.assert_array_equal(pairs(np.concatenate([along, np.full(len(side), np.nan)])), 0)


def test_the_draws_along_a_blind_wall_take_the_odometry_measured():
    """One wall: the proposal knows nothing along it (the motion prior's variance there). Drawn at
    a measured odometry noise of 0.1 of the model's variance, the along-wall variance is a tenth of
    the prior's, the across-wall and heading variances (the scan's) stay; at 1, the proposal's own."""
    _, cov, res = run(ONE_WALL)
    info = np.linalg.inv(cov)
    assert draw_covariance(res, info, 1.0) is res.cov
    draw = draw_covariance(res, info, 0.1)
    along = np.einsum("i,pij,j->p", DIR_30, res.cov[:, :2, :2], DIR_30)
    assert np.all(along > 0.8 * PRIOR_SIGMA_XY_M**2)  # (the scan leaves it to the prior)
    drawn_along = np.einsum("i,pij,j->p", DIR_30, draw[:, :2, :2], DIR_30)
    np.testing.assert_allclose(drawn_along, 0.1 * along, rtol=0.15)
    across = np.einsum("i,pij,j->p", NORMAL_30, draw[:, :2, :2], NORMAL_30)
    np.testing.assert_allclose(
        across, np.einsum("i,pij,j->p", NORMAL_30, res.cov[:, :2, :2], NORMAL_30), rtol=0.05
    )
    np.testing.assert_allclose(draw[:, 2, 2], res.cov[:, 2, 2], rtol=0.05)
    assert np.all(np.linalg.eigvalsh(draw) > 0)


def test_the_odometry_noise_is_measured_where_the_scan_pins_the_pose():
    """Steps whose scan-matched pose lies off odometry's prediction as N(0, 0.2 Σ): the measure
    comes to 0.2 of the model's variance; steps the scan does not pin (along a corridor) and
    odometry worse than the model leave the model's (1); the floor holds."""
    rng = np.random.default_rng(0)
    cfg = ProposalConfig()
    motion = np.tile(np.diag([0.02**2, 0.02**2, 0.01**2]), (10, 1, 1))
    pinned, corridor = motion * 0.1, motion * np.array([1.0, 0.1, 0.1])[:, None]
    good, blind, bad, floor = (MeasuredOdometry() for _ in range(4))
    for _ in range(1000):
        d = rng.normal(size=(10, 3)) * 0.02 * np.array([1.0, 1.0, 0.5])
        good.add(d * np.sqrt(0.2), motion, pinned, cfg)
        blind.add(d * np.sqrt(0.2), motion, corridor, cfg)
        bad.add(d * 3.0, motion, pinned, cfg)
        floor.add(d * 1e-3, motion, pinned, cfg)
    assert good.ratio(cfg) == pytest.approx(0.2, rel=0.1)
    assert blind.steps == 0 and blind.ratio(cfg) == 1.0
    assert bad.ratio(cfg) == 1.0
    assert floor.ratio(cfg) == cfg.min_odometry_ratio
    assert good.steps < cfg.odometry_horizon_steps  # (older steps forgotten: bounded)
