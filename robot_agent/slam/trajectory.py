"""Every particle's full trajectory without copying it at each resampling: an ancestry tree.

Each processed step stores the propagated poses ``(P,3)`` and each particle's parent index in
the previous step; the best particle's trajectory is read back by walking the parents. Scans
skipped for too little motion are stored as an odometry increment from the last processed step,
so the output has one pose for every scan, with the scan's own timestamp.
"""

from __future__ import annotations

import numpy as np

from shared.geometry import compose


class Trajectory:
    def __init__(self) -> None:
        self._poses: list[np.ndarray] = []  # per step k: (P,3) poses of the propagated set
        self._parents: list[np.ndarray] = []  # per step k: (P,) parent index in step k-1
        self._pending: np.ndarray | None = None  # current particle -> index in the last record
        self._jumped: list[np.ndarray] = []  # per step k: (P,) the pose was reached by a jump
        self._jumping: np.ndarray | None = None  # current particle: injected since the last record
        self._scan_stamps: list[float] = []
        self._scan_anchor: list[int] = []  # processed step each scan hangs from
        self._scan_rel: list[np.ndarray] = []  # (3,) odometry from that step's pose
        self._step_scan: list[int] = []  # per step k: the scan it processed

    def __len__(self) -> int:
        return len(self._scan_stamps)

    def record(self, stamp_s: float, poses: np.ndarray) -> None:
        """A processed scan: the particles' poses ``(P,3)`` (before any resampling)."""
        p = len(poses)
        self._parents.append(self._pending if self._pending is not None else np.arange(p))
        self._jumped.append(self._jumping if self._jumping is not None else np.zeros(p, bool))
        self._poses.append(poses.copy())
        self._pending = np.arange(p)
        self._jumping = np.zeros(p, bool)
        self._step_scan.append(len(self._scan_stamps))
        self._scan_stamps.append(stamp_s)
        self._scan_anchor.append(len(self._poses) - 1)
        self._scan_rel.append(np.zeros(3))

    def bridge(self, stamp_s: float, odometry_from_last: np.ndarray) -> None:
        """A scan not processed: its pose is the last step's composed with odometry."""
        if not self._poses:
            raise ValueError("bridge() before the first processed scan")
        self._scan_stamps.append(stamp_s)
        self._scan_anchor.append(len(self._poses) - 1)
        self._scan_rel.append(np.asarray(odometry_from_last, dtype=float).copy())

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
        """``stamps (S,)`` and poses ``(S,3)`` for every scan along ``particle``'s ancestry."""
        line, _ = self._lineage(particle)
        if len(line) == 0:
            return np.zeros(0), np.zeros((0, 3))
        anchors = np.asarray(self._scan_anchor)
        poses = compose(line[anchors], np.asarray(self._scan_rel))
        return np.asarray(self._scan_stamps), poses

    def jumps(self, particle: int) -> np.ndarray:
        """Mask ``(S,)`` of the scans along ``particle``'s ancestry that were reached by a
        jump (a relocalization put the ancestor there), not by a motion from the scan before."""
        anchors = np.asarray(self._scan_anchor, dtype=int)
        if len(anchors) == 0:
            return np.zeros(0, bool)
        _, jumped = self._lineage(particle)
        first = np.r_[True, anchors[1:] != anchors[:-1]]  # the first scan of each processed step
        return first & jumped[anchors]

    def lineage_at(self, particle: int, scans: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Poses ``(N,3)`` and jump flags ``(N,)`` of scans ``scans (N,)`` along ``particle``'s
        ancestry (as :meth:`backtrack` and :meth:`jumps`, for those scans only)."""
        scans = np.asarray(scans, dtype=int)
        if len(scans) == 0:
            return np.zeros((0, 3)), np.zeros(0, bool)
        line, jumped = self._lineage(particle)
        anchors = np.asarray(self._scan_anchor, dtype=int)[scans]
        rel = np.asarray(self._scan_rel)[scans]
        before = np.asarray(self._scan_anchor, dtype=int)[np.maximum(scans - 1, 0)]
        first = (scans == 0) | (before != anchors)
        return compose(line[anchors], rel), first & jumped[anchors]

    def scan_of_step(self, steps: np.ndarray) -> np.ndarray:
        """The scan each processed step (``FastSLAM.step_index``, from 1) processed."""
        return np.asarray(self._step_scan, dtype=int)[np.asarray(steps, dtype=int) - 1]

    def _lineage(self, particle: int) -> tuple[np.ndarray, np.ndarray]:
        """Poses ``(K,3)`` and jump flags ``(K,)`` of ``particle``'s ancestor at every step."""
        k_steps = len(self._poses)
        line = np.empty((k_steps, 3))
        jumped = np.zeros(k_steps, bool)
        if k_steps == 0:
            return line, jumped
        i = int(self._pending[particle])
        for k in range(k_steps - 1, -1, -1):
            line[k] = self._poses[k][i]
            jumped[k] = self._jumped[k][i]
            i = int(self._parents[k][i])
        return line, jumped
