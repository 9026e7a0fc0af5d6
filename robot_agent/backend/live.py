"""The online back end beside a running filter: what an agent runs.

:class:`LiveCorrector` keeps the few scans the back end has not turned into keyframes yet, hands
it the filter's best path every ``online_every_s`` of the source's time, and holds the latest
:class:`~robot_agent.backend.online.Correction` — which the agent applies to the pose and the map
it publishes. The back end works in a process of its own (:class:`ProcessRunner`): the filter
never waits for it, and does not share the interpreter's lock with it; :class:`InlineRunner` runs
it in the caller's thread instead (tests, and a replay's deterministic snapshots).

What is handed over per update is bounded: the path from the back end's last keyframe on (scans
kept for it at most ``max_tail`` — a robot that stands still for long keeps the newest), the path's
poses at the keyframes, the relocalizations since the last update.
"""

from __future__ import annotations

import multiprocessing
import time
from collections import deque
from dataclasses import dataclass

import numpy as np

from robot_agent.backend.online import Correction, OnlineBackend, Track
from robot_agent.slam.extraction import scan_points
from robot_agent.slam.fastslam import FastSLAM, SlamConfig
from robot_agent.slam.trajectory import keyframe_of
from shared.geometry import apply_points, compose, inverse
from shared.memory import release_free_memory
from shared.messages import MAX_GRAPH_EDGES, MAX_KEYFRAMES, info_upper


@dataclass(frozen=True)
class ScanRecord:
    """What the back end needs of one scan: its index in the run, stamp, raw odometry, and its
    points in the robot frame (valid beams, laser mount applied; float32)."""

    index: int
    stamp_s: float
    odometry: np.ndarray
    points: np.ndarray


@dataclass(frozen=True)
class Job:
    track: Track
    points: dict  # scan index -> (N,2) robot-frame points of the track's scans
    kf_poses: np.ndarray
    hints: list
    final: bool = False
    keep: tuple | None = None  # (scans, first): what the caller will still ask corrections of
    late_jumps: tuple = ()  # (scan, pose before, pose at): jumps between keyframes already made


def run_job(backend: OnlineBackend, job: Job) -> tuple[Correction, dict]:
    def points_of(i: int) -> np.ndarray:
        return np.asarray(job.points[i], dtype=float)

    how = backend.finish if job.final else backend.update
    late = list(job.late_jumps)
    corr = how(job.track, points_of, kf_poses=job.kf_poses, hints=job.hints, keep=job.keep, late_jumps=late)
    return corr, dict(backend.stats)


@dataclass(frozen=True)
class Failure:
    """An update the back end could not do, and why (the back end itself goes on)."""

    error: str


class InlineRunner:
    """The back end in the caller's thread: ``submit`` computes at once."""

    def __init__(self, cfg: SlamConfig):
        self.backend = OnlineBackend(cfg.backend)
        self._done: tuple[Correction, dict] | None = None

    @property
    def busy(self) -> bool:
        return False

    def submit(self, job: Job) -> None:
        try:
            self._done = run_job(self.backend, job)
        except Exception as exc:  # as the process runner: the caller goes on
            self._done = Failure(f"{type(exc).__name__}: {exc}")

    def poll(self, timeout_s: float = 0.0) -> tuple[Correction, dict] | None:
        done, self._done = self._done, None
        return done

    def close(self) -> None:
        pass


def _serve(conn, cfg: SlamConfig) -> None:  # pragma: no cover - runs in the child process
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the agent decides when its back end stops
    backend = OnlineBackend(cfg.backend)
    while True:
        try:
            job = conn.recv()
        except (EOFError, OSError):
            return
        if job is None:
            return
        try:
            conn.send(run_job(backend, job))
        except Exception as exc:  # an update that fails must not take the back end with it
            conn.send(Failure(f"{type(exc).__name__}: {exc}"))
        del job
        release_free_memory()  # the update's temporaries back to the system (runs for days)


