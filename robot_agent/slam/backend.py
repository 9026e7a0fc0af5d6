"""Pose-graph back end: loop closures that correct the past trajectory, not only the present.

The filter's trajectory is locally accurate (a few cm over a minute) but drifts globally: a
loop closure fixes the current pose and leaves the surviving particle's past as it was. The
back end takes that trajectory as the odometry of a pose graph and adds loop edges:

1. keyframes every ``keyframe_m`` / ``keyframe_rad`` of the trajectory; each keeps its scan points;
2. chain edges: the trajectory's relative motion between consecutive keyframes; across the
   filter's own relocalization jumps (it says where: ``FastSLAM.best_jumps``), odometry, loosely;
3. loop edges: a keyframe's points (with its recent neighbours) matched against the local
   cloud of an old keyframe nearby (its neighbours in time, locally consistent) by correlative
   search over a likelihood field (scanmatch.py, Olson 2009), refined by ICP. The first pass
   searches as wide as the path between the two may have drifted (a share of the distance
   driven between them, by branch and bound); later passes search around the corrected path.
   A match keeps the covariance of its score surface: in a corridor it holds across and in
   heading, not along — refused only when it holds in neither translation direction or not in
   heading, or too few points overlap after ICP. The filter's confirmed relocalizations are
   tried first, the search starting where they put the robot;
4. sparse Gauss-Newton with a robust kernel on the loop edges (posegraph.py); loop edges that
   still disagree after it are dropped and the graph solved again;
5. every scan follows its keyframe rigidly.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from robot_agent.slam import posegraph
from shared.geometry import apply_points, compose, relative, relative_one, transform_points, wrap_angle
from shared.scanmatch import (
    Field,
    MatchConfig,
    SurfaceConfig,
    branch_and_bound,
    likelihood_field,
    local_cloud,
    voxel_thin,
    window_match,
)


@dataclass(frozen=True)
class BackendConfig:
    enabled: bool = True
    compiled: bool = True  # the scan matcher's sums by the compiled kernels (kernels.py) when built
    keyframe_m: float = 0.5  # a keyframe every this much travel ...
    keyframe_rad: float = np.radians(15.0)  # ... or this much turning
    cloud_neighbours: int = 4  # an old keyframe's cloud: its scan and this many on each side
    query_neighbours: int = 2  # the query: a keyframe's scan and this many before it
    voxel_m: float = 0.05  # clouds thinned to one point per voxel
    query_points: int = 200  # query thinned to at most this many points
    min_gap_s: float = 30.0  # loop candidates: older than this ...
    min_gap_keyframes: int = 20  # ... and this many keyframes back ...
    candidate_radius_m: float = 2.5  # ... and within this distance in the current estimate, plus
    # the drift the path between them may hold (below)
    candidates: int = 2  # old keyframes tried per query
    check_every: int = 2  # every this many keyframes a query is tried
    search_xy_m: float = 0.8  # correlative search window (half width) ...
    search_theta_rad: float = np.radians(8.0)
    search_step_m: float = 0.1
    search_step_rad: float = np.radians(2.0)
    # the first pass searches wider, by the drift the filter's path may hold between the two
    # keyframes: this share of the path driven between them (branch and bound, scanmatch.py)
    drift_xy_per_m: float = 0.02
    drift_theta_rad_per_m: float = np.radians(0.1)
    max_drift_xy_m: float = 8.0
    max_drift_theta_rad: float = np.radians(25.0)
    min_wide_step_rad: float = np.radians(0.5)  # the wide search's heading step: the far query
    # points move by at most a cell of the field (search_step_m) from one heading to the next
    wide_points: int = 100  # query points the wide search scores (evenly thinned)
    wide_keep_ratio: float = 0.95  # it keeps poses scoring this share of the best (rivals)
    field_sigma_m: float = 0.08  # likelihood field: exp(-d^2 / 2 sigma^2)
    surface: SurfaceConfig = field(default_factory=SurfaceConfig)  # a match's covariance
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
    # online (robot_agent/backend/online.py): an update every this much of the source's time, ...
    online_every_s: float = 5.0
    online_requeries: int = 100  # ... re-searching at most this many moved keyframes, and none
    online_budget_s: float = 2.0  # once the update took this long (the rest wait); loops
    online_surprises: int = 3  # that the estimate contradicts go in when this many have come
    # each update's optimization: when its new loops all agree with the last solution, the narrow
    # kernel alone from there (the wide-to-narrow schedule when surprises or jumps came in, and at
    # the end); no Gauss-Newton iteration starts after this much of it (0: no bound)
    online_optimize_s: float = 3.0
    # a keyframe the corrected path puts within this of an older one (the robot passing a known
    # place again) leaves the graph once this many keyframes are newer: its scans follow that
    # older one from then on, its edges are carried over to it (robot_agent/backend/online.py)
    online_retire_m: float = 0.3  # (0: never)
    online_retire_rad: float = np.radians(10.0)
    online_window: int = 100
    online_max_keyframes: int = 2000  # the graph's bound: beyond it, keyframes older than the
    # window retire onto their nearest older one, nearest first, down to 90 % of it (0: no bound)
    online_adopt: bool = True  # the filter continues from each correction as it comes: its
    # particles, their maps and history move with it (False: the correction is applied only to
    # what is published, the filter keeps drifting in its own frame)
    # the map frame held where the first keyframe's own scan puts the start (start_gauge): the
    # first keyframe is the graph's fixed node, and the filter's heading at it drifts by a tenth
    # of a degree over the next keyframes (simulated office: 0.115° mean against the whole path,
    # up to 0.30°) — every other keyframe, and the map, turned against it; its scan matched
    # point to line on the scans of the keyframes within gauge_radius_m (at most gauge_keyframes,
    # nearest first) says where it is on that map, and the whole map moves so that it is there
    gauge: bool = True
    gauge_radius_m: float = 30.0
    gauge_keyframes: int = 150
    gauge_gate_m: tuple[float, ...] = (0.2, 0.1, 0.05)  # point-to-line gates, narrowing
    gauge_min_share: float = 0.6  # of the first scan's points within the last gate
    gauge_max_m: float = 0.3  # a start moved further than this (or turned more) is not taken
    gauge_max_rad: float = np.radians(1.5)

    def match_config(self) -> MatchConfig:
        """The narrow match's part of this (shared/scanmatch.window_match)."""
        return MatchConfig(
            self.search_xy_m, self.search_theta_rad, self.search_step_m, self.search_step_rad,
            self.field_sigma_m, self.surface, self.min_score, self.icp_iterations, self.icp_max_m,
            self.inlier_m, self.min_inlier_share, self.loop_sigma_xy_m, self.loop_sigma_theta_rad,
            self.compiled,
        )  # fmt: skip


