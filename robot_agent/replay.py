"""Run the FastSLAM over a recorded log (offline, one robot) — the library side of `replay`."""

from __future__ import annotations

import resource
import sys
import time
from dataclasses import dataclass, field

import numpy as np

from robot_agent.backend import correct_trajectory, feed
from robot_agent.slam.fastslam import FastSLAM, SlamConfig
from robot_agent.sources import LaserLog


@dataclass(frozen=True)
class Snapshot:
    """What the robot would have published as its trajectory after its first ``scans`` scans:
    ``stamps_s (S,)``, ``poses (S,3)`` (today the filter's best particle's path: the back end
    runs when the source ends)."""

    scans: int
    stamps_s: np.ndarray
    poses: np.ndarray


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
    live: list[Snapshot] = field(default_factory=list)  # snapshots during the run (``snapshots``)

    @property
    def scans(self) -> int:
        return len(self.stamps_s)


def replay(
    log: LaserLog,
    cfg: SlamConfig,
    seed: int = 0,
    progress: bool | None = None,
    limit: int | None = None,
    snapshots: int = 0,
) -> ReplayResult:
    """Feed every scan of ``log`` (up to ``limit``) to a fresh filter seeded with ``seed``.
    ``snapshots``: cut the run into that many equal parts and record, at the end of each but the
    last, the trajectory the robot would publish at that moment (:class:`Snapshot`)."""
    n = len(log) if limit is None else min(limit, len(log))
    slam = FastSLAM(cfg, np.random.default_rng(seed))
    marks = (
        set(np.linspace(0, n, snapshots + 1).round().astype(int)[1:-1].tolist()) if snapshots > 1 else set()
    )
    live: list[Snapshot] = []

    def step(i: int) -> None:
        feed(slam, log, i)
        if i + 1 in marks:
            live.append(Snapshot(i + 1, *slam.best_trajectory()))

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
                step(i)
                if i % 50 == 0:
                    bar.update(task, completed=i + 1)
            bar.update(task, completed=n)
    else:
        for i in range(n):
            step(i)
    stamps, poses = slam.best_trajectory()
    t1 = time.perf_counter()
    corrected, stats = correct_trajectory(log, 0, stamps, poses, cfg, slam.loop_hints, slam.best_jumps())
    wall = time.perf_counter() - t0
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024  # Linux reports KiB
    return ReplayResult(stamps, corrected, slam, wall, peak, poses, time.perf_counter() - t1, stats, live)
