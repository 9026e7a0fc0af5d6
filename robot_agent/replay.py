"""Run the FastSLAM over a recorded log (offline, one robot) — the library side of `replay`."""

from __future__ import annotations

import dataclasses
import resource
import sys
import time
from dataclasses import dataclass, field

import numpy as np

from robot_agent.backend import Correction, OnlineBackend, Track, correct_trajectory, feed, scan_points_robot
from robot_agent.backend.live import NO_CORRECTION, Frame
from robot_agent.slam.fastslam import FastSLAM, SlamConfig
from robot_agent.sources import LaserLog


@dataclass(frozen=True)
class Snapshot:
    """What the robot would have published as its trajectory after its first ``scans`` scans:
    ``stamps_s (S,)``, ``poses (S,3)`` — the filter's best path as the online back end's latest
    result corrects it (the one before the update in flight: a robot's back end works while the
    filter goes on); ``filter_poses (S,3)`` the path before it."""

    scans: int
    stamps_s: np.ndarray
    poses: np.ndarray
    filter_poses: np.ndarray


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
    online_poses: np.ndarray | None = None  # (S,3) the online back end's path at the end
    online_stats: dict | None = None  # its statistics (time per update: online_s, update_s_max)
    cpu_s: float = 0.0  # the process's CPU time over the same span as ``wall_s`` (all its threads)

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
    """Feed every scan of ``log`` (up to ``limit``) to a fresh filter seeded with ``seed``; the
    pose-graph back end over the whole path at the end (offline).
    ``snapshots``: also run the online back end as an agent does (an update every
    ``online_every_s`` of log time), cut the run into that many equal parts and record, at the
    end of each but the last, the trajectory the robot would publish at that moment
    (:class:`Snapshot`), and the online back end's path at the end (``online_poses``)."""
    n = len(log) if limit is None else min(limit, len(log))
    slam = FastSLAM(cfg, np.random.default_rng(seed))
    marks = (
        set(np.linspace(0, n, snapshots + 1).round().astype(int)[1:-1].tolist()) if snapshots > 1 else set()
    )
    live: list[Snapshot] = []
    online = LiveBackend(log, cfg) if snapshots > 1 and cfg.backend.enabled else None

    def step(i: int) -> None:
        feed(slam, log, i)
        if online is not None:
            online.after(slam, i)
        if i + 1 in marks:
            stamps, poses = slam.best_trajectory()
            if online is None:
                live.append(Snapshot(i + 1, stamps, poses, poses))
            else:
                live.append(Snapshot(i + 1, stamps, online.shown(slam, poses), online.raw(slam, poses)))

    show = sys.stderr.isatty() if progress is None else progress
    t0, c0 = time.perf_counter(), time.process_time()
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
    online_poses = online_stats = None
    hints = slam.loop_hints
    if online is not None:
        online.finish(slam, n)
        online_stats = dict(online.backend.stats, online_s=online.seconds, adoptions=online.frame.adoptions)
        stamps, poses = slam.best_trajectory()  # the filter continued from the corrections
        online_poses = online.shown(slam, poses)
        poses = online.raw(slam, poses)  # the filter's own path: what the offline back end takes
        hints = online.frame.raw_hints(slam, hints)
    else:
        stamps, poses = slam.best_trajectory()
    t1 = time.perf_counter()
    corrected, stats = correct_trajectory(log, 0, stamps, poses, cfg, hints, slam.best_jumps())
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024  # Linux reports KiB
    return ReplayResult(
        stamps,
        corrected,
        slam,
        wall,
        peak,
        poses,
        time.perf_counter() - t1,
        stats,
        live,
        online_poses,
        online_stats,
        cpu,
    )


class LiveBackend:
    """The online back end beside a replayed filter, as an agent runs it: an update every
    ``online_every_s`` of log time over the filter's best path then; what the robot publishes
    meanwhile is the result of the update before (``published``: the one in flight is not
    done yet). Without the agent's time bounds per update (``online_budget_s``,
    ``online_optimize_s``): a replay gives the same result on any machine (on the development
    logs no update comes near them: 2.0 s at most on Intel, no optimization cut)."""

    def __init__(self, log: LaserLog, cfg: SlamConfig):
        self.log, self.cfg = log, cfg
        unbounded = dataclasses.replace(cfg.backend, online_budget_s=0.0, online_optimize_s=0.0)
        self.backend = OnlineBackend(unbounded)
        self.published = NO_CORRECTION
        self._pending = self.published
        self.frame = Frame()  # the correction the filter continues from (backend.online_adopt)
        self._next_s = -np.inf
        self._clock = -np.inf
        self.seconds = 0.0  # spent in updates
        self._hints = 0  # the filter's relocalizations passed on so far

    def after(self, slam: FastSLAM, i: int) -> None:
        """Scan ``i`` was just fed to ``slam``: update when due."""
        self._clock = max(self._clock, float(self.log.stamps_s[i]))
        if self._clock < self._next_s:
            return
        self._next_s = self._clock + self.cfg.backend.online_every_s
        self._publish(slam, self._pending)
        self._pending = self._update(slam, i + 1, self.backend.update)

    def finish(self, slam: FastSLAM, n: int) -> Correction:
        """The last update, at the end of the source (every moved keyframe searched again)."""
        self._pending = self._update(slam, n, self.backend.finish)
        self._publish(slam, self._pending)
        return self.published

    def raw(self, slam: FastSLAM, poses: np.ndarray) -> np.ndarray:
        """The filter's whole path ``poses (S,3)`` without the correction it continues from."""
        return self.frame.raw(slam, np.arange(len(poses)), poses)

    def shown(self, slam: FastSLAM, poses: np.ndarray) -> np.ndarray:
        """The filter's whole path as the robot publishes it: the published correction's."""
        return self.published.apply(self.raw(slam, poses))

    def _publish(self, slam: FastSLAM, c: Correction) -> None:
        self.published = c
        if self.cfg.backend.online_adopt:
            self.frame.adopt(slam, c)

    def _update(self, slam: FastSLAM, n: int, how) -> Correction:
        t0 = time.perf_counter()
        stamps, poses = slam.best_trajectory()
        track = Track.whole(stamps, self.raw(slam, poses), self.log.odometry[:n], slam.best_jumps())
        hints, self._hints = slam.hints_since(self._hints)
        out = how(
            track, lambda k: scan_points_robot(self.log, k, self.cfg), hints=self.frame.raw_hints(slam, hints)
        )
        self.seconds += time.perf_counter() - t0
        return out
