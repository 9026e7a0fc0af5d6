"""Improved proposal: align the scan to each particle's own map, then sample around the result.

FastSLAM 2.0 (Montemerlo et al. 2003) / GMapping (Grisetti et al. 2007): instead of sampling
from the motion model alone, each particle's pose is refined by the current scan against its
map and sampled from the Gaussian ``N(x*, (H + Σ_motion⁻¹)⁻¹)`` — the motion prior fused with
the measurement.

The measurement term is point-to-line least squares, ``r_i = n·(R p_i + t) - ρ`` for a point
``p_i`` against the line ``(n, ρ)`` of its associated element. Two measurements share one
Gauss-Newton solver (``_gauss_newton``):

- ``measurement = "points"`` (default): every scan point (thinned to ``max_points``), each
  associated with the nearest element whose extent it falls in and whose free side faces the
  sensor, Cauchy-weighted. It uses what extraction drops: sparse points of walls seen at grazing
  angles, far along a corridor, which lock the rotation.
- ``measurement = "segments"``: only the points of the extracted segments. Because the
sum over a segment's points of ``r_i²`` and its derivatives only involve the points' first and
second moments, the Gauss-Newton normal equations are assembled from the segment moments:
with ``q = R p`` (moments of the rotated points: ``N, s = Σq, S = Σqqᵀ``), ``e = n·t - ρ`` and
``m = (n_y, -n_x)`` (so that ``∂r/∂θ = m·q``)::

    H_tt = N n nᵀ        H_tθ = n (m·s)         H_θθ = mᵀ S m
    g_t  = n (n·s + N e)                         g_θ  = mᵀ S n + e (m·s)

— all particles × observations at once, a 3×3 solve per particle, no per-point work.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from robot_agent.slam import kernels
from robot_agent.slam.association import AssociationConfig, associate, observe
from robot_agent.slam.lines import transform_moments
from robot_agent.slam.particles import SegmentMaps
from shared.geometry import apply_points, wrap_angle

ASSOCIATION_CHUNK = 1 << 18  # particle x (point, element) pairs evaluated at once (2 MB per array)


@dataclass(frozen=True)
class ProposalConfig:
    enabled: bool = True
    iterations: int = 4  # Gauss-Newton iterations
    reassociate_after: int = 1  # re-associate with the normal gates after this many iterations
    point_sigma_m: float = 0.03  # per-point residual std used in the alignment (> laser noise:
    # it also covers map error and the correlation of neighbouring points)
    max_points_per_segment: float = 40.0  # cap on a segment's weight (long walls do not dominate)
    robust_scale_m: float = 0.10  # Cauchy scale on a segment's RMS residual
    # scale on the proposal covariance when the particles are drawn: under 1 the particles are
    # drawn nearer the scan match's pose (fewer, tighter hypotheses: each particle's path carries
    # less of the proposal's own spread into its map). 0.7 against 1.0 (bench_logs.py, seeds 0-5):
    # Intel 0.0244 -> 0.0234 m, ACES 0.0399 -> 0.0390, MIT-CSAIL 0.0314 -> 0.0315 (12 seeds); the 60
    # simulated robots of bench_merge: ATE 0.023 -> 0.019 m, own map frames over 0.05 m 5 -> 0. At
    # 0.5 a simulated office robot lost its way (17 deg off); the filter alone drifts more (Intel
    # 0.53 -> 0.63 m before the back end)
    sample_scale: float = 0.7
    # the path (the trajectory, the back end's keyframes and chain edges, the published path)
    # records each particle's scan-match pose, the proposal's mean, rather than the pose drawn
    # from it: the draw's spread (its purpose: the particles' maps differ) is noise on the path,
    # and each keyframe carried it into the chain edges. The particles' own poses and maps are
    # drawn as before. The simulated fleets' own edges against the truth 0.0058 m / 0.067 deg ->
    # 0.0032 m / 0.026 deg at the median (bench_merge, 60 robots); bench_logs seeds 0-5: Intel
    # 0.02258 -> 0.02221 m, ACES 0.03907 -> 0.03851, MIT-CSAIL 0.03058 -> 0.02973. Mapping at the
    # mean as well (the maps without the draw's spread) lost ACES seed 4 (1.65 m): the particles'
    # maps no longer differ enough to hold the alternatives a loop needs
    record_mean: bool = True
    # the particles are drawn with the motion prior's translation at the odometry's own noise where
    # the scans measured it under the motion model's (never over it): a step measures it where its
    # proposal's variances are all under ``pinned_share`` of the motion's (the scan pins the pose),
    # as the scan-matched pose's distance from odometry's prediction, d Σ⁻¹ d / 2 over x and y
    # (MeasuredOdometry). Along a blind aisle the draws are the motion prior's, and each particle's
    # path wanders with them: a simulated robot drifted 4 cm along an aisle with perfect odometry
    # (the simulated robots measure 0.1 of the model's variance). The 60 simulated robots, two
    # seeds of the filter each, the first form (no forgetting; ATE, own map frames against starts):
    # office 0.0135 / 0.0144 -> 0.0124 / 0.0132 m, 0.0171 / 0.0191 -> 0.0185 / 0.0147 m; warehouse
    # 0.0217 / 0.0247 -> 0.0142 / 0.0148 m, 0.0211 / 0.0274 -> 0.0149 / 0.0152 m; bench_merge (new
    # recordings): final transform errors over 0.05 m 5 -> 3 of 40, mean 0.026 -> 0.021 m, the fused
    # map within 0.05 m 96.4 -> 98.1 %. The development logs measure 1.3-4 times the model's: ACES
    # and MIT-CSAIL unchanged to the digit; Intel's first part measures under it (bench_logs.py
    # seeds 0-2: 0.02247 -> 0.02223 m, the online back end at the end 0.0222 -> 0.0220 m)
    draw_measured_odometry: bool = True
    pinned_share: float = 0.5
    odometry_prior_steps: float = 20.0  # the measure starts at the model's, worth this many steps ...
    odometry_horizon_steps: float = 2000.0  # ... and forgets older steps at this horizon
    min_odometry_ratio: float = 0.05  # the draws' prior never under this share of the model's variance
    gate_scale_predicted: float = 2.5  # wider gates for the first association at the predicted pose
    measurement: str = "points"  # "points": every scan point against the map's segments;
    # "segments": only the extracted segments (assembled from their moments)
    max_points: int = 240  # scan points used by the point alignment (evenly thinned beyond)
    point_gate_m: float = 0.2  # a point is associated with an element closer than this ...
    extent_margin_m: float = 0.2  # ... whose extent (plus this margin) its projection falls in
    # ... and whose line is this near the line of the point's own piece of the scan, where one fits
    # (extraction.ScanSegments.point_alpha; np.pi / 2: no gate), from the re-association on (the
    # first, at the predicted pose, may be turned far: ACES seed 2 jumped 38 m with it there). A
    # face too short to keep as a segment (a pillar's side, a door jamb) stands within the point
    # gate of the wall it juts from, and its points, paired with the wall's line, turned the path
    # one way: the simulated warehouse's robot3 0.19 deg in 30 s along its pillars (20 seeds; 0.04
    # with the gate, 0.02 without the pillars). bench_logs seeds 0-5: Intel 0.02315 -> 0.02258 m,
    # ACES 0.03901 -> 0.03907 (seeds 6-11: 0.03990 -> 0.03908), MIT-CSAIL 0.03165 -> 0.03058; the
    # filter alone on MIT-CSAIL 0.044 -> 0.030 m
    point_angle_gate_rad: float = np.radians(30.0)
    compiled: bool = True  # the point alignment by the compiled kernel (kernels.py) when it is built


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
    cov: np.ndarray  # (P,3,3) its covariance (the particles are drawn from it times sample_scale)
    n_matched: np.ndarray  # (P,) observations used in the alignment
    scan_info: np.ndarray  # (P,3,3) the scan's information H at ``mean`` (cov = (H + Σ⁻¹)⁻¹)
    prior_info: np.ndarray  # (P,3,3) the motion prior's information Σ⁻¹ it was solved with


@dataclass
class MeasuredOdometry:
    """The odometry's translation noise as the scans measure it, in units of the motion model's
    variance (ProposalConfig.draw_measured_odometry): a forgetting average of each measuring step's
    ``d Σ⁻¹ d / 2``, starting at 1 (the model's)."""

    total: float = 0.0
    steps: float = 0.0

    def add(
        self, d: np.ndarray, motion_cov: np.ndarray, proposal_cov: np.ndarray, cfg: ProposalConfig
    ) -> None:
        """One step's particles: ``d (P,3)`` scan-matched pose minus odometry's prediction,
        ``motion_cov, proposal_cov (P,3,3)``. Only the particles whose proposal the scan pinned
        (every variance under ``cfg.pinned_share`` of the motion's) measure it."""
        mv, pv = np.einsum("pii->pi", motion_cov), np.einsum("pii->pi", proposal_cov)
        pinned = np.all(pv < cfg.pinned_share * mv, axis=1)
        if not pinned.any():
            return
        dxy = d[pinned, :2]
        m = np.einsum("pi,pij,pj->p", dxy, np.linalg.inv(motion_cov[pinned, :2, :2]), dxy) / 2.0
        keep = 1.0 - 1.0 / cfg.odometry_horizon_steps
        self.total = self.total * keep + float(np.mean(m))
        self.steps = self.steps * keep + 1.0

    def ratio(self, cfg: ProposalConfig) -> float:
        """The measured variance over the model's, within ``[cfg.min_odometry_ratio, 1]``."""
        n0 = cfg.odometry_prior_steps
        return float(np.clip((n0 + self.total) / (n0 + self.steps), cfg.min_odometry_ratio, 1.0))


def draw_covariance(prop: ProposalResult, motion_info: np.ndarray, ratio: float) -> np.ndarray:
    """The covariance the particles are drawn from ``(P,3,3)``: the proposal's ``(H + Σ⁻¹)⁻¹``
    (``motion_info``: the motion prior's ``Σ⁻¹``, as the filter has it for the weights) with the
    prior's translation variance times ``ratio`` (``(H + S⁻¹ Σ⁻¹ S⁻¹)⁻¹``,
    ``S = diag(√ratio, √ratio, 1)``); the proposal's own at 1."""
    if ratio >= 1.0:
        return prop.cov
    s = 1.0 / np.sqrt(np.array([ratio, ratio, 1.0]))
    out = np.linalg.inv(prop.scan_info + motion_info * s[None, :, None] * s[None, None, :])
    return 0.5 * (out + np.transpose(out, (0, 2, 1)))


def _rotate(poses: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Robot-frame ``points (N,2)`` rotated by each particle's heading: ``qx, qy (P,N)``."""
    heading_only = np.zeros_like(poses)
    heading_only[:, 2] = poses[:, 2]
    q = apply_points(heading_only, points)
    return q[..., 0], q[..., 1]


def associate_points(
    poses: np.ndarray,
    points: np.ndarray,
    maps: SegmentMaps,
    gate_m: np.ndarray | float,
    margin_m: float,
    point_alpha: np.ndarray | None = None,
    angle_gate_rad: float = np.pi / 2,
) -> np.ndarray:
    """Element index ``(P,N)`` (or -1) of every scan point ``points (N,2)`` (robot frame) seen
    from ``poses (P,3)``: the element nearest to the point whose line is within ``gate_m``
    (scalar or ``(P,)``), whose extent (plus ``margin_m``) the point projects into, and whose
    free side faces the sensor — the back of a thin wall and a wall's continuation past a
    doorway are not evidence — and, given the normal angle of each point's own line
    ``point_alpha (N,)`` (robot frame; NaN: none), whose line is within ``angle_gate_rad`` of it:
    a pillar's side is no evidence for the wall behind it. Ties go to the lower column.

    The particles see the scan from nearly the same place, so the (point, element) pairs that
    can pass the gate are found once, from a reference pose, against a box around every
    particle's copy of each element (a superset: the box is widened by the gate, the margin
    and how far any particle's view of a point is from the reference's); the exact test runs
    on those pairs only — the same result as testing every pair, at a fraction of the work."""
    qx, qy = _rotate(poses, points)
    wx, wy = qx + poses[:, None, 0], qy + poses[:, None, 1]  # (P,N) map frame
    turn = None
    if point_alpha is not None and angle_gate_rad < np.pi / 2:
        turn = (np.asarray(point_alpha, float), poses[:, 2], np.sin(angle_gate_rad))
    pt, col = _candidate_pairs(wx, wy, maps, float(np.max(gate_m)), margin_m)
    out = np.full((len(poses), points.shape[0]), -1)
    if len(pt) == 0:
        return out
    # wide gates (an uncertain prediction) can pair every point with many elements: the pairs
    # are taken in runs of whole points, at most ASSOCIATION_CHUNK particle x pair elements each
    # (Intel: a 22 MB transient in one step, which the process's memory kept)
    per = max(1, ASSOCIATION_CHUNK // max(len(poses), 1))
    bounds = [0, len(pt)]
    if len(pt) > per:
        first_of_point = np.flatnonzero(np.r_[True, pt[1:] != pt[:-1]])
        cuts = first_of_point[np.searchsorted(first_of_point, np.arange(per, len(pt), per), side="right") - 1]
        bounds = sorted({0, len(pt), *cuts.tolist()})
    for a, b in itertools.pairwise(bounds):
        _nearest_elements(out, qx, qy, wx, wy, pt[a:b], col[a:b], maps, gate_m, margin_m, turn)
    return out


def _nearest_elements(out, qx, qy, wx, wy, pt, col, maps, gate_m, margin_m, turn=None) -> None:
    """:func:`associate_points` for the candidate pairs ``(pt, col)`` (sorted, whole points),
    written into ``out (P,N)``."""
    px, py = wx[:, pt], wy[:, pt]  # (P,K)
    nx, ny = np.cos(maps.alpha[:, col]), np.sin(maps.alpha[:, col])
    perp = np.abs(nx * px + ny * py - maps.rho[:, col])
    t_pt = ny * px - nx * py  # along the line, direction (-n_y, n_x) up to sign, as the ends:
    seg = maps.seg[:, col]
    t0 = ny * seg[..., 0, 0] - nx * seg[..., 0, 1]
    t1 = ny * seg[..., 1, 0] - nx * seg[..., 1, 1]
    inside = (t_pt > np.minimum(t0, t1) - margin_m) & (t_pt < np.maximum(t0, t1) + margin_m)
    # the sensor must be on the element's free side: facing · (sensor - point) > 0
    front = np.cos(maps.facing[:, col]) * qx[:, pt] + np.sin(maps.facing[:, col]) * qy[:, pt] < 0
    gate = np.reshape(gate_m, (-1, 1)) if np.ndim(gate_m) else gate_m
    ok = maps.valid[:, col] & inside & front & (perp < gate)
    if turn is not None:  # the point's own line (where one fits it) near the element's
        pa, heading, max_sin = turn
        d = np.abs(np.sin(pa[pt][None, :] + heading[:, None] - maps.alpha[:, col]))
        ok &= np.isnan(pa[pt])[None, :] | (d <= max_sin)
    cost = np.where(ok, perp, np.inf)
    # nearest per point: pairs are sorted by point, then column (the lower column wins a tie)
    starts = np.flatnonzero(np.r_[True, pt[1:] != pt[:-1]])
    low = np.minimum.reduceat(cost, starts, axis=1)  # (P,Q)
    counts = np.diff(np.r_[starts, len(pt)])
    rank = len(pt) - np.arange(len(pt))  # larger for earlier pairs
    first = np.maximum.reduceat(
        np.where(ok & (cost == np.repeat(low, counts, axis=1)), rank, 0), starts, axis=1
    )
    out[:, pt[starts]] = np.where(first > 0, col[len(pt) - np.maximum(first, 1)], -1)


def _candidate_pairs(
    wx: np.ndarray, wy: np.ndarray, maps: SegmentMaps, gate_m: float, margin_m: float
) -> tuple[np.ndarray, np.ndarray]:
    """``(point, column)`` index pairs ``(K,)``, sorted, that may pass :func:`associate_points`'
    gate for some particle; ``wx, wy (P,N)`` the points in the map frame per particle."""
    ref_x, ref_y = wx.mean(axis=0), wy.mean(axis=0)  # (N,)
    spread = np.max(np.hypot(wx - ref_x, wy - ref_y))  # any particle's view of any point
    reach = np.hypot(gate_m, margin_m) + spread
    valid = maps.valid
    used = np.flatnonzero(valid.any(axis=0))
    if len(used) == 0 or wx.shape[1] == 0:
        return np.zeros(0, int), np.zeros(0, int)
    seg = maps.seg[:, used]  # (P,C,2,2)
    ex = np.where(valid[:, used, None], seg[..., 0], np.nan)  # (P,C,2): both ends' x
    ey = np.where(valid[:, used, None], seg[..., 1], np.nan)
    lo_x, hi_x = np.nanmin(ex, axis=(0, 2)) - reach, np.nanmax(ex, axis=(0, 2)) + reach  # (C,)
    lo_y, hi_y = np.nanmin(ey, axis=(0, 2)) - reach, np.nanmax(ey, axis=(0, 2)) + reach
    near = (
        (ref_x[:, None] >= lo_x)
        & (ref_x[:, None] <= hi_x)
        & (ref_y[:, None] >= lo_y)
        & (ref_y[:, None] <= hi_y)
    )  # (N,C)
    pt, c = np.nonzero(near)
    return pt, used[c]


def _point_normal_equations(
    poses: np.ndarray,
    points: np.ndarray,
    n_m: np.ndarray,
    rho_m: np.ndarray,
    matched: np.ndarray,
    cfg: ProposalConfig,
) -> tuple[np.ndarray, np.ndarray]:
    """``H (P,3,3)``, ``g (P,3)`` of the point-to-line residuals ``r = n·(R p + t) - ρ`` of the
    associated points (lines ``n_m (P,N,2)``, ``rho_m (P,N)``), Cauchy-weighted."""
    qx, qy = _rotate(poses, points)
    n_x, n_y = n_m[..., 0], n_m[..., 1]
    r = n_x * (qx + poses[:, None, 0]) + n_y * (qy + poses[:, None, 1]) - rho_m
    j_th = n_y * qx - n_x * qy  # ∂r/∂θ = m·q with m = (n_y, -n_x)
    w = np.where(matched, 1.0 / (1.0 + (r / cfg.robust_scale_m) ** 2), 0.0) / cfg.point_sigma_m**2
    jac = np.stack([n_x, n_y, j_th], axis=-1)  # (P,N,3)
    wjac_t = np.swapaxes(w[..., None] * jac, 1, 2)  # (P,3,N)
    h = wjac_t @ jac
    g = (wjac_t @ np.where(matched, r, 0.0)[..., None])[..., 0]
    return h, g


def _element_lines(maps: SegmentMaps, idx: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Normals ``(P,K,2)`` and distances ``(P,K)`` of the elements ``idx (P,K)`` (-1: any)."""
    safe = np.maximum(idx, 0)
    a_m = np.take_along_axis(maps.alpha, safe, axis=1)
    return np.stack([np.cos(a_m), np.sin(a_m)], axis=-1), np.take_along_axis(maps.rho, safe, axis=1)


def _gauss_newton(
    prior_mean: np.ndarray,
    prior_cov: np.ndarray,
    maps: SegmentMaps,
    cfg: ProposalConfig,
    associate_at: Callable[[np.ndarray, bool], np.ndarray],
    normal_equations: Callable[..., tuple[np.ndarray, np.ndarray]],
    init: np.ndarray | None = None,
) -> ProposalResult:
    """The motion prior fused with a point-to-line measurement, by Gauss-Newton.

    ``associate_at(x, wide)`` gives the element index ``(P,K)`` (-1: none) of every measured
    item (point or segment) at poses ``x``, with gates widened for the predicted pose when
    ``wide``; it runs at the first iteration and again at ``cfg.reassociate_after``.
    ``normal_equations(x, n_m, rho_m, matched)`` gives ``H (P,3,3)`` and ``g (P,3)``. The
    iterations start from ``init (P,3)`` when given (a coarse search's result), else the prior mean."""
    x = prior_mean.copy() if init is None else init.copy()
    info_prior = np.linalg.inv(prior_cov)
    h = np.zeros_like(prior_cov)
    idx = np.full((len(x), 0), -1)
    for it in range(cfg.iterations):
        if it == 0 or it == cfg.reassociate_after:
            idx = associate_at(x, it == 0)
            n_m, rho_m = _element_lines(maps, idx)
        h, g = normal_equations(x, n_m, rho_m, idx >= 0)
        dx_prior = x - prior_mean
        dx_prior[:, 2] = wrap_angle(dx_prior[:, 2])
        rhs = -(g + np.einsum("pij,pj->pi", info_prior, dx_prior))
        step = np.linalg.solve(h + info_prior, rhs[..., None])[..., 0]
        x = x + step
        x[:, 2] = wrap_angle(x[:, 2])
    return _result(x, h, info_prior, idx, cfg)


def _result(x: np.ndarray, h: np.ndarray, info_prior: np.ndarray, idx: np.ndarray, cfg: ProposalConfig):
    """The proposal at the refined poses ``x``: covariance from the last measurement information
    ``h`` and the prior's, the observations matched by the last association ``idx``."""
    cov = np.linalg.inv(h + info_prior)
    cov = 0.5 * (cov + np.transpose(cov, (0, 2, 1)))
    return ProposalResult(x, cov, np.sum(idx >= 0, axis=1), h, info_prior)


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
    points_robot: np.ndarray | None = None,
    init: np.ndarray | None = None,
    point_alpha: np.ndarray | None = None,
) -> ProposalResult:
    """Refine ``prior_mean (P,3)`` by point-to-line alignment of the scan (robot frame) to each
    particle's local map: its points when given and ``cfg.measurement == "points"``, else its
    segments (moments, ends, facing, line covariance). The Gaussian proposal per particle."""
    if cfg.measurement == "points" and points_robot is not None:
        return align_points(prior_mean, prior_cov, points_robot, maps, cfg, init, point_alpha)
    var_a = prior_cov[:, 2, 2][:, None, None]
    var_p = (prior_cov[:, 0, 0] + prior_cov[:, 1, 1])[:, None, None]

    def associate_at(x: np.ndarray, wide: bool) -> np.ndarray:
        obs = observe(
            x, moments_robot, ends_robot, facing_robot, cov_robot, assoc_cfg.point_sigma_m, assoc_cfg.compiled
        )
        if wide:
            return associate(obs, maps, assoc_cfg, var_a, var_p, cfg.gate_scale_predicted).index
        return associate(obs, maps, assoc_cfg).index

    def normal_equations(x, n_m, rho_m, matched):
        return _normal_equations(x, moments_robot, n_m, rho_m, matched, cfg)

    return _gauss_newton(prior_mean, prior_cov, maps, cfg, associate_at, normal_equations, init)


def align_points(
    prior_mean: np.ndarray,
    prior_cov: np.ndarray,
    points_robot: np.ndarray,
    maps: SegmentMaps,
    cfg: ProposalConfig,
    init: np.ndarray | None = None,
    point_alpha: np.ndarray | None = None,
) -> ProposalResult:
    """Refine ``prior_mean (P,3)`` by aligning the scan points ``points_robot (N,2)`` (robot
    frame) to each particle's map; the Gaussian proposal per particle. ``point_alpha (N,)``: the
    normal angle of each point's own line (NaN: none), checked against its element's from the
    re-association on (``cfg.point_angle_gate_rad``)."""
    pts = np.asarray(points_robot, dtype=float).reshape(-1, 2)
    if len(pts) > cfg.max_points:
        keep = np.linspace(0, len(pts) - 1, cfg.max_points).round().astype(int)
        pts = pts[keep]
        point_alpha = None if point_alpha is None else np.asarray(point_alpha)[keep]
    # the first association's gate covers the prior's uncertainty at the points' mean range
    reach = float(np.mean(np.hypot(pts[:, 0], pts[:, 1]))) if len(pts) else 0.0
    spread = np.sqrt(prior_cov[:, 0, 0] + prior_cov[:, 1, 1] + (reach**2) * prior_cov[:, 2, 2])
    gated = point_alpha is not None and cfg.point_angle_gate_rad < np.pi / 2
    if cfg.compiled and kernels.AVAILABLE:  # the same iterations, compiled
        info_prior = np.linalg.inv(prior_cov)
        x, h, idx = kernels.gn_points(
            prior_mean if init is None else init,
            prior_mean,
            info_prior,
            pts,
            maps.alpha,
            maps.rho,
            maps.seg,
            maps.facing,
            maps.valid,
            cfg.point_gate_m + cfg.gate_scale_predicted * spread,
            cfg.iterations,
            cfg.reassociate_after,
            cfg.point_gate_m,
            cfg.extent_margin_m,
            cfg.robust_scale_m,
            cfg.point_sigma_m,
            point_alpha if gated else None,
            float(np.sin(cfg.point_angle_gate_rad)),
        )
        return _result(x, h, info_prior, idx, cfg)

    def associate_at(x: np.ndarray, wide: bool) -> np.ndarray:
        gate = cfg.point_gate_m + (cfg.gate_scale_predicted * spread if wide else 0.0)
        lines = None if wide else point_alpha  # (the predicted heading may be far off)
        return associate_points(x, pts, maps, gate, cfg.extent_margin_m, lines, cfg.point_angle_gate_rad)

    def normal_equations(x, n_m, rho_m, matched):
        return _point_normal_equations(x, pts, n_m, rho_m, matched, cfg)

    return _gauss_newton(prior_mean, prior_cov, maps, cfg, associate_at, normal_equations, init)