class ProcessRunner:
    """The back end in a child process (spawned: no state of the parent's bus is inherited)."""

    def __init__(self, cfg: SlamConfig):
        ctx = multiprocessing.get_context("spawn")
        self._conn, child = ctx.Pipe()
        self._proc = ctx.Process(target=_serve, args=(child, cfg), name="fleet-slam-backend", daemon=True)
        self._proc.start()
        child.close()
        self._busy = False

    @property
    def busy(self) -> bool:
        return self._busy

    @property
    def pid(self) -> int | None:
        return self._proc.pid

    def submit(self, job: Job) -> None:
        if self._busy:
            raise RuntimeError("the back end is still working on the last update")
        self._conn.send(job)
        self._busy = True

    def poll(self, timeout_s: float = 0.0) -> tuple[Correction, dict] | None:
        if not self._busy:
            return None
        if not self._proc.is_alive() and not self._conn.poll():
            raise RuntimeError(f"the back end process exited (code {self._proc.exitcode})")
        if not self._conn.poll(timeout_s):
            return None
        self._busy = False
        return self._conn.recv()

    def close(self) -> None:
        try:
            self._conn.send(None)
        except (OSError, ValueError):
            pass
        self._proc.join(2.0)
        if self._proc.is_alive():
            self._proc.terminate()
            self._proc.join(2.0)
        self._conn.close()


NO_CORRECTION = Correction(np.zeros(0, int), np.zeros((0, 3)), np.zeros((0, 3)))


def correction_moves(c: Correction, scans: np.ndarray) -> np.ndarray:
    """The transform ``(N,3)`` (on the left) that correction ``c`` moves scans ``scans (N,)``
    by: its last keyframe's at or before each (before the first, the first's; none: identity)."""
    scans = np.asarray(scans)
    if len(c.kf_scan) == 0:
        return np.zeros((*scans.shape, 3))
    k = keyframe_of(c.kf_scan, scans)
    return compose(c.corrected[k], inverse(c.filter[k]))


class Frame:
    """Which correction the filter's own frame already carries (:meth:`adopt`): the back end
    works on the filter's path as it would be without any (:meth:`raw`), so that its chain
    edges stay the filter's own motions and its answers stay whole corrections of that path.
    Every kept scan moves with its processed step's scan (:meth:`Trajectory.anchor_scans`), as
    :meth:`FastSLAM.move_frame` moves it."""

    def __init__(self) -> None:
        self.adopted = NO_CORRECTION
        self.adoptions = 0

    def raw(self, slam: FastSLAM, scans: np.ndarray, poses: np.ndarray) -> np.ndarray:
        """Poses ``(N,3)`` of kept scans ``scans (N,)`` in the filter's frame, as they would be
        without the adopted correction."""
        if len(self.adopted.kf_scan) == 0 or len(scans) == 0:
            return np.asarray(poses, float)
        at = correction_moves(self.adopted, slam.trajectory.anchor_scans(scans))
        return compose(inverse(at), poses)

    def raw_hints(self, slam: FastSLAM, hints: list) -> list:
        """The relocalizations ``[(scan, pose (3,)), ...]`` of scans still kept, as :meth:`raw`."""
        kept = [(int(i), p) for i, p in hints if i >= slam.trajectory.first_scan]
        if not kept:
            return []
        raw = self.raw(slam, np.array([i for i, _ in kept]), np.array([p for _, p in kept]))
        return [(i, r) for (i, _), r in zip(kept, raw, strict=True)]

    def relative_moves(self, c: Correction, scans: np.ndarray) -> np.ndarray:
        """What correction ``c`` still moves the filter's current frame by at scans ``scans``."""
        return compose(correction_moves(c, scans), inverse(correction_moves(self.adopted, scans)))

    def adopt(self, slam: FastSLAM, c: Correction) -> None:
        """The filter continues from correction ``c``: its frame moves by what ``c`` adds to
        the adopted one, piecewise between the keyframes of both — but for ``c``'s gauge, which
        only what is published takes (Correction.ungauged: the filter's frame stays its own
        start's, and the filter runs as it would without the gauge)."""
        c = c.ungauged()
        breaks = np.union1d(c.kf_scan, self.adopted.kf_scan).astype(int)
        if len(breaks):
            slam.move_frame(breaks, self.relative_moves(c, breaks))
        self.adopted = c
        self.adoptions += 1


