"""Line sufficient statistics: TLS fits, exact moment transforms, covariance."""

import numpy as np
import pytest

from robot_agent.slam.lines import (
    fit_lines,
    line_covariance,
    moments_from_points,
    moments_of,
    points_on_line,
    project_to_line,
    segment_endpoints,
    transform_lines,
    transform_moments,
)
from shared.geometry import apply_points, line_angle_diff, wrap_angle

BATCH_SHAPES = [(), (3,), (2, 4)]


def _random_poses(rng, shape):
    return np.concatenate([rng.uniform(-5, 5, (*shape, 2)), rng.uniform(-np.pi, np.pi, (*shape, 1))], axis=-1)


def _line_points(alpha, rho, t):
    return points_on_line(alpha, rho, np.asarray(t, dtype=float))


@pytest.mark.parametrize(
    ("points", "alpha", "rho"),
    [
        # y = 2: normal +y
        (np.c_[np.linspace(-1, 3, 20), np.full(20, 2.0)], np.pi / 2, 2.0),
        # y = -2: normal -y keeps rho >= 0
        (np.c_[np.linspace(-1, 3, 20), np.full(20, -2.0)], -np.pi / 2, 2.0),
        # x = 3
        (np.c_[np.full(9, 3.0), np.linspace(-4, 1, 9)], 0.0, 3.0),
        # x = -0.5: normal -x
        (np.c_[np.full(9, -0.5), np.linspace(-4, 1, 9)], -np.pi, 0.5),
        # y = x + 1  <=>  -x/√2 + y/√2 = 1/√2
        (np.c_[np.linspace(-2, 2, 11), np.linspace(-2, 2, 11) + 1.0], 3 * np.pi / 4, 2**-0.5),
    ],
)
def test_fit_hand_made_lines(points, alpha, rho):
    a, r, s2 = fit_lines(moments_of(points))
    assert abs(wrap_angle(a - alpha)) < 1e-9
    assert r == pytest.approx(rho, abs=1e-9)
    assert s2 == pytest.approx(0.0, abs=1e-12)
    assert r >= 0


def test_fit_residual_variance_of_offset_points():
    # every x once at y = 1.1 and once at 0.9: the line is y = 1, residual variance 0.01
    x = np.repeat(np.linspace(0, 5, 5), 2)
    y = 1.0 + 0.1 * (-1.0) ** np.arange(10)
    a, r, s2 = fit_lines(moments_of(np.c_[x, y]))
    assert abs(wrap_angle(a - np.pi / 2)) < 1e-9
    assert r == pytest.approx(1.0, abs=1e-12)
    assert s2 == pytest.approx(0.01, rel=1e-9)


def test_fit_noisy_line_recovers_parameters():
    rng = np.random.default_rng(3)
    alpha, rho = 0.7, 2.5
    pts = _line_points(alpha, rho, rng.uniform(-2, 2, 200)) + rng.normal(0, 0.01, (200, 2))
    a, r, s2 = fit_lines(moments_of(pts))
    assert abs(wrap_angle(a - alpha)) < 3e-3
    assert r == pytest.approx(rho, abs=3e-3)
    assert np.sqrt(s2) == pytest.approx(0.01, rel=0.15)


def test_fit_fewer_than_two_points_is_nan():
    m = np.stack([moments_of(np.zeros((0, 2))), moments_of(np.ones((1, 2)))])
    a, r, s2 = fit_lines(m)
    assert np.all(np.isnan(a)) and np.all(np.isnan(r)) and np.all(np.isnan(s2))


def test_moments_from_points_groups_and_ignores_negative_labels():
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(30, 2))
    labels = rng.integers(-1, 4, 30)
    m = moments_from_points(pts, labels, 5)
    assert m.shape == (5, 6)
    for k in range(5):
        np.testing.assert_allclose(m[k], moments_of(pts[labels == k]), atol=1e-12)
    assert m[:, 0].sum() == np.count_nonzero(labels >= 0)


def test_moments_add_like_point_sets():
    rng = np.random.default_rng(1)
    a, b = rng.normal(size=(7, 2)), rng.normal(size=(5, 2))
    np.testing.assert_allclose(moments_of(a) + moments_of(b), moments_of(np.r_[a, b]))


@pytest.mark.parametrize("shape", BATCH_SHAPES)
def test_transform_moments_equals_moments_of_transformed_points(shape):
    rng = np.random.default_rng(len(shape))
    poses = _random_poses(rng, shape)
    pts = rng.normal(2.0, 3.0, (*shape, 12, 2))
    expected = moments_of(apply_points(poses, pts))
    got = transform_moments(poses, moments_of(pts))
    assert got.shape == (*shape, 6)
    np.testing.assert_allclose(got, expected, rtol=1e-10, atol=1e-9)


