"""Odometry: exact without noise, biased drift grows with distance, seeded and per robot."""

from __future__ import annotations

import numpy as np
import pytest

from robot_agent.sim.odometry import (
    OdometryBias,
    OdometryNoise,
    accumulate,
    draw_bias,
    integrate_odometry,
)
from robot_agent.sim.robot import RobotConfig, drive_route
from robot_agent.sim.worlds import builtin_world
from shared.geometry import compose, identity, relative, wrap_angle


@pytest.fixture(scope="module")
def trajectory():
    w = builtin_world("office")
    poses, _ = drive_route(w.routes[0], w.starts[0], RobotConfig(), 120.0)
    return poses


def straight(length_m=20.0, steps=400):
    x = np.linspace(0.0, length_m, steps + 1)
    return np.column_stack([x + 3.0, np.full_like(x, -2.0), np.full_like(x, 0.4)])


def test_zero_noise_reproduces_relative_motion_exactly(trajectory):
    odom = integrate_odometry(np.random.default_rng(0), trajectory, OdometryNoise.none())
    np.testing.assert_array_equal(odom[0], identity())
    for step in (1, 37, len(trajectory) - 1):
        want = relative(trajectory[:-step], trajectory[step:])
        got = relative(odom[:-step], odom[step:])
        np.testing.assert_allclose(got[:, :2], want[:, :2], atol=1e-9)
        np.testing.assert_allclose(wrap_angle(got[:, 2] - want[:, 2]), 0.0, atol=1e-9)


def test_accumulate_matches_sequential_composition():
    inc = np.random.default_rng(1).normal(0, 0.3, (50, 3))
    pose, expected = identity(), [identity()]
    for d in inc:
        pose = compose(pose, d)
        expected.append(pose)
    np.testing.assert_allclose(accumulate(inc), expected, atol=1e-12)


def test_scale_error_scales_distance():
    noise = OdometryNoise.none()
    odom = integrate_odometry(np.random.default_rng(0), straight(20.0), noise, OdometryBias(scale_error=0.05))
    assert np.hypot(*odom[-1, :2]) == pytest.approx(21.0)
    assert odom[-1, 2] == pytest.approx(0.0)


def test_heading_drift_grows_with_distance():
    bias = OdometryBias(heading_drift_rad_per_m=0.01)
    truth = straight(20.0)
    odom = integrate_odometry(np.random.default_rng(0), truth, OdometryNoise.none(), bias)
    assert odom[-1, 2] == pytest.approx(0.2)  # 20 m × 0.01 rad/m
    # position error (odometry vs truth, both from the start) grows with distance driven
    truth_local = relative(truth[:1], truth)
    err = np.hypot(*(odom[:, :2] - truth_local[:, :2]).T)
    at = [100, 200, 400]  # 5, 10, 20 m
    assert err[at[0]] < err[at[1]] < err[at[2]]
    # small-angle: lateral error ≈ drift × d² / 2
    assert err[400] == pytest.approx(0.01 * 20.0**2 / 2, rel=0.05)


def test_random_noise_has_the_configured_size():
    noise = OdometryNoise(
        trans_per_m=0.0,
        trans_per_rad=0.0,
        rot_per_rad=0.0,
        rot_per_m=0.005,
        scale_error_sigma=0.0,
        heading_drift_sigma_rad_per_m=0.0,
    )
    truth = straight(10.0, steps=100)  # steps of 0.1 m: per-step heading std 0.0005 rad
    finals = np.array([integrate_odometry(np.random.default_rng(k), truth, noise)[-1, 2] for k in range(400)])
    assert finals.std() == pytest.approx(np.sqrt(100) * 0.0005, rel=0.12)
    assert abs(finals.mean()) < 0.0005


def test_bias_draw_statistics():
    noise = OdometryNoise()
    biases = [draw_bias(np.random.default_rng(k), noise) for k in range(2000)]
    scales = np.array([b.scale_error for b in biases])
    drifts = np.array([b.heading_drift_rad_per_m for b in biases])
    assert scales.std() == pytest.approx(noise.scale_error_sigma, rel=0.06)
    assert drifts.std() == pytest.approx(noise.heading_drift_sigma_rad_per_m, rel=0.06)


def test_reproducible_and_different_per_robot(trajectory):
    noise = OdometryNoise()
    a = integrate_odometry(np.random.default_rng([5, 0]), trajectory, noise)
    b = integrate_odometry(np.random.default_rng([5, 0]), trajectory, noise)
    c = integrate_odometry(np.random.default_rng([5, 1]), trajectory, noise)
    np.testing.assert_array_equal(a, b)
    assert np.hypot(*(a[-1, :2] - c[-1, :2])) > 0.05
    # default noise drifts noticeably over a 60 m+ patrol, as real odometry does
    truth_local = relative(trajectory[:1], trajectory)
    assert np.hypot(*(a[-1, :2] - truth_local[-1, :2])) > 0.05
