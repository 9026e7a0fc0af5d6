"""What an agent publishes: its top particles' trusted segment maps (report §5, sent to the server).

Pure numpy: the arrays of a :class:`shared.messages.RobotMap`, built from the filter's particles.
Elements that several top particles hold in the very same version (same element, same endpoints —
the common case after resampling) are sent once with a membership bitmask, so sending ``K``
particles costs little more than sending one.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from robot_agent.slam.fastslam import FastSLAM
from robot_agent.slam.resampling import normalized_weights
from robot_agent.slam.update import element_trust


@dataclass(frozen=True)
class PublishConfig:
    top_particles: int = 5  # particles whose maps are sent (the server fuses across them)
    min_trust: float | None = None  # None: the filter's consensus.publish_min_trust
    min_hits: int | None = None  # None: the filter's consensus.publish_min_hits


@dataclass(frozen=True)
class MapArrays:
    """The arrays of one robot map (see :class:`shared.messages.RobotMap` for their meaning)."""

    particle_weights: np.ndarray  # (K,)
    particle_poses: np.ndarray  # (K,3)
    seg: np.ndarray  # (N,2,2) directed: the sensor saw the wall from the left of p0 -> p1
    element: np.ndarray  # (N,)
    members: np.ndarray  # (N,) bitmask over the K particles
    trust: np.ndarray  # (N,)
    hits: np.ndarray  # (N,)
    age: np.ndarray  # (N,) filter steps since the element was born

    def fingerprint(self) -> bytes:
        """Changes when the published content changes (not when only weights and poses move)."""
        return self.seg.astype(np.float32).tobytes() + self.element.tobytes() + self.members.tobytes()


def directed(seg: np.ndarray, facing_rad: np.ndarray) -> np.ndarray:
    """``seg (N,2,2)`` with endpoints ordered so that ``facing`` is the left normal of p0 -> p1."""
    d = seg[:, 1] - seg[:, 0]
    left = np.stack([-d[:, 1], d[:, 0]], axis=-1)
    flip = np.sum(left * np.stack([np.cos(facing_rad), np.sin(facing_rad)], axis=-1), axis=-1) < 0
    out = seg.copy()
    out[flip] = seg[flip][:, ::-1]
    return out


def top_particle_maps(slam: FastSLAM, cfg: PublishConfig = PublishConfig()) -> MapArrays:
    """The trusted elements of the ``cfg.top_particles`` heaviest particles, deduplicated."""
    ps, step = slam.particles, slam.step_index
    consensus = slam.cfg.consensus
    min_trust = consensus.publish_min_trust if cfg.min_trust is None else cfg.min_trust
    min_hits = consensus.publish_min_hits if cfg.min_hits is None else cfg.min_hits
    w = normalized_weights(ps.log_weights)
    top = np.argsort(-w, kind="stable")[: max(1, min(cfg.top_particles, ps.n))]
    maps = ps.maps.take(top)
    cols = maps.used_columns()
    sub = maps.columns(cols)
    trust = element_trust(sub, step, slam.cfg.trust)  # (K,G)
    keep = sub.valid & (trust >= min_trust) & (sub.hits >= min_hits)
    k_idx, g_idx = np.nonzero(keep)
    seg = directed(sub.seg[k_idx, g_idx], sub.facing[k_idx, g_idx])
    element = cols[g_idx].astype(np.int64)
    # one row per distinct (element, endpoints) version; members = the particles holding it
    key = np.concatenate([element[:, None].astype(np.float64), seg.reshape(-1, 4)], axis=1)
    if len(key):
        uniq, first, inverse = np.unique(key, axis=0, return_index=True, return_inverse=True)
    else:
        uniq, first, inverse = key, np.zeros(0, int), np.zeros(0, int)
    inverse = inverse.ravel()
    members = np.zeros(len(uniq), np.int64)
    np.bitwise_or.at(members, inverse, np.left_shift(1, k_idx).astype(np.int64))
    best_trust = np.zeros(len(uniq))
    np.maximum.at(best_trust, inverse, trust[k_idx, g_idx])
    hits = np.zeros(len(uniq), np.int64)
    np.maximum.at(hits, inverse, sub.hits[k_idx, g_idx].astype(np.int64))
    age = np.maximum(step - sub.born[k_idx, g_idx][first], 0).astype(np.int64)
    return MapArrays(
        particle_weights=np.clip(w[top], 0.0, 1.0),
        particle_poses=ps.poses[top].copy(),
        seg=seg[first],
        element=element[first],
        members=members,
        trust=np.clip(best_trust, 0.0, 1.0),
        hits=hits,
        age=age,
    )
