"""The compiled kernels (robot_agent/slam/_kernels.c) against their numpy versions, which stay the
reference and the fallback: the same association, element for element, and the same poses,
covariances and counts to rounding, on random maps of many particles."""

import dataclasses
import os
import shutil
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree

from robot_agent.backend.batch import feed
from robot_agent.slam import kernels
from robot_agent.slam.association import AssociationConfig, associate, observe
from robot_agent.slam.coarse import CoarseConfig, heading_offset
from robot_agent.slam.config import apply_overrides
from robot_agent.slam.extraction import ExtractionConfig, extract_segments
from robot_agent.slam.fastslam import FastSLAM, SlamConfig
from robot_agent.slam.kidnap import KidnapConfig, overlap
from robot_agent.slam.lines import fit_lines, moments_of
from robot_agent.slam.particles import SegmentMaps
from robot_agent.slam.proposal import ProposalConfig, align_points, associate_points
from robot_agent.slam.update import CleaningConfig, UpdateConfig, _redundant_pairs, visibility
from robot_agent.sources import carmen
from shared import kernels as shared_kernels
from shared.geometry import apply_points, inverse, relative, sample_segments, wrap_angle
from shared.scanmatch import branch_and_bound, likelihood_field, window_scores

DATA = Path(__file__).resolve().parents[1] / "data"

needs_kernels = pytest.mark.skipif(not kernels.AVAILABLE, reason="the compiled kernels are not built")


def test_the_kernels_are_built_where_a_c_compiler_is():
    """`pip install` builds the extension when a compiler is there (setup.py, optional): in CI it
    must be, or every comparison below would skip and the numpy code run alone, unnoticed."""
    if os.environ.get("CI") or shutil.which("cc") or shutil.which("gcc"):
        assert kernels.AVAILABLE, "robot_agent/slam/_kernels.c was not built: reinstall (pip install -e .)"


def random_world(rng, n_particles, n_walls, spread_m=0.05):
    """Walls around the origin, one copy per particle moved by up to ``spread_m``, some columns
    invalid in some particles; the scan points of the true walls seen from a pose near the origin."""
    centre = rng.uniform(-6, 6, (n_walls, 2))
    heading = rng.uniform(-np.pi, np.pi, n_walls)
    half = rng.uniform(0.3, 3.0, n_walls)[:, None]
    d = np.stack([np.cos(heading), np.sin(heading)], axis=1)
    ends = np.stack([centre - half * d, centre + half * d], axis=1)  # (W,2,2)
    maps = SegmentMaps.empty(n_particles, n_walls)
    for p in range(n_particles):
        moved = ends + rng.normal(0, spread_m, (n_walls, 1, 2))
        for c in range(n_walls):
            a, b = moved[c]
            pts = a + np.linspace(0, 1, 20)[:, None] * (b - a)
            alpha, rho, _ = fit_lines(moments_of(pts)[None])
            maps.valid[p, c] = rng.random() > 0.1
            maps.seg[p, c] = moved[c]
            maps.alpha[p, c], maps.rho[p, c] = alpha[0], rho[0]
            # the free side: toward the origin (where the robot is), sometimes the other
            toward = -(a + b) / 2
            n = np.array([np.cos(alpha[0]), np.sin(alpha[0])])
            facing = alpha[0] if n @ toward > 0 else alpha[0] + np.pi
            maps.facing[p, c] = wrap_angle(facing + (np.pi if rng.random() < 0.1 else 0.0))
    true_pose = np.array([rng.normal(0, 0.3), rng.normal(0, 0.3), rng.uniform(-np.pi, np.pi)])
    samples = ends[:, :1] + rng.random((n_walls, 15, 1)) * (ends[:, 1:] - ends[:, :1])
    points = apply_points(inverse(true_pose), samples.reshape(-1, 2) + rng.normal(0, 0.01, (n_walls * 15, 2)))
    rng.shuffle(points)
    poses = true_pose + rng.normal(0, [0.1, 0.1, 0.05], (n_particles, 3))
    return maps, points, poses