def start_gauge(kf_poses: np.ndarray, kf_points: list[np.ndarray], cfg: BackendConfig) -> np.ndarray | None:
    """Where the first keyframe's own scan ``kf_points[0]`` (its frame) lies on the map that the
    other keyframes' scans make at ``kf_poses (K,3)`` (those within ``gauge_radius_m`` of it,
    at most ``gauge_keyframes``, nearest first): its pose ``(3,)`` there, by point-to-line
    Gauss-Newton from ``kf_poses[0]`` (each point on the line through its nearest map points,
    robust, the gates narrowing), or None when too little of the scan lies on the map or the
    pose moved beyond ``gauge_max_m`` / ``gauge_max_rad``."""
    if len(kf_poses) < 2 or len(kf_points) < 2 or kf_points[0] is None or len(kf_points[0]) < 20:
        return None
    d = np.hypot(*(kf_poses[1:, :2] - kf_poses[0, :2]).T)
    near = 1 + np.argsort(d, kind="stable")[: cfg.gauge_keyframes]
    near = near[d[near - 1] <= cfg.gauge_radius_m]
    near = [k for k in near if kf_points[k] is not None]
    if not near:
        return None
    counts = [len(kf_points[k]) for k in near]  # every point by its keyframe's pose, in one go
    pts = np.concatenate([kf_points[k] for k in near])
    cloud = voxel_thin(transform_points(np.repeat(kf_poses[near], counts, axis=0), pts), cfg.voxel_m)
    if len(cloud) < 30:
        return None
    tree = cKDTree(cloud)
    query = np.asarray(kf_points[0], float)
    x = np.asarray(kf_poses[0], float).copy()
    for gate in cfg.gauge_gate_m:
        for _ in range(10):
            p = apply_points(x, query)
            dist, j = tree.query(p, k=6, distance_upper_bound=gate + 0.25)
            ok = (dist[:, 0] <= gate) & np.isfinite(dist).all(axis=1)  # (a line through six near)
            if ok.sum() < 20:
                return None
            nb = cloud[j[ok]]  # (M,6,2)
            c = nb.mean(axis=1)
            cov = np.einsum("mki,mkj->mij", nb - c[:, None], nb - c[:, None])
            w_eig, v = np.linalg.eigh(cov)
            line = w_eig[:, 0] < 0.1 * w_eig[:, 1]  # (a corner or a blob: no line)
            n = v[:, :, 0]
            r = np.sum((p[ok] - c) * n, axis=1)
            rel = p[ok] - x[:2]
            jac = np.column_stack([n[:, 0], n[:, 1], n[:, 1] * rel[:, 0] - n[:, 0] * rel[:, 1]])
            w = line / (1.0 + (r / 0.02) ** 2)
            h = jac.T @ (w[:, None] * jac) + np.diag([1.0, 1.0, 10.0])  # (weakly held where it is)
            step = -np.linalg.solve(h, jac.T @ (w * r))
            x = x + step
            if np.abs(step).max() < 1e-6:
                break
    p = apply_points(x, query)
    dist, _ = tree.query(p, distance_upper_bound=cfg.gauge_gate_m[-1])
    if np.mean(np.isfinite(dist)) < cfg.gauge_min_share:
        return None
    moved = relative_one(kf_poses[0], x)
    if np.hypot(moved[0], moved[1]) > cfg.gauge_max_m or abs(moved[2]) > cfg.gauge_max_rad:
        return None
    return x


