"""Scans bridged for too little motion take their pose from the scan, not from odometry."""

import numpy as np
import pytest

from robot_agent.sim.lidar import cast_rays
from robot_agent.slam.config import apply_overrides
from robot_agent.slam.fastslam import FastSLAM, SlamConfig
from shared.geometry import compose, wrap_angle
from tests.rooms import ANGLES, L_ROOM, TRUE_POSE


def ranges_at(pose):
    return cast_rays(pose[None, :2], (pose[2] + ANGLES)[None], L_ROOM, 30.0)[0]


@pytest.mark.parametrize("refine", [True, False])
def test_bridged_scan_follows_the_scan_when_odometry_lags(refine):
    """The robot turns 3° (under the 5° processing threshold) but odometry has not seen it yet
    (it lags the laser): the refined bridge reports the turn, plain odometry does not."""
    cfg = apply_overrides(SlamConfig(particles=5), [f"filter.refine_bridged={refine}"])
    slam = FastSLAM(cfg, np.random.default_rng(0), start=TRUE_POSE)
    first = slam.step(0.0, np.zeros(3), ranges_at(TRUE_POSE), ANGLES, np.zeros(3), 30.0)
    assert first.processed
    # the truth turns 3° in place; the filter's pose of the first scan is a sample near the truth
    turned = compose(TRUE_POSE, np.array([0.0, 0.0, np.radians(3.0)]))
    second = slam.step(0.2, np.zeros(3), ranges_at(turned), ANGLES, np.zeros(3), 30.0)
    assert not second.processed
    _, poses = slam.best_trajectory()
    np.testing.assert_allclose(poses[-1], second.pose, atol=1e-9)  # the trajectory agrees
    turn = np.degrees(wrap_angle(second.pose[2] - first.pose[2]))
    if refine:
        assert abs(turn - 3.0) < 0.05, turn
        assert np.hypot(*(second.pose[:2] - first.pose[:2])) < 0.01
    else:
        assert abs(turn) < 1e-9
