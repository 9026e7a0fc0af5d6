"""The compiled kernels (``_kernels.c``), given arrays of the dtype and layout they take;
``AVAILABLE`` is False when the extension was not built (no C compiler at install): the callers
then run their numpy code, which stays the reference (tests/slam/test_kernels.py holds both to
the same results)."""

from __future__ import annotations

import numpy as np

from shared.kernels import f64, i64, require

try:
    from robot_agent.slam import _kernels
except ImportError:  # built without a C compiler: the numpy versions run
    _kernels = None

AVAILABLE = _kernels is not None


def _lib():
    return require(_kernels)


def _u8(mask: np.ndarray) -> np.ndarray:
    """A boolean mask as bytes for the kernels: a view when it is contiguous, a copy else."""
    mask = np.asarray(mask)
    if mask.dtype == np.bool_ and mask.flags.c_contiguous:
        return mask.view(np.uint8)
    return np.ascontiguousarray(mask, dtype=np.uint8)


def gn_points(
    x: np.ndarray,
    prior_mean: np.ndarray,
    info_prior: np.ndarray,
    pts: np.ndarray,
    alpha: np.ndarray,
    rho: np.ndarray,
    seg: np.ndarray,
    facing: np.ndarray,
    valid: np.ndarray,
    gate_wide: np.ndarray,
    iterations: int,
    reassociate_after: int,
    gate_m: float,
    margin_m: float,
    robust_scale_m: float,
    point_sigma_m: float,
    point_alpha: np.ndarray | None = None,
    max_sin: float = 1.0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """proposal.align_points' Gauss-Newton (association, normal equations, the prior-fused
    step) for poses ``x (P,3)`` from a local map of ``C`` columns (``alpha, rho, facing, valid
    (P,C)``, ``seg (P,C,2,2)``) and points ``pts (N,2)``: the refined poses ``(P,3)``, the last
    iteration's measurement information ``(P,3,3)`` and the last association ``(P,N)``."""
    lib = _lib()
    x = np.array(x, dtype=np.float64, order="C")
    p, n, c = len(x), len(pts), alpha.shape[1]
    h = np.zeros((p, 3, 3))
    idx = np.empty((p, n), dtype=np.int64)
    gate = np.broadcast_to(np.asarray(gate_wide, dtype=np.float64), (p,))
    pa = np.full(n, np.nan) if point_alpha is None else point_alpha
    lib.gn_points(
        x,
        f64(prior_mean),
        f64(info_prior),
        f64(pts),
        f64(np.cos(alpha)),
        f64(np.sin(alpha)),
        f64(rho),
        f64(seg),
        f64(np.cos(facing)),
        f64(np.sin(facing)),
        _u8(valid),
        f64(gate),
        h,
        idx,
        f64(pa),
        p,
        n,
        c,
        int(iterations),
        int(reassociate_after),
        float(gate_m),
        float(margin_m),
        float(robust_scale_m),
        float(point_sigma_m),
        float(max_sin),
    )
    return x, h, idx


def associate_segments(
    obs_facing: np.ndarray,
    centroid: np.ndarray,
    obs_ends: np.ndarray,
    var_angle: np.ndarray,
    var_perp: np.ndarray,
    alpha: np.ndarray,
    rho: np.ndarray,
    facing: np.ndarray,
    seg: np.ndarray,
    valid: np.ndarray,
    angle_gate: float,
    perp_gate: float,
    gap_gate: float,
    sigma_gap: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """association.associate for observations ``(P,O)`` (facing, ``centroid (P,O,2)``, ``ends
    (P,O,2,2)``, the distance's variances ``(P,O)``) and a local map ``(P,C)``: element index
    (-1: none), cost, facing difference and signed offset of the chosen pair, each ``(P,O)``."""
    lib = _lib()
    p, o = obs_facing.shape
    c = alpha.shape[1]
    idx = np.empty((p, o), dtype=np.int64)
    cost, d_angle, d_perp = np.empty((p, o)), np.empty((p, o)), np.empty((p, o))
    lib.associate_segments(
        f64(obs_facing),
        f64(centroid[..., 0]),
        f64(centroid[..., 1]),
        f64(obs_ends),
        f64(var_angle),
        f64(var_perp),
        f64(np.cos(alpha)),
        f64(np.sin(alpha)),
        f64(rho),
        f64(facing),
        f64(seg),
        _u8(valid),
        idx,
        cost,
        d_angle,
        d_perp,
        p,
        o,
        c,
        float(angle_gate),
        float(perp_gate),
        float(gap_gate),
        float(sigma_gap),
    )
    return idx, cost, d_angle, d_perp


def visibility(
    seg: np.ndarray,
    alpha: np.ndarray,
    facing: np.ndarray,
    valid: np.ndarray,
    laser_poses: np.ndarray,
    ranges_m: np.ndarray,
    samples: np.ndarray,
    a0: float,
    da: float,
    usable_range_m: float,
    sin_min_incidence: float,
    margin_m: float,
    margin_rel: float,
    min_span_rad: float,
) -> tuple[np.ndarray, np.ndarray]:
    """update.visibility for elements ``(P,C)`` (``seg (P,C,2,2)``) seen from ``laser_poses (P,3)``
    by beams ``a0 + i da`` of ``ranges_m (B,)``: ``through (P,C)`` int and ``in_view (P,C)`` bool."""
    lib = _lib()
    p, c = alpha.shape
    through = np.empty((p, c), dtype=np.int64)
    in_view = np.empty((p, c), dtype=np.uint8)
    lib.visibility(
        f64(seg),
        f64(np.cos(alpha)),
        f64(np.sin(alpha)),
        f64(np.cos(facing)),
        f64(np.sin(facing)),
        _u8(valid),
        f64(laser_poses),
        f64(ranges_m),
        f64(samples),
        through,
        in_view,
        p,
        c,
        len(ranges_m),
        float(a0),
        float(da),
        float(usable_range_m),
        float(sin_min_incidence),
        float(margin_m),
        float(margin_rel),
        float(min_span_rad),
    )
    return through, in_view.view(bool)


def nearest_within(samples: np.ndarray, queries: np.ndarray, radius_m: float) -> np.ndarray:
    """Distance ``(Q,)`` from each of ``queries (Q,2)`` to the nearest of ``samples (S,2)`` when
    below ``radius_m``, else inf: ``cKDTree(samples).query(queries, distance_upper_bound=radius_m)[0]``."""
    lib = _lib()
    samples, queries = f64(samples).reshape(-1, 2), f64(queries).reshape(-1, 2)
    d = np.empty(len(queries))
    lib.nearest_within(samples, queries, d, len(samples), len(queries), float(radius_m))
    return d


def split_pieces(pts: np.ndarray, threshold: np.ndarray, starts: np.ndarray, min_points: int) -> np.ndarray:
    """extraction._split: the piece starts after iterative end-point fit of ``pts (K,2)``."""
    lib = _lib()
    out = np.empty(len(pts), dtype=np.int64)
    starts = i64(starts)
    n = lib.split_pieces(f64(pts), f64(threshold), starts, out, len(pts), len(starts), int(min_points))
    return out[:n]


def merge_pieces(
    pts: np.ndarray,
    threshold: np.ndarray,
    starts: np.ndarray,
    cluster: np.ndarray,
    max_rms_m: float,
    range_sigma_m: float,
    merge_angle_rad: float,
    merge_angle_n_sigma: float,
) -> tuple[np.ndarray, np.ndarray]:
    """extraction._merge: starts and cluster of the pieces after merging adjacent collinear ones."""
    lib = _lib()
    starts = np.array(starts, dtype=np.int64)
    cluster = np.array(cluster, dtype=np.int64)
    n = lib.merge_pieces(
        f64(pts),
        f64(threshold),
        starts,
        cluster,
        len(pts),
        len(starts),
        float(max_rms_m),
        float(range_sigma_m),
        float(merge_angle_rad),
        float(merge_angle_n_sigma),
    )
    return starts[:n], cluster[:n]


def local_columns(
    valid: np.ndarray, seg: np.ndarray, rows: np.ndarray, centre: np.ndarray, limit_m: float
) -> np.ndarray:
    """Columns ``(K,)`` of maps ``valid (P,M)``, ``seg (P,M,2,2)`` with an element in one of the
    particles ``rows`` whose midpoint is nearer ``centre (2,)`` than ``limit_m`` plus its half length."""
    lib = _lib()
    p, m = valid.shape
    out = np.empty(m, dtype=np.int64)
    rows = i64(rows)
    n = lib.local_columns(
        _u8(valid),
        f64(seg), rows, out, p, m, len(rows), float(centre[0]), float(centre[1]), float(limit_m),
    )  # fmt: skip
    return out[:n]


def redundant_pairs(
    valid: np.ndarray,
    seg: np.ndarray,
    alpha: np.ndarray,
    rho: np.ndarray,
    facing: np.ndarray,
    recent: np.ndarray,
    max_angle_rad: float,
    max_perp_m: float,
    min_overlap_m: float,
) -> np.ndarray:
    """update._redundant_pairs for maps ``(P,C)`` and recent columns ``(R,)``: ``(P,C,R)`` bool."""
    lib = _lib()
    p, c = valid.shape
    recent = i64(recent)
    out = np.empty((p, c, len(recent)), dtype=np.uint8)
    lib.redundant_pairs(
        _u8(valid), f64(seg), f64(np.cos(alpha)), f64(np.sin(alpha)), f64(rho), f64(facing), recent, out,
        p, c, len(recent), float(max_angle_rad), float(max_perp_m), float(min_overlap_m),
    )  # fmt: skip
    return out.view(bool)


def observe_segments(
    poses: np.ndarray, moments: np.ndarray, ends: np.ndarray, facing: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """association.observe's geometry: robot-frame segments (``moments (O,6)``, ``ends (O,2,2)``,
    ``facing (O,)``) in the map frame of every particle ``poses (P,3)``: moments ``(P,O,6)``,
    alpha, rho, facing ``(P,O)`` and ends ``(P,O,2,2)``."""
    lib = _lib()
    p, o = len(poses), len(moments)
    mo, al, rh, fo, eo = (
        np.empty((p, o, 6)),
        np.empty((p, o)),
        np.empty((p, o)),
        np.empty((p, o)),
        np.empty((p, o, 2, 2)),
    )
    lib.observe_segments(f64(poses), f64(moments), f64(ends), f64(facing), mo, al, rh, fo, eo, p, o)
    return mo, al, rh, fo, eo


def segment_samples(segments: np.ndarray, step_m: float) -> np.ndarray:
    """``geometry.sample_segments(segments, step_m)[0]``: the middle of each piece of the segments
    ``(S,2,2)`` cut into equal pieces no longer than ``step_m`` (counted as sample_segments does)."""
    lib = _lib()
    seg = f64(segments).reshape(-1, 2, 2)
    d = seg[:, 1] - seg[:, 0]
    counts = i64(np.maximum(np.ceil(np.hypot(d[:, 0], d[:, 1]) / step_m).astype(int), 1))
    out = np.empty((int(counts.sum()), 2))
    lib.segment_samples(seg, counts, out, len(seg), len(out))
    return out
