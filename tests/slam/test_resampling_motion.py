"""Systematic resampling, ESS, the slip-aware motion model and its sampling."""

import numpy as np
import pytest

from robot_agent.slam.motion import (
    MotionConfig,
    odometry_increment,
    predict,
    sample_gaussian,
    slip_jacobian,
    update_slip,
    walk_slip,
)
from robot_agent.slam.resampling import effective_sample_size, normalized_weights, systematic_resample
from shared.geometry import compose, wrap_angle

WEIGHTS = np.array([0.05, 0.3, 0.125, 0.02, 0.405, 0.1])  # P w = 0.3, 1.8, 0.75, 0.12, 2.43, 0.6


def test_normalized_weights_from_unnormalized_logs():
    w = normalized_weights(np.log(WEIGHTS) + 1234.5)  # a huge common offset must not overflow
    np.testing.assert_allclose(w, WEIGHTS, rtol=1e-12)


def test_systematic_resampling_copies_floor_or_ceil_of_p_w():
    p = len(WEIGHTS)
    expected = p * WEIGHTS
    counts = np.array(
        [
            np.bincount(systematic_resample(np.random.default_rng(s), np.log(WEIGHTS)), minlength=p)
            for s in range(2000)
        ]
    )
    assert np.all(counts.sum(axis=1) == p)
    assert np.all(counts >= np.floor(expected)) and np.all(counts <= np.ceil(expected))
    # unbiased: the mean count is P w (std of each mean below 0.5 / sqrt(2000) ≈ 0.011)
    np.testing.assert_allclose(counts.mean(axis=0), expected, atol=0.05)
    # both floor and ceil occur where P w is fractional
    frac = expected % 1 > 0
    assert np.all(counts.min(axis=0)[frac] == np.floor(expected[frac]))
    assert np.all(counts.max(axis=0)[frac] == np.ceil(expected[frac]))


def test_systematic_resampling_of_equal_weights_keeps_everyone_once():
    idx = systematic_resample(np.random.default_rng(3), np.zeros(7))
    np.testing.assert_array_equal(np.sort(idx), np.arange(7))


def test_systematic_resampling_indices_are_sorted_and_in_range():
    rng = np.random.default_rng(1)
    for _ in range(50):
        lw = rng.normal(size=20) * 3
        idx = systematic_resample(rng, lw)
        assert idx.shape == (20,) and np.all(np.diff(idx) >= 0)
        assert idx.min() >= 0 and idx.max() < 20


def test_ess_uniform_one_hot_and_hand_computed():
    assert effective_sample_size(np.full(10, -np.log(10))) == pytest.approx(10.0)
    assert effective_sample_size(np.array([0.0, -1000.0, -1000.0, -1000.0])) == pytest.approx(1.0)
    assert effective_sample_size(np.array([0.0, -np.inf, -np.inf])) == pytest.approx(1.0)
    # w = (1/2, 1/4, 1/4): 1 / (1/4 + 1/16 + 1/16) = 8/3
    assert effective_sample_size(np.log([0.5, 0.25, 0.25]) + 7.0) == pytest.approx(8.0 / 3.0)


POSES = np.array([[0.0, 0.0, 0.0], [1.0, -2.0, 0.7], [-3.0, 0.5, -2.9]])
U = np.array([0.8, 0.1, 0.3])


def test_odometry_increment_recomposes():
    a, b = np.array([1.0, 2.0, 0.5]), np.array([1.5, 2.7, 1.1])
    np.testing.assert_allclose(compose(a, odometry_increment(a, b)), b, atol=1e-12)


def test_predict_without_slip_is_compose():
    mean, cov = predict(POSES, np.zeros((3, 2)), U, MotionConfig())
    np.testing.assert_allclose(mean, compose(POSES, U), atol=1e-12)
    assert cov.shape == (3, 3, 3)


def test_predict_slip_scale_scales_the_translation():
    slip = np.array([[0.1, 0.0], [0.1, 0.0], [-0.1, 0.0]])
    mean, _ = predict(POSES, slip, U, MotionConfig())
    np.testing.assert_allclose(mean[:2], compose(POSES[:2], [1.1 * U[0], 1.1 * U[1], U[2]]), atol=1e-12)
    np.testing.assert_allclose(mean[2], compose(POSES[2], [0.9 * U[0], 0.9 * U[1], U[2]]), atol=1e-12)
    # distance driven from the first pose: |1.1 (0.8, 0.1)|
    assert np.hypot(*(mean[0, :2] - POSES[0, :2])) == pytest.approx(1.1 * np.hypot(0.8, 0.1))