def prior_cov(n, sigma_xy=0.1, sigma_th=0.05):
    return np.tile(np.diag([sigma_xy**2, sigma_xy**2, sigma_th**2]), (n, 1, 1))


def own_lines(rng, maps, pts, poses) -> np.ndarray:
    """Each point's own line (robot frame), as extraction gives it: the element it pairs with
    unchecked, turned by up to 60 degrees (about half beyond a 30 degree gate); NaN for a tenth
    of the points and for those that pair with nothing."""
    idx = associate_points(poses, pts, maps, 0.6, 0.2)[0]
    out = maps.alpha[0, np.maximum(idx, 0)] - poses[0, 2] + rng.uniform(-np.pi / 3, np.pi / 3, len(pts))
    return np.where((idx >= 0) & (rng.random(len(pts)) > 0.1), out, np.nan)


@needs_kernels
@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("lined", [False, True], ids=["unchecked", "own-lines"])
def test_the_association_is_the_numpy_one_element_for_element(seed, lined):
    rng = np.random.default_rng(seed)
    maps, pts, poses = random_world(rng, 12, 40)
    gate = rng.uniform(0.1, 0.6, len(poses))
    if lined:  # the points' own lines count from the re-association on (the pose no longer only
        # predicted): a second iteration with the normal gate, after a step the prior holds still
        point_alpha, turn = own_lines(rng, maps, pts, poses), np.radians(30.0)
        expected = associate_points(poses, pts, maps, 0.3, 0.2, point_alpha, turn)
        args = (np.tile(1e12 * np.eye(3), (len(poses), 1, 1)), 2, 0.3, point_alpha, np.sin(turn))
    else:  # one iteration: the association at the start poses, with the wide gates
        expected = associate_points(poses, pts, maps, gate, 0.2)
        args = (np.linalg.inv(prior_cov(len(poses))), 1, 0.2, None, 1.0)
    info, iterations, gate_m, point_alpha, max_sin = args
    _, _, idx = kernels.gn_points(
        poses, poses, info, pts, maps.alpha, maps.rho, maps.seg, maps.facing, maps.valid, gate,
        iterations, 1, gate_m, 0.2, 0.1, 0.03, point_alpha, max_sin,
    )  # fmt: skip
    assert (expected >= 0).sum() > 0.3 * expected.size  # a test of matches, not of -1s
    if lined:  # ... and of refusals
        unchecked = associate_points(poses, pts, maps, 0.3, 0.2)
        assert ((unchecked >= 0) & (expected < 0)).sum() > 0.1 * expected.size
    np.testing.assert_array_equal(idx, expected)


@needs_kernels
@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize(
    "changes",
    [{}, {"iterations": 1}, {"iterations": 0}, {"reassociate_after": 9}, {"max_points": 50}, "lined"],
    ids=["defaults", "one-iteration", "no-iteration", "no-reassociation", "thinned", "own-lines"],
)
def test_the_alignment_is_the_numpy_one(seed, changes):
    rng = np.random.default_rng(100 + seed)
    maps, pts, poses = random_world(rng, 20, 30)
    cov = prior_cov(len(poses))
    init = poses + rng.normal(0, 0.02, poses.shape) if seed % 2 else None
    point_alpha = own_lines(rng, maps, pts, poses) if changes == "lined" else None
    changes = {"max_points": 200} if changes == "lined" else changes  # (thinned with its lines)
    cfg = dataclasses.replace(ProposalConfig(), **changes)
    ref = align_points(poses, cov, pts, maps, dataclasses.replace(cfg, compiled=False), init, point_alpha)
    got = align_points(poses, cov, pts, maps, cfg, init, point_alpha)
    d = got.mean - ref.mean
    d[:, 2] = wrap_angle(d[:, 2])
    np.testing.assert_allclose(d, 0.0, atol=1e-9)
    np.testing.assert_allclose(got.cov, ref.cov, rtol=1e-7, atol=1e-15)
    np.testing.assert_array_equal(got.n_matched, ref.n_matched)
    if changes.get("iterations") != 0:
        assert np.all(ref.n_matched > 0)


