"""Scan -> clusters -> segments on synthetic scans with known walls, and on the Intel log."""

from pathlib import Path

import numpy as np
import pytest

from robot_agent.slam import extraction
from robot_agent.slam.extraction import (
    ExtractionConfig,
    ExtractionError,
    ScanSegments,
    extract_segments,
    scan_points,
)
from robot_agent.slam.lines import fit_lines, line_covariance
from shared.geometry import inverse, line_angle_diff, transform_points, wrap_angle

INTEL_HEAD = Path(__file__).resolve().parents[1] / "data" / "intel_head.clf.gz"
DEG = np.pi / 180


def cast(walls, angles_rad, origin=(0.0, 0.0), noise_m=0.0, seed=0):
    """Ranges ``(B,)`` from ``origin`` to the nearest of ``walls (M,2,2)``; inf on no hit."""
    walls = np.asarray(walls, dtype=float)
    d = np.stack([np.cos(angles_rad), np.sin(angles_rad)], axis=-1)[:, None, :]  # (B,1,2)
    a = walls[None, :, 0] - np.asarray(origin)
    e = walls[None, :, 1] - walls[None, :, 0]

    def cross(p, q):
        return p[..., 0] * q[..., 1] - p[..., 1] * q[..., 0]

    with np.errstate(divide="ignore", invalid="ignore"):
        den = cross(d, e)
        t = cross(a, e) / den
        u = cross(a, d) / den
    hit = (np.abs(den) > 1e-12) & (t > 0) & (u >= 0) & (u <= 1)
    r = np.where(hit, t, np.inf).min(axis=1)
    return r + np.random.default_rng(seed).normal(0.0, noise_m, r.shape)


def beams(n, fov_rad=np.pi):
    """``n`` beam angles centred on 0 over ``fov_rad``; a full circle excludes the end."""
    if np.isclose(fov_rad, 2 * np.pi):
        return -np.pi + np.arange(n) * (2 * np.pi / n)
    return np.linspace(-fov_rad / 2, fov_rad / 2, n)


CORNER = [[[2.0, -5.0], [2.0, 2.0]], [[-5.0, 2.0], [2.0, 2.0]]]  # x = 2 and y = 2


def _line_error(seg, i, alpha, rho):
    return line_angle_diff(seg.alpha[i], alpha), abs(seg.rho[i] - rho)


def _assert_line(seg, i, alpha, rho, tol=1e-2):
    da, dr = _line_error(seg, i, alpha, rho)
    assert da < tol and dr < tol, (seg.alpha[i], seg.rho[i], alpha, rho)
    assert abs(wrap_angle(seg.alpha[i] - alpha)) < tol  # rho >= 0 fixes the normal's sign


@pytest.mark.parametrize(("n_beams", "fov_deg"), [(181, 180), (361, 180), (1081, 270)])
def test_corner_gives_two_walls_meeting_at_the_corner(n_beams, fov_deg):
    ang = beams(n_beams, fov_deg * DEG)
    seg = extract_segments(cast(CORNER, ang, noise_m=0.01), ang)
    assert len(seg) == 2
    _assert_line(seg, 0, 0.0, 2.0)  # x = 2 comes first in scan order (beams start at -90°)
    _assert_line(seg, 1, np.pi / 2, 2.0)
    corner = np.array([2.0, 2.0])
    assert np.linalg.norm(seg.endpoints[0, 1] - corner) < 0.1  # ordered in scan order
    assert np.linalg.norm(seg.endpoints[1, 0] - corner) < 0.1
    assert seg.endpoints[0, 0, 1] < -4.0  # first wall starts where the scan sees it start
    assert np.all(seg.rms_m < 0.015)
    assert np.all(seg.n_points >= 30)
    # every labelled point is near its line; most points are labelled
    lab = seg.point_segment >= 0
    assert lab.mean() > 0.9
    p, k = seg.points[lab], seg.point_segment[lab]
    resid = p[:, 0] * np.cos(seg.alpha[k]) + p[:, 1] * np.sin(seg.alpha[k]) - seg.rho[k]
    assert np.max(np.abs(resid)) < 0.05