def select_keyframes(poses: np.ndarray, cfg: BackendConfig, jumps: np.ndarray | None = None) -> np.ndarray:
    """Indices ``(K,)`` into ``poses (S,3)``: the first pose, then one each keyframe_m / _rad,
    and one right after every jump."""
    keep = [0]
    last = poses[0]
    for i in range(1, len(poses)):
        d = relative_one(last, poses[i])
        if (
            (jumps is not None and jumps[i])
            or np.hypot(d[0], d[1]) >= cfg.keyframe_m
            or abs(d[2]) >= cfg.keyframe_rad
        ):
            keep.append(i)
            last = poses[i]
    return np.asarray(keep)


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
    drift: tuple[float, float] = (0.0, 0.0),
) -> Loop | None:
    """Verified relative pose of keyframe ``new`` in keyframe ``old``'s frame, or None. The
    clouds are built with ``kf_poses (K,3)`` (the filter's path: locally right); the search
    starts from ``estimate (K,3)`` when given (the path corrected so far) and covers the base
    window widened by ``drift`` (m, rad) — wider than it, by branch and bound first."""
    w = cfg.cloud_neighbours
    cloud = voxel_thin(local_cloud(kf_poses, kf_points, old, old - w, old + w), cfg.voxel_m)
    query = voxel_thin(local_cloud(kf_poses, kf_points, new, new - cfg.query_neighbours, new), cfg.voxel_m)
    if len(cloud) < 30 or len(query) < 30:
        return None
    if len(query) > cfg.query_points:
        query = query[np.linspace(0, len(query) - 1, cfg.query_points).astype(int)]
    est = kf_poses if estimate is None else estimate
    guess = relative_one(est[old], est[new])
    fld = likelihood_field(cloud, cfg.search_step_m, cfg.field_sigma_m, 4.0 * cfg.field_sigma_m)
    stats["matches"] = stats.get("matches", 0) + 1
    wide = None
    if drift[0] > 0 or drift[1] > 0:
        stats["wide"] = stats.get("wide", 0) + 1
        wide = _wide_search(fld, query, guess, drift, cfg)
        if wide is None:
            return None
        guess = wide[0][0]  # the small window around the wide search's best
    found = window_match(fld, cloud, query, guess, cfg.match_config(), stats, wide)
    if found is None:
        return None
    z, best, info, share = found
    return Loop(old, new, z, best, info, share)


