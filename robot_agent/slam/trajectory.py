"""Every particle's full trajectory without copying it at each resampling: an ancestry tree.

Each processed step stores the propagated poses ``(P,3)`` and each particle's parent index in
the previous step; the best particle's trajectory is read back by walking the parents. Scans
skipped for too little motion are stored as an odometry increment from the last processed step,
so the output has one pose for every scan, with the scan's own timestamp.

Bounded by what is still open: once every living particle descends from one ancestor at some
step (the lineages coalesce, as they do within a few resamplings), the steps up to it have one
history left, and are kept as that one pose per step (24 bytes instead of ``P`` poses and
parents). What stays per scan is its stamp, its step and its offset from it (40 bytes).

A run without end keeps the newest ``max_scans`` scans (:meth:`Trajectory.forget`; 0: all):
scan and step numbers stay those of the whole run (``first_scan`` is the first still kept), and
the scan of a forgotten step is remembered for the steps the caller still refers to (its map's
elements were made there).
"""

from __future__ import annotations

import numpy as np

from shared.geometry import compose

COMPACT_EVERY = 32  # processed steps between looks for a common ancestor


def keyframe_of(kf_scan: np.ndarray, scans) -> np.ndarray:
    """Index into ``kf_scan (K,)`` (increasing) of the last keyframe at or before each of
    ``scans`` (before the first, the first): whose correction moves that scan."""
    return np.maximum(np.searchsorted(kf_scan, scans, side="right") - 1, 0)


class GrowingArray:
    """A numpy array that grows at its end (amortized doubling)."""

    def __init__(self, tail: tuple = (), dtype=float):
        self._a = np.zeros((64, *tail), dtype)
        self.n = 0

    def append(self, row) -> None:
        if self.n == len(self._a):
            self._a = np.concatenate([self._a, np.zeros_like(self._a)])
        self._a[self.n] = row
        self.n += 1

    def extend(self, rows: np.ndarray) -> None:
        while self.n + len(rows) > len(self._a):
            self._a = np.concatenate([self._a, np.zeros_like(self._a)])
        self._a[self.n : self.n + len(rows)] = rows
        self.n += len(rows)

    def view(self) -> np.ndarray:
        return self._a[: self.n]

    def drop_front(self, k: int) -> None:
        """Forget the first ``k`` rows (in place: the capacity stays)."""
        k = min(max(int(k), 0), self.n)
        if k:
            self._a[: self.n - k] = self._a[k : self.n].copy()
            self.n -= k

    def __len__(self) -> int:
        return self.n


