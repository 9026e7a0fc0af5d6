"""Improved proposal: align the scan to each particle's own map, then sample around the result.

FastSLAM 2.0 (Montemerlo et al. 2003) / GMapping (Grisetti et al. 2007): instead of sampling
from the motion model alone, each particle's pose is refined by the current scan against its
map and sampled from the Gaussian ``N(x*, (H + Σ_motion⁻¹)⁻¹)`` — the motion prior fused with
the measurement.

The measurement term is point-to-line least squares: every point ``p_i`` of an observed segment
against the line ``(n, ρ)`` of its associated element, ``r_i = n·(R p_i + t) - ρ``. Because the
sum over a segment's points of ``r_i²`` and its derivatives only involve the points' first and
second moments, the Gauss-Newton normal equations are assembled from the segment moments:
with ``q = R p`` (moments of the rotated points: ``N, s = Σq, S = Σqqᵀ``), ``e = n·t - ρ`` and
``m = (n_y, -n_x)`` (so that ``∂r/∂θ = m·q``)::

    H_tt = N n nᵀ        H_tθ = n (m·s)         H_θθ = mᵀ S m
    g_t  = n (n·s + N e)                         g_θ  = mᵀ S n + e (m·s)

— all particles × observations at once, a 3×3 solve per particle, no per-point work.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from robot_agent.slam.association import AssociationConfig, associate, observe
from robot_agent.slam.lines import transform_moments
from robot_agent.slam.particles import SegmentMaps
from shared.geometry import wrap_angle


@dataclass(frozen=True)
class ProposalConfig:
    enabled: bool = True
    iterations: int = 4  # Gauss-Newton iterations
    reassociate_after: int = 1  # re-associate with the normal gates after this many iterations
    point_sigma_m: float = 0.05  # per-point residual std used in the alignment (> laser noise:
    # it also covers map error and the correlation of neighbouring points)
    max_points_per_segment: float = 40.0  # cap on a segment's weight (long walls do not dominate)
    robust_scale_m: float = 0.10  # Cauchy scale on a segment's RMS residual
    sample_scale: float = 1.0  # scale on the proposal covariance when sampling
    gate_scale_predicted: float = 2.5  # wider gates for the first association at the predicted pose


def _normal_equations(
    poses: np.ndarray,
    moments_robot: np.ndarray,
    n_m: np.ndarray,
    rho_m: np.ndarray,
    matched: np.ndarray,
    cfg: ProposalConfig,
) -> tuple[np.ndarray, np.ndarray]:
    """``H (P,3,3)`` and ``g (P,3)`` at ``poses (P,3)``."""
    rot = np.zeros_like(poses)
    rot[:, 2] = poses[:, 2]
    q = transform_moments(rot[:, None, :], moments_robot[None])  # (P,O,6)
    n_pts = q[..., 0]
    s = q[..., 1:3]
    sxx, sxy, syy = q[..., 3], q[..., 4], q[..., 5]
    nx, ny = n_m[..., 0], n_m[..., 1]
    mx, my = ny, -nx
    e = nx * poses[:, None, 0] + ny * poses[:, None, 1] - rho_m
    ns = nx * s[..., 0] + ny * s[..., 1]
    ms = mx * s[..., 0] + my * s[..., 1]
    nSn = nx * nx * sxx + 2 * nx * ny * sxy + ny * ny * syy
    mSm = mx * mx * sxx + 2 * mx * my * sxy + my * my * syy
    mSn = mx * nx * sxx + (mx * ny + my * nx) * sxy + my * ny * syy
    sum_r2 = nSn + 2 * e * ns + n_pts * e * e
    rms = np.sqrt(np.maximum(sum_r2, 0.0) / np.maximum(n_pts, 1.0))
    # weight: 1/σ², capped point count, Cauchy on the segment's RMS residual, 0 if unmatched
    w = np.minimum(1.0, cfg.max_points_per_segment / np.maximum(n_pts, 1.0))
    w = w / (1.0 + (rms / cfg.robust_scale_m) ** 2) / cfg.point_sigma_m**2
    w = np.where(matched, w, 0.0)
    h = np.zeros((*poses.shape[:1], 3, 3))
    h[:, 0, 0] = np.sum(w * n_pts * nx * nx, axis=1)
    h[:, 0, 1] = h[:, 1, 0] = np.sum(w * n_pts * nx * ny, axis=1)
    h[:, 1, 1] = np.sum(w * n_pts * ny * ny, axis=1)
    h[:, 0, 2] = h[:, 2, 0] = np.sum(w * nx * ms, axis=1)
    h[:, 1, 2] = h[:, 2, 1] = np.sum(w * ny * ms, axis=1)
    h[:, 2, 2] = np.sum(w * mSm, axis=1)
    sr = ns + n_pts * e
    g = np.stack(
        [np.sum(w * nx * sr, axis=1), np.sum(w * ny * sr, axis=1), np.sum(w * (mSn + e * ms), axis=1)], axis=1
    )
    return h, g


@dataclass(frozen=True)
class ProposalResult:
    mean: np.ndarray  # (P,3) refined poses
    cov: np.ndarray  # (P,3,3) proposal covariance
    n_matched: np.ndarray  # (P,) observations used in the alignment


def align(
    prior_mean: np.ndarray,
    prior_cov: np.ndarray,
    moments_robot: np.ndarray,
    ends_robot: np.ndarray,
    facing_robot: np.ndarray,
    cov_robot: np.ndarray,
    maps: SegmentMaps,
    assoc_cfg: AssociationConfig,
    cfg: ProposalConfig,
) -> ProposalResult:
    """Refine ``prior_mean (P,3)`` by point-to-line alignment of the scan segments (robot frame)
    to each particle's local map; returns the Gaussian proposal per particle."""
    x = prior_mean.copy()
    info_prior = np.linalg.inv(prior_cov)
    var_a = prior_cov[:, 2, 2][:, None, None]
    var_p = (prior_cov[:, 0, 0] + prior_cov[:, 1, 1])[:, None, None]
    assoc = None
    h = np.zeros_like(prior_cov)
    for it in range(cfg.iterations):
        if it == 0 or it == cfg.reassociate_after:
            obs = observe(x, moments_robot, ends_robot, facing_robot, cov_robot, assoc_cfg.point_sigma_m)
            if it == 0:
                assoc = associate(obs, maps, assoc_cfg, var_a, var_p, cfg.gate_scale_predicted)
            else:
                assoc = associate(obs, maps, assoc_cfg)
            idx = np.maximum(assoc.index, 0)
            a_m = np.take_along_axis(maps.alpha, idx, axis=1)
            rho_m = np.take_along_axis(maps.rho, idx, axis=1)
            n_m = np.stack([np.cos(a_m), np.sin(a_m)], axis=-1)
        h, g = _normal_equations(x, moments_robot, n_m, rho_m, assoc.matched, cfg)
        dx_prior = x - prior_mean
        dx_prior[:, 2] = wrap_angle(dx_prior[:, 2])
        lhs = h + info_prior
        rhs = -(g + np.einsum("pij,pj->pi", info_prior, dx_prior))
        step = np.linalg.solve(lhs, rhs[..., None])[..., 0]
        x = x + step
        x[:, 2] = wrap_angle(x[:, 2])
    cov = np.linalg.inv(h + info_prior) * cfg.sample_scale
    cov = 0.5 * (cov + np.transpose(cov, (0, 2, 1)))
    return ProposalResult(x, cov, assoc.matched.sum(axis=1) if assoc is not None else np.zeros(len(x), int))