def _wide_search(
    fld: Field, query: np.ndarray, guess: np.ndarray, drift: tuple[float, float], cfg: BackendConfig
) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """Branch and bound over the small window widened by ``drift`` (m, rad) around ``guess``: the
    near-best poses ``(K,3)`` (best first), their scores ``(K,)`` and whether each lies on the wide
    window's edge ``(K,)``; None when no pose reaches ``cfg.min_score``."""
    half_xy, half_th = cfg.search_xy_m + drift[0], cfg.search_theta_rad + drift[1]
    few = query[np.linspace(0, len(query) - 1, min(len(query), cfg.wide_points)).astype(int)]
    reach = float(np.percentile(np.hypot(few[:, 0], few[:, 1]), 90))
    step = max(cfg.min_wide_step_rad, np.arctan2(fld.res_m, reach))  # far points within a cell
    depth = int(np.clip(np.ceil(np.log2(half_xy / cfg.search_step_m)) - 1, 1, 6))
    poses, scores = branch_and_bound(
        fld,
        few,
        guess,
        half_xy,
        half_th,
        step,
        cfg.min_score,
        cfg.wide_keep_ratio,
        depth,
        compiled=cfg.compiled,
    )
    if len(poses) == 0:
        return None
    edge = (np.max(np.abs(poses[:, :2] - guess[:2]), axis=1) >= half_xy - cfg.search_step_m) | (
        np.abs(wrap_angle(poses[:, 2] - guess[2])) >= half_th - step
    )
    return poses, scores, edge


def path_drift(arc_m: np.ndarray, old: np.ndarray | int, new: int, cfg: BackendConfig) -> tuple:
    """How far (m, rad) the filter's path may have drifted between keyframes ``old`` and ``new``:
    shares of the path driven between them, ``arc_m (K,)`` its length up to each keyframe."""
    driven = np.abs(arc_m[new] - arc_m[old])
    return (
        np.minimum(cfg.max_drift_xy_m, cfg.drift_xy_per_m * driven),
        np.minimum(cfg.max_drift_theta_rad, cfg.drift_theta_rad_per_m * driven),
    )


