"""Correlative scan matching of a point cloud against another: where does a keyframe's scan fit
an old place, and how sure is that (the back end's loop closures).

- a likelihood field of the old cloud, ``exp(-d²/2σ²)`` on a grid (Olson 2009);
- :func:`window_scores`: every pose of a small window, brute force — the score surface;
- :func:`branch_and_bound`: a wide window, searched through a pyramid of the field where each
  level holds the maximum over blocks twice as large (Hess et al. 2016, §V): a block whose bound
  cannot reach the threshold is never opened, so a drift of metres costs little more than one
  of decimetres;
- :func:`match_covariance`: the uncertainty of the best pose from the scores of all the others
  (a corridor: certain across, uncertain along);
- :func:`icp`: the final fit, point to point;
- :func:`window_match`: the narrow search, its covariance and the ICP together — a keyframe's
  scan against an old keyframe's cloud (the agent's loops, robot_agent/slam/backend.py) or
  against another robot's (the fleet graph's constraints, map_server/posegraph.py).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.ndimage import distance_transform_edt
from scipy.spatial import cKDTree

from shared import kernels
from shared.geometry import apply_points, compose, relative_one, wrap_angle


@dataclass(frozen=True)
class SurfaceConfig:
    """How a match's score surface becomes its covariance (:func:`match_covariance`)."""

    sharpness: float = 20.0  # a pose scoring s is exp(-k (1 - s / best)) as likely as the best
    max_cross_sigma_m: float = 0.15  # a match this uncertain across its best-determined direction ...
    max_theta_sigma_rad: float = float(np.radians(3.0))  # ... or in heading is ambiguous: refused
    edge_mass: float = 0.05  # likelihood this large at the window's edge: unbounded along that axis
    unbounded_sigma_m: float = 5.0  # ... then its std along it


@dataclass(frozen=True)
class MatchConfig:
    """A match around a guess (:func:`window_match`): the correlative window and its steps, the
    score it needs, the covariance's floor (its own resolution plus ``sigma_*``), the ICP and the
    overlap it needs after it."""

    search_xy_m: float = 0.8  # half widths of the window ...
    search_theta_rad: float = float(np.radians(8.0))
    search_step_m: float = 0.1  # ... its steps (and the field's cells)
    search_step_rad: float = float(np.radians(2.0))
    field_sigma_m: float = 0.08  # likelihood field: exp(-d^2 / 2 sigma^2)
    surface: SurfaceConfig = SurfaceConfig()
    min_score: float = 0.4  # mean likelihood of the query at the best pose
    icp_iterations: int = 8
    icp_max_m: float = 0.15
    inlier_m: float = 0.05
    min_inlier_share: float = 0.6  # verified overlap after ICP
    sigma_xy_m: float = 0.05  # added to the window's resolution in the covariance's floor
    sigma_theta_rad: float = float(np.radians(1.0))
    compiled: bool = True  # the window's sums by the compiled kernels when built
    # a best pose whose likelihood reaches the window's edge (more than ``surface.edge_mass``) away
    # from its centre: the window centred on it and searched again, at most this many times — a
    # guess off by about the window's half width leaves the true place on the edge, and the match
    # would say nothing along that axis though the place is well determined (a fleet's keyframes
    # where the graph put them ~0.9 m apart: ``map_server/posegraph.py``). A corridor stays
    # unbounded: its likelihood reaches the edge of every window
    recentre: int = 0


@dataclass(frozen=True)
class Field:
    values: np.ndarray  # (W,H) likelihood
    origin: np.ndarray  # (2,) xy of cell (0,0)
    res_m: float


def likelihood_field(points: np.ndarray, res_m: float, sigma_m: float, margin_m: float) -> Field:
    """The field ``exp(-d²/2σ²)`` of ``points (N,2)``, ``d`` the distance to the nearest one, on a
    grid of ``res_m`` cells over their extent plus ``margin_m``."""
    lo = points.min(axis=0) - margin_m
    shape = np.ceil((points.max(axis=0) + margin_m - lo) / res_m).astype(int) + 1
    occ = np.zeros(shape, bool)
    c = np.round((points - lo) / res_m).astype(int)
    occ[c[:, 0], c[:, 1]] = True
    d = distance_transform_edt(~occ) * res_m
    return Field(np.exp(-0.5 * (d / sigma_m) ** 2), lo, res_m)