@needs_kernels
def test_nothing_to_align_gives_the_prior():
    """No valid element (the numpy code's callers skip a map of no columns and a scan of no points;
    the kernel gives the prior for both)."""
    rng = np.random.default_rng(7)
    maps, pts, poses = random_world(rng, 5, 10)
    cov = prior_cov(len(poses))
    blank = dataclasses.replace(maps, valid=np.zeros_like(maps.valid))
    ref = align_points(poses, cov, pts, blank, ProposalConfig(compiled=False))
    got = align_points(poses, cov, pts, blank, ProposalConfig())
    np.testing.assert_allclose(got.mean, ref.mean, atol=1e-12)
    np.testing.assert_allclose(got.cov, ref.cov, rtol=1e-9)
    np.testing.assert_array_equal(got.n_matched, 0)
    for m, p in ((maps.columns(np.zeros(0, int)), pts), (maps, np.zeros((0, 2)))):
        got = align_points(poses, cov, p, m, ProposalConfig())
        np.testing.assert_allclose(got.mean, poses, atol=1e-12)
        np.testing.assert_allclose(got.cov, cov, rtol=1e-9)
        np.testing.assert_array_equal(got.n_matched, 0)


def scan_segments(rng, maps, pose, n_obs):
    """Robot-frame segments of particle 0's walls (noisy, some cut short) seen from ``pose``: moments,
    ends, facing and line covariance, as extraction gives them."""
    cols = rng.choice(np.flatnonzero(maps.valid[0]), n_obs, replace=False)
    moments, ends, facing = [], [], []
    for c in cols:
        a, b = apply_points(inverse(pose), maps.seg[0, c] + rng.normal(0, 0.03, (2, 2)))
        t = np.sort(rng.uniform(0, 1, 2))
        pts = a + np.linspace(t[0], t[1], 12)[:, None] * (b - a) + rng.normal(0, 0.01, (12, 2))
        moments.append(moments_of(pts))
        ends.append(pts[[0, -1]])
        facing.append(wrap_angle(maps.facing[0, c] - pose[2] + rng.normal(0, 0.05)))
    cov = np.tile(np.diag([1e-4, 1e-4]), (n_obs, 1, 1))
    return np.array(moments), np.array(ends), np.array(facing), cov


@needs_kernels
@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("wide", [False, True], ids=["normal", "widened"])
def test_the_segment_association_is_the_numpy_one_bit_for_bit(seed, wide):
    rng = np.random.default_rng(200 + seed)
    maps, _, poses = random_world(rng, 15, 40, spread_m=0.1)
    obs = observe(poses, *scan_segments(rng, maps, poses[0], 12), 0.02)
    extra = {}
    if wide:
        extra = {"pose_var_angle": rng.uniform(0, 0.01, (15, 1, 1)), "pose_var_perp": 0.02, "gate_scale": 2.5}
    ref = associate(obs, maps, AssociationConfig(compiled=False), **extra)
    got = associate(obs, maps, AssociationConfig(), **extra)
    assert ref.matched.sum() > 0.2 * ref.matched.size  # a test of matches, not of -1s
    for name in ("index", "cost", "d_angle", "d_perp"):
        np.testing.assert_array_equal(getattr(got, name), getattr(ref, name), err_msg=name)


def ray_cast(walls: np.ndarray, pose: np.ndarray, angles: np.ndarray) -> np.ndarray:
    """Ranges ``(B,)`` from ``pose`` to the nearest of ``walls (W,2,2)`` along each beam (inf: none)."""
    d = np.stack([np.cos(pose[2] + angles), np.sin(pose[2] + angles)], axis=1)  # (B,2)
    a, e = walls[:, 0] - pose[:2], walls[:, 1] - walls[:, 0]  # (W,2)
    den = d[:, None, 0] * e[None, :, 1] - d[:, None, 1] * e[None, :, 0]
    with np.errstate(divide="ignore", invalid="ignore"):
        r = (a[None, :, 0] * e[None, :, 1] - a[None, :, 1] * e[None, :, 0]) / den
        u = (a[None, :, 0] * d[:, None, 1] - a[None, :, 1] * d[:, None, 0]) / den
    r = np.where((r > 0) & (u >= 0) & (u <= 1), r, np.inf)
    return r.min(axis=1)


