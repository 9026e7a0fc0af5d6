"""Maximum-likelihood association of observed segments with map elements (report §4.2).

The distance between an observed segment ``e`` and a map element ``f`` combines
(report: "Euclidean distance + orientation difference", made precise here):

- ``d_angle``: difference of the *facing* directions (normal toward the side the sensor saw),
  so the two faces of a thin wall are different elements;
- ``d_perp``: offset of the observation's centroid from ``f``'s line;
- ``gap``: distance between their extents along ``f``'s line (0 when they overlap), so two walls
  on one line across a doorway stay two elements.

Each is normalised by its standard deviation (observation + element + pose uncertainty) and
summed (a Mahalanobis distance with a diagonal covariance); the ML element is the ``argmin``
among those inside every gate, computed for all particles × observations × elements at once.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from robot_agent.slam import kernels
from robot_agent.slam.lines import fit_lines, interval_overlap, project_to_line, transform_moments
from robot_agent.slam.particles import SegmentMaps
from shared.geometry import apply_segments, wrap_angle


@dataclass(frozen=True)
class AssociationConfig:
    angle_gate_rad: float = np.radians(12.0)  # max facing difference
    perp_gate_m: float = 0.25  # max centroid-to-line offset
    gap_gate_m: float = 0.3  # max gap between extents along the line (doors are ~0.8 m)
    sigma_angle_rad: float = np.radians(2.0)  # element + pose angular std (added to the observation's)
    sigma_perp_m: float = 0.05  # element + pose offset std (added to the observation's)
    sigma_gap_m: float = 0.3  # scale of the extent gap in the distance
    point_sigma_m: float = 0.02  # laser point noise, for an observation's own line covariance
    compiled: bool = True  # the compiled kernel (kernels.py) when it is built; the numpy code else


@dataclass(frozen=True)
class Observations:
    """A scan's segments seen from every particle, in the map frame. ``O`` segments.

    ``moments (P,O,6)``, ``alpha/rho/facing (P,O)``, ``ends (P,O,2,2)``; ``n_points (O,)``;
    ``var_angle (O,)`` and ``var_perp (O,)`` the segment fit's own variances."""

    moments: np.ndarray
    alpha: np.ndarray
    rho: np.ndarray
    facing: np.ndarray
    ends: np.ndarray
    n_points: np.ndarray
    var_angle: np.ndarray
    var_perp: np.ndarray

    @property
    def n(self) -> int:
        return self.alpha.shape[1]

    @property
    def centroid(self) -> np.ndarray:
        return self.moments[..., 1:3] / self.moments[..., :1]


def observe(
    poses: np.ndarray,
    moments_robot: np.ndarray,
    ends_robot: np.ndarray,
    facing_robot: np.ndarray,
    cov_robot: np.ndarray,
    point_sigma_m: float,
    compiled: bool = True,
) -> Observations:
    """Move a scan's segments (robot frame: ``moments (O,6)``, ``ends (O,2,2)``, ``facing (O,)``,
    line covariance ``(O,2,2)``) into the map frame of each particle ``poses (P,3)``
    (``compiled``: by the compiled kernel when it is built)."""
    if compiled and kernels.AVAILABLE:
        m, alpha, rho, facing, ends = kernels.observe_segments(poses, moments_robot, ends_robot, facing_robot)
    else:
        m = transform_moments(poses[:, None, :], moments_robot[None])
        alpha, rho, _ = fit_lines(m)
        ends = apply_segments(poses, ends_robot)
        facing = wrap_angle(facing_robot[None, :] + poses[:, 2:3])
    n = moments_robot[:, 0]
    return Observations(
        moments=m,
        alpha=alpha,
        rho=rho,
        facing=facing,
        ends=ends,
        n_points=n,
        var_angle=cov_robot[:, 0, 0],
        var_perp=point_sigma_m**2 / np.maximum(n, 1.0),
    )


@dataclass(frozen=True)
class Association:
    """``index (P,O)`` column in the local map or -1; ``cost (P,O)`` the normalised squared
    distance (inf when unmatched); ``d_angle``, ``d_perp`` ``(P,O)`` of the chosen pair."""

    index: np.ndarray
    cost: np.ndarray
    d_angle: np.ndarray
    d_perp: np.ndarray

    @property
    def matched(self) -> np.ndarray:
        return self.index >= 0


