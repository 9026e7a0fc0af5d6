"""Coarse rotation search: where the scan fits the map, before the proposal refines it.

The proposal's Gauss-Newton (proposal.py) converges only from within a few degrees: it
associates each point with the nearest element, and a point 3 m away is 0.5 m off after a 10°
heading error. Odometry's heading is least reliable exactly while the robot turns: on
MIT-CSAIL the odometry read with a laser line turns 30° where the robot turned 17° (its
reading and the scan are not taken at the same instant), and a filter that starts the alignment
there fits the scan to the wrong walls, then maps them — a doubled corridor at a wrong angle,
never undone. So before the alignment the scan is scored against the best particle's local map
at every heading within a window around the prediction (the correlative idea of Olson 2009,
along the one axis odometry gets wrong), and every particle's alignment starts from the best.

The window grows with the turn odometry reports (``window_rad + window_per_rad * |turn|``, at most
``max_window_rad``); the score of a heading is ``Σ exp(-d²/2σ²)`` over the thinned scan points,
``d`` the distance to the map sampled every ``sample_m`` along its segments (a k-d tree).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from robot_agent.slam import kernels
from shared.geometry import sample_segments


@dataclass(frozen=True)
class CoarseConfig:
    enabled: bool = True
    window_rad: float = float(np.radians(5.0))  # half window when odometry reports no turn ...
    window_per_rad: float = 0.5  # ... plus this share of the turn it reports ...
    max_window_rad: float = float(np.radians(20.0))  # ... at most this (Cartographer's window; at
    # 30° MIT-CSAIL's scan fit a junction 28° off better than the right heading)
    step_rad: float = float(np.radians(1.0))  # headings tried: within the Gauss-Newton's reach
    points: int = 90  # scan points scored (evenly thinned)
    sample_m: float = 0.05  # map segments sampled this densely (a point mid each piece)
    sigma_m: float = 0.1  # score kernel width: tolerant of the translation left to refine
    compiled: bool = True  # the nearest-sample search by the compiled kernel (kernels.py) when built


def heading_offset(
    pose: np.ndarray, points: np.ndarray, segments: np.ndarray, turn_rad: float, cfg: CoarseConfig
) -> float:
    """The heading offset [rad] (a multiple of ``cfg.step_rad``) at which ``points (N,2)`` (robot
    frame) seen from ``pose (3,)`` rotated by it fit ``segments (C,2,2)`` (map frame) best; 0.0
    when nothing to search or no heading scores better than the prediction."""
    if len(points) == 0 or len(segments) == 0:
        return 0.0
    window = min(cfg.max_window_rad, cfg.window_rad + cfg.window_per_rad * abs(turn_rad))
    n = int(window / cfg.step_rad)
    if n == 0:
        return 0.0
    pts = points
    if len(pts) > cfg.points:
        pts = pts[np.linspace(0, len(pts) - 1, cfg.points).round().astype(int)]
    offsets = cfg.step_rad * np.arange(-n, n + 1)
    th = pose[2] + offsets
    c, s = np.cos(th)[:, None], np.sin(th)[:, None]
    world = np.stack(
        [c * pts[:, 0] - s * pts[:, 1] + pose[0], s * pts[:, 0] + c * pts[:, 1] + pose[1]], axis=-1
    )  # (A,N,2)
    if cfg.compiled and kernels.AVAILABLE:
        samples = kernels.segment_samples(segments, cfg.sample_m)
        d = kernels.nearest_within(samples, world.reshape(-1, 2), 3.0 * cfg.sigma_m)
    else:
        samples = sample_segments(segments, cfg.sample_m)[0]
        d, _ = cKDTree(samples).query(world.reshape(-1, 2), distance_upper_bound=3.0 * cfg.sigma_m)
    score = np.exp(-0.5 * (d.reshape(len(offsets), -1) / cfg.sigma_m) ** 2).sum(axis=1)  # inf -> 0
    best = int(np.argmax(score))
    return float(offsets[best]) if score[best] > score[n] else 0.0
