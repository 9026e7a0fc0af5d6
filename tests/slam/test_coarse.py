"""Coarse heading search before the proposal: the scan scored against the map over headings."""

import numpy as np
import pytest

from robot_agent.sim.lidar import cast_rays
from robot_agent.slam.coarse import CoarseConfig, heading_offset
from tests.rooms import L_ROOM, TRUE_POSE

FRONT = np.linspace(-np.pi / 2, np.pi / 2, 181)  # a SICK LMS: 180°, 1° apart


def scan_points(pose, angles=FRONT):
    """The L-room's walls hit by a laser at ``pose``: points (N,2) in the robot frame."""
    r = cast_rays(pose[None, :2], (pose[2] + angles)[None], L_ROOM, 30.0)[0]
    hit = r < 30.0
    return np.column_stack([r[hit] * np.cos(angles[hit]), r[hit] * np.sin(angles[hit])])


@pytest.mark.parametrize("error_deg", [-14.0, -6.0, 9.0, 13.0])
def test_a_turned_prediction_is_turned_back(error_deg):
    """Odometry that turned too far or not far enough (the MIT-CSAIL case): the search finds the
    heading at which the scan fits the walls, within one step of the truth."""
    cfg = CoarseConfig()
    predicted = TRUE_POSE + np.array([0.05, -0.04, np.radians(error_deg)])
    turn = np.radians(30.0)  # the window: 5° + 15°
    offset = heading_offset(predicted, scan_points(TRUE_POSE), L_ROOM, turn, cfg)
    assert abs(np.degrees(offset) + error_deg) <= np.degrees(cfg.step_rad)


def test_window_follows_the_turn_odometry_reports():
    """A 12° heading error is outside the 5° window of a robot that did not turn; a 30° turn
    widens the window to reach it."""
    cfg = CoarseConfig()
    predicted = TRUE_POSE + np.array([0.0, 0.0, np.radians(12.0)])
    pts = scan_points(TRUE_POSE)
    assert abs(heading_offset(predicted, pts, L_ROOM, 0.0, cfg)) <= cfg.window_rad + 1e-12
    assert np.degrees(heading_offset(predicted, pts, L_ROOM, np.radians(30.0), cfg)) == pytest.approx(-12.0)


def test_a_right_prediction_stays_and_nothing_to_match_is_no_move():
    cfg = CoarseConfig()
    pts = scan_points(TRUE_POSE)
    assert heading_offset(TRUE_POSE, pts, L_ROOM, np.radians(20.0), cfg) == 0.0
    assert heading_offset(TRUE_POSE, pts, np.zeros((0, 2, 2)), 0.3, cfg) == 0.0
    assert heading_offset(TRUE_POSE, np.zeros((0, 2)), L_ROOM, 0.3, cfg) == 0.0
