"""Pose hypotheses from segment and corner correspondences, scored by overlap (pure numpy).

Used by relocalization on the agent (report §6: "geometrically identify the likely positions by
using the geometric properties of the global map") and by cross-robot alignment on the server.

Segments are described by their endpoints ``(N,2,2)`` and their *facing* angle — the normal
pointing to the side the sensor saw — so a wall's two faces never match. A pair of non-parallel
segments fixes a pose: the rotation from the facings, the translation from the two lines
(``f_a·t = c_a - c_o``, with ``c = f·p`` for any point ``p`` of the line, two equations).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from shared.geometry import apply_segments, point_segment_distance, transform_points, wrap_angle

# Hypotheses × observed × map triples facing-tested at once; bounds the temporaries (measured:
# 38 MB at a million, the whole-map search of a robot in doubt on ACES; ~10 MB at this).
SCORE_CHUNK_ELEMENTS = 250_000


@dataclass(frozen=True)
class MatchingConfig:
    min_pair_angle_rad: float = np.radians(30.0)  # pairs closer to parallel fix no pose
    pair_angle_tol_rad: float = np.radians(4.0)  # relative angle of the two pairs must agree
    max_pair_gap_m: float = 1.5  # a map pair's segments must be this close (corners, near-corners)
    obs_max_pair_gap_m: float | None = None  # the same for observed pairs (None: any; a scan is
    # small, but a whole robot map matched against another map needs its pairs local too)
    max_obs_pairs: int = 60  # from the longest observed segments
    gap_to_segment: bool = False  # a pair's gap: endpoint to segment (a wall ending on another's
    # middle, a T, is a pair too) instead of endpoint to endpoint
    min_length_m: float = 0.5  # segments shorter than this take no part in hypotheses
    score_perp_m: float = 0.12  # a transformed segment lies on an element within this offset ...
    score_angle_rad: float = np.radians(5.0)  # ... and this facing difference ...
    score_overlap_m: float = 0.0  # ... overlapping it by at least this much


def _facing_vectors(facing: np.ndarray) -> np.ndarray:
    return np.stack([np.cos(facing), np.sin(facing)], axis=-1)


def _segment_gap(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Smallest endpoint-to-endpoint distance between segments ``a (...,2,2)`` and ``b``."""
    d = a[..., :, None, :] - b[..., None, :, :]
    return np.min(np.hypot(d[..., 0], d[..., 1]), axis=(-1, -2))