def graph_fields(c: Correction, scans: np.ndarray, gauge: np.ndarray | None = None) -> dict:
    """Correction ``c``'s pose graph as a map message's fields (``kf_id`` ... ``anchor``,
    :class:`shared.messages.RobotMap`) for elements made from ``scans (N,)``; ``gauge (3,)``: the
    published map frame is the correction's moved by it (a rebuilt map's start gauge). Empty
    without a graph, or with more keyframes than a message may hold (the map then moves
    rigidly); edges beyond a message's bound: the last loops are left out (the chain and the
    edges carried over come first)."""
    g = c.graph
    if g is None or len(g.scan) > MAX_KEYFRAMES:
        return {}
    e = min(len(g.a), MAX_GRAPH_EDGES)
    return dict(
        kf_id=g.scan, kf_stamp=g.stamp_s, kf_pose=g.pose if gauge is None else compose(gauge, g.pose),
        edge_ids=np.column_stack([g.a[:e], g.b[:e]]), edge_z=g.z[:e], edge_info=info_upper(g.info[:e]),
        anchor=c.anchors(scans),
    )  # fmt: skip


class LiveCorrector:
    """Feeds the online back end from a running filter and holds its latest correction.

    Call :meth:`on_scan` after every scan given to the filter and :meth:`tick` as often as
    convenient (it never blocks); apply :attr:`correction` to what is published
    (:meth:`pose`, :meth:`segments`)."""

    def __init__(self, slam: FastSLAM, runner=None, max_tail: int = 2000):
        self.slam = slam
        self.cfg = slam.cfg
        self.runner = InlineRunner(slam.cfg) if runner is None else runner
        self.correction = NO_CORRECTION  # the latest, of the filter's path without any (Frame.raw)
        self.frame = Frame()  # the correction the filter continues from (backend.online_adopt)
        self.stats: dict = {}
        self.max_tail = max_tail
        self.dropped_tail = 0  # scans dropped from an overlong tail (the robot stood still)
        self.scans: dict[int, np.ndarray] = {}  # graph keyframe (scan) -> its scan's points, robot frame
        self._tail: deque[ScanRecord] = deque()
        self._kf_scan = np.zeros(0, int)  # the back end's keyframes as of its last answer
        self._hints = 0
        self._clock = -np.inf
        self._next_s = -np.inf
        self.updates = 0
        self.seconds_waited = 0.0  # the caller's time spent waiting (only in finish)
        self.update_s_recent = 0.0  # the longest update collected since the caller reset it
        self._sent = 0  # scans of the tail handed over in the update in flight
        self.failures = 0  # updates the back end could not do (it said why: last_failure)
        self.last_failure = ""

    def on_scan(
        self, stamp_s: float, odometry, ranges_m, angles_rad, laser_offset, range_max_m=np.inf
    ) -> None:
        """The scan just given to the filter (the filter's scan index is the count so far)."""
        index = len(self.slam.trajectory) - 1
        ext = self.cfg.extraction
        pts = apply_points(
            laser_offset, scan_points(np.asarray(ranges_m), np.asarray(angles_rad), ext, range_max_m)
        )
        rec = ScanRecord(index, float(stamp_s), np.asarray(odometry, float).copy(), pts.astype(np.float32))
        self._tail.append(rec)
        # too long (the robot stood still for long, or the back end is slow): the oldest scan
        # not handed over goes — never the last keyframe's (the first), nor one handed over in
        # the update in flight (it may be that update's newest keyframe, which the next update's
        # path must start from), nor the newest
        drop = max(self._sent, 1)
        if len(self._tail) > self.max_tail and drop < len(self._tail) - 1:
            del self._tail[drop]
            self.dropped_tail += 1
        self._clock = max(self._clock, float(stamp_s))

    def tick(self) -> bool:
        """Collect a finished update (True when a new correction came) and start the next one
        when it is due and the back end is idle."""
        fresh = self._collect(self.runner.poll(0.0))
        if self._tail and not self.runner.busy and self._clock >= self._next_s:
            self._next_s = self._clock + self.cfg.backend.online_every_s
            self.runner.submit(self._job(final=False))
            fresh = self._collect(self.runner.poll(0.0)) or fresh
        return fresh

    def finish(self, timeout_s: float) -> bool:
        """The last update (every moved keyframe searched again), waited for at most
        ``timeout_s`` (the update in flight first); True when it came in time."""
        t0 = time.monotonic()
        try:
            while self.runner.busy:
                left = timeout_s - (time.monotonic() - t0)
                if left <= 0:
                    return False
                self._collect(self.runner.poll(min(left, 0.1)))
            if not self._tail:
                return True
            self.runner.submit(self._job(final=True))
            while True:
                left = timeout_s - (time.monotonic() - t0)
                if left <= 0:
                    return False
                if self._collect(self.runner.poll(min(left, 0.1))):
                    return True
                if not self.runner.busy:  # it could not (last_failure says why)
                    return False
        finally:
            self.seconds_waited += time.monotonic() - t0

    def close(self) -> None:
        self.runner.close()

    # --- applying the correction -----------------------------------------------------------

    def pose(self, pose: np.ndarray) -> np.ndarray:
        """The corrected pose of the newest scan, at ``pose`` in the filter's map."""
        traj = self.slam.trajectory
        if len(self.correction.kf_scan) == 0 or len(traj) == 0:
            return np.array(pose, dtype=float, copy=True)
        newest = len(traj) - 1
        return self.correction.pose(newest, self.frame.raw(self.slam, np.array([newest]), pose[None])[0])

    def raw_path(self, poses: np.ndarray, first: int = 0) -> np.ndarray:
        """The filter's path ``poses (S,3)`` (scan ``first + i`` is ``poses[i]``) without the
        correction it continues from: the filter's own."""
        return self.frame.raw(self.slam, np.arange(first, first + len(poses)), poses)

    def corrected_path(self, poses: np.ndarray, first: int = 0) -> np.ndarray:
        """The filter's path ``poses (S,3)`` (from scan ``first``) as the latest correction
        puts it."""
        return self.correction.apply(self.raw_path(poses, first), first)

    def segments(self, seg: np.ndarray, born_step: np.ndarray) -> np.ndarray:
        """Segments ``(N,2,2)`` of the filter's map, each moved with the keyframe of the scan
        that created it (``born_step (N,)``: :attr:`SegmentMaps.born`)."""
        c = self.correction
        if len(c.kf_scan) == 0 or len(seg) == 0 or c is self.frame.adopted:  # (the filter's map is it)
            return seg
        scan = self.slam.trajectory.scan_of_step(np.maximum(born_step, 1))
        move = self.frame.relative_moves(c, scan)  # (N,3): filter map -> corrected
        cos, sin = np.cos(move[:, 2]), np.sin(move[:, 2])
        x, y = seg[..., 0], seg[..., 1]
        out = np.empty_like(seg)
        out[..., 0] = cos[:, None] * x - sin[:, None] * y + move[:, 0, None]
        out[..., 1] = sin[:, None] * x + cos[:, None] * y + move[:, 1, None]
        return out

    def graph_fields(self, born_step: np.ndarray) -> dict:
        """:func:`graph_fields` of the latest correction, for elements born at ``born_step (N,)``
        (each anchored to the graph keyframe its scan's keyframe moves with)."""
        scan = self.slam.trajectory.scan_of_step(np.maximum(np.asarray(born_step), 1))
        return graph_fields(self.correction, scan)

    # --- the hand-over ---------------------------------------------------------------------

    def _job(self, final: bool) -> Job:
        slam = self.slam
        best = slam.particles.best()
        recs = list(self._tail)
        self._sent = len(recs)
        idx = np.array([r.index for r in recs], dtype=int)
        poses, jumps = self._filter_poses(best, idx)  # (the last keyframe's may be forgotten)
        track = Track(
            idx,
            np.array([r.stamp_s for r in recs]),
            poses,
            np.array([r.odometry for r in recs]).reshape(-1, 3),
            jumps,
        )
        kf_poses, _ = self._filter_poses(best, self._kf_scan)
        hints, self._hints = slam.hints_since(self._hints)
        hints = self.frame.raw_hints(slam, hints)  # in the filter's own frame, as the path
        keep = None
        traj = slam.trajectory
        if traj.first_scan > 0:  # a run without end: what the map and the kept path refer to
            keep = (traj.scan_of_step(np.maximum(slam.referenced_steps(), 1)), traj.first_scan)
        late = self._late_jumps(best)
        return Job(track, {r.index: r.points for r in recs}, kf_poses, list(hints), final, keep, late)

    def _late_jumps(self, particle: int) -> tuple:
        """The relocalization jumps on ``particle``'s lineage between the back end's first and
        last keyframes (``(scan, pose before, pose at)``, in the filter's own frame): a lineage
        that became the best after its keyframes were made brings its jumps only here (the
        track holds the scans since the last keyframe). Of the scans the filter still keeps."""
        if len(self._kf_scan) < 2:
            return ()
        lo = max(int(self._kf_scan[0]), self.slam.trajectory.first_scan)
        hi = int(self._kf_scan[-1])
        if hi <= lo:
            return ()
        scans = np.arange(lo, hi + 1)
        poses, jumps = self.slam.trajectory.lineage_at(particle, scans)
        at = np.flatnonzero(jumps[1:]) + 1
        if not len(at):
            return ()
        poses = self.frame.raw(self.slam, scans, poses)
        return tuple((int(scans[i]), poses[i - 1], poses[i]) for i in at)

    def _filter_poses(self, particle: int, scans: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The filter's poses ``(N,3)`` and jump flags ``(N,)`` of scans ``scans (N,)`` along
        ``particle``'s history (:meth:`Trajectory.lineage_at`), without the adopted correction
        (:meth:`Frame.raw`); of scans the filter no longer
        keeps (its path's oldest part is closed, and forgotten in a run without end), the poses
        the back end reported last (no jump)."""
        old = scans < self.slam.trajectory.first_scan
        if not old.any():
            poses, jumps = self.slam.trajectory.lineage_at(particle, scans)
            return self.frame.raw(self.slam, scans, poses), jumps
        out, jumps = np.empty((len(scans), 3)), np.zeros(len(scans), bool)
        out[~old], jumps[~old] = self.slam.trajectory.lineage_at(particle, scans[~old])
        out[~old] = self.frame.raw(self.slam, scans[~old], out[~old])
        c = self.correction
        at = np.searchsorted(c.kf_scan, scans[old])
        if np.any(at >= len(c.kf_scan)) or np.any(
            c.kf_scan[np.minimum(at, len(c.kf_scan) - 1)] != scans[old]
        ):
            raise ValueError("a keyframe's scan is neither kept by the filter nor in the last correction")
        out[old] = c.filter[at]
        return out, jumps

    def _keep_scans(self, g) -> None:
        """The keyframe scans ``g`` hands out, kept for what is published (those of keyframes no
        longer in the graph dropped: bounded by the graph)."""
        if g is None:
            return
        self.scans.update(zip(g.new_scan.tolist(), g.new_points, strict=True))
        if len(self.scans) > len(g.scan):
            self.scans = {k: self.scans[k] for k in g.scan.tolist() if k in self.scans}

    def _collect(self, done) -> bool:
        if done is None:
            return False
        self._sent = 0
        if isinstance(done, Failure):  # the robot goes on with the last correction; the scans
            self.failures += 1  # stay for the next update
            self.last_failure = done.error
            return False
        self.correction, self.stats = done
        self.updates += 1
        self._keep_scans(self.correction.graph)
        if self.cfg.backend.online_adopt:
            self.frame.adopt(self.slam, self.correction)
        self.update_s_recent = max(self.update_s_recent, self.stats.get("update_s_last", 0.0))
        graph = self.correction.graph_scan
        self._kf_scan = self.correction.kf_scan if graph is None else graph
        if len(self._kf_scan):  # the back end will not need the scans before its last keyframe
            last = int(self._kf_scan[-1])
            while self._tail and self._tail[0].index < last:
                self._tail.popleft()
        return True
