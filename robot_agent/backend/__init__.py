"""The robot's back end: the pose graph that corrects the path the filter drew — over a whole
trajectory at the end of a run (:mod:`robot_agent.backend.batch`) or while the robot runs
(:mod:`robot_agent.backend.online`) — and the map rebuilt along the corrected path."""

from robot_agent.backend.batch import correct_trajectory, feed, remap, scan_points_robot
from robot_agent.backend.online import Correction, OnlineBackend, Track

__all__ = ["Correction", "OnlineBackend", "Track", "correct_trajectory", "feed", "remap", "scan_points_robot"]
