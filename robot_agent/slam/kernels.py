"""The compiled kernels (``_kernels.c``) behind a check of what they are given, or ``None`` when
the extension was not built (no C compiler at install): the callers then run their numpy code,
which stays the reference (tests/slam/test_kernels.py holds both to the same results)."""

from __future__ import annotations

import numpy as np

try:
    from robot_agent.slam import _kernels
except ImportError:  # built without a C compiler: the numpy versions run
    _kernels = None

AVAILABLE = _kernels is not None


def _f64(a: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(a, dtype=np.float64)


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
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """proposal.align_points' Gauss-Newton (association, normal equations, the prior-fused
    step) for poses ``x (P,3)`` from a local map of ``C`` columns (``alpha, rho, facing, valid
    (P,C)``, ``seg (P,C,2,2)``) and points ``pts (N,2)``: the refined poses ``(P,3)``, the last
    iteration's measurement information ``(P,3,3)`` and the last association ``(P,N)``."""
    if _kernels is None:
        raise RuntimeError("the compiled kernels are not built (no C compiler at install)")
    x = np.array(x, dtype=np.float64, order="C")
    p, n, c = len(x), len(pts), alpha.shape[1]
    h = np.zeros((p, 3, 3))
    idx = np.empty((p, n), dtype=np.int64)
    gate = np.broadcast_to(np.asarray(gate_wide, dtype=np.float64), (p,))
    _kernels.gn_points(
        x,
        _f64(prior_mean),
        _f64(info_prior),
        _f64(pts),
        _f64(np.cos(alpha)),
        _f64(np.sin(alpha)),
        _f64(rho),
        _f64(seg),
        _f64(np.cos(facing)),
        _f64(np.sin(facing)),
        np.ascontiguousarray(valid, dtype=np.uint8),
        _f64(gate),
        h,
        idx,
        p,
        n,
        c,
        int(iterations),
        int(reassociate_after),
        float(gate_m),
        float(margin_m),
        float(robust_scale_m),
        float(point_sigma_m),
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
    if _kernels is None:
        raise RuntimeError("the compiled kernels are not built (no C compiler at install)")
    p, o = obs_facing.shape
    c = alpha.shape[1]
    idx = np.empty((p, o), dtype=np.int64)
    cost, d_angle, d_perp = np.empty((p, o)), np.empty((p, o)), np.empty((p, o))
    _kernels.associate_segments(
        _f64(obs_facing),
        _f64(centroid[..., 0]),
        _f64(centroid[..., 1]),
        _f64(obs_ends),
        _f64(var_angle),
        _f64(var_perp),
        _f64(np.cos(alpha)),
        _f64(np.sin(alpha)),
        _f64(rho),
        _f64(facing),
        _f64(seg),
        np.ascontiguousarray(valid, dtype=np.uint8),
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