def test_predict_heading_drift_adds_drift_times_distance():
    mean, _ = predict(POSES, np.array([[0.0, 0.02]] * 3), U, MotionConfig())
    d = np.hypot(U[0], U[1])
    np.testing.assert_allclose(mean, compose(POSES, [U[0], U[1], U[2] + 0.02 * d]), atol=1e-12)


def test_predict_covariance_hand_computed():
    cfg = MotionConfig(
        trans_per_m=0.05,
        trans_per_rad=0.02,
        trans_min_m=0.005,
        rot_per_rad=0.05,
        rot_per_m=0.02,
        rot_min_rad=0.002,
    )
    _, cov = predict(POSES[:1], np.zeros((1, 2)), np.array([1.0, 0.0, -0.5]), cfg)
    s_xy2 = 0.05**2 * 1.0 + (0.02 * 0.5) ** 2 + 0.005**2
    s_th2 = (0.05 * 0.5) ** 2 + (0.02 * 1.0) ** 2 + 0.002**2
    np.testing.assert_allclose(cov[0], np.diag([s_xy2, s_xy2, s_th2]), rtol=1e-12)
    # standing still: only the floors
    _, cov0 = predict(POSES[:1], np.zeros((1, 2)), np.zeros(3), cfg)
    np.testing.assert_allclose(np.diag(cov0[0]), [0.005**2, 0.005**2, 0.002**2], rtol=1e-12)


def test_sample_gaussian_matches_mean_and_covariance():
    n = 20000
    mean = np.array([1.0, -2.0, 0.3])
    cov = np.array([[0.04, 0.01, 0.002], [0.01, 0.02, -0.001], [0.002, -0.001, 0.003]])
    x = sample_gaussian(np.random.default_rng(42), np.tile(mean, (n, 1)), np.tile(cov, (n, 1, 1)))
    assert x.shape == (n, 3)
    sd = np.sqrt(np.diag(cov))
    np.testing.assert_array_less(np.abs(x.mean(axis=0) - mean), 4 * sd / np.sqrt(n))
    emp = np.cov(x.T)
    # within 5 % of the scale sqrt(c_ii c_jj) for every entry (diagonal: 5 % relative)
    np.testing.assert_array_less(np.abs(emp - cov), 0.05 * np.outer(sd, sd))


def test_sample_gaussian_wraps_the_heading():
    n = 5000
    x = sample_gaussian(
        np.random.default_rng(0),
        np.tile([0.0, 0.0, np.pi - 0.01], (n, 1)),
        np.tile(np.diag([1e-4, 1e-4, 0.01]), (n, 1, 1)),
    )
    assert np.all((x[:, 2] >= -np.pi) & (x[:, 2] < np.pi))
    assert np.mean(x[:, 2] < 0) > 0.3  # about half went past pi and wrapped
    # on the circle the spread is still 0.1 rad around pi - 0.01
    assert np.std(wrap_angle(x[:, 2] - (np.pi - 0.01))) == pytest.approx(0.1, rel=0.05)


def test_walk_slip_grows_the_beliefs_variance_with_distance():
    cfg = MotionConfig()
    cov = np.tile(np.diag([1e-4, 4e-5]), (3, 1, 1))
    grown = walk_slip(cov, 4.0, cfg)
    np.testing.assert_allclose(
        grown - cov,
        np.tile(
            np.diag([4.0 * cfg.slip_scale_walk_per_sqrt_m**2, 4.0 * cfg.slip_drift_walk_per_sqrt_m**2]),
            (3, 1, 1),
        ),
    )
    np.testing.assert_array_equal(walk_slip(cov, 0.0, cfg), cov)  # no motion, no growth
    np.testing.assert_array_equal(walk_slip(cov, -1.0, cfg), cov)


def _joint_conditioning(slip, slip_cov, jac, q, h, z):
    """Reference: the slip's posterior from the explicit joint Gaussian of (pose, slip) and a
    pose measurement ``z`` (relative to the predicted mean) with information ``h`` (full rank)."""
    s_xx = q + jac @ slip_cov @ jac.T
    s_xs = jac @ slip_cov
    s_zz = s_xx + np.linalg.inv(h)
    gain = s_xs.T @ np.linalg.inv(s_zz)
    return slip + gain @ z, slip_cov - gain @ s_xs


def _alignment_result(jac, slip_cov, q, h, z):
    """What the proposal hands over: the prior covariance it used, its posterior covariance and
    the posterior mean's shift from the predicted pose."""
    prior = q + jac @ slip_cov @ jac.T
    post = np.linalg.inv(np.linalg.inv(prior) + h)
    shift = post @ h @ z
    return prior, post, shift


