"""Whole simulated runs: shapes, clock, reproducibility, consistency of scans with the truth."""

from __future__ import annotations

import numpy as np
import pytest

from robot_agent.sim.lidar import LidarConfig, cast_rays
from robot_agent.sim.odometry import OdometryNoise
from robot_agent.sim.simulate import SimConfig, simulate_robot
from robot_agent.sim.worlds import builtin_world
from robot_agent.sources.base import Scan
from shared.geometry import relative


@pytest.fixture(scope="module")
def office():
    return builtin_world("office")


def test_run_shapes_and_clock(office):
    cfg = SimConfig()
    run = simulate_robot(office, 0, 30.0, seed=1, cfg=cfg)
    n = int(30.0 * cfg.lidar.rate_hz) + 1
    assert run.stamps_s.shape == (n,) and run.truth.shape == (n, 3) and run.odometry.shape == (n, 3)
    assert run.ranges_m.shape == (n, 181) and run.angles_rad.shape == (181,)
    assert run.stamps_s[0] == cfg.epoch_s
    np.testing.assert_allclose(np.diff(run.stamps_s), 1.0 / cfg.lidar.rate_hz)
    np.testing.assert_allclose(np.diff(run.odom_stamps_s), cfg.robot.dt_s)
    np.testing.assert_array_equal(run.truth[0], office.starts[0])
    np.testing.assert_array_equal(run.odometry[0], [0.0, 0.0, 0.0])
    # scan-time arrays are samples of the dense ones
    idx = np.searchsorted(run.odom_stamps_s, run.stamps_s)
    np.testing.assert_array_equal(run.odom_poses[idx], run.odometry)
    np.testing.assert_array_equal(run.truth_dense[idx], run.truth)
    scans = list(run.scans())
    assert len(scans) == n and isinstance(scans[0], Scan) and scans[3].stamp_s == run.stamps_s[3]


def test_reproducible_and_robots_differ(office):
    a = simulate_robot(office, 1, 10.0, seed=4)
    b = simulate_robot(office, 1, 10.0, seed=4)
    np.testing.assert_array_equal(a.ranges_m, b.ranges_m)
    np.testing.assert_array_equal(a.odometry, b.odometry)
    c = simulate_robot(office, 1, 10.0, seed=5)
    assert not np.array_equal(a.ranges_m, c.ranges_m)
    assert a.bias != simulate_robot(office, 2, 1.0, seed=4).bias


def test_noise_free_scans_match_casting_at_the_truth(office):
    cfg = SimConfig(
        lidar=LidarConfig(range_sigma_m=0.0), odometry=OdometryNoise.none(), laser_offset=(0.2, 0.0, 0.0)
    )
    run = simulate_robot(office, 2, 8.0, seed=0, cfg=cfg)
    c, s = np.cos(run.truth[:, 2]), np.sin(run.truth[:, 2])
    laser_xy = run.truth[:, :2] + 0.2 * np.c_[c, s]
    expected = cast_rays(laser_xy, run.truth[:, 2:3] + run.angles_rad, office.walls, cfg.lidar.range_max_m)
    np.testing.assert_array_equal(run.ranges_m, expected)
    assert 0.3 < run.ranges_m.min() and np.median(run.ranges_m) < 10.0  # indoors: walls close by
    np.testing.assert_allclose(
        relative(run.odometry[:-1], run.odometry[1:]), relative(run.truth[:-1], run.truth[1:]), atol=1e-9
    )


def test_bad_arguments(office):
    with pytest.raises(ValueError, match="robot_index 4"):
        simulate_robot(office, 4, 1.0)
    with pytest.raises(ValueError, match="whole multiple"):
        SimConfig(lidar=LidarConfig(rate_hz=7.0))