def _end_to_segment_gap(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Smallest distance from an endpoint of ``a (...,2,2)`` to segment ``b`` or back."""
    d_ab = point_segment_distance(a, b[..., None, :, :]).min(axis=-1)
    d_ba = point_segment_distance(b, a[..., None, :, :]).min(axis=-1)
    return np.minimum(d_ab, d_ba)


def _pairs(ends: np.ndarray, facing: np.ndarray, cfg: MatchingConfig, max_gap: float | None) -> tuple:
    n = len(ends)
    i, j = np.triu_indices(n, 1)
    rel = wrap_angle(facing[j] - facing[i])
    ok = np.abs(np.sin(rel)) >= np.sin(cfg.min_pair_angle_rad)
    if max_gap is not None:
        # no gap is smaller than the centres' distance less the half lengths: the pairs farther
        # apart go before the gap is computed (its temporaries are tens of bytes a pair)
        mid = 0.5 * (ends[:, 0] + ends[:, 1])
        half = 0.5 * np.hypot(*(ends[:, 1] - ends[:, 0]).T)
        ok &= np.hypot(*(mid[i] - mid[j]).T) - half[i] - half[j] <= max_gap
        i, j, rel = i[ok], j[ok], rel[ok]
        gap = _end_to_segment_gap if cfg.gap_to_segment else _segment_gap
        ok = gap(ends[i], ends[j]) <= max_gap
    return i[ok], j[ok], rel[ok]


def pose_hypotheses(
    obs_ends: np.ndarray,
    obs_facing: np.ndarray,
    map_ends: np.ndarray,
    map_facing: np.ndarray,
    cfg: MatchingConfig,
) -> np.ndarray:
    """Poses ``(H,3)`` that would put a pair of observed segments onto a pair of map segments.

    ``obs_*`` in the sensor's (robot's) frame, ``map_*`` in the map frame; the pose maps the
    former into the latter.
    """
    lo = np.hypot(*(obs_ends[:, 1] - obs_ends[:, 0]).T)
    lm = np.hypot(*(map_ends[:, 1] - map_ends[:, 0]).T)
    ko = np.flatnonzero(lo >= cfg.min_length_m)
    ko = ko[np.argsort(-lo[ko])]
    km = np.flatnonzero(lm >= cfg.min_length_m)
    if len(ko) < 2 or len(km) < 2:
        return np.zeros((0, 3))
    oi, oj, orel = _pairs(obs_ends[ko], obs_facing[ko], cfg, cfg.obs_max_pair_gap_m)
    oi, oj, orel = oi[: cfg.max_obs_pairs], oj[: cfg.max_obs_pairs], orel[: cfg.max_obs_pairs]
    mi, mj, mrel = _pairs(map_ends[km], map_facing[km], cfg, cfg.max_pair_gap_m)
    if len(oi) == 0 or len(mi) == 0:
        return np.zeros((0, 3))
    # both orders of a map pair: (i, j) and (j, i)
    mi, mj, mrel = np.concatenate([mi, mj]), np.concatenate([mj, mi]), np.concatenate([mrel, -mrel])
    agree = np.abs(wrap_angle(orel[:, None] - mrel[None, :])) <= cfg.pair_angle_tol_rad
    a, b = np.nonzero(agree)
    o1, o2, m1, m2 = ko[oi[a]], ko[oj[a]], km[mi[b]], km[mj[b]]
    theta = wrap_angle(map_facing[m1] - obs_facing[o1])
    # rotated observed lines must coincide with the map lines: f_m·t = c_m - f_m·(R p_o)
    f1, f2 = _facing_vectors(map_facing[m1]), _facing_vectors(map_facing[m2])
    heading = np.column_stack([np.zeros_like(theta), np.zeros_like(theta), theta])  # rotation only
    rhs1 = np.sum(f1 * map_ends[m1, 0], axis=1) - np.sum(
        f1 * transform_points(heading, obs_ends[o1, 0]), axis=1
    )
    rhs2 = np.sum(f2 * map_ends[m2, 0], axis=1) - np.sum(
        f2 * transform_points(heading, obs_ends[o2, 0]), axis=1
    )
    det = f1[:, 0] * f2[:, 1] - f1[:, 1] * f2[:, 0]
    tx = (rhs1 * f2[:, 1] - rhs2 * f1[:, 1]) / det
    ty = (f1[:, 0] * rhs2 - f2[:, 0] * rhs1) / det
    return np.column_stack([tx, ty, theta])


def overlap_scores(
    poses: np.ndarray,
    obs_ends: np.ndarray,
    obs_facing: np.ndarray,
    map_ends: np.ndarray,
    map_facing: np.ndarray,
    cfg: MatchingConfig,
) -> np.ndarray:
    """Observed length ``(H,)`` [m] that lies on map segments when moved by each pose ``(H,3)``.

    An observed segment counts with the part of its length that overlaps a map segment it lies
    on (offset ≤ ``score_perp_m``, facing within ``score_angle_rad``); the best map segment per
    observed segment counts once.

    The facing test comes first, over every (pose, observed, map) triple as one product of unit
    vectors; the offsets and overlaps are computed only for the triples it admits (a few percent:
    a wall faces one of many directions). Chunked over poses to bound the temporaries.
    """
    n_h, n_o, n_m = len(poses), len(obs_ends), len(map_ends)
    if n_h == 0 or n_o == 0 or n_m == 0:
        return np.zeros(n_h)
    chunk = max(1, SCORE_CHUNK_ELEMENTS // (n_o * n_m))
    if n_h > chunk:
        return np.concatenate(
            [
                overlap_scores(poses[s : s + chunk], obs_ends, obs_facing, map_ends, map_facing, cfg)
                for s in range(0, n_h, chunk)
            ]
        )
    fm = _facing_vectors(map_facing)  # (M,2)
    fo = _facing_vectors(obs_facing[None, :] + poses[:, 2:3]).reshape(-1, 2)  # (H·O,2)
    # facing within the angle: cos of the difference, the dot product of the unit vectors
    ho, m = np.nonzero(fo @ fm.T >= np.cos(cfg.score_angle_rad))  # (K,) each
    best = np.zeros(n_h * n_o)  # the best overlap per (pose, observed segment)
    if len(ho):
        moved = apply_segments(poses, obs_ends).reshape(-1, 2, 2)[ho]  # (K,2,2)
        a = map_ends[m, 0]  # (K,2)
        f = fm[m]
        d = np.stack([-f[:, 1], f[:, 0]], axis=-1)  # along each map segment
        rel = moved - a[:, None, :]  # (K,2,2)
        perp = rel[..., 0] * f[:, None, 0] + rel[..., 1] * f[:, None, 1]  # (K,2)
        t = rel[..., 0] * d[:, None, 0] + rel[..., 1] * d[:, None, 1]
        e = map_ends[m, 1] - a
        tm = e[:, 0] * d[:, 0] + e[:, 1] * d[:, 1]  # (K,)
        t_lo = np.maximum(np.minimum(t[:, 0], t[:, 1]), np.minimum(0.0, tm))
        t_hi = np.minimum(np.maximum(t[:, 0], t[:, 1]), np.maximum(0.0, tm))
        overlap = t_hi - t_lo
        ok = (np.max(np.abs(perp), axis=-1) <= cfg.score_perp_m) & (overlap > cfg.score_overlap_m)
        np.maximum.at(best, ho[ok], overlap[ok])
    return best.reshape(n_h, n_o).sum(axis=1)


def cluster_poses(
    poses: np.ndarray, scores: np.ndarray, radius_m: float, radius_rad: float, max_clusters: int = 16
) -> np.ndarray:
    """Indices of the best pose of each cluster (greedy non-maximum suppression), best first:
    take the best remaining pose, drop every pose within ``radius_m`` and ``radius_rad`` of it."""
    alive = np.ones(len(poses), bool)
    keep: list[int] = []
    while alive.any() and len(keep) < max_clusters:
        i = int(np.argmax(np.where(alive, scores, -np.inf)))
        keep.append(i)
        near = (np.hypot(*(poses[:, :2] - poses[i, :2]).T) <= radius_m) & (
            np.abs(wrap_angle(poses[:, 2] - poses[i, 2])) <= radius_rad
        )
        alive &= ~near
    return np.asarray(keep, dtype=int)