@needs_kernels
@pytest.mark.parametrize("beams", [181, 361, 1081])
def test_visibility_is_the_numpy_one_bit_for_bit(beams):
    """Scans of two thirds of the walls (the rest are seen through), noisy, with blind beams."""
    cfg = UpdateConfig()
    seen_through = in_view = 0
    for seed in range(8):
        rng = np.random.default_rng(300 + seed)
        maps, _, poses = random_world(rng, 10, 15, spread_m=0.05)
        span = np.pi if beams < 1000 else np.radians(270.0)
        angles = np.linspace(-span / 2, span / 2, beams)
        there = rng.random(15) < 0.67
        ranges = ray_cast(maps.seg[0, there], poses[0], angles) + rng.normal(0, 0.01, beams)
        ranges[rng.random(beams) < 0.05] = np.nan  # blind beams
        ref = visibility(maps, poses, ranges, angles, 8.0, dataclasses.replace(cfg, compiled=False))
        got = visibility(maps, poses, ranges, angles, 8.0, cfg)
        np.testing.assert_array_equal(got[0], ref[0])
        np.testing.assert_array_equal(got[1], ref[1])
        assert got[1].dtype == bool
        seen_through += int((ref[0] >= 2).sum())
        in_view += int(ref[1].sum())
    assert seen_through > 10 and in_view > 10  # both outcomes are tested


@needs_kernels
@pytest.mark.parametrize("seed", range(5))
def test_nearest_within_is_the_k_d_tree_query(seed):
    rng = np.random.default_rng(400 + seed)
    samples = rng.uniform(-5, 5, (rng.integers(1, 3000), 2))
    samples[rng.random(len(samples)) < 0.1] += 1000.0  # far away, and negative cells too
    queries = np.vstack([rng.uniform(-6, 6, (2000, 2)), samples[:50] + rng.normal(0, 0.05, (50, 2))])
    for radius in (0.05, 0.3, 2.0):
        expected = cKDTree(samples).query(queries, distance_upper_bound=radius)[0]
        got = kernels.nearest_within(samples, queries, radius)
        assert np.isfinite(expected).sum() > 10
        np.testing.assert_array_equal(got, expected)


@needs_kernels
@pytest.mark.parametrize("step", [0.05, 0.3, 5.0])
def test_segment_samples_are_the_numpy_ones(step):
    rng = np.random.default_rng(1100)
    seg = rng.uniform(-10, 10, (200, 2, 2))
    seg[:5, 1] = seg[:5, 0]  # points: one sample each
    np.testing.assert_array_equal(kernels.segment_samples(seg, step), sample_segments(seg, step)[0])
    assert kernels.segment_samples(np.zeros((0, 2, 2)), step).shape == (0, 2)


@needs_kernels
def test_nearest_within_edges():
    assert np.all(np.isinf(kernels.nearest_within(np.zeros((0, 2)), np.ones((3, 2)), 0.3)))
    assert kernels.nearest_within(np.ones((3, 2)), np.zeros((0, 2)), 0.3).shape == (0,)
    got = kernels.nearest_within(
        np.array([[0.0, 0.0], [np.nan, 0.0]]), np.array([[0.1, 0.0], [np.inf, 0]]), 0.3
    )
    np.testing.assert_array_equal(got, [0.1, np.inf])
    with pytest.raises(ValueError, match="radius must be finite and > 0"):
        kernels.nearest_within(np.ones((3, 2)), np.ones((3, 2)), 0.0)


