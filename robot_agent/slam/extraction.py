"""Scan -> clusters -> line segments ("segment the laser scan data into clusters, fit elements").

The report (§4.2) segments each scan into clusters and fits line "elements" to them. Steps:

1. keep readings in ``[range_min_m, min(max_usable_range_m, range_max_m))`` (finite only);
2. break the scan into clusters where a reading is missing, consecutive points are farther than
   the adaptive breakpoint distance (Borges & Aldon 2004), or than ``max_point_gap_m``;
3. split clusters by iterative end-point fit (all pieces split at once, one round per level),
   and give each split point to the neighbouring line it is nearer;
4. merge adjacent collinear pieces using summed moments (a TLS refit of the union);
5. keep pieces with enough points, length and a small residual; their TLS lines
   (:mod:`robot_agent.slam.lines`) carry a covariance, and endpoints are the points' extent
   projected on the line.

Everything is in the frame of the given beam angles (the laser frame); use
:meth:`ScanSegments.transformed` to move the result, e.g. into the robot frame.
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace

import numpy as np

from robot_agent.slam import kernels
from robot_agent.slam.lines import (
    fit_lines,
    line_covariance,
    moments_from_points,
    project_to_line,
    segment_endpoints,
    transform_lines,
    transform_moments,
)
from shared.geometry import line_angle_diff, transform_points, wrap_angle

#: A scan whose first and last beams are at most this many mean beam spacings apart in
#: angle is a full circle: its last beam neighbours its first one.
_CIRCULAR_SPACING_FACTOR = 1.5


class ExtractionError(ValueError):
    """Malformed scan or configuration given to segment extraction."""


@dataclass(frozen=True)
class ExtractionConfig:
    """Parameters of :func:`extract_segments`; defaults suit SICK LMS and Hokuyo scanners
    with 0.25°–1° beam spacing over 180° or 360°.

    range_min_m: readings below are dropped (dust, the robot's own body, zero = error code).
    max_usable_range_m: readings at or beyond are dropped: far points are sparse and noisy.
        Readings at or beyond the scan's own ``range_max_m`` are "no return" in any case.
        30 m (Cartographer's 2D default): in a long aisle the only thing that fixes the
        position along it may be the wall beyond its far end, seen through the aisle by a few
        beams (with 20 m the simulated warehouse drifted 0.1 m along its 28 m aisles).
    breakpoint_lambda_rad: the Borges & Aldon angle λ, the shallowest incidence angle at which
        consecutive points of one surface are still linked.
    range_sigma_m: range noise (1σ) of the sensor; used in the breakpoint distance and as a
        floor of the per-point noise in the line covariance.
    breakpoint_n_sigma: how many ``range_sigma_m`` the breakpoint distance allows on top.
    max_point_gap_m: consecutive points farther apart always start a new cluster, so a door
        or gap in a wall is not bridged.
    split_threshold_m: iterative end-point fit splits a piece where a point is farther than
        ``split_threshold_m + split_threshold_per_m * range`` from the piece's chord.
    split_threshold_per_m: range-proportional part of that threshold (beam angle errors).
    merge_angle_rad: adjacent pieces merge only if their lines differ by at most this angle
        plus ``merge_angle_n_sigma`` standard deviations of the difference (from the line
        covariances: a short piece's direction is uncertain); and only if every point of the
        merged piece is within the split threshold of the merged line.
    merge_angle_n_sigma: width of that angle gate in standard deviations.
    min_points: fewest points a segment is fitted to.
    min_length_m: shortest segment kept.
    max_rms_m: largest RMS perpendicular residual of a kept segment (rejects noisy fits).
    compiled: run the split and merge rounds in the compiled kernels when they are built (the
        numpy code below is the reference and the fallback).
    """

    range_min_m: float = 0.05
    max_usable_range_m: float = 30.0
    breakpoint_lambda_rad: float = float(np.deg2rad(10.0))
    range_sigma_m: float = 0.02
    breakpoint_n_sigma: float = 3.0
    max_point_gap_m: float = 0.5
    split_threshold_m: float = 0.05
    split_threshold_per_m: float = 0.005
    merge_angle_rad: float = float(np.deg2rad(3.0))
    merge_angle_n_sigma: float = 3.0
    min_points: int = 5
    min_length_m: float = 0.3
    max_rms_m: float = 0.03
    compiled: bool = True  # the split and merge rounds by the compiled kernels (kernels.py) when built

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if not np.isfinite(value) or value < 0:
                raise ExtractionError(f"ExtractionConfig.{f.name} must be >= 0, got {value!r}")
        if self.min_points < 2:
            raise ExtractionError(f"ExtractionConfig.min_points must be >= 2, got {self.min_points}")
        if not 0 < self.breakpoint_lambda_rad < np.pi / 2:
            lam = self.breakpoint_lambda_rad
            raise ExtractionError(f"ExtractionConfig.breakpoint_lambda_rad must be in (0, pi/2), got {lam}")


@dataclass(frozen=True)
class ScanSegments:
    """Segments of one scan, ``N`` segments from ``K`` valid readings, all in one frame."""

    endpoints: np.ndarray  # (N, 2, 2) on the fitted line; the first at the scan's start side
    alpha: np.ndarray  # (N,) line x cos(alpha) + y sin(alpha) = rho ...
    rho: np.ndarray  # (N,) ... with rho >= 0
    cov: np.ndarray  # (N, 2, 2) covariance of (alpha, rho)
    n_points: np.ndarray  # (N,) int
    moments: np.ndarray  # (N, 6) [n, Σx, Σy, Σxx, Σxy, Σyy] of the segment's points
    rms_m: np.ndarray  # (N,) RMS perpendicular residual
    points: np.ndarray  # (K, 2) every valid reading in scan order (full circle: from a break)
    point_segment: np.ndarray  # (K,) int index of the point's segment, or -1
    point_beam: np.ndarray  # (K,) int index of the point's beam in the input arrays
    point_alpha: np.ndarray  # (K,) normal angle of the line through the point's piece (kept as a
    # segment or not: a face too short to keep is still a line), NaN where no line fits it

    def __len__(self) -> int:
        return int(self.alpha.shape[0])

    @property
    def lengths_m(self) -> np.ndarray:
        """Segment lengths ``(N,)``."""
        d = self.endpoints[:, 1] - self.endpoints[:, 0]
        return np.hypot(d[:, 0], d[:, 1])

    def transformed(self, pose: np.ndarray) -> ScanSegments:
        """The same segments mapped by ``pose (3,)`` (e.g. the laser pose in the robot frame)."""
        pose = np.asarray(pose, dtype=float).reshape(3)
        alpha, rho, cov = transform_lines(pose, self.alpha, self.rho, self.cov)
        return replace(
            self,
            alpha=alpha,
            rho=rho,
            cov=cov,
            moments=transform_moments(pose, self.moments),
            endpoints=transform_points(pose, self.endpoints),
            points=transform_points(pose, self.points),
            point_alpha=self.point_alpha + pose[2],
        )


def extract_segments(
    ranges_m: np.ndarray,
    angles_rad: np.ndarray,
    cfg: ExtractionConfig | None = None,
    range_max_m: float = np.inf,
) -> ScanSegments:
    """Line segments of one scan in the laser frame.

    ``ranges_m (B,)`` at ``angles_rad (B,)`` (monotonic, any spacing; a scan covering the full
    circle is treated as closed). Readings that are non-finite, below ``cfg.range_min_m``, or
    at/over ``min(cfg.max_usable_range_m, range_max_m)`` are dropped. Raises
    :class:`ExtractionError` on arrays of different or non-1-D shapes, or non-finite angles.
    """
    cfg = ExtractionConfig() if cfg is None else cfg
    r = np.asarray(ranges_m, dtype=float)
    phi = np.asarray(angles_rad, dtype=float)
    if r.ndim != 1 or phi.shape != r.shape:
        raise ExtractionError(
            f"ranges_m and angles_rad must be equal 1-D arrays, got {r.shape} and {phi.shape}"
        )
    if not np.all(np.isfinite(phi)):
        raise ExtractionError(f"angles_rad must be finite, got {phi[~np.isfinite(phi)][:3]}")
    valid = usable_readings(r, cfg, range_max_m)
    r = np.where(valid, r, 0.0)
    xy = np.stack([r * np.cos(phi), r * np.sin(phi)], axis=-1)

    beam, cluster_starts = _clusters(xy, r, phi, valid, cfg)
    pts = xy[beam]
    threshold = cfg.split_threshold_m + cfg.split_threshold_per_m * r[beam]
    starts = _split(pts, threshold, cluster_starts, cfg)
    cluster = np.searchsorted(cluster_starts, starts, side="right") - 1
    starts = _refine_boundaries(pts, starts, cluster, cfg)
    merged, cluster = _merge(pts, threshold, starts, cluster, cfg)
    if merged.size < starts.size:  # merged pieces' lines moved: their boundaries may too
        merged = _refine_boundaries(pts, merged, cluster, cfg)
    return _assemble(pts, beam, merged, cfg)


def usable_readings(ranges_m: np.ndarray, cfg: ExtractionConfig, range_max_m: float = np.inf) -> np.ndarray:
    """Mask ``(B,)`` of the readings extraction uses: finite, at least ``cfg.range_min_m``, below
    ``min(cfg.max_usable_range_m, range_max_m)``."""
    with np.errstate(invalid="ignore"):
        return (ranges_m >= cfg.range_min_m) & (ranges_m < min(cfg.max_usable_range_m, range_max_m))


def scan_points(
    ranges_m: np.ndarray, angles_rad: np.ndarray, cfg: ExtractionConfig, range_max_m: float = np.inf
) -> np.ndarray:
    """The usable readings as points ``(K,2)`` in the laser frame, in scan order (the points
    :func:`extract_segments` works on, without the segmentation)."""
    r = np.asarray(ranges_m, dtype=float)
    phi = np.asarray(angles_rad, dtype=float)
    ok = usable_readings(r, cfg, range_max_m)
    return np.stack([r[ok] * np.cos(phi[ok]), r[ok] * np.sin(phi[ok])], axis=-1)


def _clusters(
    xy: np.ndarray, r: np.ndarray, phi: np.ndarray, valid: np.ndarray, cfg: ExtractionConfig
) -> tuple[np.ndarray, np.ndarray]:
    """Valid beams in scan order ``(K,)`` and the point indices where clusters start ``(C,)``."""
    n_beams = r.shape[0]
    prev = np.roll(np.arange(n_beams), 1)
    dphi = np.abs(wrap_angle(phi - phi[prev]))
    gap = np.hypot(*(xy - xy[prev]).T)
    lam = cfg.breakpoint_lambda_rad
    with np.errstate(divide="ignore", invalid="ignore"):
        # Borges & Aldon 2004: the gap seen between two beams hitting one surface at incidence
        # angle λ is r sin Δφ / sin(λ - Δφ); plus n σ_r for range noise.
        d_max = np.where(lam > dphi, r[prev] * np.sin(dphi) / np.sin(lam - dphi), np.inf)
    d_max = np.minimum(d_max + cfg.breakpoint_n_sigma * cfg.range_sigma_m, cfg.max_point_gap_m)
    linked = valid & valid[prev] & (gap <= d_max)
    circular = n_beams > 2 and dphi[0] <= _CIRCULAR_SPACING_FACTOR * np.mean(dphi[1:])
    order = np.arange(n_beams)
    if circular:  # start the scan at a break so no cluster straddles the seam
        breaks = np.flatnonzero(~linked)
        if breaks.size:
            order = np.roll(order, -int(breaks[0]))
        else:
            # a closed contour: start at a corner of the room. The point farthest from any
            # point is a vertex (distance is convex along each wall); from that vertex the
            # farthest is one where both walls recede, a sharp maximum that noise won't move
            first = np.argmax(np.hypot(*(xy - xy[0]).T))
            order = np.roll(order, -int(np.argmax(np.hypot(*(xy - xy[first]).T))))
    else:
        linked[:1] = False
    beam = order[valid[order]]
    is_start = ~linked[beam]
    if beam.size:
        is_start[0] = True
    return beam, np.flatnonzero(is_start)


def _piece_index(starts: np.ndarray, n_points: int) -> tuple[np.ndarray, np.ndarray]:
    """Piece ends ``(S,)`` and the piece of every point ``(K,)`` for contiguous pieces."""
    ends = np.append(starts[1:], n_points)[: starts.size]  # no pieces when there are no points
    return ends, np.repeat(np.arange(starts.size), ends - starts)


def _split(pts: np.ndarray, threshold: np.ndarray, starts: np.ndarray, cfg: ExtractionConfig) -> np.ndarray:
    """Iterative end-point fit: piece starts ``(S',)`` refining the cluster starts ``(C,)``.

    Each round splits every piece that has a point farther than its ``threshold (K,)`` from
    the chord joining the piece's first and last points, at the farthest point.
    """
    if cfg.compiled and kernels.AVAILABLE:
        return kernels.split_pieces(pts, threshold, starts, cfg.min_points)
    n_points = pts.shape[0]
    while True:
        ends, piece = _piece_index(starts, n_points)
        a = pts[starts][piece]
        chord = pts[ends - 1][piece] - a
        rel = pts - a
        length = np.hypot(chord[:, 0], chord[:, 1])
        cross = np.abs(chord[:, 0] * rel[:, 1] - chord[:, 1] * rel[:, 0])
        dist = np.where(length > 0, cross / np.where(length > 0, length, 1.0), np.hypot(*rel.T))
        # split where any point is beyond its threshold, at the farthest point: distance to a
        # line is linear along each wall, so the farthest point is a corner
        beyond = np.maximum.reduceat((dist > threshold).astype(np.int8), starts) > 0
        beyond &= (ends - starts) >= cfg.min_points  # shorter pieces are never kept alone
        farthest = dist == np.maximum.reduceat(dist, starts)[piece]
        cand = np.flatnonzero(farthest & beyond[piece])
        if cand.size == 0:
            return starts
        first = cand[np.r_[True, piece[cand[1:]] != piece[cand[:-1]]]]  # one split per piece
        starts = np.union1d(starts, first)


def _merge(
    pts: np.ndarray,
    threshold: np.ndarray,
    starts: np.ndarray,
    cluster: np.ndarray,
    cfg: ExtractionConfig,
) -> tuple[np.ndarray, np.ndarray]:
    """Merge adjacent collinear pieces of one cluster; returns starts and cluster ``(S',)``.

    A pair is admissible if its lines' angles agree (see ``merge_angle_rad``), its merged TLS
    line has every point within the split ``threshold (K,)`` (so the merge undoes no split
    the line would make again) and a residual within ``max_rms_m``. Each round merges the
    admissible pairs whose merged residual is a local minimum (merged pairs never overlap).
    """
    n_points = pts.shape[0]
    if not np.any(cluster[1:] == cluster[:-1]):
        return starts, cluster
    if cfg.compiled and kernels.AVAILABLE:
        return kernels.merge_pieces(
            pts, threshold, starts, cluster, cfg.max_rms_m, cfg.range_sigma_m, cfg.merge_angle_rad,
            cfg.merge_angle_n_sigma,
        )  # fmt: skip
    _, piece = _piece_index(starts, n_points)
    moments = moments_from_points(pts, piece, starts.size)
    while starts.size > 1:
        n_pieces = starts.size
        m_alpha, m_rho, m_sigma2 = fit_lines(moments[:-1] + moments[1:])
        ok = (cluster[:-1] == cluster[1:]) & (m_sigma2 <= cfg.max_rms_m**2)
        if not ok.any():  # the usual last round: only corners are left, and they fit badly
            break
        alpha, _, sigma2 = fit_lines(moments)
        # each point against the merged line of the pair on its left (piece-1, piece) and on
        # its right (piece, piece+1); the pieces at either end have no such pair
        worst = np.zeros(n_pieces - 1)
        for side, pair in ((0, piece - 1), (1, piece)):
            has = (pair >= 0) & (pair < n_pieces - 1)
            pair = np.clip(pair, 0, n_pieces - 2)
            _, dist = project_to_line(pts, m_alpha[pair], m_rho[pair])
            ratio = np.maximum.reduceat(np.where(has, np.abs(dist) / threshold, 0.0), starts)
            worst = np.maximum(worst, ratio[1:] if side == 0 else ratio[:-1])
        # angle gate widened by the pieces' own direction uncertainty (short pieces have
        # little); pieces with fewer than two points have none and pass
        var_a = line_covariance(moments, alpha, np.maximum(sigma2, cfg.range_sigma_m**2))
        var_a = var_a[:, 0, 0]
        gate = cfg.merge_angle_rad + cfg.merge_angle_n_sigma * np.sqrt(var_a[:-1] + var_a[1:])
        angle_ok = ~(line_angle_diff(alpha[:-1], alpha[1:]) > gate)
        ok &= angle_ok & (worst <= 1.0)
        if not ok.any():
            break
        cost = np.where(ok, m_sigma2, np.inf)
        pick = ok & (cost < np.r_[np.inf, cost[:-1]]) & (cost <= np.r_[cost[1:], np.inf])
        j = np.flatnonzero(pick)
        moments[j] += moments[j + 1]
        keep = np.ones(n_pieces, dtype=bool)
        keep[j + 1] = False
        starts, moments, cluster = starts[keep], moments[keep], cluster[keep]
        _, piece = _piece_index(starts, n_points)
    return starts, cluster


def _refine_boundaries(
    pts: np.ndarray, starts: np.ndarray, cluster: np.ndarray, cfg: ExtractionConfig
) -> np.ndarray:
    """Move each split point between two pieces of one cluster to the line it is nearer.

    A split at the point farthest from a chord is a corner, or with noise one point off it;
    the piece that wrongly got it has a point a beam spacing off its line. Pieces too short
    to be kept are left alone (a line through two points is near anything).
    """
    sizes = np.diff(np.append(starts, pts.shape[0]))
    long_enough = sizes >= max(cfg.min_points, 3)  # >= 3: a piece may lose a point at each end
    j = np.flatnonzero((cluster[1:] == cluster[:-1]) & long_enough[:-1] & long_enough[1:])
    if j.size == 0:
        return starts
    _, piece = _piece_index(starts, pts.shape[0])
    alpha, rho, _ = fit_lines(moments_from_points(pts, piece, starts.size))
    b = starts[j + 1]  # first point of piece j + 1
    # distances of (first of j+1, first of j+1, last of j, last of j) to lines (j+1, j, j, j+1)
    point, line = np.stack([b, b, b - 1, b - 1]), np.stack([j + 1, j, j, j + 1])
    first_here, first_prev, last_here, last_next = np.abs(
        project_to_line(pts[point], alpha[line], rho[line])[1]
    )
    forward = first_prev < first_here
    back = (last_next < last_here) & ~forward
    starts = starts.copy()
    starts[j + 1] = b + forward.astype(int) - back.astype(int)
    return starts


def _assemble(pts: np.ndarray, beam: np.ndarray, starts: np.ndarray, cfg: ExtractionConfig) -> ScanSegments:
    """Fit, bound and filter the pieces; label the points with the kept segments."""
    n_points = pts.shape[0]
    ends, piece = _piece_index(starts, n_points)
    moments = moments_from_points(pts, piece, starts.size)
    alpha, rho, sigma2 = fit_lines(moments)
    # extent of each piece's points along its line, oriented in scan order
    t, _ = project_to_line(pts, alpha[piece], rho[piece])
    t_min, t_max = np.minimum.reduceat(t, starts), np.maximum.reduceat(t, starts)
    forward = t[starts] <= t[ends - 1]
    t0, t1 = np.where(forward, t_min, t_max), np.where(forward, t_max, t_min)
    n = moments[:, 0]
    with np.errstate(invalid="ignore"):
        fits = sigma2 <= cfg.max_rms_m**2
        keep = (n >= cfg.min_points) & (t_max - t_min >= cfg.min_length_m) & fits
    seg_of_piece = np.where(keep, np.cumsum(keep) - 1, -1)
    # every piece's own line, kept or not (two points always fit one: three are the least evidence)
    piece_alpha = np.where((n >= 3) & fits, alpha, np.nan)
    alpha, rho, sigma2, moments = alpha[keep], rho[keep], sigma2[keep], moments[keep]
    # floor the point noise at the sensor's: a few points can fit by chance too well
    cov = line_covariance(moments, alpha, np.maximum(sigma2, cfg.range_sigma_m**2))
    return ScanSegments(
        endpoints=segment_endpoints(alpha, rho, t0[keep], t1[keep]),
        alpha=alpha,
        rho=rho,
        cov=cov,
        n_points=n[keep].astype(int),
        moments=moments,
        rms_m=np.sqrt(sigma2),
        points=pts,
        point_segment=seg_of_piece[piece],
        point_beam=beam.astype(int),
        point_alpha=piece_alpha[piece],
    )