def near_old_keyframes(
    kf_stamps: np.ndarray, est: np.ndarray, new: int, cfg: BackendConfig, arc_m: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Loop candidates for keyframe ``new``: the keyframes old enough (min_gap_s and
    min_gap_keyframes back) within candidate_radius_m of it in ``est (K,3)`` — plus the drift the
    path between them may hold when ``arc_m (K,)`` (:func:`path_drift`) is given; and the
    distances ``(K,)`` of every keyframe to it there."""
    old_ok = (kf_stamps <= kf_stamps[new] - cfg.min_gap_s) & (
        np.arange(len(est)) <= new - cfg.min_gap_keyframes
    )
    d = np.hypot(*(est[:, :2] - est[new, :2]).T)
    radius = cfg.candidate_radius_m
    if arc_m is not None:
        radius = radius + path_drift(arc_m, np.arange(len(est)), new, cfg)[0]
    return np.flatnonzero(old_ok & (d < radius)), d


def find_loops(
    kf_stamps: np.ndarray,
    kf_poses: np.ndarray,
    kf_points: list[np.ndarray],
    cfg: BackendConfig,
    stats: dict,
    estimate: np.ndarray | None = None,
    skip: set | None = None,
    arc_m: np.ndarray | None = None,
) -> list[Loop]:
    """Verified loops over every keyframe (offline: the whole trajectory at once); candidates
    near in ``estimate`` (default ``kf_poses``); queries in ``skip`` are not tried. With
    ``arc_m (K,)`` (the path's length at each keyframe) candidates and search windows widen by
    the drift the path between the two keyframes may hold (:func:`path_drift`)."""
    loops: list[Loop] = []
    est = kf_poses if estimate is None else estimate
    for new in range(0, len(kf_poses), cfg.check_every):
        if skip is not None and new in skip:
            continue
        cand, d = near_old_keyframes(kf_stamps, est, new, cfg, arc_m)
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
            drift = (0.0, 0.0) if arc_m is None else path_drift(arc_m, old, new, cfg)
            loop = match_loop(kf_poses, kf_points, old, new, cfg, stats, estimate, drift)
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


def held_edges(
    kf_poses: np.ndarray,
    cfg: BackendConfig,
    jump_edges: dict | None = None,
    chain_keep: np.ndarray | None = None,
    extra: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The edges :func:`optimize` holds like the chain (no robust kernel): ``a, b (E,)`` keyframe
    indices, ``z (E,3)``, ``info (E,3,3)`` — the chain on ``kf_poses`` (but ``chain_keep``), the
    jumps' odometry, the ``extra`` edges."""
    a, b, z, info = posegraph.chain_edges(kf_poses, cfg.chain)
    for e, motion in (jump_edges or {}).items():
        z[e] = motion
        info[e] = 1.0 / np.array([cfg.jump_sigma_xy_m, cfg.jump_sigma_xy_m, cfg.jump_sigma_theta_rad]) ** 2
    info = posegraph.full_information(info)
    if chain_keep is not None:
        a, b, z, info = a[chain_keep], b[chain_keep], z[chain_keep], info[chain_keep]
    if extra is not None and len(extra[0]):
        a, b = np.concatenate([a, extra[0]]), np.concatenate([b, extra[1]])
        z, info = np.vstack([z, extra[2]]), np.vstack([info, extra[3]])
    return a, b, z, info


def optimize(
    kf_poses: np.ndarray,
    loops: list[Loop],
    cfg: BackendConfig,
    stats: dict,
    jump_edges: dict | None = None,
    x0: np.ndarray | None = None,
    chain_keep: np.ndarray | None = None,
    extra: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None = None,
    warm: bool = False,
    stop: Callable[[], bool] | None = None,
) -> np.ndarray:
    """Keyframe poses ``(K,3)`` after the pose graph (chain + verified loops, robust), from
    ``x0 (K,3)`` (default ``kf_poses``, the path the chain is measured on).
    ``jump_edges``: chain edge index -> motion to use instead, loosely held; ``chain_keep (K-1,)``:
    the chain edges used (default all); ``extra``: more edges ``a, b (E,), z (E,3), info (E,3,3)``
    held like the chain (not robust). ``warm``: ``x0`` already agrees with every loop but a few
    that agree with it too (an online update's new loops): the narrow kernel alone, no wide one
    first. No Gauss-Newton iteration starts once ``stop()`` says so (the caller's clock): the
    solution so far is returned, and ``stats["optimize_cut"]`` counts it."""
    a, b, z, info = held_edges(kf_poses, cfg, jump_edges, chain_keep, extra)
    start = kf_poses if x0 is None else x0
    if not loops and not jump_edges and extra is None:
        return start.copy()
    la = np.array([lp.old for lp in loops], dtype=int)
    lb = np.array([lp.new for lp in loops], dtype=int)
    lz = np.array([lp.z for lp in loops], dtype=float).reshape(-1, 3)
    li = np.array([lp.info for lp in loops], dtype=float).reshape(-1, 3, 3)
    keep = np.ones(len(la), bool)
    # a wide kernel first, then narrower: loops far from the initial path (a large drift) must
    # pull it before the narrow kernel may call the ones that still disagree outliers
    kernels = (cfg.robust_wide_k, np.sqrt(cfg.robust_wide_k * cfg.robust_k), cfg.robust_k)
    for _round in range(3):
        x = start.copy()
        for k in kernels[-1:] if warm else kernels:
            x = posegraph.optimize(
                x,
                np.concatenate([a, la[keep]]),
                np.concatenate([b, lb[keep]]),
                np.vstack([z, lz[keep]]),
                np.vstack([info, li[keep]]),
                iterations=10,
                robust_from=len(a),
                robust_k=k,
                stop=stop,
            )
            cut = stop is not None and stop()
            if cut:
                break
        if cut:
            stats["optimize_cut"] = stats.get("optimize_cut", 0) + 1
            break
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
    step = relative(kf_poses[:-1], kf_poses[1:])
    arc = np.concatenate([[0.0], np.cumsum(np.hypot(step[:, 0], step[:, 1]))])
    for p in range(cfg.passes):  # the first pass searches as wide as the path may have drifted;
        # later ones search from the corrected path, near where its loops pulled it
        found = find_loops(
            stamps_s[kf], kf_poses, kf_points, cfg, stats, new if p else None, skip, None if p else arc
        )
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