@needs_kernels
@pytest.mark.parametrize("seed", range(8))
def test_the_coarse_heading_is_the_numpy_one(seed):
    rng = np.random.default_rng(500 + seed)
    maps, pts, poses = random_world(rng, 1, 20)
    turn = rng.uniform(-0.5, 0.5)
    pose = poses[0] + [0, 0, rng.uniform(-0.2, 0.2)]  # the heading off by up to 11°
    cfg = CoarseConfig()
    ref = heading_offset(pose, pts, maps.seg[0], turn, dataclasses.replace(cfg, compiled=False))
    assert heading_offset(pose, pts, maps.seg[0], turn, cfg) == ref


@needs_kernels
@pytest.mark.parametrize("name", ["intel_head", "aces_head", "mit_csail_head"])
def test_the_extraction_is_the_numpy_one_on_real_scans(name):
    """Every scan of the three excerpts (180 and 361 beams): the same pieces, point for point, the
    same lines to rounding (the kernels' atan2 and hypot are the C library's, numpy's may be its own)."""
    log = carmen.read_log(DATA / f"{name}.clf.gz")
    cfg = ExtractionConfig()
    segments = 0
    for scan in log.scans():
        args = (scan.ranges_m, scan.angles_rad)
        ref = extract_segments(*args, dataclasses.replace(cfg, compiled=False), scan.range_max_m)
        got = extract_segments(*args, cfg, scan.range_max_m)
        np.testing.assert_array_equal(got.point_segment, ref.point_segment)
        np.testing.assert_array_equal(got.n_points, ref.n_points)
        for field in ("endpoints", "alpha", "rho", "cov", "moments", "rms_m"):
            np.testing.assert_allclose(getattr(got, field), getattr(ref, field), rtol=1e-9, atol=1e-12)
        segments += len(ref)
    assert segments > 5 * len(log)


@needs_kernels
@pytest.mark.parametrize("seed", range(20))
def test_the_extraction_is_the_numpy_one_on_random_rooms(seed):
    """Noisy scans of random walls, with blind beams: short pieces, corners, collinear runs."""
    rng = np.random.default_rng(600 + seed)
    maps, _, poses = random_world(rng, 1, 12)
    angles = (
        np.linspace(-np.pi, np.pi, 720, endpoint=False)
        if seed % 2
        else np.linspace(-np.pi / 2, np.pi / 2, 181)
    )
    ranges = ray_cast(maps.seg[0], poses[0], angles) + rng.normal(0, 0.01, len(angles))
    ranges[rng.random(len(angles)) < 0.03] = np.nan
    cfg = ExtractionConfig()
    ref = extract_segments(ranges, angles, dataclasses.replace(cfg, compiled=False))
    got = extract_segments(ranges, angles, cfg)
    np.testing.assert_array_equal(got.point_segment, ref.point_segment)
    np.testing.assert_allclose(got.endpoints, ref.endpoints, rtol=1e-9, atol=1e-12)
    assert len(ref) >= 2


def match_case(seed):
    """A cloud of random walls, a query of the same walls seen from a pose up to 1 m and 10° off."""
    rng = np.random.default_rng(700 + seed)
    maps, _, _ = random_world(rng, 1, 15)
    walls = maps.seg[0]
    cloud = (walls[:, :1] + rng.random((15, 80, 1)) * (walls[:, 1:] - walls[:, :1])).reshape(-1, 2)
    true = np.array([rng.normal(0, 0.5), rng.normal(0, 0.5), rng.normal(0, 0.1)])
    query = apply_points(inverse(true), cloud[rng.choice(len(cloud), 150, replace=False)])
    return likelihood_field(cloud, 0.05, 0.05, 0.2), query, true


@needs_kernels
@pytest.mark.parametrize("seed", range(5))
def test_the_window_scores_are_the_numpy_ones(seed):
    fld, query, true = match_case(seed)
    guess = true + np.array([0.1, -0.1, 0.03])
    ref = window_scores(fld, query, guess, 0.3, np.radians(6.0), 0.05, np.radians(1.0), compiled=False)
    got = window_scores(fld, query, guess, 0.3, np.radians(6.0), 0.05, np.radians(1.0))
    np.testing.assert_allclose(got[0], ref[0], rtol=1e-12, atol=1e-15)
    assert np.argmax(got[0]) == np.argmax(ref[0]) and ref[0].max() > 0.5
    for a, b in zip(got[1:], ref[1:], strict=True):
        np.testing.assert_array_equal(a, b)