def _query_cells(fld: Field, query: np.ndarray, guess: np.ndarray, angles: np.ndarray) -> np.ndarray:
    """Cells ``(A,N,2)`` of the query points ``(N,2)`` at ``guess``'s translation, turned to each
    of ``angles (A,)``."""
    c, s = np.cos(angles)[:, None], np.sin(angles)[:, None]
    px = c * query[:, 0] - s * query[:, 1] + guess[0]
    py = s * query[:, 0] + c * query[:, 1] + guess[1]
    return np.stack(
        [np.round((px - fld.origin[0]) / fld.res_m), np.round((py - fld.origin[1]) / fld.res_m)], axis=-1
    ).astype(int)


def _lookup(grid: np.ndarray, ix: np.ndarray, iy: np.ndarray) -> np.ndarray:
    """``grid[ix, iy]``, 0 outside."""
    w, h = grid.shape
    ok = (ix >= 0) & (ix < w) & (iy >= 0) & (iy < h)
    return np.where(ok, grid.ravel()[np.where(ok, ix * h + iy, 0)], 0.0)


def window_scores(
    fld: Field,
    query: np.ndarray,
    guess: np.ndarray,
    half_xy_m: float,
    half_theta_rad: float,
    step_m: float,
    step_rad: float,
    compiled: bool = True,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Scores ``(A,T)`` (mean likelihood of the query points ``(N,2)``) at every pose of the window
    around ``guess (3,)``; the angles ``(A,)`` and translation offsets ``(T,2)`` [m] from it
    (``compiled``: the sums by the compiled kernel when it is built)."""
    n_xy = round(half_xy_m / step_m)
    n_th = round(half_theta_rad / step_rad)
    angles = guess[2] + step_rad * np.arange(-n_th, n_th + 1)
    o = round(step_m / fld.res_m) * np.arange(-n_xy, n_xy + 1)
    ox, oy = (g.ravel() for g in np.meshgrid(o, o, indexing="ij"))
    cells = _query_cells(fld, query, guess, angles)
    if compiled and kernels.AVAILABLE:
        scores = kernels.window_sums(fld.values, cells, ox, oy)
    else:
        scores = np.empty((len(angles), len(ox)))
        for a in range(len(angles)):
            ix = cells[a, None, :, 0] + ox[:, None]
            iy = cells[a, None, :, 1] + oy[:, None]
            scores[a] = _lookup(fld.values, ix, iy).mean(axis=1)
    return scores, angles, np.column_stack([ox, oy]) * fld.res_m


def max_pyramid(values: np.ndarray, depth: int) -> list[np.ndarray]:
    """Levels ``0..depth``: level ``k`` at cell ``(i, j)`` holds the maximum of ``values`` over the
    block ``[i, i + 2^k) × [j, j + 2^k)`` (0 beyond the grid) — an upper bound of the score of
    every translation in that block."""
    levels = [values]
    for k in range(1, depth + 1):
        prev, s = levels[-1], 2 ** (k - 1)
        m = prev.copy()
        m[:-s] = np.maximum(prev[:-s], prev[s:])
        out = m.copy()
        out[:, :-s] = np.maximum(m[:, :-s], m[:, s:])
        levels.append(out)
    return levels


def branch_and_bound(
    fld: Field,
    query: np.ndarray,
    guess: np.ndarray,
    half_xy_m: float,
    half_theta_rad: float,
    step_rad: float,
    min_score: float,
    keep_ratio: float,
    depth: int,
    max_open: int = 1024,
    probes: int = 32,
    compiled: bool = True,
) -> tuple[np.ndarray, np.ndarray]:
    """Poses ``(K,3)`` in the window around ``guess`` (translations on the field's cells, headings
    ``step_rad`` apart) scoring at least ``min_score`` and ``keep_ratio`` × the best, with their
    scores ``(K,)``, best first; empty when none reaches ``min_score``. Exact while at most
    ``max_open`` blocks stay open at a level (beyond, the lowest-bounded ones are dropped); at
    every level the exact score of the ``probes`` best-bounded blocks' first poses raises the
    threshold. ``compiled``: the scores by the compiled kernel when it is built."""
    n_th = int(np.ceil(half_theta_rad / step_rad))
    angles = guess[2] + step_rad * np.arange(-n_th, n_th + 1)
    w = int(np.ceil(half_xy_m / fld.res_m))
    top = 2**depth
    cells = _query_cells(fld, query, guess, angles)  # (A,N,2)
    if compiled and kernels.AVAILABLE:  # bounds tested per lookup: no padded copies of the levels
        levels = [v.astype(np.float32) for v in max_pyramid(fld.values, depth)]

        def score(k: int, a: np.ndarray, ox: np.ndarray, oy: np.ndarray) -> np.ndarray:
            return kernels.block_sums(levels[k], cells, a, ox, oy)

    else:  # the query cells clipped to just beyond the reach of any offset (-w .. w + top) — a point
        # that far stays off the grid whatever the offset — and every level padded with zeros by
        # as much: a lookup is one flat index, no bounds test
        pad = 2 * w + top + 1
        levels = [np.pad(v.astype(np.float32), pad) for v in max_pyramid(fld.values, depth)]
        height = levels[0].shape[1]
        cx = np.clip(cells[..., 0], -(w + top + 1), fld.values.shape[0] + w) + pad
        cy = np.clip(cells[..., 1], -(w + top + 1), fld.values.shape[1] + w) + pad
        flat = cx * height + cy  # (A,N)
        n_points = query.shape[0]

        def score(k: int, a: np.ndarray, ox: np.ndarray, oy: np.ndarray) -> np.ndarray:
            return levels[k].ravel()[flat[a] + (ox * height + oy)[:, None]].sum(axis=1) / n_points

    starts = np.arange(-w, w + 1, top)
    a, ox, oy = (g.ravel() for g in np.meshgrid(np.arange(len(angles)), starts, starts, indexing="ij"))
    best_low = 0.0  # a score some pose reaches: prunes blocks that cannot come near it
    for k in range(depth, -1, -1):
        bound = score(k, a, ox, oy)
        if k > 0:  # the exact score of the best-bounded blocks' first poses
            probe = np.argsort(-bound)[:probes]
            best_low = max(best_low, float(score(0, a[probe], ox[probe], oy[probe]).max(initial=0.0)))
        else:
            best_low = max(best_low, float(bound.max(initial=0.0)))
        keep = bound >= max(min_score, keep_ratio * best_low)
        if k > 0 and keep.sum() > max_open:
            keep &= bound >= np.sort(bound[keep])[-max_open]
        a, ox, oy, bound = a[keep], ox[keep], oy[keep], bound[keep]
        if k > 0:  # open the blocks: four children of half the size
            h = 2 ** (k - 1)
            dx, dy = np.array([0, h, 0, h]), np.array([0, 0, h, h])
            a = np.repeat(a, 4)
            ox, oy = (np.repeat(ox, 4) + np.tile(dx, len(ox))), (np.repeat(oy, 4) + np.tile(dy, len(oy)))
            inside = (ox <= w) & (oy <= w)
            a, ox, oy = a[inside], ox[inside], oy[inside]
    order = np.argsort(-bound, kind="stable")
    poses = np.column_stack(
        [guess[0] + ox[order] * fld.res_m, guess[1] + oy[order] * fld.res_m, angles[a[order]]]
    )
    return poses, bound[order]


def match_covariance(
    offsets: np.ndarray,
    scores: np.ndarray,
    best_score: float,
    edge: np.ndarray,
    floor: np.ndarray,
    cfg: SurfaceConfig,
) -> np.ndarray | None:
    """Covariance ``(3,3)`` of a match from the scores ``(K,)`` of poses at ``offsets (K,3)`` from
    the best (Olson 2009): each weighted ``exp(-sharpness (1 - s / best))``, second moments about
    the best, plus ``floor (3,)`` variances (grid steps, the fit itself). None when even the
    best-determined direction or the heading is uncertain beyond ``cfg.max_*`` (alike places:
    the match is ambiguous). Mass beyond ``cfg.edge_mass`` on poses at the window's edge ``(K,)``:
    the likelihood goes on past what was searched, so along the weak axis the match says
    nothing (std ``cfg.unbounded_sigma_m``)."""
    w = _weights(scores, best_score, cfg)
    cov = np.einsum("k,ki,kj->ij", w, offsets, offsets) + np.diag(floor)
    if cov[2, 2] > cfg.max_theta_sigma_rad**2:
        return None
    values, vectors = np.linalg.eigh(cov[:2, :2])
    if values[0] > cfg.max_cross_sigma_m**2:
        return None
    if w[edge].sum() > cfg.edge_mass and cfg.unbounded_sigma_m**2 > values[1]:
        weak = vectors[:, 1]
        cov[:2, :2] += (cfg.unbounded_sigma_m**2 - values[1]) * np.outer(weak, weak)
    return cov


def _weights(scores: np.ndarray, best_score: float, cfg: SurfaceConfig) -> np.ndarray:
    """Each pose's share of the likelihood, a pose scoring ``s`` ``exp(-sharpness (1 - s / best))``
    as likely as the best."""
    p = np.exp(-cfg.sharpness * (1.0 - scores / best_score))
    return p / p.sum()


def window_surface(
    scores: np.ndarray, angles: np.ndarray, offs: np.ndarray, half_xy_m: float, half_theta_rad: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`window_scores`' result as the best pose ``(3,)`` — its translation offset from the
    window's centre and its heading — and every pose's offset from it ``(A·T,3)`` with its edge
    flag ``(A·T,)`` (on the window's boundary)."""
    a, t = np.unravel_index(np.argmax(scores), scores.shape)
    d = np.empty((len(angles), len(offs), 3))
    d[..., :2] = (offs - offs[t])[None]
    d[..., 2] = (angles - angles[a])[:, None]
    centre = angles[len(angles) // 2]
    edge = (np.max(np.abs(offs), axis=1) >= half_xy_m - 1e-9)[None, :] | (
        np.abs(angles - centre) >= half_theta_rad - 1e-9
    )[:, None]
    return np.array([offs[t, 0], offs[t, 1], angles[a]]), d.reshape(-1, 3), edge.ravel()


def icp(
    target: cKDTree, target_pts: np.ndarray, query: np.ndarray, pose: np.ndarray, iterations: int,
    max_m: float, inlier_m: float,
) -> tuple[np.ndarray, float]:  # fmt: skip
    """Point-to-point ICP of ``query (N,2)`` onto the target from ``pose (3,)``: the pose and the
    share of query points within ``inlier_m`` of the target there."""
    x = pose.copy()
    for _ in range(iterations):
        p = apply_points(x, query)
        d, j = target.query(p, distance_upper_bound=max_m)
        ok = np.isfinite(d)
        if ok.sum() < 10:
            break
        a, b = p[ok], target_pts[j[ok]]
        ma, mb = a.mean(axis=0), b.mean(axis=0)
        hmat = (a - ma).T @ (b - mb)
        th = np.arctan2(hmat[0, 1] - hmat[1, 0], hmat[0, 0] + hmat[1, 1])
        c, s = np.cos(th), np.sin(th)
        t = mb - np.array([c * ma[0] - s * ma[1], s * ma[0] + c * ma[1]])
        x = compose(np.array([t[0], t[1], th]), x)
    d, _ = target.query(apply_points(x, query), distance_upper_bound=inlier_m)
    return x, float(np.mean(np.isfinite(d)))


def voxel_thin(points: np.ndarray, voxel_m: float) -> np.ndarray:
    """The first of ``points (K,2)`` in each ``voxel_m`` square cell, in their order: a scan
    thinned to a spatial resolution (near walls hold many points per cell, far ones few)."""
    if len(points) == 0 or voxel_m <= 0:
        return points
    key = np.floor(points / voxel_m).astype(np.int64)
    _, first = np.unique(key[:, 0] * 1_000_003 + key[:, 1], return_index=True)
    return points[np.sort(first)]


def local_cloud(
    kf_poses: np.ndarray, kf_points: list[np.ndarray], centre: int, lo: int, hi: int
) -> np.ndarray:
    """Points of keyframes ``lo..hi`` (inclusive) in keyframe ``centre``'s frame."""
    parts = []
    for m in range(max(lo, 0), min(hi, len(kf_points) - 1) + 1):
        rel = relative_one(kf_poses[centre], kf_poses[m])
        parts.append(apply_points(rel, kf_points[m]))
    return np.vstack(parts) if parts else np.zeros((0, 2))


def window_match(
    fld: Field,
    cloud: np.ndarray,
    query: np.ndarray,
    guess: np.ndarray,
    cfg: MatchConfig,
    stats: dict,
    wide: tuple | None = None,
) -> tuple[np.ndarray, float, np.ndarray, float] | None:
    """Where ``query (Q,2)`` fits ``cloud (C,2)`` (``fld`` its likelihood field) near ``guess
    (3,)``: ``(pose (3,), best score, information (3,3), inlier share)``, or None (counted in
    ``stats``: too low a score, ambiguous, too little overlap after ICP). ``wide``: a wide
    search's near-best poses, scores and edge flags (:func:`branch_and_bound`), which join the
    window's surface in the covariance. A best pose off the window's centre with more than
    ``surface.edge_mass`` of the likelihood on the window's edge: the window centred on it and
    searched again, at most ``cfg.recentre`` times (counted ``recentred`` in ``stats``)."""
    for left in range(cfg.recentre, -1, -1):
        scores, angles, offs = window_scores(
            fld, query, guess, cfg.search_xy_m, cfg.search_theta_rad, cfg.search_step_m, cfg.search_step_rad,
            compiled=cfg.compiled,
        )  # fmt: skip
        best = float(scores.max())
        if best < cfg.min_score:
            return None
        rel, d_local, edge_local = window_surface(scores, angles, offs, cfg.search_xy_m, cfg.search_theta_rad)
        pose0 = np.array([guess[0] + rel[0], guess[1] + rel[1], rel[2]])
        if (
            not left
            or np.hypot(rel[0], rel[1]) < cfg.search_step_m
            or _weights(scores.ravel(), best, cfg.surface)[edge_local].sum() <= cfg.surface.edge_mass
        ):
            break
        guess = pose0  # (the window centred on its best)
        stats["recentred"] = stats.get("recentred", 0) + 1
    # the score surface: the window around the best, and the wide search's near-best poses (which
    # went beyond the small window's edge)
    d, s, edge = d_local, scores.ravel(), edge_local
    if wide is not None:
        d_wide = wide[0] - pose0
        d_wide[:, 2] = wrap_angle(d_wide[:, 2])
        d, s = np.vstack([d, d_wide]), np.concatenate([s, wide[1]])
        edge = np.concatenate([np.zeros_like(edge), wide[2]])
    floor = np.array([cfg.search_step_m**2 / 12 + cfg.sigma_xy_m**2] * 2
                     + [cfg.search_step_rad**2 / 12 + cfg.sigma_theta_rad**2])  # fmt: skip
    cov = match_covariance(d, s, float(s.max()), edge, floor, cfg.surface)
    if cov is None:
        stats["ambiguous"] = stats.get("ambiguous", 0) + 1
        return None
    z, share = icp(cKDTree(cloud), cloud, query, pose0, cfg.icp_iterations, cfg.icp_max_m, cfg.inlier_m)
    if share < cfg.min_inlier_share:
        stats["low_overlap"] = stats.get("low_overlap", 0) + 1
        return None
    z[2] = wrap_angle(z[2])
    return z, best, np.linalg.inv(cov), share
