"""Run the FastSLAM over a recorded log (offline, one robot) — the library side of `replay`."""

from __future__ import annotations

import resource
import sys
import time
from dataclasses import dataclass

import numpy as np

from robot_agent.slam.backend import run_backend
from robot_agent.slam.extraction import scan_points
from robot_agent.slam.fastslam import FastSLAM, SlamConfig
from robot_agent.sources import LaserLog
from shared.geometry import apply_points


@dataclass
class ReplayResult:
    stamps_s: np.ndarray  # (S,) every scan's own timestamp
    poses: np.ndarray  # (S,3) final best particle's trajectory, corrected by the back end
    slam: FastSLAM
    wall_s: float
    peak_rss_bytes: int
    filter_poses: np.ndarray | None = None  # (S,3) the same before the back end
    backend_s: float = 0.0
    backend_stats: dict | None = None

    @property
    def scans(self) -> int:
        return len(self.stamps_s)


def replay(
    log: LaserLog,
    cfg: SlamConfig,
    seed: int = 0,
    progress: bool | None = None,
    limit: int | None = None,
) -> ReplayResult:
    """Feed every scan of ``log`` (up to ``limit``) to a fresh filter seeded with ``seed``."""
    n = len(log) if limit is None else min(limit, len(log))
    slam = FastSLAM(cfg, np.random.default_rng(seed))
    show = sys.stderr.isatty() if progress is None else progress
    t0 = time.perf_counter()
    if show:
        from rich.progress import BarColumn, MofNCompleteColumn, Progress, TimeRemainingColumn

        with Progress(
            "[progress.description]{task.description}",
            BarColumn(),
            MofNCompleteColumn(),
            TimeRemainingColumn(),
        ) as bar:
            task = bar.add_task("replay", total=n)
            for i in range(n):
                _step(slam, log, i)
                if i % 50 == 0:
                    bar.update(task, completed=i + 1)
            bar.update(task, completed=n)
    else:
        for i in range(n):
            _step(slam, log, i)
    stamps, poses = slam.best_trajectory()
    t1 = time.perf_counter()
    corrected, stats = poses, None
    if cfg.backend.enabled and len(poses) > 1:

        def points(i: int) -> np.ndarray:
            xy = scan_points(log.ranges_m[i], log.angles_rad, cfg.extraction, log.range_max_m)
            return apply_points(log.laser_offset, xy)

        corrected, stats = run_backend(stamps, poses, log.odometry[:n], points, cfg.backend)
    wall = time.perf_counter() - t0
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024  # Linux reports KiB
    return ReplayResult(stamps, corrected, slam, wall, peak, poses, time.perf_counter() - t1, stats)


def _step(slam: FastSLAM, log: LaserLog, i: int) -> None:
    slam.step(
        float(log.stamps_s[i]),
        log.odometry[i],
        log.ranges_m[i],
        log.angles_rad,
        log.laser_offset,
        log.range_max_m,
    )
