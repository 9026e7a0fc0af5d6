"""Run the FastSLAM over a recorded log (offline, one robot) — the library side of `replay`."""

from __future__ import annotations

import resource
import sys
import time
from dataclasses import dataclass, field, replace

import numpy as np

from robot_agent.slam.backend import run_backend
from robot_agent.slam.extraction import scan_points
from robot_agent.slam.fastslam import FastSLAM, SlamConfig
from robot_agent.sources import LaserLog
from shared.geometry import apply_points, compose, inverse
from shared.metrics import align_se2


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
        _step(slam, log, i)
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


def correct_trajectory(
    log: LaserLog,
    first: int,
    stamps: np.ndarray,
    poses: np.ndarray,
    cfg: SlamConfig,
    hints: list[tuple[int, np.ndarray]] | None = None,
    jumps: np.ndarray | None = None,
    gauge: str = "fit",
) -> tuple[np.ndarray, dict | None]:
    """The back end (pose graph) over ``poses (S,3)``, the trajectory of scans ``first ..
    first + S - 1`` of ``log``: the corrected poses and the back end's statistics (``poses`` and
    ``None`` when it is disabled).

    ``gauge``: ``"fit"`` puts the corrected trajectory where it fits ``poses`` best (it then
    agrees with the filter's map, drawn along ``poses``); ``"start"`` keeps its first pose at
    ``poses[0]`` — the map frame stays the robot's start frame, for a map rebuilt along the
    corrected path (:func:`remap`) that a server places against a start prior or other robots."""
    if gauge not in ("fit", "start"):
        raise ValueError(f"gauge must be 'fit' or 'start', got {gauge!r}")
    if not cfg.backend.enabled or len(poses) < 2:
        return poses, None

    def points(i: int) -> np.ndarray:
        scan = log.scan(first + i)
        xy = scan_points(scan.ranges_m, scan.angles_rad, cfg.extraction, scan.range_max_m)
        return apply_points(scan.laser_offset, xy)

    odometry = log.odometry[first : first + len(poses)]
    corrected, stats = run_backend(stamps, poses, odometry, points, cfg.backend, hints, jumps)
    if gauge == "start":
        return compose(compose(poses[0], inverse(corrected[0])), corrected), stats
    # the pose graph holds the first pose fixed, an arbitrary gauge: the map (built along the
    # filter's trajectory) is in the frame that fits the filter's trajectory best, so that is where
    # the corrected trajectory is put (relative motions, what relations score, are unchanged)
    gauge = align_se2(corrected[:, :2], poses[:, :2])
    return compose(gauge, corrected), stats


def remap(log: LaserLog, first: int, poses: np.ndarray, cfg: SlamConfig) -> FastSLAM:
    """A one-particle filter whose map is built along ``poses (S,3)``, the known poses of scans
    ``first .. first + S - 1`` of ``log`` (e.g. the back end's corrected trajectory): the same
    extraction, association, update and cleaning, no sampling and no relocalization. Its map and
    those poses agree, which the filter's map (drawn along the uncorrected path) does not."""
    known = replace(cfg, particles=1, relocalization=replace(cfg.relocalization, enabled=False))
    slam = FastSLAM(known, np.random.default_rng(0))
    for i in range(len(poses)):
        _step(slam, log, first + i, poses[i])
    return slam


def _step(slam: FastSLAM, log: LaserLog, i: int, pose: np.ndarray | None = None) -> None:
    scan = log.scan(i)  # its own beams: the geometry may change from scan to scan
    slam.step(
        scan.stamp_s, scan.odometry, scan.ranges_m, scan.angles_rad, scan.laser_offset, scan.range_max_m, pose
    )