@needs_kernels
@pytest.mark.parametrize("seed", range(5))
def test_branch_and_bound_finds_what_the_numpy_one_finds(seed):
    """The same best pose, and scores equal to float32 rounding (the numpy code sums float32)."""
    fld, query, true = match_case(seed)
    guess = true + np.array([0.8, -0.6, 0.12])
    args = (fld, query, guess, 1.2, np.radians(10.0), np.radians(1.0), 0.3, 0.9, 4)
    ref_poses, ref_scores = branch_and_bound(*args, compiled=False)
    poses, scores = branch_and_bound(*args)
    assert len(ref_poses) > 0
    np.testing.assert_allclose(poses[0], ref_poses[0], atol=1e-9)
    np.testing.assert_allclose(scores[0], ref_scores[0], rtol=1e-5)
    assert abs(len(poses) - len(ref_poses)) <= max(2, len(ref_poses) // 20)  # ties at the keep ratio


@needs_kernels
@pytest.mark.parametrize("seed", range(6))
def test_the_kidnap_overlap_is_the_numpy_one(seed):
    rng = np.random.default_rng(800 + seed)
    ref = rng.uniform(-8, 8, (100, 2))
    odo_ref, odo = np.zeros(3), np.array([0.3, 0.1, 0.05])
    points = apply_points(relative(odo, odo_ref), ref) + rng.normal(0, 0.15 * (seed + 1), ref.shape)
    cfg = KidnapConfig()
    expected = overlap(ref, odo_ref, points, odo, dataclasses.replace(cfg, compiled=False))
    assert 0.0 < expected < 1.0
    assert overlap(ref, odo_ref, points, odo, cfg) == expected


@needs_kernels
def test_the_local_columns_are_the_numpy_ones():
    """FastSLAM._local_columns over the map of an excerpt's 675 scans, from every particle and
    from one, at several radii: the same columns."""
    log = carmen.read_log(DATA / "aces_head.clf.gz")
    slam = FastSLAM(SlamConfig(particles=10), np.random.default_rng(0))
    for i in range(len(log)):
        feed(slam, log, i)
    numpy_cfg = dataclasses.replace(slam.cfg, filter=dataclasses.replace(slam.cfg.filter, compiled=False))
    poses = slam.particles.poses
    assert slam.particles.maps.valid.any(axis=0).sum() > 30
    for radius in (0.5, 3.0, 10.0):
        for rows in (None, np.array([3]), np.array([0, 7])):
            got = slam._local_columns(poses, radius, rows)
            compiled_cfg, slam.cfg = slam.cfg, numpy_cfg
            try:
                ref = slam._local_columns(poses, radius, rows)
            finally:
                slam.cfg = compiled_cfg
            np.testing.assert_array_equal(got, ref)
            assert 0 < len(ref) or radius < 1.0


@needs_kernels
@pytest.mark.parametrize("seed", range(5))
def test_the_redundant_pairs_are_the_numpy_ones(seed):
    """Maps with near-duplicates of their elements (shifted along and across, turned a little)."""
    rng = np.random.default_rng(900 + seed)
    maps, _, _ = random_world(rng, 6, 40)
    dup = rng.choice(40, 15, replace=False)
    src = rng.choice(40, 15, replace=False)
    for d, s_ in zip(dup, src, strict=True):  # column d becomes a noisy copy of column s_
        shift = rng.normal(0, [0.3, 0.03])
        for field in ("valid", "alpha", "rho", "facing"):
            getattr(maps, field)[:, d] = getattr(maps, field)[:, s_]
        a = maps.alpha[:, s_]
        along = np.stack([-np.sin(a), np.cos(a)], axis=-1) * shift[0]
        across = np.stack([np.cos(a), np.sin(a)], axis=-1) * shift[1]
        maps.seg[:, d] = maps.seg[:, s_] + (along + across)[:, None, :]
        maps.rho[:, d] += shift[1]
        maps.facing[:, d] += rng.normal(0, 0.03)
    recent = np.sort(rng.choice(40, 20, replace=False))
    cfg = CleaningConfig()
    ref = _redundant_pairs(maps, dataclasses.replace(cfg, compiled=False), recent)
    got = _redundant_pairs(maps, cfg, recent)
    assert ref.sum() >= 3
    np.testing.assert_array_equal(got, ref)


@needs_kernels
@pytest.mark.parametrize("seed", range(4))
def test_the_observations_are_the_numpy_ones(seed):
    """The scan's segments in every particle's frame: moments and ends exactly (the same operations),
    lines to rounding (the kernel's atan2 and hypot are the C library's)."""
    rng = np.random.default_rng(1000 + seed)
    maps, _, poses = random_world(rng, 12, 20)
    args = (poses, *scan_segments(rng, maps, poses[0], 10), 0.02)
    ref, got = observe(*args, compiled=False), observe(*args)
    for name in ("moments", "ends", "facing", "n_points", "var_angle", "var_perp"):
        np.testing.assert_array_equal(getattr(got, name), getattr(ref, name), err_msg=name)
    np.testing.assert_allclose(got.rho, ref.rho, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(wrap_angle(got.alpha - ref.alpha), 0.0, atol=1e-12)


@needs_kernels
def test_a_block_of_an_angle_not_searched_is_refused():
    with pytest.raises(IndexError, match="angle 3 of 1"):
        shared_kernels.block_sums(np.zeros((4, 4), np.float32), np.zeros((1, 2, 2), np.int64), np.array([3]),
                           np.array([0]), np.array([0]))  # fmt: skip


@needs_kernels
def test_arrays_of_the_wrong_size_are_refused_by_name():
    rng = np.random.default_rng(3)
    maps, pts, poses = random_world(rng, 4, 6)
    with pytest.raises(ValueError, match="argument 3 holds"):
        kernels._kernels.gn_points(
            poses.copy(), poses, np.zeros((4, 3, 3)), pts[:-1], np.cos(maps.alpha), np.sin(maps.alpha),
            maps.rho, maps.seg, np.cos(maps.facing), np.sin(maps.facing), maps.valid.astype(np.uint8),
            np.full(4, 0.2), np.zeros((4, 3, 3)), np.zeros((4, len(pts)), np.int64), np.zeros(len(pts)),
            4, len(pts), 6, 4, 1, 0.2, 0.2, 0.1, 0.03, 1.0,
        )  # fmt: skip


def test_one_override_turns_every_kernel_off():
    """``--set compiled=false``: every section with the switch, and nothing else."""
    cfg = apply_overrides(SlamConfig(), ["compiled=false"])
    switched = {
        f.name
        for f in dataclasses.fields(cfg)
        if dataclasses.is_dataclass(getattr(cfg, f.name)) and hasattr(getattr(cfg, f.name), "compiled")
    }
    assert switched >= {
        "proposal",
        "association",
        "update",
        "coarse",
        "extraction",
        "filter",
        "kidnap",
        "backend",
    }
    assert all(getattr(cfg, name).compiled is False for name in switched)
    assert dataclasses.replace(cfg, **{n: getattr(SlamConfig(), n) for n in switched}) == SlamConfig()
    assert apply_overrides(SlamConfig(), ["compiled=true"]) == SlamConfig()


def test_row_columns_is_take_then_columns():
    rng = np.random.default_rng(1200)
    maps, _, _ = random_world(rng, 5, 30)
    cols = np.array([3, 7, 8, 21])
    a, b = maps.row_columns(2, cols), maps.take(np.array([2])).columns(cols)
    for name, v in a.arrays().items():
        np.testing.assert_array_equal(v, getattr(b, name), err_msg=name)
        assert v.shape[:2] == (1, 4)