def test_transform_moments_broadcasts_poses_against_segments():
    # particles (P,) x segments (M,): poses (P,1,3) against moments (M,6)
    rng = np.random.default_rng(5)
    poses = _random_poses(rng, (4, 1))
    pts = rng.normal(size=(3, 8, 2))
    got = transform_moments(poses, moments_of(pts))
    assert got.shape == (4, 3, 6)
    expected = moments_of(apply_points(poses, pts))  # (4,1,1,3) x (3,8,2) -> (4,3,8,2)
    np.testing.assert_allclose(got, expected, rtol=1e-10, atol=1e-9)


@pytest.mark.parametrize("shape", BATCH_SHAPES)
def test_transform_lines_agrees_with_refit_of_transformed_moments(shape):
    rng = np.random.default_rng(10 + len(shape))
    poses = _random_poses(rng, shape)
    alpha = rng.uniform(-np.pi, np.pi, shape)
    rho = rng.uniform(0.5, 4, shape)
    pts = _line_points(alpha[..., None], rho[..., None], rng.uniform(-2, 2, (*shape, 10)))
    pts = pts + rng.normal(0, 0.02, pts.shape)
    m = moments_of(pts)
    a0, r0, s2 = fit_lines(m)
    cov0 = line_covariance(m, a0, s2)
    a1, r1, cov1 = transform_lines(poses, a0, r0, cov0)
    m1 = transform_moments(poses, m)
    a2, r2, s2b = fit_lines(m1)
    assert np.all(line_angle_diff(a1, a2) < 1e-9) and np.all(np.abs(wrap_angle(a1 - a2)) < 1e-9)
    np.testing.assert_allclose(r1, r2, atol=1e-9)
    np.testing.assert_allclose(s2b, s2, rtol=1e-6, atol=1e-12)
    np.testing.assert_allclose(cov1, line_covariance(m1, a2, s2), rtol=1e-6, atol=1e-14)
    assert np.all(r1 >= 0)


def test_covariance_shrinks_with_more_points():
    t = [np.linspace(-1, 1, n) for n in (10, 40, 160)]
    covs = [line_covariance(moments_of(_line_points(0.3, 2.0, ti)), 0.3, 1e-4) for ti in t]
    var_a = [c[0, 0] for c in covs]
    var_r = [c[1, 1] for c in covs]
    assert var_a[0] > var_a[1] > var_a[2] > 0
    assert var_r[0] > var_r[1] > var_r[2] > 0
    # var(alpha) = sigma2 / sum t_i^2 ~ 1/n
    assert var_a[0] / var_a[2] == pytest.approx(np.sum(t[2] ** 2) / np.sum(t[0] ** 2), rel=1e-9)


def test_covariance_matches_monte_carlo():
    rng = np.random.default_rng(42)
    alpha, rho, sigma = 1.0, 3.0, 0.02
    t = np.linspace(0.5, 3.0, 30)  # centroid off the foot point: alpha and rho correlate
    clean = _line_points(alpha, rho, t)
    trials = 4000
    noisy = clean + rng.normal(0, sigma, (trials, *clean.shape))
    a, r, _ = fit_lines(moments_of(noisy))
    sample = np.cov(np.stack([wrap_angle(a - alpha), r - rho]))
    predicted = line_covariance(moments_of(clean), alpha, sigma**2)
    assert sample[0, 0] == pytest.approx(predicted[0, 0], rel=0.2)
    assert sample[1, 1] == pytest.approx(predicted[1, 1], rel=0.2)
    assert sample[0, 1] == pytest.approx(predicted[0, 1], rel=0.2)
    assert abs(predicted[0, 1]) > 0.5 * np.sqrt(predicted[0, 0] * predicted[1, 1])


def test_project_and_endpoints_round_trip():
    alpha = np.array([0.2, -2.5, 1.4])
    rho = np.array([1.0, 0.3, 7.0])
    t = np.array([-1.0, 0.5, 3.0])
    p = points_on_line(alpha, rho, t)
    t_back, dist = project_to_line(p, alpha, rho)
    np.testing.assert_allclose(t_back, t, atol=1e-12)
    np.testing.assert_allclose(dist, 0.0, atol=1e-12)
    # a point pushed along the normal has that signed distance and the same t
    normal = np.stack([np.cos(alpha), np.sin(alpha)], axis=-1)
    t2, d2 = project_to_line(p + 0.25 * normal, alpha, rho)
    np.testing.assert_allclose(t2, t, atol=1e-12)
    np.testing.assert_allclose(d2, 0.25, atol=1e-12)
    seg = segment_endpoints(alpha, rho, t, t + 2.0)
    assert seg.shape == (3, 2, 2)
    np.testing.assert_allclose(np.linalg.norm(seg[:, 1] - seg[:, 0], axis=-1), 2.0)
    np.testing.assert_allclose(project_to_line(seg, alpha[:, None], rho[:, None])[1], 0, atol=1e-12)