def test_segment_arrays_are_consistent():
    ang = beams(181)
    seg = extract_segments(cast(CORNER, ang, noise_m=0.01), ang)
    assert isinstance(seg, ScanSegments)
    n = len(seg)
    assert seg.endpoints.shape == (n, 2, 2) and seg.cov.shape == (n, 2, 2)
    assert seg.moments.shape == (n, 6) and seg.n_points.dtype.kind == "i"
    np.testing.assert_array_equal(seg.n_points, np.bincount(seg.point_segment + 1)[1:])
    a, r, s2 = fit_lines(seg.moments)
    np.testing.assert_allclose(a, seg.alpha)
    np.testing.assert_allclose(r, seg.rho)
    np.testing.assert_allclose(np.sqrt(s2), seg.rms_m)
    assert np.all(np.linalg.eigvalsh(seg.cov) > 0)
    # endpoints on their lines
    for j in range(2):
        e = seg.endpoints[:, j]
        np.testing.assert_allclose(
            e[:, 0] * np.cos(seg.alpha) + e[:, 1] * np.sin(seg.alpha), seg.rho, atol=1e-9
        )


def test_every_point_carries_the_line_of_its_own_piece_kept_or_not():
    """``point_alpha``: a point of a kept segment has the segment's line; a face too short to be
    kept (a pillar's side, 0.25 m) still has its own line through its points, at right angles
    to the wall beside it, not the wall's; a point alone has none (NaN)."""
    walls = [[[-5.0, 1.0], [5.0, 1.0]], [[1.2, 1.0], [1.2, 0.75]], [[1.2, 0.75], [1.6, 0.75]]]
    ang = beams(721)
    seg = extract_segments(cast(walls, ang, noise_m=0.002, seed=4), ang)
    on_wall = seg.point_segment >= 0
    np.testing.assert_array_equal(seg.point_alpha[on_wall], seg.alpha[seg.point_segment[on_wall]])
    pts = seg.points
    side = (np.abs(pts[:, 0] - 1.2) < 0.01) & (pts[:, 1] > 0.78) & (pts[:, 1] < 0.97)  # the pillar's side
    assert side.sum() >= 5 and np.all(seg.point_segment[side] == -1)  # too short to keep
    assert np.all(line_angle_diff(seg.point_alpha[side], 0.0) < 5 * DEG)  # x = 1.2: normal along x
    lone = extract_segments(np.array([2.0, np.inf, np.inf]), np.array([0.0, 0.5, 1.0]))
    assert len(lone.points) == 1 and np.isnan(lone.point_alpha).all()


def test_door_gap_with_open_space_behind_is_not_bridged():
    wall = [[[3.0, -6.0], [3.0, -0.5]], [[3.0, 0.5], [3.0, 6.0]]]  # x = 3, 1 m door at |y|<0.5
    ang = beams(181)
    seg = extract_segments(cast(wall, ang, noise_m=0.005), ang)
    assert len(seg) == 2
    for i in range(2):
        _assert_line(seg, i, 0.0, 3.0)
    ys = np.sort(seg.endpoints[:, :, 1], axis=1)
    assert ys[0, 1] < -0.45 and ys[1, 0] > 0.45  # neither spans the door


def test_door_gap_with_beams_missing_from_the_arrays_is_not_bridged():
    # the beams through the door are absent (not "no return"): only max_point_gap_m can split
    wall = [[[3.0, -6.0], [3.0, 6.0]]]
    ang = beams(181)
    keep = np.abs(3.0 * np.tan(ang)) > 0.5
    r = cast(wall, ang, noise_m=0.005)[keep]
    seg = extract_segments(r, ang[keep])
    assert len(seg) == 2
    ys = np.sort(seg.endpoints[:, :, 1], axis=1)
    assert ys[0, 1] < -0.45 and ys[1, 0] > 0.45
    merged = extract_segments(r, ang[keep], ExtractionConfig(max_point_gap_m=5.0))
    assert len(merged) == 1  # the gap is the only reason for the split


def test_range_jump_separates_near_box_from_far_wall():
    box = [[1.0, -0.5], [1.0, 0.5]]
    far = [[4.0, -6.0], [4.0, 6.0]]
    ang = beams(181)
    seg = extract_segments(cast([box, far], ang, noise_m=0.005), ang)
    assert len(seg) == 3
    np.testing.assert_allclose(seg.rho, [4.0, 1.0, 4.0], atol=1e-2)
    for i in range(3):
        _assert_line(seg, i, 0.0, seg.rho[i])
    ys = np.sort(seg.endpoints[1, :, 1])
    np.testing.assert_allclose(ys, [-0.5, 0.5], atol=0.05)
    box_pts = seg.point_segment[np.abs(seg.points[:, 0] - 1.0) < 0.1]
    assert np.all(box_pts == 1)