def pair_terms(obs: Observations, maps: SegmentMaps) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``d_angle``, signed ``d_perp`` and ``gap`` for every (particle, observation, element):
    each ``(P,O,C)``."""
    d_angle = np.abs(wrap_angle(obs.facing[:, :, None] - maps.facing[:, None, :]))
    c = obs.centroid
    a, r = maps.alpha[:, None, :], maps.rho[:, None, :]
    _, d_perp = project_to_line(c[:, :, None, :], a, r)
    t_obs, _ = project_to_line(obs.ends[:, :, None, :, :], a[..., None], r[..., None])  # (P,O,C,2)
    t_map, _ = project_to_line(maps.seg[:, None, :, :, :], a[..., None], r[..., None])  # (P,1,C,2)
    gap = np.maximum(-interval_overlap(t_obs, t_map), 0.0)
    return d_angle, d_perp, gap


def associate(
    obs: Observations,
    maps: SegmentMaps,
    cfg: AssociationConfig,
    pose_var_angle: float | np.ndarray = 0.0,
    pose_var_perp: float | np.ndarray = 0.0,
    gate_scale: float = 1.0,
) -> Association:
    """ML association of every observation with the elements of a local map ``(P,C)``.

    ``pose_var_*`` (scalar or ``(P,1,1)``) widen the distance for an uncertain pose (e.g. before
    the proposal aligned it); ``gate_scale`` widens the gates likewise.
    """
    p, o = obs.alpha.shape
    if maps.capacity == 0 or o == 0:
        none = np.full((p, o), -1)
        inf = np.full((p, o), np.inf)
        return Association(none, inf, inf, inf)
    var_a = obs.var_angle[None, :, None] + cfg.sigma_angle_rad**2 + pose_var_angle
    var_p = obs.var_perp[None, :, None] + cfg.sigma_perp_m**2 + pose_var_perp
    if cfg.compiled and kernels.AVAILABLE:  # the same gates and costs, compiled
        return Association(
            *kernels.associate_segments(
                obs.facing,
                obs.centroid,
                obs.ends,
                np.broadcast_to(var_a, (p, o, 1))[..., 0],
                np.broadcast_to(var_p, (p, o, 1))[..., 0],
                maps.alpha,
                maps.rho,
                maps.facing,
                maps.seg,
                maps.valid,
                cfg.angle_gate_rad * gate_scale,
                cfg.perp_gate_m * gate_scale,
                cfg.gap_gate_m * gate_scale,
                cfg.sigma_gap_m,
            )
        )
    d_angle, d_perp, gap = pair_terms(obs, maps)
    cost = d_angle**2 / var_a + d_perp**2 / var_p + (gap / cfg.sigma_gap_m) ** 2
    ok = (
        maps.valid[:, None, :]
        & (d_angle < cfg.angle_gate_rad * gate_scale)
        & (np.abs(d_perp) < cfg.perp_gate_m * gate_scale)
        & (gap < cfg.gap_gate_m * gate_scale)
    )
    cost = np.where(ok, cost, np.inf)
    idx = np.argmin(cost, axis=2)
    best = np.take_along_axis(cost, idx[..., None], axis=2)[..., 0]
    matched = np.isfinite(best)
    da = np.take_along_axis(d_angle, idx[..., None], axis=2)[..., 0]
    dp = np.take_along_axis(d_perp, idx[..., None], axis=2)[..., 0]
    return Association(
        np.where(matched, idx, -1), best, np.where(matched, da, np.inf), np.where(matched, dp, np.inf)
    )


def match_log_likelihood(
    assoc: Association, obs: Observations, cfg: AssociationConfig, log_p_new: float
) -> np.ndarray:
    """Per-(particle, observation) log-likelihood ``(P,O)``: Gaussian in (angle, offset) for a
    match, ``log_p_new`` (the likelihood of seeing a new element) otherwise — capped below by
    it, so one bad match costs no more than a new element (robust to clutter)."""
    var_a = obs.var_angle[None, :] + cfg.sigma_angle_rad**2
    var_p = obs.var_perp[None, :] + cfg.sigma_perp_m**2
    ll = -0.5 * (assoc.d_angle**2 / var_a + assoc.d_perp**2 / var_p)
    ll = np.where(assoc.matched, ll, -np.inf)
    return np.maximum(ll, log_p_new)