class Trajectory:
    def __init__(self, compact_every: int = COMPACT_EVERY, max_scans: int = 0) -> None:
        # steps before ``_frozen``'s length: one history (the lineages coalesced there)
        self._frozen = GrowingArray((3,))
        self._frozen_jumped = GrowingArray((), bool)
        # the open steps after them, per step k: (P,3) poses of the propagated set, (P,) parent
        # index in step k-1, (P,) whether the pose was reached by a jump
        self._poses: list[np.ndarray] = []
        self._parents: list[np.ndarray] = []
        self._jumped: list[np.ndarray] = []
        self._pending: np.ndarray | None = None  # current particle -> index in the last record
        self._jumping: np.ndarray | None = None  # current particle: injected since the last record
        self._scan_stamps = GrowingArray()
        self._scan_anchor = GrowingArray((), np.int64)  # processed step each scan hangs from
        self._scan_rel = GrowingArray((3,))  # odometry from that step's pose
        self._step_scan = GrowingArray((), np.int64)  # per step k: the scan it processed
        self.compact_every = compact_every
        self._since_compact = 0
        self.max_scans = max_scans
        self.first_scan = 0  # the first scan still kept (the run's scan numbers throughout)
        self._step0 = 0  # the first step still kept (0-based)
        self._old_step = np.zeros(0, np.int64)  # forgotten steps still referred to (from 1) ...
        self._old_scan = np.zeros(0, np.int64)  # ... and the scan each processed

    def __len__(self) -> int:
        """Scans so far (in the whole run, forgotten ones too)."""
        return self.first_scan + len(self._scan_stamps)

    @property
    def steps(self) -> int:
        return self._step0 + len(self._frozen) + len(self._poses)

    @property
    def kept_scans(self) -> int:
        return len(self._scan_stamps)

    @property
    def over(self) -> bool:
        """More than max_scans by a quarter: time for :meth:`forget`."""
        return bool(self.max_scans) and len(self._scan_stamps) > self.max_scans * 5 // 4

    def forget(self, keep_steps: np.ndarray) -> int:
        """The oldest scans beyond the newest ``max_scans`` (and the closed steps they hang
        from) are forgotten; the scans of the forgotten steps in ``keep_steps`` (from 1) are
        remembered. Returns how many scans were forgotten."""
        if not self.max_scans or len(self._scan_stamps) <= self.max_scans:
            return 0
        anchors = self._scan_anchor.view() - self._step0
        cut = len(self._scan_stamps) - self.max_scans
        fcut = min(int(anchors[cut]), len(self._frozen))  # closed steps only
        cut = int(np.searchsorted(anchors, fcut, side="left"))  # the scans hanging from them
        if cut <= 0 or fcut <= 0:
            return 0
        keep_steps = np.unique(np.asarray(keep_steps, np.int64))
        gone = np.arange(self._step0 + 1, self._step0 + fcut + 1)
        asked = np.isin(gone, keep_steps, assume_unique=True)
        still = np.isin(self._old_step, keep_steps, assume_unique=True)
        self._old_step = np.concatenate([self._old_step[still], gone[asked]])
        self._old_scan = np.concatenate([self._old_scan[still], self._step_scan.view()[:fcut][asked]])
        for a in (self._frozen, self._frozen_jumped, self._step_scan):
            a.drop_front(fcut)
        for a in (self._scan_stamps, self._scan_anchor, self._scan_rel):
            a.drop_front(cut)
        self._step0 += fcut
        self.first_scan += cut
        return cut

    @property
    def open_steps(self) -> int:
        """Steps still kept per particle (after the last common ancestor)."""
        return len(self._poses)

    def record(self, stamp_s: float, poses: np.ndarray) -> None:
        """A processed scan: the particles' poses ``(P,3)`` (before any resampling)."""
        p = len(poses)
        self._since_compact += 1
        if self.compact_every and self._since_compact >= self.compact_every:
            self._since_compact = 0
            self._compact()
        self._parents.append(self._pending if self._pending is not None else np.arange(p))
        self._jumped.append(self._jumping if self._jumping is not None else np.zeros(p, bool))
        self._poses.append(poses.copy())
        self._pending = np.arange(p)
        self._jumping = np.zeros(p, bool)
        self._step_scan.append(len(self))
        self._scan_stamps.append(stamp_s)
        self._scan_anchor.append(self.steps - 1)
        self._scan_rel.append(np.zeros(3))

    def bridge(self, stamp_s: float, odometry_from_last: np.ndarray) -> None:
        """A scan not processed: its pose is the last step's composed with odometry."""
        if self.steps == 0:
            raise ValueError("bridge() before the first processed scan")
        self._scan_stamps.append(stamp_s)
        self._scan_anchor.append(self.steps - 1)
        self._scan_rel.append(np.asarray(odometry_from_last, dtype=float))

    def reparent(self, idx: np.ndarray) -> None:
        """After resampling: new particle ``j`` is old particle ``idx[j]``."""
        self._pending = self._pending[idx]
        self._jumping = self._jumping[idx]

    def inherit(self, targets: np.ndarray, sources: np.ndarray) -> None:
        """Particles ``targets`` now continue the history of particles ``sources`` from a pose
        that was put there (a relocalization): their next step is a jump, not a motion."""
        self._pending[targets] = self._pending[sources]
        self._jumping[targets] = True

    def backtrack(self, particle: int) -> tuple[np.ndarray, np.ndarray]:
        """``stamps (S,)`` and poses ``(S,3)`` for every scan along ``particle``'s ancestry (the
        scans kept: from ``first_scan`` on)."""
        if self.kept_scans == 0:
            return np.zeros(0), np.zeros((0, 3))
        line, _ = self._lineage(particle)
        poses = compose(line[self._scan_anchor.view() - self._step0], self._scan_rel.view())
        return self._scan_stamps.view().copy(), poses

    def jumps(self, particle: int) -> np.ndarray:
        """Mask ``(S,)`` of the scans along ``particle``'s ancestry that were reached by a
        jump (a relocalization put the ancestor there), not by a motion from the scan before."""
        anchors = self._scan_anchor.view() - self._step0
        if len(anchors) == 0:
            return np.zeros(0, bool)
        _, jumped = self._lineage(particle)
        first = np.r_[True, anchors[1:] != anchors[:-1]]  # the first scan of each processed step
        return first & jumped[anchors]

    def lineage_at(self, particle: int, scans: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Poses ``(N,3)`` and jump flags ``(N,)`` of scans ``scans (N,)`` along ``particle``'s
        ancestry (as :meth:`backtrack` and :meth:`jumps`, for those scans only: the closed steps
        are read, only the open ones walked)."""
        scans = np.asarray(scans, dtype=int)
        if len(scans) == 0:
            return np.zeros((0, 3)), np.zeros(0, bool)
        f = len(self._frozen)
        open_line, open_jumped = self._open_lineage(particle)
        if np.any(scans < self.first_scan):
            raise ValueError(f"scan {int(scans.min())} is forgotten (kept from {self.first_scan} on)")
        scans = scans - self.first_scan
        all_anchors = self._scan_anchor.view() - self._step0
        anchors = all_anchors[scans]
        closed = anchors < f
        at = np.empty((len(scans), 3))
        jumped = np.zeros(len(scans), bool)
        at[closed] = self._frozen.view()[anchors[closed]]
        jumped[closed] = self._frozen_jumped.view()[anchors[closed]]
        at[~closed] = open_line[anchors[~closed] - f]
        jumped[~closed] = open_jumped[anchors[~closed] - f]
        before = all_anchors[np.maximum(scans - 1, 0)]
        first = (scans == 0) | (before != anchors)
        return compose(at, self._scan_rel.view()[scans]), first & jumped

    def anchor_scans(self, scans: np.ndarray) -> np.ndarray:
        """The scan of the processed step each kept scan of ``scans (N,)`` hangs from (itself if
        processed): a scan's pose moves with that step's (:meth:`move`)."""
        local = np.asarray(scans, dtype=np.int64) - self.first_scan
        return self._step_scan.view()[self._scan_anchor.view()[local] - self._step0]

    def move(self, kf_scan: np.ndarray, moves: np.ndarray) -> None:
        """Every kept step's poses (of every particle's history) moved by the transform
        ``moves (K,3)`` (applied on the left: the map frame bent) of the last of ``kf_scan (K,)``
        (increasing) at or before the step's scan — before the first, the first's. The scans
        between steps keep their offsets from their step, so they move with it."""
        if len(kf_scan) == 0:
            return
        kf_scan, moves = np.asarray(kf_scan), np.asarray(moves, dtype=float)
        at = moves[keyframe_of(kf_scan, self._step_scan.view())]  # (steps,3)
        f = len(self._frozen)
        if f:
            self._frozen.view()[:] = compose(at[:f], self._frozen.view())
        if self._poses:  # the open steps at once: (steps, P, 3)
            moved = compose(at[f:, None, :], np.stack(self._poses))
            self._poses = [p.copy() for p in moved]  # own arrays: no step keeps the whole stack alive

    def scan_of_step(self, steps: np.ndarray) -> np.ndarray:
        """The scan each processed step (``FastSLAM.step_index``, from 1) processed (of a
        forgotten step not remembered: of the newest remembered before it)."""
        steps = np.asarray(steps, dtype=np.int64)
        local = steps - 1 - self._step0
        kept = local >= 0
        if kept.all():
            return self._step_scan.view()[local]
        out = np.empty(steps.shape, np.int64)
        out[kept] = self._step_scan.view()[local[kept]]
        at = np.searchsorted(self._old_step, steps[~kept], side="right") - 1
        out[~kept] = self._old_scan[np.maximum(at, 0)] if len(self._old_step) else self.first_scan
        return out

    def _open_lineage(self, particle: int) -> tuple[np.ndarray, np.ndarray]:
        """Poses ``(L,3)`` and jump flags ``(L,)`` of ``particle``'s ancestor at every open step."""
        n = len(self._poses)
        line = np.empty((n, 3))
        jumped = np.zeros(n, bool)
        if n == 0:
            return line, jumped
        i = int(self._pending[particle])
        for k in range(n - 1, -1, -1):
            line[k] = self._poses[k][i]
            jumped[k] = self._jumped[k][i]
            i = int(self._parents[k][i])
        return line, jumped

    def _lineage(self, particle: int) -> tuple[np.ndarray, np.ndarray]:
        """Poses ``(K,3)`` and jump flags ``(K,)`` of ``particle``'s ancestor at every step."""
        open_line, open_jumped = self._open_lineage(particle)
        return (
            np.concatenate([self._frozen.view(), open_line]),
            np.concatenate([self._frozen_jumped.view(), open_jumped]),
        )

    def close(self, particle: int, keep: int) -> int:
        """Close every open step but the newest ``keep`` along ``particle``'s ancestry, whether
        or not the other particles descend from it there (a bound for runs whose particles do not
        coalesce: their older history becomes ``particle``'s). Returns how many were closed."""
        n = len(self._poses) - keep
        if n <= 0:
            return 0
        i = int(self._pending[particle])
        for k in range(len(self._poses) - 1, n - 1, -1):  # its ancestor at step n - 1
            i = int(self._parents[k][i])
        self._freeze(n - 1, i)
        return n

    def _compact(self) -> None:
        """Close the steps up to the newest common ancestor of every living particle."""
        if self._pending is None or not self._poses:
            return
        alive = np.unique(self._pending)  # indices into the last open step
        k = len(self._poses) - 1
        while len(alive) > 1 and k > 0:
            alive = np.unique(self._parents[k][alive])
            k -= 1
        if len(alive) > 1:
            return
        self._freeze(k, int(alive[0]))

    def _freeze(self, k: int, i: int) -> None:
        """Open steps ``0..k`` become closed, along the history of particle ``i`` at step ``k``."""
        line = np.empty((k + 1, 3))
        jumped = np.zeros(k + 1, bool)
        for j in range(k, -1, -1):
            line[j] = self._poses[j][i]
            jumped[j] = self._jumped[j][i]
            i = int(self._parents[j][i])
        self._frozen.extend(line)
        self._frozen_jumped.extend(jumped)
        del self._poses[: k + 1], self._parents[: k + 1], self._jumped[: k + 1]
