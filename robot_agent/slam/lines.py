"""Infinite lines from point sets through sufficient statistics (moments).

A point set is summarized by its moments ``(..., 6) = [n, Σx, Σy, Σxx, Σxy, Σyy]``. Moments add
(merging two observations of a wall is ``m1 + m2``) and move exactly under SE(2)
(:func:`transform_moments`), so a map element can be refitted from all the points ever
assigned to it without keeping the points.

A line is ``(alpha, rho)`` in Hessian normal form: ``x cos(alpha) + y sin(alpha) = rho`` with
``rho >= 0``; ``n = (cos alpha, sin alpha)`` is the unit normal pointing from the origin to the
line and ``d = (-sin alpha, cos alpha)`` the direction along it. A point of the line is
``rho n + t d``; ``t`` is its coordinate along the line.

References: K. O. Arras, R. Siegwart, "Feature extraction and scene interpretation for
map-based navigation and map building", SPIE 1997 (TLS line fit in polar form);
S. T. Pfister, S. I. Roumeliotis, J. W. Burdick, "Weighted line fitting algorithms for mobile
robot map building and efficient data representation", ICRA 2003 (line covariance).
"""

from __future__ import annotations

import numpy as np

from shared.geometry import wrap_angle

#: Column order of a moments array ``(..., 6)``.
MOMENT_FIELDS = ("n", "sx", "sy", "sxx", "sxy", "syy")


def moments_from_points(points: np.ndarray, labels: np.ndarray, n_labels: int) -> np.ndarray:
    """Moments ``(n_labels, 6)`` of the points ``(K, 2)`` grouped by ``labels (K,)``.

    Points whose label is outside ``[0, n_labels)`` (e.g. ``-1``) are ignored.
    """
    points = np.asarray(points, dtype=float).reshape(-1, 2)
    labels = np.asarray(labels).reshape(-1)
    keep = (labels >= 0) & (labels < n_labels)
    x, y, lab = points[keep, 0], points[keep, 1], labels[keep]
    columns = np.stack([np.ones_like(x), x, y, x * x, x * y, y * y], axis=-1)  # (K', 6)
    bins = lab[:, None] * 6 + np.arange(6)  # one bincount for all six sums
    out = np.bincount(bins.ravel(), weights=columns.ravel(), minlength=6 * n_labels)
    return out.reshape(n_labels, 6)


def moments_of(points: np.ndarray) -> np.ndarray:
    """Moments ``(..., 6)`` of point sets ``(..., K, 2)`` (one set per leading index)."""
    p = np.asarray(points, dtype=float)
    x, y = p[..., 0], p[..., 1]
    n = np.full(x.shape[:-1], float(x.shape[-1]))
    return np.stack([n, x.sum(-1), y.sum(-1), (x * x).sum(-1), (x * y).sum(-1), (y * y).sum(-1)], axis=-1)


def transform_moments(pose: np.ndarray, moments: np.ndarray) -> np.ndarray:
    """Exact moments ``(..., 6)`` of the points mapped by ``x' = R x + t``; batch axes broadcast.

    With ``s = (Σx, Σy)`` and ``S = [[Σxx, Σxy], [Σxy, Σyy]]``:
    ``s' = R s + n t`` and ``S' = R S Rᵀ + R s tᵀ + t (R s)ᵀ + n t tᵀ``.
    """
    pose = np.asarray(pose, dtype=float)
    m = np.asarray(moments, dtype=float)
    c, s = np.cos(pose[..., 2]), np.sin(pose[..., 2])
    tx, ty = pose[..., 0], pose[..., 1]
    n, sx, sy, sxx, sxy, syy = (m[..., j] for j in range(6))
    ux, uy = c * sx - s * sy, s * sx + c * sy  # R s
    # R S Rᵀ, written out for the symmetric 2×2 S
    rxx = c * c * sxx - 2.0 * c * s * sxy + s * s * syy
    ryy = s * s * sxx + 2.0 * c * s * sxy + c * c * syy
    rxy = c * s * (sxx - syy) + (c * c - s * s) * sxy
    out = [
        n,
        ux + n * tx,
        uy + n * ty,
        rxx + 2.0 * ux * tx + n * tx * tx,
        rxy + ux * ty + uy * tx + n * tx * ty,
        ryy + 2.0 * uy * ty + n * ty * ty,
    ]
    return np.stack(np.broadcast_arrays(*out), axis=-1)