def test_update_slip_is_the_exact_gaussian_conditioning_of_the_slip_on_the_scan():
    cfg = MotionConfig()
    rng = np.random.default_rng(7)
    poses = np.array([[1.0, 2.0, 0.4], [0.0, 0.0, -2.0]])
    u = np.array([0.3, 0.02, 0.05])
    jac = slip_jacobian(poses, u)
    slip = np.array([[0.01, -0.002], [-0.02, 0.004]])
    slip_cov = np.tile(np.array([[9e-4, 1e-5], [1e-5, 4e-4]]), (2, 1, 1))
    q = np.tile(np.diag([1e-4, 1e-4, 3e-4]), (2, 1, 1))
    a = rng.normal(size=(2, 3, 3))
    h = np.einsum("pij,pkj->pik", a, a) * 1e4 + np.eye(3) * 1e3  # a well-constraining scan
    z = rng.normal(0.0, 0.02, (2, 3))
    prior, post, shift = (
        np.stack(x)
        for x in zip(
            *[_alignment_result(jac[p], slip_cov[p], q[p], h[p], z[p]) for p in range(2)], strict=True
        )
    )
    got, got_cov = update_slip(slip, slip_cov, jac, np.linalg.inv(prior), post, shift, cfg)
    for p in range(2):
        ref, ref_cov = _joint_conditioning(slip[p], slip_cov[p], jac[p], q[p], h[p], z[p])
        np.testing.assert_allclose(got[p], ref, rtol=1e-6, atol=1e-12)
        np.testing.assert_allclose(got_cov[p], ref_cov, rtol=1e-6, atol=1e-14)
    assert np.all(np.linalg.eigvalsh(got_cov) > 0)
    assert np.all(np.diagonal(got_cov, axis1=1, axis2=2) < np.diagonal(slip_cov, axis1=1, axis2=2))


def test_a_scan_that_says_nothing_along_the_motion_teaches_nothing_about_the_scale():
    """Driving along x in a corridor whose walls constrain only y and the heading: the distance
    scale stays where it was, with its variance; the heading drift is learned."""
    cfg = MotionConfig()
    poses = np.zeros((1, 3))
    u = np.array([0.3, 0.0, 0.0])
    jac = slip_jacobian(poses, u)
    np.testing.assert_allclose(jac[0], [[0.3, 0.0], [0.0, 0.0], [0.0, 0.3]])
    slip = np.array([[0.02, 0.0]])
    slip_cov = np.diag([9e-4, 4e-4])[None]
    q = np.diag([1e-4, 1e-4, 3e-4])[None]
    h = np.diag([0.0, 1e6, 1e6])[None]  # y and heading measured, x not at all
    prior = q + np.einsum("pij,pjk,plk->pil", jac, slip_cov, jac)
    post = np.linalg.inv(np.linalg.inv(prior) + h)
    truth_offset = np.array([0.0, 0.01, 0.006])  # the scan saw a heading drift of 0.02 rad/m
    shift = (post @ h @ truth_offset[:, None])[..., 0]
    got, got_cov = update_slip(slip, slip_cov, jac, np.linalg.inv(prior), post, shift, cfg)
    assert got[0, 0] == pytest.approx(0.02, abs=1e-9)
    assert got_cov[0, 0, 0] == pytest.approx(9e-4, rel=1e-6)
    # the heading offset is split between this step's noise and the drift by their variances
    # (the scan measured it almost exactly: 1e6 information)
    share = 0.3**2 * 4e-4 / (3e-4 + 0.3**2 * 4e-4)
    assert got[0, 1] == pytest.approx(0.02 * share, rel=1e-2)
    assert got_cov[0, 1, 1] == pytest.approx(4e-4 * (1 - share), rel=1e-2)


def test_update_slip_keeps_the_slip_within_its_bounds():
    cfg = MotionConfig()
    jac = slip_jacobian(np.zeros((1, 3)), np.array([0.3, 0.0, 0.0]))
    slip_cov = np.diag([1.0, 1.0])[None]  # a wildly uncertain belief ...
    q = np.diag([1e-6, 1e-6, 1e-6])[None]
    prior = q + np.einsum("pij,pjk,plk->pil", jac, slip_cov, jac)
    post = q.copy()
    got, _ = update_slip(
        np.zeros((1, 2)), slip_cov, jac, np.linalg.inv(prior), post, np.array([[5.0, 0.0, 3.0]]), cfg
    )  # ... told a huge slip
    assert got[0, 0] == cfg.slip_scale_max
    assert got[0, 1] == cfg.slip_drift_max_rad_per_m
