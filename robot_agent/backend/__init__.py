"""The robot's back end: the pose graph that corrects the path the filter drew, and the map
rebuilt along the corrected path (:mod:`robot_agent.backend.batch`)."""

from robot_agent.backend.batch import correct_trajectory, feed, remap

__all__ = ["correct_trajectory", "feed", "remap"]