def _central(moments: np.ndarray):
    """Count, centroid and centred scatter ``(Sxx, Sxy, Syy)`` of moments ``(..., 6)``."""
    m = np.asarray(moments, dtype=float)
    n = m[..., 0]
    with np.errstate(divide="ignore", invalid="ignore"):
        xc, yc = m[..., 1] / n, m[..., 2] / n
    sxx = m[..., 3] - n * xc * xc
    sxy = m[..., 4] - n * xc * yc
    syy = m[..., 5] - n * yc * yc
    return n, xc, yc, sxx, sxy, syy


def fit_lines(moments: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Total-least-squares lines of moments ``(..., 6)``: ``alpha, rho, sigma2``, each ``(...)``.

    Minimizing ``Σ (x_i cos α + y_i sin α - ρ)²`` gives ``ρ = x̄ cos α + ȳ sin α`` and
    ``tan 2α = -2 Sxy / (Syy - Sxx)`` on the centred scatter (Arras & Siegwart 1997, eq. 5-6);
    the ``atan2`` branch picks the minimum. ``sigma2`` is the residual variance: the smallest
    eigenvalue of the scatter over ``n``. Sets with ``n < 2`` give ``nan``.
    """
    n, xc, yc, sxx, sxy, syy = _central(moments)
    alpha = 0.5 * np.arctan2(-2.0 * sxy, syy - sxx)
    rho = xc * np.cos(alpha) + yc * np.sin(alpha)
    flip = rho < 0.0  # keep rho >= 0: the same line with the opposite normal
    alpha = wrap_angle(np.where(flip, alpha + np.pi, alpha))
    rho = np.abs(rho)
    half_trace = 0.5 * (sxx + syy)
    lam_min = half_trace - np.hypot(0.5 * (sxx - syy), sxy)
    with np.errstate(divide="ignore", invalid="ignore"):
        sigma2 = np.maximum(lam_min, 0.0) / n
    bad = ~(n >= 2)
    if np.any(bad):
        alpha, rho, sigma2 = (np.where(bad, np.nan, v) for v in (alpha, rho, sigma2))
    return alpha, rho, sigma2


def line_covariance(moments: np.ndarray, alpha: np.ndarray, sigma2: np.ndarray) -> np.ndarray:
    """First-order covariance ``(..., 2, 2)`` of a TLS ``(alpha, rho)`` fit.

    Each point has isotropic noise of variance ``sigma2``; only its component along the normal
    moves the line. With ``t_i`` the centred points' coordinates along the line direction
    ``d``, the normal angle is perturbed by ``δα = Σ t_i ε_i / Σ t_i²`` so
    ``var(α) = σ² / S_perp`` with ``S_perp = Σ t_i²`` (Pfister et al. 2003, eq. 14).
    From ``ρ = x̄ cos α + ȳ sin α``: ``δρ = n·δc + (-x̄ sin α + ȳ cos α) δα = n·δc + t_c δα``,
    ``t_c`` being the centroid's coordinate along the line. ``n·δc`` (variance ``σ²/n``) is
    uncorrelated with ``δα`` because ``Σ t_i = 0``, hence
    ``var(ρ) = σ²/n + t_c² var(α)`` and ``cov(α, ρ) = t_c var(α)``.
    """
    n, xc, yc, sxx, sxy, syy = _central(moments)
    alpha = np.asarray(alpha, dtype=float)
    sigma2 = np.asarray(sigma2, dtype=float)
    c, s = np.cos(alpha), np.sin(alpha)
    s_perp = s * s * sxx - 2.0 * c * s * sxy + c * c * syy  # dᵀ S d
    t_c = -xc * s + yc * c
    with np.errstate(divide="ignore", invalid="ignore"):
        var_a = sigma2 / s_perp
        var_r = sigma2 / n + t_c * t_c * var_a
    cov_ar = t_c * var_a
    out = np.stack(np.broadcast_arrays(var_a, cov_ar, cov_ar, var_r), axis=-1)
    return out.reshape((*out.shape[:-1], 2, 2))


def transform_lines(
    pose: np.ndarray, alpha: np.ndarray, rho: np.ndarray, cov: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Lines (and optionally their ``(..., 2, 2)`` covariances) mapped by ``pose (..., 3)``.

    ``α' = α + θ``, ``ρ' = ρ + tx cos α' + ty sin α'``; if ``ρ' < 0`` the normal is flipped
    (``α' + π``, ``-ρ'``). Jacobian ``J = [[1, 0], [sgn k, sgn]]`` with
    ``k = dρ'/dα = -tx sin α' + ty cos α'`` and ``sgn = ±1`` the flip; ``cov' = J cov Jᵀ``.
    """
    pose = np.asarray(pose, dtype=float)
    a = np.asarray(alpha, dtype=float) + pose[..., 2]
    tx, ty = pose[..., 0], pose[..., 1]
    r = np.asarray(rho, dtype=float) + tx * np.cos(a) + ty * np.sin(a)
    k = -tx * np.sin(a) + ty * np.cos(a)
    sgn = np.where(r < 0.0, -1.0, 1.0)
    a_out = wrap_angle(np.where(sgn < 0, a + np.pi, a))
    r_out = np.abs(r)
    if cov is None:
        return a_out, r_out, None
    cov = np.asarray(cov, dtype=float)
    # rows of J: dα'/d(α, ρ) = (1, 0); dρ'/d(α, ρ) = sgn (k, 1)
    j_ra, j_rr = sgn * k, sgn
    vaa, var_, vrr = cov[..., 0, 0], cov[..., 0, 1], cov[..., 1, 1]
    out_ar = j_ra * vaa + j_rr * var_
    out_rr = j_ra * j_ra * vaa + 2.0 * j_ra * j_rr * var_ + j_rr * j_rr * vrr
    out = np.stack(np.broadcast_arrays(vaa, out_ar, out_ar, out_rr), axis=-1)
    return a_out, r_out, out.reshape((*out.shape[:-1], 2, 2))


def interval_overlap(t_a: np.ndarray, t_b: np.ndarray) -> np.ndarray:
    """How far intervals given by their two ends ``(..., 2)`` (in any order) overlap; negative:
    the gap between them. (Elementwise over the two ends: a reduction over an axis of two costs
    many times more, and this runs for every particle x observation x element.)"""
    lo = np.maximum(np.minimum(t_a[..., 0], t_a[..., 1]), np.minimum(t_b[..., 0], t_b[..., 1]))
    hi = np.minimum(np.maximum(t_a[..., 0], t_a[..., 1]), np.maximum(t_b[..., 0], t_b[..., 1]))
    return hi - lo


def project_to_line(points: np.ndarray, alpha: np.ndarray, rho: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Coordinates of points ``(..., 2)`` relative to lines ``(...)``: ``(t, dist)``, each ``(...)``.

    ``t`` is the coordinate along the direction ``d = (-sin α, cos α)`` of the foot point
    ``ρ n + t d``; ``dist`` is the signed distance ``p·n - ρ`` (positive away from the origin).
    """
    p = np.asarray(points, dtype=float)
    c, s = np.cos(alpha), np.sin(alpha)
    t = -s * p[..., 0] + c * p[..., 1]
    dist = c * p[..., 0] + s * p[..., 1] - rho
    return t, dist


def points_on_line(alpha: np.ndarray, rho: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Points ``(..., 2)`` of lines ``(alpha, rho)`` at coordinates ``t`` along them."""
    c, s = np.cos(alpha), np.sin(alpha)
    x = rho * c - t * s
    y = rho * s + t * c
    return np.stack(np.broadcast_arrays(x, y), axis=-1)


def segment_endpoints(
    alpha: np.ndarray, rho: np.ndarray, t_start: np.ndarray, t_end: np.ndarray
) -> np.ndarray:
    """Segments ``(..., 2, 2)`` on lines ``(alpha, rho)`` from ``t_start`` to ``t_end``."""
    return np.stack([points_on_line(alpha, rho, t_start), points_on_line(alpha, rho, t_end)], axis=-2)
