"""Score a SLAM run on a simulated log against the simulator's truth (benchmarks and tests).

- ATE RMSE after SE(2) alignment of the estimated to the true path (shared/metrics.py);
- map precision and completeness of the published segments (aligned by the same transform)
  against the walls the robot actually saw from its true path (docs/design.md);
- loop closure: for every pair of true poses that are close in space but far apart in time
  (the robot came back), the error of the estimated relative pose. A loop is closed when the
  95th percentile of that error is below ``loop_tolerance_m``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from robot_agent.sim.lidar import LidarConfig, beam_angles, cast_rays
from robot_agent.sim.simulate import SimRun
from robot_agent.sim.world import World
from shared.geometry import apply_segments, relative
from shared.metrics import ate, map_quality

SEEN_EVERY = 5  # scans between the true-path poses used to decide which walls were seen


@dataclass(frozen=True)
class SimScore:
    ate_rmse_m: float
    precision: float
    completeness: float
    revisit_pairs: int  # pairs of true poses close in space and far in time
    revisit_p95_m: float  # 95th percentile of their relative-pose error (nan without pairs)
    loop_closed: bool

    def as_dict(self) -> dict:
        return {k: getattr(self, k) for k in self.__dataclass_fields__}


def seen_wall_points(
    world: World, truth: np.ndarray, lidar: LidarConfig, every: int = SEEN_EVERY
) -> np.ndarray:
    """Points ``(K,2)`` where the true beams hit walls, from every ``every``-th true pose."""
    poses = truth[::every]
    dirs = poses[:, 2:3] + beam_angles(lidar)[None, :]
    ranges = cast_rays(poses[:, :2], dirs, world.walls, lidar.range_max_m)
    hit = ranges < lidar.range_max_m
    pts = np.stack([poses[:, :1] + ranges * np.cos(dirs), poses[:, 1:2] + ranges * np.sin(dirs)], -1)
    return pts[hit]


def true_beams(
    world: World, truth: np.ndarray, lidar: LidarConfig, every: int = SEEN_EVERY
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The true beams from every ``every``-th true pose: origins ``(N,2)``, ends ``(N,2)`` and
    whether each hit a wall ``(N,)`` (what the sensors covered, for scoring a free-space grid)."""
    poses = truth[::every]
    dirs = poses[:, 2:3] + beam_angles(lidar)[None, :]
    ranges = cast_rays(poses[:, :2], dirs, world.walls, lidar.range_max_m)
    ends = np.stack([poses[:, :1] + ranges * np.cos(dirs), poses[:, 1:2] + ranges * np.sin(dirs)], -1)
    origins = np.broadcast_to(poses[:, None, :2], ends.shape)
    return origins.reshape(-1, 2), ends.reshape(-1, 2), (ranges < lidar.range_max_m).ravel()


def revisit_errors(
    truth: np.ndarray,
    stamps_s: np.ndarray,
    estimate: np.ndarray,
    radius_m: float = 1.0,
    min_gap_s: float = 60.0,
    stride: int = 10,
) -> np.ndarray:
    """Relative-pose translation errors ``(R,)`` over pairs of scans (every ``stride``-th) whose
    true positions are within ``radius_m`` and whose stamps differ by ``min_gap_s`` or more."""
    idx = np.arange(0, len(truth), stride)
    t, e, s = truth[idx], estimate[idx], stamps_s[idx]
    near = np.hypot(*(t[:, None, :2] - t[None, :, :2]).transpose(2, 0, 1)) < radius_m
    far = (s[None, :] - s[:, None]) >= min_gap_s
    i, j = np.nonzero(near & far)
    if len(i) == 0:
        return np.zeros(0)
    err = relative(e[i], e[j]) - relative(t[i], t[j])
    return np.hypot(err[:, 0], err[:, 1])


def score_run(
    sim: SimRun,
    world: World,
    stamps_s: np.ndarray,
    poses: np.ndarray,
    segments: np.ndarray,
    lidar: LidarConfig | None = None,
    loop_tolerance_m: float = 0.2,
    map_poses: np.ndarray | None = None,
) -> SimScore:
    """Score the estimated ``poses (S,3)`` (one per scan of ``sim``) and mapped ``segments``. The
    map is put in the world frame by the best fit of ``map_poses`` — the trajectory in the map's
    own frame (the filter's, when ``poses`` were corrected afterwards by the back end) — to the
    truth; default ``poses``."""
    if len(poses) != len(sim.stamps_s):
        raise ValueError(f"poses must have one row per scan ({len(sim.stamps_s)}), got {len(poses)}")
    a = ate(stamps_s, poses, sim.stamps_s, sim.truth)
    frame = a if map_poses is None else ate(stamps_s, map_poses, sim.stamps_s, sim.truth)
    mapped = apply_segments(frame.alignment, np.asarray(segments, dtype=float).reshape(-1, 2, 2))
    seen = seen_wall_points(world, sim.truth, lidar or LidarConfig())
    q = map_quality(mapped, world.walls, seen_points=seen)
    rev = revisit_errors(sim.truth, sim.stamps_s, poses)
    p95 = float(np.percentile(rev, 95)) if len(rev) else float("nan")
    return SimScore(
        a.rmse_m, q.precision, q.completeness, len(rev), p95, bool(len(rev)) and p95 < loop_tolerance_m
    )