def test_invalid_readings_are_dropped():
    ang = beams(181)
    r = cast(CORNER, ang, noise_m=0.01)
    bad = {10: np.nan, 40: 0.0, 70: 0.01, 100: 8.0, 120: np.inf, 150: 30.0}
    for k, v in bad.items():
        r[k] = v
    seg = extract_segments(r, ang, range_max_m=8.0)
    assert not set(bad) & set(seg.point_beam.tolist())
    expected = np.isfinite(r) & (r >= 0.05) & (r < 8.0)
    np.testing.assert_array_equal(np.sort(seg.point_beam), np.flatnonzero(expected))
    np.testing.assert_allclose(seg.points, np.c_[r * np.cos(ang), r * np.sin(ang)][seg.point_beam])
    assert np.all(np.isfinite(seg.endpoints)) and np.all(np.isfinite(seg.cov))
    # scan_points keeps the same readings, without segmenting them
    np.testing.assert_array_equal(scan_points(r, ang, ExtractionConfig(), range_max_m=8.0), seg.points)
    # a reading beyond max_usable_range_m is dropped even below the scan's range_max_m
    seg = extract_segments(r, ang, ExtractionConfig(max_usable_range_m=3.0), range_max_m=80.0)
    assert np.all(r[seg.point_beam] < 3.0)
    np.testing.assert_array_equal(
        scan_points(r, ang, ExtractionConfig(max_usable_range_m=3.0), 80.0), seg.points
    )


def test_no_valid_reading_gives_empty_result():
    seg = extract_segments(np.full(181, np.nan), beams(181))
    assert len(seg) == 0 and seg.endpoints.shape == (0, 2, 2) and seg.points.shape == (0, 2)


@pytest.mark.parametrize("seed", range(5))
def test_pure_noise_gives_no_segments(seed):
    ang = beams(181)
    r = np.random.default_rng(seed).uniform(0.2, 10.0, ang.shape)
    assert len(extract_segments(r, ang)) <= 1


def test_noisy_wall_is_rejected_by_max_rms():
    wall = [[[3.0, -6.0], [3.0, 6.0]]]
    ang = beams(181)
    r = cast(wall, ang, noise_m=0.06, seed=1)
    loose = ExtractionConfig(breakpoint_n_sigma=20.0, split_threshold_m=1.0, max_rms_m=1.0)
    seg = extract_segments(r, ang, loose)
    assert len(seg) >= 1 and np.all(seg.rms_m > 0.03)  # only the rms check can reject these
    strict = ExtractionConfig(breakpoint_n_sigma=20.0, split_threshold_m=1.0)
    assert len(extract_segments(r, ang, strict)) == 0


@pytest.mark.parametrize("origin", [(0.5, -0.3), (-2.0, 1.0)])
def test_full_circle_square_room_gives_four_walls(origin):
    c = np.array([[-3.0, -2.0], [3.0, -2.0], [3.0, 2.0], [-3.0, 2.0]])
    walls = np.stack([c, np.roll(c, -1, axis=0)], axis=1)
    ang = beams(360, 2 * np.pi)
    seg = extract_segments(cast(walls, ang, origin, noise_m=0.01), ang)
    assert len(seg) == 4
    ox, oy = origin
    expected = {(0.0, 3.0 - ox), (np.pi, 3.0 + ox), (np.pi / 2, 2.0 - oy), (-np.pi / 2, 2.0 + oy)}
    for alpha, rho in expected:
        errs = [max(_line_error(seg, i, alpha, rho)) for i in range(4)]
        assert min(errs) < 1e-2, (alpha, rho)
    # the room's corners are the segments' endpoints
    corners = c - np.asarray(origin)
    d = np.linalg.norm(seg.endpoints.reshape(-1, 1, 2) - corners[None], axis=-1)
    assert np.all(d.min(axis=0) < 0.1)


def test_full_circle_room_from_many_positions():
    # the seam of a closed contour and one-point-off splits at corners must not leave a
    # stray piece of a wall behind
    c = np.array([[-3.0, -2.0], [3.0, -2.0], [3.0, 2.0], [-3.0, 2.0]])
    walls = np.stack([c, np.roll(c, -1, axis=0)], axis=1)
    ang = beams(360, 2 * np.pi)
    rng = np.random.default_rng(7)
    for seed in range(300):
        origin = rng.uniform([-2.0, -1.2], [2.0, 1.2])
        seg = extract_segments(cast(walls, ang, origin, noise_m=0.01, seed=seed), ang)
        assert len(seg) == 4, origin
        assert np.all(np.abs(np.sin(2 * seg.alpha)) < 1e-2)  # axis-aligned walls, within 0.3°


