"""Particles as arrays: poses, log-weights, slip states and per-particle segment maps.

Maps are *column aligned*: column ``j`` of every particle's map is the same map element
(one identity, descended from one observation), valid in the particles that have it. A new
observation that no particle could associate gets one fresh column for all of them; resampling
gathers rows and keeps columns; the cross-particle global map (report §5) is a reduction over
the particle axis of each column. Shapes: ``P`` particles, ``M`` columns (capacity).
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np

from robot_agent.slam.lines import fit_lines, project_to_line, segment_endpoints
from shared.geometry import wrap_angle

INITIAL_CAPACITY = 256


@dataclass
class SegmentMaps:
    """Per-particle segment maps, padded to a common capacity, with a validity mask.

    Every array has the particle axis first and the element (column) axis second.
    """

    valid: np.ndarray  # (P,M) bool
    seg: np.ndarray  # (P,M,2,2) endpoints on the fitted line, map frame [m]
    moments: np.ndarray  # (P,M,6) sufficient statistics of every point merged in (lines.py)
    alpha: np.ndarray  # (P,M) line normal angle [rad] (fit of `moments`)
    rho: np.ndarray  # (P,M) line distance to the origin [m]
    facing: np.ndarray  # (P,M) direction of the free side's normal [rad]: the side the sensor saw
    hits: np.ndarray  # (P,M) number of observations merged
    born: np.ndarray  # (P,M) step at which the element was created
    last_seen: np.ndarray  # (P,M) step of the last merge
    misses: np.ndarray  # (P,M) decayed count of "should have been seen but was not / seen through"
    quality: np.ndarray  # (P,M) running mean of match quality in [0, 1]

    @classmethod
    def empty(cls, n_particles: int, capacity: int = INITIAL_CAPACITY) -> SegmentMaps:
        p, m = n_particles, capacity
        return cls(
            valid=np.zeros((p, m), bool),
            seg=np.zeros((p, m, 2, 2)),
            moments=np.zeros((p, m, 6)),
            alpha=np.zeros((p, m)),
            rho=np.zeros((p, m)),
            facing=np.zeros((p, m)),
            hits=np.zeros((p, m), np.int32),
            born=np.zeros((p, m), np.int32),
            last_seen=np.zeros((p, m), np.int32),
            misses=np.zeros((p, m), np.float32),
            quality=np.zeros((p, m), np.float32),
        )

    @property
    def n_particles(self) -> int:
        return self.valid.shape[0]

    @property
    def capacity(self) -> int:
        return self.valid.shape[1]

    def arrays(self) -> dict[str, np.ndarray]:
        return {f.name: getattr(self, f.name) for f in fields(self)}

    def take(self, idx: np.ndarray) -> SegmentMaps:
        """Rows ``idx (P',)`` of every array (resampling, injection)."""
        return SegmentMaps(**{k: v[idx] for k, v in self.arrays().items()})

    def columns(self, cols: np.ndarray) -> SegmentMaps:
        """A local view-copy of columns ``cols (C,)`` (all particles)."""
        return SegmentMaps(**{k: v[:, cols] for k, v in self.arrays().items()})

    def row_columns(self, row: int, cols: np.ndarray) -> SegmentMaps:
        """``take([row]).columns(cols)`` without copying the row's other columns first."""
        return SegmentMaps(**{k: v[row : row + 1, cols] for k, v in self.arrays().items()})

    def put_columns(self, cols: np.ndarray, local: SegmentMaps) -> None:
        """Write a local copy made by :meth:`columns` back."""
        for k, v in self.arrays().items():
            v[:, cols] = getattr(local, k)

    def free_columns(self, k: int) -> np.ndarray:
        """``k`` columns valid in no particle, growing the capacity (doubling) if needed."""
        free = np.flatnonzero(~self.valid.any(axis=0))
        if len(free) < k:
            self._grow(max(self.capacity, k - len(free)))
            free = np.flatnonzero(~self.valid.any(axis=0))
        return free[:k]

    def _grow(self, extra: int) -> None:
        for k, v in self.arrays().items():
            pad = np.zeros((v.shape[0], extra, *v.shape[2:]), v.dtype)
            setattr(self, k, np.concatenate([v, pad], axis=1))

    def used_columns(self) -> np.ndarray:
        return np.flatnonzero(self.valid.any(axis=0))

    def refit_extend(self, p_idx: np.ndarray, c_idx: np.ndarray, extra_ends: np.ndarray) -> None:
        """Refit the lines of elements ``(p_idx, c_idx) (K,)`` from their moments and set each
        extent to the union of its old endpoints and ``extra_ends (K,2,2)`` on the new line.
        The facing keeps its side and turns with the line: association and weights compare
        facings, so a facing left at the element's first observation would charge every later
        match that observation's angle error (a tilted first view biased the weights by 2 deg).

        A pair may repeat (several observations merged into one element): extents are combined
        by scatter-min/max so none is lost.
        """
        alpha, rho, _ = fit_lines(self.moments[p_idx, c_idx])
        pts = np.concatenate([self.seg[p_idx, c_idx], extra_ends], axis=1)  # (K,4,2)
        t, _ = project_to_line(pts, alpha[:, None], rho[:, None])
        lo = np.full(self.valid.shape, np.inf)
        hi = np.full(self.valid.shape, -np.inf)
        np.minimum.at(lo, (p_idx, c_idx), t.min(axis=-1))
        np.maximum.at(hi, (p_idx, c_idx), t.max(axis=-1))
        self.alpha[p_idx, c_idx], self.rho[p_idx, c_idx] = alpha, rho
        same_side = np.cos(alpha - self.facing[p_idx, c_idx]) >= 0
        self.facing[p_idx, c_idx] = np.where(same_side, alpha, wrap_angle(alpha + np.pi))
        self.seg[p_idx, c_idx] = segment_endpoints(alpha, rho, lo[p_idx, c_idx], hi[p_idx, c_idx])


@dataclass
class ParticleSet:
    """The filter state. ``poses (P,3)`` robot poses in the map frame, ``log_weights (P,)``
    normalized so that ``logsumexp == 0``, ``slip (P,2)`` each particle's belief of the
    systematic odometry error (distance scale error, heading drift [rad/m]) — the mean of a
    Gaussian whose covariance is ``slip_cov (P,2,2)`` — and ``maps``."""

    poses: np.ndarray
    log_weights: np.ndarray
    slip: np.ndarray
    slip_cov: np.ndarray
    maps: SegmentMaps

    @classmethod
    def create(
        cls, n_particles: int, start: np.ndarray | None = None, slip_sigma: tuple[float, float] = (0.0, 0.0)
    ) -> ParticleSet:
        poses = (
            np.zeros((n_particles, 3))
            if start is None
            else np.tile(np.asarray(start, float), (n_particles, 1))
        )
        return cls(
            poses=poses,
            log_weights=np.full(n_particles, -np.log(n_particles)),
            slip=np.zeros((n_particles, 2)),
            slip_cov=np.tile(np.diag(np.square(slip_sigma)), (n_particles, 1, 1)),
            maps=SegmentMaps.empty(n_particles),
        )

    @property
    def n(self) -> int:
        return len(self.poses)

    def take(self, idx: np.ndarray) -> ParticleSet:
        return ParticleSet(
            self.poses[idx].copy(),
            self.log_weights[idx].copy(),
            self.slip[idx].copy(),
            self.slip_cov[idx].copy(),
            self.maps.take(idx),
        )

    def best(self) -> int:
        return int(np.argmax(self.log_weights))

    def normalize(self) -> None:
        lw = self.log_weights
        mx = lw.max()
        self.log_weights = lw - (mx + np.log(np.sum(np.exp(lw - mx))))
