"""Pose-graph back end: loop closures that correct the past trajectory, not only the present.

The filter's trajectory is locally accurate (a few cm over a minute) but drifts globally: a
loop closure fixes the current pose and leaves the surviving particle's past as it was. The
back end takes that trajectory as the odometry of a pose graph and adds loop edges:

1. keyframes every ``keyframe_m`` / ``keyframe_rad`` of the trajectory; each keeps its scan points;
2. chain edges: the trajectory's relative motion between consecutive keyframes;
3. loop edges: a keyframe's points (with its recent neighbours) matched against the local
   cloud of an old keyframe nearby (its neighbours in time, locally consistent) by correlative
   search over a likelihood field (Olson 2009), refined by ICP; kept only when verified (enough
   overlap, no rival peak — the check of map_server/alignment.py); the filter's confirmed
   relocalizations are tried first, the search starting where they put the robot (a drift
   beyond the search window, which the filter bridged but could not keep, is still closed);
4. sparse Gauss-Newton with a robust kernel on the loop edges (posegraph.py); loop edges that
   still disagree after it are dropped and the graph solved again;
5. every scan follows its keyframe rigidly.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from scipy.ndimage import distance_transform_edt
from scipy.spatial import cKDTree

from robot_agent.slam import posegraph
from shared.geometry import apply_points, compose, relative, wrap_angle


@dataclass(frozen=True)
class BackendConfig:
    enabled: bool = True
    keyframe_m: float = 0.5  # a keyframe every this much travel ...
    keyframe_rad: float = np.radians(15.0)  # ... or this much turning
    cloud_neighbours: int = 4  # an old keyframe's cloud: its scan and this many on each side
    query_neighbours: int = 2  # the query: a keyframe's scan and this many before it
    voxel_m: float = 0.05  # clouds thinned to one point per voxel
    query_points: int = 200  # query thinned to at most this many points
    min_gap_s: float = 30.0  # loop candidates: older than this ...
    min_gap_keyframes: int = 20  # ... and this many keyframes back ...
    candidate_radius_m: float = 2.5  # ... and within this distance in the current estimate
    candidates: int = 2  # old keyframes tried per query
    check_every: int = 2  # every this many keyframes a query is tried
    search_xy_m: float = 0.8  # correlative search window (half width) ...
    search_theta_rad: float = np.radians(8.0)
    search_step_m: float = 0.1
    search_step_rad: float = np.radians(2.0)
    field_sigma_m: float = 0.08  # likelihood field: exp(-d^2 / 2 sigma^2)
    score_sharpness: float = 20.0  # a pose scoring s is exp(-k (1 - s / best)) as likely as the best
    max_cross_sigma_m: float = 0.15  # a match this uncertain across its best-determined direction ...
    max_theta_sigma_rad: float = np.radians(3.0)  # ... or in heading is ambiguous: refused
    edge_mass: float = 0.05  # likelihood this large at the window's edge: unbounded along that axis
    unbounded_sigma_m: float = 5.0  # ... then its std along it
    min_score: float = 0.4  # mean likelihood of the query at the best pose
    icp_iterations: int = 8
    icp_max_m: float = 0.15
    inlier_m: float = 0.05
    min_inlier_share: float = 0.6  # verified overlap after ICP
    loop_sigma_xy_m: float = 0.05
    loop_sigma_theta_rad: float = np.radians(1.0)
    robust_k: float = 3.0  # Cauchy kernel width (in sigmas) on loop edges ...
    robust_wide_k: float = 100.0  # ... reached from this wide one (and their geometric mean)
    max_loop_chi: float = 5.0  # loop edges with a normalized residual above are dropped
    passes: int = 5  # loop search passes, each from the path the previous one corrected ...
    min_pass_loops: int = 10  # ... until one finds fewer new loops than this
    pass_moved_m: float = 0.1  # a later pass queries only keyframes moved this much ...
    pass_moved_rad: float = np.radians(1.0)  # ... or this much by the previous one
    chain: posegraph.ChainNoise = field(default_factory=posegraph.ChainNoise)
    jump_sigma_xy_m: float = 0.3  # a relocalization's jump: its chain edge takes the odometry,
    jump_sigma_theta_rad: float = np.radians(5.0)  # held this loosely


def select_keyframes(poses: np.ndarray, cfg: BackendConfig, jumps: np.ndarray | None = None) -> np.ndarray:
    """Indices ``(K,)`` into ``poses (S,3)``: the first pose, then one each keyframe_m / _rad,
    and one right after every jump."""
    keep = [0]
    last = poses[0]
    for i in range(1, len(poses)):
        d = relative(last, poses[i])
        if (
            (jumps is not None and jumps[i])
            or np.hypot(d[0], d[1]) >= cfg.keyframe_m
            or abs(d[2]) >= cfg.keyframe_rad
        ):
            keep.append(i)
            last = poses[i]
    return np.asarray(keep)


def voxel_thin(points: np.ndarray, voxel_m: float) -> np.ndarray:
    if len(points) == 0:
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
        rel = relative(kf_poses[centre], kf_poses[m])
        parts.append(apply_points(rel, kf_points[m]))
    return np.vstack(parts) if parts else np.zeros((0, 2))


@dataclass(frozen=True)
class Field:
    values: np.ndarray  # (W,H) likelihood
    origin: np.ndarray  # (2,) xy of cell (0,0)
    res_m: float


def likelihood_field(points: np.ndarray, res_m: float, sigma_m: float, margin_m: float) -> Field:
    lo = points.min(axis=0) - margin_m
    shape = np.ceil((points.max(axis=0) + margin_m - lo) / res_m).astype(int) + 1
    occ = np.zeros(shape, bool)
    c = np.round((points - lo) / res_m).astype(int)
    occ[c[:, 0], c[:, 1]] = True
    d = distance_transform_edt(~occ) * res_m
    return Field(np.exp(-0.5 * (d / sigma_m) ** 2), lo, res_m)


def correlative_search(fld: Field, query: np.ndarray, guess: np.ndarray, cfg: BackendConfig):
    """Scores ``(A,T)`` of the query points ``(N,2)`` at every pose of the window around
    ``guess``; also the angles ``(A,)`` and translation offsets ``(T,2)`` [m]."""
    n_xy = round(cfg.search_xy_m / cfg.search_step_m)
    n_th = round(cfg.search_theta_rad / cfg.search_step_rad)
    angles = guess[2] + cfg.search_step_rad * np.arange(-n_th, n_th + 1)
    steps = round(cfg.search_step_m / fld.res_m)
    o = steps * np.arange(-n_xy, n_xy + 1)
    ox, oy = np.meshgrid(o, o, indexing="ij")
    ox, oy = ox.ravel(), oy.ravel()
    w, h = fld.values.shape
    flat = fld.values.ravel()
    scores = np.empty((len(angles), len(ox)))
    for a, th in enumerate(angles):
        c, s = np.cos(th), np.sin(th)
        px = c * query[:, 0] - s * query[:, 1] + guess[0]
        py = s * query[:, 0] + c * query[:, 1] + guess[1]
        cx = np.round((px - fld.origin[0]) / fld.res_m).astype(int)
        cy = np.round((py - fld.origin[1]) / fld.res_m).astype(int)
        ix = cx[None, :] + ox[:, None]
        iy = cy[None, :] + oy[:, None]
        ok = (ix >= 0) & (ix < w) & (iy >= 0) & (iy < h)
        v = np.where(ok, flat[np.where(ok, ix * h + iy, 0)], 0.0)
        scores[a] = v.mean(axis=1)
    return scores, angles, np.column_stack([ox, oy]) * fld.res_m


def icp(target: cKDTree, target_pts: np.ndarray, query: np.ndarray, pose: np.ndarray, cfg: BackendConfig):
    """Point-to-point ICP of ``query`` onto the target from ``pose``; the pose and inlier share."""
    x = pose.copy()
    for _ in range(cfg.icp_iterations):
        p = apply_points(x, query)
        d, j = target.query(p, distance_upper_bound=cfg.icp_max_m)
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
    d, _ = target.query(apply_points(x, query), distance_upper_bound=cfg.inlier_m)
    return x, float(np.mean(np.isfinite(d)))


@dataclass(frozen=True)
class Loop:
    old: int  # keyframe index
    new: int
    z: np.ndarray  # (3,) pose of new in old's frame
    score: float
    info: np.ndarray  # (3,3) information of z: narrow across a corridor, wide along it
    inliers: float


def match_loop(
    kf_poses: np.ndarray,
    kf_points: list[np.ndarray],
    old: int,
    new: int,
    cfg: BackendConfig,
    stats: dict,
    estimate: np.ndarray | None = None,
) -> Loop | None:
    """Verified relative pose of keyframe ``new`` in keyframe ``old``'s frame, or None. The
    clouds are built with ``kf_poses (K,3)`` (the filter's path: locally right); the search
    starts from ``estimate (K,3)`` when given (the path corrected so far)."""
    w = cfg.cloud_neighbours
    cloud = voxel_thin(local_cloud(kf_poses, kf_points, old, old - w, old + w), cfg.voxel_m)
    query = voxel_thin(local_cloud(kf_poses, kf_points, new, new - cfg.query_neighbours, new), cfg.voxel_m)
    if len(cloud) < 30 or len(query) < 30:
        return None
    if len(query) > cfg.query_points:
        query = query[np.linspace(0, len(query) - 1, cfg.query_points).astype(int)]
    est = kf_poses if estimate is None else estimate
    guess = relative(est[old], est[new])
    fld = likelihood_field(cloud, cfg.search_step_m, cfg.field_sigma_m, 4.0 * cfg.field_sigma_m)
    scores, angles, offs = correlative_search(fld, query, guess, cfg)
    stats["matches"] = stats.get("matches", 0) + 1
    a, t = np.unravel_index(np.argmax(scores), scores.shape)
    best = float(scores[a, t])
    if best < cfg.min_score:
        return None
    cov = match_covariance(scores, angles, offs, (a, t), cfg)
    if cov is None:
        stats["ambiguous"] = stats.get("ambiguous", 0) + 1
        return None
    pose0 = np.array([guess[0] + offs[t, 0], guess[1] + offs[t, 1], angles[a]])
    tree = cKDTree(cloud)
    z, share = icp(tree, cloud, query, pose0, cfg)
    if share < cfg.min_inlier_share:
        stats["low_overlap"] = stats.get("low_overlap", 0) + 1
        return None
    z[2] = wrap_angle(z[2])
    return Loop(old, new, z, best, np.linalg.inv(cov), share)


def match_covariance(
    scores: np.ndarray, angles: np.ndarray, offs: np.ndarray, best: tuple[int, int], cfg: BackendConfig
) -> np.ndarray | None:
    """Covariance ``(3,3)`` of a correlative match (x, y, θ in the old keyframe's frame) from its
    score surface ``scores (A,T)`` over ``angles (A,)`` × ``offs (T,2)`` (Olson 2009): every pose
    weighted by how likely it is against the best, second moments about the best. Along a
    corridor many poses score alike: the match constrains only across it and in heading — it
    is kept with that information, not refused. None when even the best-determined direction
    or the heading is uncertain (a different place scores alike: ambiguous)."""
    a, t = best
    p = np.exp(-cfg.score_sharpness * (1.0 - scores / scores[a, t]))  # (A,T)
    d = np.empty((*scores.shape, 3))
    d[..., :2] = (offs - offs[t])[None, :, :]
    d[..., 2] = (angles - angles[a])[:, None]
    w = p / p.sum()
    cov = np.einsum("at,ati,atj->ij", w, d, d)
    cov += np.diag([cfg.search_step_m**2 / 12 + cfg.loop_sigma_xy_m**2] * 2 + [
        cfg.search_step_rad**2 / 12 + cfg.loop_sigma_theta_rad**2
    ])  # fmt: skip
    if cov[2, 2] > cfg.max_theta_sigma_rad**2:
        return None
    values, vectors = np.linalg.eigh(cov[:2, :2])
    if values[0] > cfg.max_cross_sigma_m**2:
        return None
    # mass at the window's edge along the weak axis: the likelihood goes on beyond what was
    # searched, the match says nothing along it
    half = np.max(np.abs(offs), axis=0)
    edge = np.any(np.abs(offs) >= half - 1e-9, axis=1)  # (T,)
    if w[:, edge].sum() > cfg.edge_mass:
        weak = vectors[:, 1]
        extra = cfg.unbounded_sigma_m**2 - values[1]
        if extra > 0:
            cov[:2, :2] += extra * np.outer(weak, weak)
    return cov


def near_old_keyframes(
    kf_stamps: np.ndarray, est: np.ndarray, new: int, cfg: BackendConfig
) -> tuple[np.ndarray, np.ndarray]:
    """Loop candidates for keyframe ``new``: the keyframes old enough (min_gap_s and
    min_gap_keyframes back) within candidate_radius_m of it in ``est (K,3)``; and the distances
    ``(K,)`` of every keyframe to it there."""
    old_ok = (kf_stamps <= kf_stamps[new] - cfg.min_gap_s) & (
        np.arange(len(est)) <= new - cfg.min_gap_keyframes
    )
    d = np.hypot(*(est[:, :2] - est[new, :2]).T)
    return np.flatnonzero(old_ok & (d < cfg.candidate_radius_m)), d


def find_loops(
    kf_stamps: np.ndarray,
    kf_poses: np.ndarray,
    kf_points: list[np.ndarray],
    cfg: BackendConfig,
    stats: dict,
    estimate: np.ndarray | None = None,
    skip: set | None = None,
) -> list[Loop]:
    """Verified loops over every keyframe (offline: the whole trajectory at once); candidates
    near in ``estimate`` (default ``kf_poses``); queries in ``skip`` are not tried."""
    loops: list[Loop] = []
    est = kf_poses if estimate is None else estimate
    for new in range(0, len(kf_poses), cfg.check_every):
        if skip is not None and new in skip:
            continue
        cand, d = near_old_keyframes(kf_stamps, est, new, cfg)
        if len(cand) == 0:
            continue
        dth = np.abs(wrap_angle(est[cand, 2] - est[new, 2]))
        order = cand[np.argsort(d[cand] + 1.0 * dth)]
        picked: list[int] = []
        for c in order:  # distinct places: not two neighbours of one old pass
            if all(abs(c - p) > 2 * cfg.cloud_neighbours for p in picked):
                picked.append(int(c))
            if len(picked) >= cfg.candidates:
                break
        for old in picked:
            loop = match_loop(kf_poses, kf_points, old, new, cfg, stats, estimate)
            if loop is not None:
                loops.append(loop)
    return loops


def hinted_loops(
    kf_stamps: np.ndarray,
    kf_poses: np.ndarray,
    kf_points: list[np.ndarray],
    kf: np.ndarray,
    poses: np.ndarray,
    hints: list[tuple[int, np.ndarray]],
    cfg: BackendConfig,
    stats: dict,
) -> list[Loop]:
    """Verified loops at the filter's relocalizations: ``hints`` are ``(scan i, pose (3,))`` —
    where the filter found scan ``i`` to be among old elements, ``poses[i]`` being where its path
    says it was (``kf (K,)``: the keyframes' scan indices). The search starts from the hinted
    pose: the drift a relocalization bridges is larger than the window around the path."""
    loops: list[Loop] = []
    for i, pose in hints:
        new = int(np.searchsorted(kf, i, side="right")) - 1  # the keyframe scan i hangs from
        est = kf_poses.copy()
        est[new] = compose(pose, relative(poses[i], kf_poses[new]))
        cand, d = near_old_keyframes(kf_stamps, est, new, cfg)
        for old in cand[np.argsort(d[cand])][: cfg.candidates]:
            loop = match_loop(kf_poses, kf_points, int(old), new, cfg, stats, est)
            if loop is not None:
                loops.append(loop)
                break
    stats["loops_hinted"] = len(loops)
    return loops


def optimize(
    kf_poses: np.ndarray, loops: list[Loop], cfg: BackendConfig, stats: dict, jump_edges: dict | None = None
) -> np.ndarray:
    """Keyframe poses ``(K,3)`` after the pose graph (chain + verified loops, robust).
    ``jump_edges``: chain edge index -> motion to use instead, loosely held."""
    a, b, z, info = posegraph.chain_edges(kf_poses, cfg.chain)
    for e, motion in (jump_edges or {}).items():
        z[e] = motion
        info[e] = 1.0 / np.array([cfg.jump_sigma_xy_m, cfg.jump_sigma_xy_m, cfg.jump_sigma_theta_rad]) ** 2
    if not loops and not jump_edges:
        return kf_poses.copy()
    la = np.array([lp.old for lp in loops], dtype=int)
    lb = np.array([lp.new for lp in loops], dtype=int)
    lz = np.array([lp.z for lp in loops], dtype=float).reshape(-1, 3)
    li = np.array([lp.info for lp in loops], dtype=float).reshape(-1, 3, 3)
    info = posegraph.full_information(info)
    keep = np.ones(len(la), bool)
    for _round in range(3):
        # a wide kernel first, then narrower: loops far from the initial path (a large drift)
        # must pull it before the narrow kernel may call the ones that still disagree outliers
        x = kf_poses.copy()
        for k in (cfg.robust_wide_k, np.sqrt(cfg.robust_wide_k * cfg.robust_k), cfg.robust_k):
            x = posegraph.optimize(
                x,
                np.concatenate([a, la[keep]]),
                np.concatenate([b, lb[keep]]),
                np.vstack([z, lz[keep]]),
                np.vstack([info, li[keep]]),
                iterations=10,
                robust_from=len(a),
                robust_k=k,
            )
        r = relative(x[la], x[lb]) - lz
        r[:, 2] = wrap_angle(r[:, 2])
        chi = np.sqrt(posegraph.mahalanobis2(r, li) / 3.0)
        new_keep = chi <= cfg.max_loop_chi
        if np.array_equal(new_keep, keep):
            break
        keep = new_keep
    stats["loops_kept"] = int(keep.sum())
    return x


def follow_keyframes(
    poses: np.ndarray, kf_index: np.ndarray, kf_old: np.ndarray, kf_new: np.ndarray
) -> np.ndarray:
    """Every pose ``(S,3)`` moved rigidly with the last keyframe at or before it."""
    owner = np.searchsorted(kf_index, np.arange(len(poses)), side="right") - 1
    return compose(kf_new[owner], relative(kf_old[owner], poses))


def run_backend(
    stamps_s: np.ndarray,
    poses: np.ndarray,
    odometry: np.ndarray,
    scan_points_robot: Callable[[int], np.ndarray],
    cfg: BackendConfig,
    hints: list[tuple[int, np.ndarray]] | None = None,
    jumps: np.ndarray | None = None,
) -> tuple[np.ndarray, dict]:
    """The corrected trajectory ``(S,3)`` and statistics, offline over the whole trajectory.
    ``odometry (S,3)``: the raw odometry of every scan; ``scan_points_robot(i)``: scan ``i``'s
    points in the robot frame (asked for keyframes only); ``hints``: the filter's relocalizations
    (:func:`hinted_loops`); ``jumps (S,)``: the scans the filter reached by a relocalization's jump
    (:meth:`FastSLAM.best_jumps`), not by motion — odometry bridges them instead."""
    jumps = np.zeros(len(poses), bool) if jumps is None else np.asarray(jumps, bool)
    kf = select_keyframes(poses, cfg, jumps)
    jump_edges = {}
    for i in np.flatnonzero(jumps):  # keyframe e+1 starts at the jump: edge e bridges it by odometry
        e = int(np.searchsorted(kf, i)) - 1
        jump_edges[e] = compose(relative(poses[kf[e]], poses[i - 1]), relative(odometry[i - 1], odometry[i]))
    kf_poses = poses[kf]
    kf_points = [voxel_thin(scan_points_robot(int(i)), cfg.voxel_m) for i in kf]
    stats: dict = {"keyframes": len(kf), "jumps": len(jump_edges)}
    loops = hinted_loops(stamps_s[kf], kf_poses, kf_points, kf, poses, hints or [], cfg, stats)
    new = kf_poses
    skip: set = set()
    for p in range(cfg.passes):  # later passes search from the corrected path: drift the first
        # pass could not bridge is now within the window where its loops pulled the path
        found = find_loops(stamps_s[kf], kf_poses, kf_points, cfg, stats, new if p else None, skip)
        stats[f"loops_pass{p}"] = len(found)
        loops += found
        if p and len(found) < cfg.min_pass_loops:
            break
        searched, new = new, optimize(kf_poses, loops, cfg, stats, jump_edges)
        # the next pass queries keyframes without a loop whose estimate this pass moved
        d = relative(searched, new)
        still = (np.hypot(d[:, 0], d[:, 1]) < cfg.pass_moved_m) & (np.abs(d[:, 2]) < cfg.pass_moved_rad)
        skip = {lp.new for lp in loops} | set(np.flatnonzero(still).tolist())
    stats["loops"] = len(loops)
    return follow_keyframes(poses, kf, kf_poses, new), stats