def test_breakpoint_follows_the_incidence_angle():
    # wall y = 1 seen from the origin: a beam at angle phi meets it at incidence phi
    wall = [[[-1.0, 1.0], [30.0, 1.0]]]
    cfg = ExtractionConfig(max_point_gap_m=100.0)  # only the adaptive breakpoint may cut
    grazing = np.arange(3.0, 9.0, 0.5) * DEG  # below lambda = 10°: every pair is cut
    seg = extract_segments(cast(wall, grazing), grazing, cfg)
    assert len(seg) == 0 and seg.points.shape == (grazing.size, 2)
    steep = np.arange(15.0, 40.0, 0.5) * DEG
    seg = extract_segments(cast(wall, steep), steep, cfg)
    assert len(seg) == 1 and np.all(seg.point_segment == 0)
    _assert_line(seg, 0, np.pi / 2, 1.0, tol=1e-6)


def test_merge_joins_collinear_pieces_of_one_cluster_only():
    t = np.linspace(0.0, 3.0, 31)
    wall = np.c_[t, np.full_like(t, 2.0)]  # y = 2
    corner = np.r_[wall, np.c_[np.full(10, 3.0), 2.0 - np.linspace(0.1, 1.0, 10)]]
    threshold = np.full(corner.shape[0], 0.05)
    cfg = ExtractionConfig()
    # three collinear pieces of one cluster -> one; the corner piece stays
    one_cluster = np.zeros(4, dtype=int)
    starts, _ = extraction._merge(corner, threshold, np.array([0, 10, 20, 31]), one_cluster, cfg)
    np.testing.assert_array_equal(starts, [0, 31])
    # the same pieces in different clusters are left alone
    starts, _ = extraction._merge(wall, threshold[:31], np.array([0, 10, 20]), np.arange(3), cfg)
    np.testing.assert_array_equal(starts, [0, 10, 20])


def test_transformed_moves_everything_and_round_trips():
    ang = beams(181)
    seg = extract_segments(cast(CORNER, ang, noise_m=0.01), ang)
    pose = np.array([0.3, -1.2, 2.0])
    moved = seg.transformed(pose)
    np.testing.assert_allclose(moved.endpoints, transform_points(pose, seg.endpoints))
    np.testing.assert_allclose(moved.points, transform_points(pose, seg.points))
    a, r, s2 = fit_lines(moved.moments)
    np.testing.assert_allclose(moved.alpha, a, atol=1e-9)
    np.testing.assert_allclose(moved.rho, r, atol=1e-9)
    np.testing.assert_allclose(moved.rms_m, np.sqrt(s2), atol=1e-9)
    floor = np.maximum(s2, ExtractionConfig().range_sigma_m ** 2)
    np.testing.assert_allclose(moved.cov, line_covariance(moved.moments, a, floor), rtol=1e-6)
    back = moved.transformed(inverse(pose))
    np.testing.assert_allclose(wrap_angle(moved.point_alpha - seg.point_alpha - pose[2]), 0.0, atol=1e-12)
    for name in ("endpoints", "alpha", "rho", "cov", "moments", "points", "point_alpha"):
        np.testing.assert_allclose(getattr(back, name), getattr(seg, name), atol=1e-9)


def test_bad_input_names_the_problem():
    with pytest.raises(ExtractionError, match="angles_rad"):
        extract_segments(np.ones(10), np.zeros(9))
    with pytest.raises(ExtractionError, match="min_points"):
        ExtractionConfig(min_points=1)
    with pytest.raises(ExtractionError, match="max_rms_m"):
        ExtractionConfig(max_rms_m=-1.0)
    with pytest.raises(ExtractionError, match="breakpoint_lambda_rad"):
        ExtractionConfig(breakpoint_lambda_rad=2.0)


def test_intel_scans_give_several_tight_segments():
    carmen = pytest.importorskip("robot_agent.sources.carmen")
    if not INTEL_HEAD.exists():
        pytest.skip(f"{INTEL_HEAD} not available")
    log = carmen.read_log(INTEL_HEAD)
    counts, rms = [], []
    for scan in map(log.scan, range(0, len(log), 10)):
        seg = extract_segments(scan.ranges_m, scan.angles_rad, range_max_m=scan.range_max_m)
        counts.append(len(seg))
        rms.extend(seg.rms_m)
        lab = seg.point_segment >= 0
        p, k = seg.points[lab], seg.point_segment[lab]
        resid = p[:, 0] * np.cos(seg.alpha[k]) + p[:, 1] * np.sin(seg.alpha[k]) - seg.rho[k]
        assert np.all(np.abs(resid) < 0.15)
    counts = np.asarray(counts)
    assert np.mean(counts >= 3) > 0.8
    assert np.mean(counts) > 4
    assert np.max(rms) <= 0.03 and np.median(rms) < 0.015
