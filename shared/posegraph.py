"""A 2D pose graph, optimized by sparse Gauss-Newton (scipy.sparse): the solver the robots'
back ends (robot_agent/slam/backend.py) and the server's fleet graph (map_server/posegraph.py)
share.

Residual of an edge ``(a, b, z)``: ``r = [Rₐᵀ(t_b − t_a) − z_xy, θ_b − θ_a − z_θ]``; of a line
tie ``(a, b, p, n, d)`` (a point ``p`` in node b's frame on the line ``n·q = d`` in node a's frame):
``r = n·Rₐᵀ(R_b p + t_b − t_a) − d``.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from shared.geometry import wrap_angle


def _residuals_and_jacobians(x: np.ndarray, a: np.ndarray, b: np.ndarray, z: np.ndarray):
    xa, xb = x[a], x[b]
    c, s = np.cos(xa[:, 2]), np.sin(xa[:, 2])
    dx, dy = xb[:, 0] - xa[:, 0], xb[:, 1] - xa[:, 1]
    r = np.column_stack(
        [c * dx + s * dy - z[:, 0], -s * dx + c * dy - z[:, 1], wrap_angle(xb[:, 2] - xa[:, 2] - z[:, 2])]
    )
    ja = np.zeros((len(a), 3, 3))
    ja[:, 0, 0], ja[:, 0, 1], ja[:, 0, 2] = -c, -s, -s * dx + c * dy
    ja[:, 1, 0], ja[:, 1, 1], ja[:, 1, 2] = s, -c, -c * dx - s * dy
    ja[:, 2, 2] = -1.0
    jb = np.zeros((len(a), 3, 3))
    jb[:, 0, 0], jb[:, 0, 1] = c, s
    jb[:, 1, 0], jb[:, 1, 1] = -s, c
    jb[:, 2, 2] = 1.0
    return r, ja, jb


class LineTies(NamedTuple):
    """Points on lines between nodes: point ``p (L,2)`` in node ``b``'s frame lies on the line
    ``n·q = d`` (``n (L,2)`` unit, ``d (L,)``) in node ``a``'s frame, with information ``w (L,)``
    (1 / variance of the point's distance to the line) and a Cauchy kernel of width ``k (L,)``
    (normalized units; 0: none)."""

    a: np.ndarray
    b: np.ndarray
    p: np.ndarray
    n: np.ndarray
    d: np.ndarray
    w: np.ndarray
    k: np.ndarray


def line_residuals(x: np.ndarray, t: LineTies) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each line tie's signed distance ``r (L,)`` at poses ``x``, and its Jacobians with respect to
    node a's and node b's poses ``(L,3)``."""
    xa, xb = x[t.a], x[t.b]
    ca, sa = np.cos(xa[:, 2]), np.sin(xa[:, 2])
    cb, sb = np.cos(xb[:, 2]), np.sin(xb[:, 2])
    rp = np.column_stack([cb * t.p[:, 0] - sb * t.p[:, 1], sb * t.p[:, 0] + cb * t.p[:, 1]])  # R_b p
    u = rp + xb[:, :2] - xa[:, :2]
    q = np.column_stack([ca * u[:, 0] + sa * u[:, 1], -sa * u[:, 0] + ca * u[:, 1]])  # Rₐᵀ u
    m = np.column_stack([ca * t.n[:, 0] - sa * t.n[:, 1], sa * t.n[:, 0] + ca * t.n[:, 1]])  # Rₐ n
    r = np.sum(t.n * q, axis=1) - t.d
    jb = np.column_stack([m[:, 0], m[:, 1], -m[:, 0] * rp[:, 1] + m[:, 1] * rp[:, 0]])
    ja = np.column_stack([-m[:, 0], -m[:, 1], t.n[:, 0] * q[:, 1] - t.n[:, 1] * q[:, 0]])
    return r, ja, jb


def line_weights(r: np.ndarray, t: LineTies) -> np.ndarray:
    """Each line tie's information after its Cauchy kernel at residuals ``r``."""
    k = np.where(t.k > 0, t.k, np.inf)
    return t.w / (1.0 + t.w * r**2 / k**2)


def optimize(
    x0: np.ndarray,
    a: np.ndarray,
    b: np.ndarray,
    z: np.ndarray,
    info: np.ndarray,
    iterations: int = 5,
    tol: float = 1e-6,
    robust_from: int | None = None,
    robust_k: float | np.ndarray = 3.0,
    stop: Callable[[], bool] | None = None,
    lines: LineTies | None = None,
) -> np.ndarray:
    """Poses ``(N,3)`` minimizing ``Σ rᵀ Ω r`` over edges ``a, b (E,)`` with measured motions
    ``z (E,3)`` and information ``Ω``: ``info (E,3,3)``, or ``(E,3)`` for a diagonal one, from
    ``x0 (N,3)``; node 0 is held fixed (the map frame). Edges from index ``robust_from`` on get a
    Cauchy kernel of width ``robust_k`` (in normalized residual units; or one per such edge), by
    iteratively reweighting. ``lines``: point-on-line ties between nodes besides
    (:class:`LineTies`). No iteration starts once ``stop()`` says so (the caller's clock: the core
    keeps none; the first iteration always runs)."""
    x = np.array(x0, dtype=float, copy=True)
    n = len(x)
    if lines is not None and not len(lines.a):
        lines = None
    if n < 2 or (len(a) == 0 and lines is None):
        return x
    a, b = np.asarray(a, int), np.asarray(b, int)
    omega = full_information(info)
    for _ in range(iterations):
        r, ja, jb = _residuals_and_jacobians(x, a, b, z)
        w = omega
        if robust_from is not None and robust_from < len(a):
            chi2 = mahalanobis2(r[robust_from:], omega[robust_from:])
            w = omega.copy()
            w[robust_from:] *= (1.0 / (1.0 + chi2 / robust_k**2))[:, None, None]
        # H = Σ Jᵀ Ω J over blocks (a,a), (a,b), (b,a), (b,b); g = Σ Jᵀ Ω r — over the free nodes
        # (node 0 held: its rows and columns are never built)
        wa, wb = w @ ja, w @ jb
        ja_t, jb_t = np.swapaxes(ja, 1, 2), np.swapaxes(jb, 1, 2)
        wr = (w @ r[..., None])[..., 0]
        blocks = [ja_t @ wa, ja_t @ wb, jb_t @ wa, jb_t @ wb]
        ga, gb = (ja_t @ wr[..., None])[..., 0], (jb_t @ wr[..., None])[..., 0]
        na, nb = a, b
        if lines is not None:
            lr, lja, ljb = line_residuals(x, lines)
            lw = line_weights(lr, lines)
            wja, wjb = lw[:, None] * lja, lw[:, None] * ljb
            for i, (p, q) in enumerate(((lja, wja), (lja, wjb), (ljb, wja), (ljb, wjb))):
                blocks[i] = np.concatenate([blocks[i], p[:, :, None] * q[:, None, :]])
            ga = np.concatenate([ga, wja * lr[:, None]])
            gb = np.concatenate([gb, wjb * lr[:, None]])
            na, nb = np.concatenate([a, lines.a]), np.concatenate([b, lines.b])
        h, g = _normal_equations(n - 1, na - 1, nb - 1, tuple(blocks), ga, gb)
        # H is symmetric: ordered by minimum degree on its own pattern (H + Hᵀ = 2H), the sparse LU
        # of a pose graph's H is ~5x faster than with the default COLAMD ordering (3,000 keyframes:
        # 57 against 307 ms), the same solution to 1e-11
        step = spla.spsolve(h, -g, permc_spec="MMD_AT_PLUS_A")
        x[1:] += step.reshape(-1, 3)
        x[:, 2] = wrap_angle(x[:, 2])
        if np.max(np.abs(step)) < tol or (stop is not None and stop()):
            break
    return x


def _normal_equations(
    m: int, a: np.ndarray, b: np.ndarray, blocks: tuple, ga: np.ndarray, gb: np.ndarray
) -> tuple[sp.csc_matrix, np.ndarray]:
    """``H (3m, 3m)`` and ``g (3m,)`` over ``m`` free nodes from the edges' blocks ``(aa, ab, ba,
    bb)`` (each ``(E,3,3)``) and gradient parts ``ga, gb (E,3)``; ``a, b`` are free-node indices,
    -1 for the held node (its entries dropped)."""
    nodes = (a, a, b, b), (a, b, a, b)
    rows, cols, vals = [], [], []
    k = np.arange(3)
    for p, q, blk in zip(*nodes, blocks, strict=True):
        keep = (p >= 0) & (q >= 0)
        shape = (int(keep.sum()), 3, 3)
        rows.append(np.broadcast_to((3 * p[keep])[:, None, None] + k[:, None], shape).ravel())
        cols.append(np.broadcast_to((3 * q[keep])[:, None, None] + k[None, :], shape).ravel())
        vals.append(blk[keep].ravel())
    ij = (np.concatenate(rows), np.concatenate(cols))
    h = sp.csc_matrix((np.concatenate(vals), ij), shape=(3 * m, 3 * m))
    g = np.zeros(3 * m)
    for idx, part in ((a, ga), (b, gb)):
        keep = idx >= 0
        g += np.bincount((3 * idx[keep, None] + k).ravel(), part[keep].ravel(), minlength=3 * m)
    return h, g


def full_information(info: np.ndarray) -> np.ndarray:
    """Information matrices ``(E,3,3)`` from ``(E,3,3)`` or diagonals ``(E,3)``."""
    info = np.asarray(info, dtype=float)
    if info.ndim == 3:
        return info
    out = np.zeros((len(info), 3, 3))
    out[:, [0, 1, 2], [0, 1, 2]] = info
    return out


def mahalanobis2(r: np.ndarray, omega: np.ndarray) -> np.ndarray:
    """``rᵀ Ω r`` per row of residuals ``r (E,3)`` with information ``omega (E,3,3)``."""
    return np.einsum("ei,eij,ej->e", r, omega, r)
