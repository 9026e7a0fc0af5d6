"""The pose-graph back end while the robot runs: keyframes and loops found as they come, the graph
re-optimized in bounded steps, the correction applied to the filter's path at any moment.

The filter's best path is locally right and globally drifting, and its recent part may still
change (resampling picks another lineage). Each :meth:`OnlineBackend.update` takes that path as
it is now and

1. extends the keyframes (scan indices, fixed once chosen; each keeps its thinned scan points);
2. rebuilds the chain edges from the path's relative motions between keyframes (odometry across
   the filter's relocalization jumps, loosely);
3. carries the last solution over: every keyframe keeps its correction, new ones follow the last;
4. queries the new keyframes for loops (the filter's new relocalizations first), searching as wide
   as the path since the old keyframe may have drifted; a loop is a measured relative pose between
   two scans, valid whatever lineage the filter settles on, and is kept for good;
5. re-optimizes when loops came in, warm-started, then re-queries (narrow, around the corrected
   path) a bounded number of keyframes that the correction moved and that have no loop yet.

The result is a :class:`Correction`: keyframe scans, the filter's poses there and the corrected
poses — small, immutable, applied to any later path of the same run (:meth:`Correction.apply`).
Keyframe indices are positions in the lists below; loops refer to them.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np
from scipy.spatial import cKDTree

from robot_agent.slam import posegraph
from robot_agent.slam.backend import (
    BackendConfig,
    Loop,
    follow_keyframes,
    held_edges,
    match_loop,
    near_old_keyframes,
    optimize,
    path_drift,
    start_gauge,
)
from shared.geometry import compose, inverse, relative, wrap_angle
from shared.scanmatch import voxel_thin


@dataclass(frozen=True)
class Track:
    """The filter's best path over scans ``scan (T,)`` (increasing indices into the run):
    ``stamps_s (T,)``, ``poses (T,3)``, raw ``odometry (T,3)`` and ``jumps (T,)`` (the scan was
    reached by a relocalization's jump, :meth:`FastSLAM.best_jumps`)."""

    scan: np.ndarray
    stamps_s: np.ndarray
    poses: np.ndarray
    odometry: np.ndarray
    jumps: np.ndarray

    @classmethod
    def whole(cls, stamps_s, poses, odometry, jumps=None) -> Track:
        """The path of scans ``0 .. S-1``."""
        n = len(poses)
        jumps = np.zeros(n, bool) if jumps is None else np.asarray(jumps, bool)
        return cls(np.arange(n), np.asarray(stamps_s), np.asarray(poses), np.asarray(odometry)[:n], jumps)

    def at(self, scans: np.ndarray) -> np.ndarray:
        """Poses ``(N,3)`` of scans ``scans (N,)``, which the track must hold."""
        t = np.searchsorted(self.scan, scans)
        if np.any(t >= len(self.scan)) or np.any(self.scan[np.minimum(t, len(self.scan) - 1)] != scans):
            raise ValueError("track: a keyframe's scan is not in it (pass kf_poses)")
        return self.poses[t]


@dataclass(frozen=True)
class Graph:
    """The back end's pose graph as last solved: keyframes ``scan (K,)`` (their identities: scan
    indices of the run), ``stamp_s (K,)``, solved poses ``pose (K,3)``; edges ``a, b (E,)``
    between keyframe scans, each measuring ``z (E,3)`` (b's pose in a's frame) with information
    ``info (E,3,3)``."""

    scan: np.ndarray
    stamp_s: np.ndarray
    pose: np.ndarray
    a: np.ndarray
    b: np.ndarray
    z: np.ndarray
    info: np.ndarray
    new_scan: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))  # keyframes (scans)
    new_points: tuple = ()  # ... added since the last graph handed out, and their points (robot
    # frame, float32, at most SCAN_POINTS each, evenly thinned): the fleet graph matches them


SCAN_POINTS = 64  # points of a keyframe's scan handed out with the graph (an Intel piece's cross-robot
# constraints on 64 points per keyframe, in centimetres, as on all ~140: 0.0268 m against 0.0269 m)


def scan_sample(points: np.ndarray, n: int = SCAN_POINTS) -> np.ndarray:
    """At most ``n`` of ``points (K,2)``, evenly along the scan, as float32."""
    if len(points) > n:
        points = points[np.unique(np.linspace(0, len(points) - 1, n).astype(int))]
    return np.asarray(points, np.float32)


@dataclass(frozen=True)
class Correction:
    """What the back end says about the path: scans ``kf_scan (K,)`` were at ``filter (K,3)`` on
    the filter's path and are at ``corrected (K,3)``. Every scan moves rigidly with the last
    keyframe at or before it (scans after the last keyframe with the last)."""

    kf_scan: np.ndarray
    filter: np.ndarray
    corrected: np.ndarray
    loops: int = 0
    graph_scan: np.ndarray | None = None  # the keyframes still in the graph (default: kf_scan),
    # whose poses on the filter's path the back end asks for at its next update
    follows: np.ndarray | None = None  # (K,) the scan of the keyframe in the graph each keyframe
    # moves with (itself, or the one it retired onto; default: itself)
    graph: Graph | None = None  # the graph as solved (what the server's fleet graph takes in)
    gauge: np.ndarray | None = None  # (3,) what ``corrected`` was moved by, on the left, after the
    # solve (OnlineBackend.gauge: the start where the first keyframe's own scan puts it); None: none
    solved: np.ndarray | None = None  # (K,3) ``corrected`` as the solve left it (with a gauge)

    def ungauged(self) -> Correction:
        """This correction without its gauge (``corrected`` as the solve left it)."""
        if self.gauge is None:
            return self
        return replace(self, corrected=self.solved, gauge=None, solved=None)

    def anchors(self, scans: np.ndarray) -> np.ndarray:
        """The graph keyframe (its scan) that each of ``scans`` moves with; -1 with no keyframes."""
        scans = np.asarray(scans)
        if len(self.kf_scan) == 0:
            return np.full(scans.shape, -1, np.int64)
        k = np.maximum(np.searchsorted(self.kf_scan, scans, side="right") - 1, 0)
        return (self.kf_scan if self.follows is None else self.follows)[k].astype(np.int64)

    def apply(self, poses: np.ndarray, first: int = 0) -> np.ndarray:
        """The corrected path ``(S,3)`` of the filter's path ``poses (S,3)`` (of this run: scan
        ``first + i`` is ``poses[i]``), which may reach past the last keyframe."""
        if len(self.kf_scan) == 0:
            return np.array(poses, dtype=float, copy=True)
        lo = max(int(np.searchsorted(self.kf_scan, first, side="right")) - 1, 0)
        index = self.kf_scan[lo:] - first
        index[0] = min(index[0], 0)
        return follow_keyframes(poses, index, self.filter[lo:], self.corrected[lo:])

    def pose(self, scan: int, pose: np.ndarray) -> np.ndarray:
        """The corrected pose of scan ``scan``, at ``pose`` on the filter's path."""
        if len(self.kf_scan) == 0:
            return np.array(pose, dtype=float, copy=True)
        k = max(int(np.searchsorted(self.kf_scan, scan, side="right")) - 1, 0)
        return compose(self.corrected[k], relative(self.filter[k], pose))


@dataclass
class OnlineBackend:
    cfg: BackendConfig
    kf_scan: list[int] = field(default_factory=list)
    kf_stamp: list[float] = field(default_factory=list)
    kf_points: list[np.ndarray] = field(default_factory=list)
    loops: list[Loop] = field(default_factory=list)
    stats: dict = field(default_factory=dict)
    _ref: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))  # filter poses, last update
    _x: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))  # corrected poses, last update
    _queried_at: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))  # estimate when queried
    _queried: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))
    _jump_edges: dict = field(default_factory=dict)  # id of the keyframe after a jump -> the
    # motion from the keyframe before it (path, then odometry across the jump)
    _surprises: list[Loop] = field(default_factory=list)  # loops the estimate contradicts, waiting
    kf_arc: list[float] = field(default_factory=list)  # length of the filter's path up to each
    kf_id: list[int] = field(default_factory=list)  # each keyframe's identity: positions change
    # when older keyframes retire, identities do not
    _broken_in: set = field(default_factory=set)  # ids whose chain edge from the keyframe before
    # was carried over to retired ones' anchors (a virtual edge instead)
    _virtual: dict = field(default_factory=dict)  # (id a, id b) -> (z (3,), cov (3,3)): edges
    # carried over from retired keyframes, held like the chain
    _ret_scan: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))  # retired
    # keyframes: scan, ...
    _ret_anchor: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))  # ... the
    # keyframe (id) it follows, ...
    _ret_rel: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))  # ... its pose in that
    # one's frame, ...
    _ret_filter: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))  # ... its filter pose
    _waiting: int = 0
    _flushed: bool = False  # the last _admit let waiting surprises in
    _handed: int = -1  # the newest keyframe (scan) whose points a graph handed out
    gauge: np.ndarray = field(default_factory=lambda: np.zeros(3))  # the published frame moved by
    # this (on the left): the map held where the first keyframe's own scan puts the start
    # (BackendConfig.gauge, start_gauge); kept as it last was once that keyframe retires

    @property
    def keyframes(self) -> int:
        return len(self.kf_scan)

    def correction(self) -> Correction:
        """The keyframes in the graph and the retired ones (each following the keyframe it
        retired to), in scan order."""
        active = np.asarray(self.kf_scan, int)
        graph = self.graph()
        gauge = self.gauge.copy() if np.any(self.gauge) else None
        anchor = np.searchsorted(np.asarray(self.kf_id, np.int64), self._ret_anchor)
        scans = np.concatenate([active, self._ret_scan])
        filt = np.vstack([self._ref, self._ret_filter])
        order = np.argsort(scans, kind="stable")
        corr = np.vstack([self._x, compose(self._x[anchor], self._ret_rel)])[order]
        follows = np.concatenate([active, active[anchor]])
        solved = None if gauge is None else corr
        return Correction(
            scans[order], filt[order], self._published(corr), len(self.loops), active, follows[order], graph,
            gauge, solved,
        )  # fmt: skip

    def update(
        self,
        track: Track,
        points_of: Callable[[int], np.ndarray],
        kf_poses: np.ndarray | None = None,
        hints: list[tuple[int, np.ndarray]] | None = None,
        requeries: int | None = None,
        keep: tuple[np.ndarray, int] | None = None,
        late_jumps: list[tuple[int, np.ndarray, np.ndarray]] | None = None,
    ) -> Correction:
        """One step over the filter's best path as it is now. ``track``: that path over the scans
        from the last keyframe on (or the whole path); ``points_of(i)`` scan ``i``'s points in
        the robot frame (asked once per new keyframe); ``kf_poses (K,3)``: the path's poses at the
        keyframes so far (default: looked up in ``track``, which must then hold them);
        ``hints``: the filter's relocalizations since the last update (``(scan, pose)``).
        ``requeries``: at most this many moved keyframes are searched again (default
        ``cfg.online_requeries``; ``-1``: all). ``keep``: ``(scans, first)``, the only scans
        the caller will still ask corrections of — ``scans`` (its map's elements were made
        from them) and every scan from ``first`` on; a retired keyframe that none of them
        follows is forgotten (default: every retired keyframe is kept). ``late_jumps``: the
        filter's relocalization jumps on the path between keyframes made before it had them
        (``(scan, pose before, pose at)``, the filter's poses at the scan before and at it):
        :meth:`_late_jumps`."""
        t0 = time.perf_counter()
        cfg = self.cfg
        if len(track.scan) == 0:
            return self.correction()
        k_prev = len(self.kf_scan)
        old = kf_poses if kf_poses is not None else track.at(np.asarray(self.kf_scan, int))
        if len(old) != k_prev:
            raise ValueError(f"kf_poses: {len(old)} poses for {k_prev} keyframes")
        self._late_jumps(old.reshape(-1, 3), late_jumps or [])
        f = np.vstack([old.reshape(-1, 3), self._extend(track, points_of)])
        kf = np.asarray(self.kf_scan, int)
        est = self._carry(f, k_prev)
        stamps = np.asarray(self.kf_stamp)
        arc = np.asarray(self.kf_arc)

        found: list[Loop] = []
        for i, pose in hints or []:
            found += self._hinted(f, kf, track, stamps, int(i), pose)
        for new in range(k_prev, len(kf)):  # the new keyframes, searched as wide as they may drift
            if new % cfg.check_every:
                continue
            found += self._query(f, est, stamps, new, arc)
        final = requeries == -1
        accepted = self._admit(found, est, final=final)
        jumped = len(self._jump_edges) != self.stats.get("jumps", 0)
        changed = accepted > 0 or jumped
        self.stats["jumps"] = len(self._jump_edges)
        warm = not (final or jumped or self._flushed)
        if changed:
            est = self._optimize(f, est, warm, bounded=not final)
            self.stats["optimizations"] = self.stats.get("optimizations", 0) + 1
            self.stats["optimizations_warm"] = self.stats.get("optimizations_warm", 0) + int(warm)
        budget = cfg.online_requeries if requeries is None else requeries
        deadline = t0 + cfg.online_budget_s if budget >= 0 and cfg.online_budget_s > 0 else np.inf
        passes = 0
        while changed and passes < (cfg.passes if budget < 0 else 1):
            # keyframes without a loop that the correction moved: searched again, narrow
            passes += 1
            more = self._requery(f, est, stamps, budget, deadline)
            if not self._admit(more, est, final=budget < 0):
                break
            est = self._optimize(f, est, warm and not self._flushed, bounded=not final)
            if budget < 0 and len(more) < cfg.min_pass_loops:
                break
        self._ref, self._x = f, est
        self._gauge_start()
        self._retire()
        if keep is not None:
            self._forget(*keep)
        self.stats["keyframes"] = len(self.kf_scan)
        self.stats["retired"] = len(self._ret_scan)
        self.stats["virtual_edges"] = len(self._virtual)
        self.stats["loops"] = len(self.loops)
        self.stats["updates"] = self.stats.get("updates", 0) + 1
        dt = time.perf_counter() - t0
        self.stats["update_s_total"] = self.stats.get("update_s_total", 0.0) + dt
        self.stats["update_s_max"] = max(self.stats.get("update_s_max", 0.0), dt)
        self.stats["update_s_last"] = dt
        return self.correction()

    def finish(self, *args, **kwargs) -> Correction:
        """The last update of a run: moved keyframes all re-searched, pass after pass, as the
        offline back end does."""
        return self.update(*args, **kwargs, requeries=-1)

    # --- the steps ---------------------------------------------------------------------------

    def _admit(self, found: list[Loop], est: np.ndarray, final: bool = False) -> int:
        """Loops into the graph; how many. A loop that the current estimate contradicts (beyond
        max_loop_chi) is a surprise: one or two surprises may be one aliased place (doorways
        alike along a corridor) that nothing yet outvotes, so surprises wait until
        ``online_surprises`` of them have come (or the run ends) and go in together, where the
        robust optimization sorts the right from the wrong by their majority."""
        for lp in found:
            r = relative(est[lp.old], est[lp.new]) - lp.z
            r[2] = wrap_angle(r[2])
            chi = np.sqrt(float(r @ lp.info @ r) / 3.0)
            (self._surprises if chi > self.cfg.max_loop_chi else self.loops).append(lp)
        admitted = len(found) - (len(self._surprises) - self._waiting)
        self._flushed = bool(self._surprises) and (final or len(self._surprises) >= self.cfg.online_surprises)
        if self._flushed:
            self.loops += self._surprises
            admitted += len(self._surprises)
            self._surprises = []
        self._waiting = len(self._surprises)
        self.stats["surprises_waiting"] = self._waiting
        self.stats["loops_admitted"] = self.stats.get("loops_admitted", 0) + admitted
        return admitted

    def _optimize(self, f: np.ndarray, est: np.ndarray, warm: bool = False, bounded: bool = True):
        """The graph: the chain between keyframes (but where retired ones were: their edges,
        carried over to the keyframes they retired to), the jumps, the loops; from ``est``, by the
        narrow kernel alone when ``warm`` (the new loops agree with it), within
        online_optimize_s when ``bounded`` (not at the end of the run)."""
        jumps, keep, extra = self._held()
        limit = self.cfg.online_optimize_s
        stop = None
        if limit > 0 and bounded:
            deadline = time.perf_counter() + limit
            stop = lambda: time.perf_counter() > deadline  # noqa: E731
        return optimize(
            f, self.loops, self.cfg, self.stats, jumps, x0=est, chain_keep=keep, extra=extra, warm=warm,
            stop=stop,
        )  # fmt: skip

    def _held(self) -> tuple[dict, np.ndarray, tuple | None]:
        """What the graph holds like the chain, in keyframe positions: the jumps' edges, which
        chain edges stay (``chain_keep``), the edges carried over from retired keyframes."""
        pos = {k: p for p, k in enumerate(self.kf_id)}
        jumps = {pos[k] - 1: motion for k, motion in self._jump_edges.items() if k in pos and pos[k] > 0}
        keep = np.array([k not in self._broken_in for k in self.kf_id[1:]], bool)
        extra = None
        if self._virtual:
            pairs = list(self._virtual.items())
            a = np.array([pos[i] for (i, _), _ in pairs], int)
            b = np.array([pos[j] for (_, j), _ in pairs], int)
            z = np.array([v[0] for _, v in pairs]).reshape(-1, 3)
            info = np.linalg.inv(np.array([v[1] for _, v in pairs]).reshape(-1, 3, 3))
            extra = (a, b, z, info)
        return jumps, keep, extra

    def graph(self) -> Graph | None:
        """The graph as last solved (None before the first update): its keyframes, their solved
        poses, every edge held like the chain and the loops that the solution keeps (normalized
        residual within max_loop_chi); and the points of the keyframes no graph handed out before
        (each call hands them out once: :meth:`correction` calls it once an update)."""
        if len(self._ref) != len(self.kf_scan) or not len(self.kf_scan):
            return None
        a, b, z, info = held_edges(self._ref, self.cfg, *self._held())
        if self.loops:
            la = np.array([lp.old for lp in self.loops], int)
            lb = np.array([lp.new for lp in self.loops], int)
            lz = np.array([lp.z for lp in self.loops], float).reshape(-1, 3)
            li = np.array([lp.info for lp in self.loops], float).reshape(-1, 3, 3)
            r = relative(self._x[la], self._x[lb]) - lz
            r[:, 2] = wrap_angle(r[:, 2])
            ok = np.sqrt(posegraph.mahalanobis2(r, li) / 3.0) <= self.cfg.max_loop_chi
            a, b = np.concatenate([a, la[ok]]), np.concatenate([b, lb[ok]])
            z, info = np.vstack([z, lz[ok]]), np.vstack([info, li[ok]])
        scan = np.asarray(self.kf_scan, np.int64)
        new = np.flatnonzero(scan > self._handed)
        self._handed = int(scan[-1]) if len(scan) else self._handed
        points = tuple(scan_sample(self.kf_points[i]) for i in new)
        return Graph(
            scan,
            np.asarray(self.kf_stamp, float),
            self._published(self._x.copy()),
            scan[a],
            scan[b],
            z,
            info,
            scan[new],
            points,
        )

    def _published(self, x: np.ndarray) -> np.ndarray:
        """Solved keyframe poses ``x (K,3)`` as published: moved by the gauge (``x`` itself without one)."""
        return compose(self.gauge, x) if np.any(self.gauge) else x

    def _gauge_start(self) -> None:
        """The gauge from the first keyframe's own scan on the others' (start_gauge), while that
        keyframe is in the graph: the frame moved so that it sits where its scan puts it."""
        if not self.cfg.gauge or not self.kf_id or self.kf_id[0] != 0:
            return
        at = start_gauge(self._x, self.kf_points, self.cfg)
        if at is not None:
            self.gauge = compose(self._x[0], inverse(at))
            self.stats["gauge"] = [float(v) for v in self.gauge]  # (m, m, rad)

    def _retire(self) -> None:
        """Keyframes older than the window leave the graph (:meth:`_retire_onto`): those that the
        corrected path puts within online_retire_m / _rad of a keyframe at least
        min_gap_keyframes older, near a loop (their place is known, and they are tied to it:
        the robot passing a known place again adds nothing to it for good); and, while the graph
        holds more than online_max_keyframes, those nearest an older keyframe (:meth:`_thin`)."""
        cfg = self.cfg
        n = len(self.kf_scan)
        limit = n - cfg.online_window
        if limit <= 1:
            return
        x = self._x
        ids = list(self.kf_id)
        pos = {k: p for p, k in enumerate(ids)}
        after_jump = [pos[k] for k in self._jump_edges if k in pos]
        fixed = {0} | set(after_jump) | {p - 1 for p in after_jump}  # a jump's two ends stay
        targets: dict[int, tuple[int, np.ndarray]] = {}
        if self.loops and cfg.online_retire_m > 0:
            near_loop = np.zeros(n, bool)
            for lp in self.loops:
                near_loop[max(lp.new - 2, 0) : lp.new + 3] = True
            tree = cKDTree(x[:limit, :2])
            cand = [k for k in np.flatnonzero(near_loop[1:limit]) + 1 if k not in fixed]
            near = tree.query_ball_point(x[cand, :2], cfg.online_retire_m) if cand else []
            # oldest first: a keyframe retired in this pass is no anchor for a later one
            for k, around in zip(cand, near, strict=True):
                older = np.array(
                    [j for j in around if j <= k - cfg.min_gap_keyframes and j not in targets], int
                )
                if len(older) == 0:
                    continue
                rel = relative(x[older], x[k])
                d = np.hypot(rel[:, 0], rel[:, 1])
                d[np.abs(rel[:, 2]) >= cfg.online_retire_rad] = np.inf
                best = int(np.argmin(d))
                if np.isfinite(d[best]):
                    targets[int(k)] = (int(older[best]), rel[best])
        thinned = 0
        if cfg.online_max_keyframes and n - len(targets) > cfg.online_max_keyframes:
            thinned = self._thin(targets, fixed, limit)
        if targets:
            self._retire_onto(targets)
            self.stats["retired_thinned"] = self.stats.get("retired_thinned", 0) + thinned

    def _thin(self, targets: dict, fixed: set, limit: int) -> int:
        """More retirements into ``targets``, until the graph keeps 90 % of online_max_keyframes:
        keyframes older than the window, each onto its nearest older keyframe (the distance in
        the plane plus the turn, weighed as online_retire_m to online_retire_rad), nearest first —
        the graph thinned where it is densest, every place it covers still covered."""
        cfg = self.cfg
        x = self._x[:limit]
        n_graph = len(self.kf_scan) - len(targets)
        excess = n_graph - int(0.9 * cfg.online_max_keyframes)
        thinned = 0
        cand = np.array([k for k in range(1, limit) if k not in fixed and k not in targets], int)
        if excess <= 0 or len(cand) == 0:
            return 0
        anchors = {j for j, _ in targets.values()}
        per_rad = cfg.online_retire_m / max(cfg.online_retire_rad, 1e-9)
        k_near = min(16, limit)
        _, near = cKDTree(x[:, :2]).query(x[cand, :2], k=k_near)
        near = np.asarray(near).reshape(len(cand), -1)
        older = near < cand[:, None]
        rel = relative(x[near].reshape(-1, 3), np.repeat(x[cand], near.shape[1], axis=0))
        d = (np.hypot(rel[:, 0], rel[:, 1]) + per_rad * np.abs(rel[:, 2])).reshape(near.shape)
        d[~older] = np.inf
        best = np.argmin(d, axis=1)
        dist = d[np.arange(len(cand)), best]
        for c in np.argsort(dist):
            if excess <= 0 or not np.isfinite(dist[c]):
                break
            k, j = int(cand[c]), int(near[c, best[c]])
            if k in anchors or j in targets:
                continue
            targets[k] = (j, relative(x[j], x[k]))
            anchors.add(j)
            excess -= 1
            thinned += 1
        return thinned

    def _retire_onto(self, targets: dict) -> None:
        """Keyframes ``targets`` (position -> (older position it follows, its pose in that one's
        frame)) leave the graph. A retired keyframe's scans follow the older one rigidly; its
        edges are carried over to that one (chain and virtual edges composed with the offset
        between the two, one edge per pair of keyframes: the stronger), loops from it as well;
        its own loops, which tied it there, go with it."""
        cfg = self.cfg
        n = len(self.kf_scan)
        ids = list(self.kf_id)
        gone = np.zeros(n, bool)
        cov_rel = np.diag([cfg.loop_sigma_xy_m**2, cfg.loop_sigma_xy_m**2, cfg.loop_sigma_theta_rad**2])
        ret_anchor = self._ret_anchor.copy()
        ret_rel = self._ret_rel.copy()
        new_scan, new_anchor, new_rel, new_filter = [], [], [], []
        for k in sorted(targets):
            j, rel = targets[k]
            ik, ij = ids[k], ids[j]
            prev = next(p for p in range(k - 1, -1, -1) if not gone[p])
            nxt = next((p for p in range(k + 1, n) if not gone[p]), None)
            # the chain edges into and out of k become edges of their own ...
            if ik not in self._broken_in:
                self._add_virtual(ids[prev], ik, relative(self._ref[prev], self._ref[k]), None)
            if nxt is not None and ids[nxt] not in self._broken_in:
                self._add_virtual(ik, ids[nxt], relative(self._ref[k], self._ref[nxt]), None)
                self._broken_in.add(ids[nxt])
            self._broken_in.discard(ik)
            # ... and every edge of k is carried over to j
            for (a, b), (z, cov) in list(self._virtual.items()):
                if ik not in (a, b):
                    continue
                del self._virtual[(a, b)]
                if a == ik:  # k -> b: j -> b
                    z2, cov2 = compose(rel, z), _rotated(cov, rel[2]) + cov_rel
                    a = ij
                else:  # a -> k: a -> j
                    z2, cov2 = compose(z, inverse(rel)), cov + cov_rel
                    b = ij
                if a != b:
                    self._add_virtual(a, b, z2, cov2)
            new_scan.append(self.kf_scan[k])
            new_anchor.append(ij)
            new_rel.append(rel)
            new_filter.append(self._ref[k])
            follow = np.flatnonzero(ret_anchor == ik)  # those that followed k now follow j
            ret_anchor[follow] = ij
            ret_rel[follow] = compose(rel, ret_rel[follow])
            gone[k] = True
        self._ret_scan = np.concatenate([self._ret_scan, np.asarray(new_scan, np.int64)])
        self._ret_anchor = np.concatenate([ret_anchor, np.asarray(new_anchor, np.int64)])
        self._ret_rel = np.vstack([ret_rel, np.asarray(new_rel).reshape(-1, 3)])
        self._ret_filter = np.vstack([self._ret_filter, np.asarray(new_filter).reshape(-1, 3)])
        newpos = np.cumsum(~gone) - 1

        def moved(lp: Loop) -> Loop | None:
            if gone[lp.new]:
                return None
            old, z, info = lp.old, lp.z, lp.info
            if gone[old]:  # a loop from k: from the keyframe k follows
                j, rel = targets[old]
                z, info, old = compose(rel, z), _rotated(info, rel[2]), j
            return Loop(int(newpos[old]), int(newpos[lp.new]), z, lp.score, info, lp.inliers)

        self.loops = [m for m in map(moved, self.loops) if m is not None]
        self._surprises = [m for m in map(moved, self._surprises) if m is not None]
        self._waiting = len(self._surprises)
        keep = ~gone
        self.kf_scan = [v for v, g in zip(self.kf_scan, gone, strict=True) if not g]
        self.kf_stamp = [v for v, g in zip(self.kf_stamp, gone, strict=True) if not g]
        self.kf_points = [v for v, g in zip(self.kf_points, gone, strict=True) if not g]
        self.kf_id = [v for v, g in zip(self.kf_id, gone, strict=True) if not g]
        self.kf_arc = [v for v, g in zip(self.kf_arc, gone, strict=True) if not g]
        self._ref, self._x = self._ref[keep], self._x[keep]
        self._queried, self._queried_at = self._queried[keep], self._queried_at[keep]

    def _forget(self, scans: np.ndarray, first: int) -> None:
        """Retired keyframes that no scan of ``scans`` and none from ``first`` on follows (the
        last keyframe at or before it) are forgotten: what the retired ones hold grows with the
        run, what a caller asks about does not."""
        if not len(self._ret_scan):
            return
        active = np.asarray(self.kf_scan, np.int64)
        every = np.concatenate([active, self._ret_scan])
        order = np.argsort(every, kind="stable")
        ranked = every[order]
        asked = np.concatenate([np.asarray(scans, np.int64).ravel(), [int(first)]])
        need = np.zeros(len(every), bool)
        at = np.searchsorted(ranked, asked, side="right") - 1
        need[order[at[at >= 0]]] = True
        need[every >= first] = True
        keep = need[len(active) :]
        if keep.all():
            return
        self.stats["forgotten"] = self.stats.get("forgotten", 0) + int((~keep).sum())
        self._ret_scan, self._ret_anchor = self._ret_scan[keep], self._ret_anchor[keep]
        self._ret_rel, self._ret_filter = self._ret_rel[keep], self._ret_filter[keep]

    def _add_virtual(self, a: int, b: int, z: np.ndarray, cov: np.ndarray | None) -> None:
        """Edge ``a -> b`` (ids); ``cov`` None: a chain edge's. One per pair: the stronger."""
        if cov is None:
            cov = np.diag(1.0 / posegraph.chain_information(z[None], self.cfg.chain)[0])
        key, rev = (a, b), (b, a)
        if rev in self._virtual:  # the same pair the other way round: compare as b -> a
            z, cov, key = inverse(z), _rotated(cov, -z[2]), rev
            # (the inverse motion's covariance, rotated into b's frame: close enough to compare)
        old = self._virtual.get(key)
        if old is None or np.trace(cov) < np.trace(old[1]):
            self._virtual[key] = (np.asarray(z, float), np.asarray(cov, float))

    def _extend(self, track: Track, points_of) -> np.ndarray:
        """New keyframes from ``track`` after the last one (one every keyframe_m / keyframe_rad
        of the path, one at each of the filter's jumps, whose chain edge is then the path up to
        the scan before it and odometry across it); their poses ``(N,3)``."""
        cfg = self.cfg
        added: list[np.ndarray] = []
        t0 = 0
        if not self.kf_scan:
            self._add(track, 0, points_of, 0.0)
            added.append(track.poses[0])
        else:
            t0 = int(np.searchsorted(track.scan, self.kf_scan[-1]))
            if t0 >= len(track.scan) or track.scan[t0] != self.kf_scan[-1]:
                raise ValueError(f"track: starts after the last keyframe (scan {self.kf_scan[-1]})")
        last_t = t0
        step = relative(track.poses[:-1], track.poses[1:])
        run = np.concatenate([[0.0], np.cumsum(np.hypot(step[:, 0], step[:, 1]))])  # along the track
        base = self.kf_arc[-1] - run[t0]
        for t in range(t0 + 1, len(track.scan)):
            d = relative(track.poses[last_t], track.poses[t])
            jump = bool(track.jumps[t])
            if jump or np.hypot(d[0], d[1]) >= cfg.keyframe_m or abs(d[2]) >= cfg.keyframe_rad:
                self._add(track, t, points_of, base + run[t])
                if jump:  # the chain edge (previous keyframe -> this one)
                    across = relative(track.odometry[t - 1], track.odometry[t])
                    self._jump_edges[self.kf_id[-1]] = compose(
                        relative(track.poses[last_t], track.poses[t - 1]), across
                    )
                added.append(track.poses[t])
                last_t = t
        return np.array(added).reshape(-1, 3)

    def _late_jumps(self, f: np.ndarray, late: list[tuple[int, np.ndarray, np.ndarray]]) -> None:
        """Jumps on the filter's path between keyframes already made (``f (K,3)``: the path's
        poses at them now): the lineage they were made on had none there, and the filter's best
        lineage changed since to one that relocalized (Intel's last third, one live run: a 3 m
        jump the chain edge took as motion, holding the 190 scans before it 2-3 m off for good).
        The chain edge over each is the path up to the scan before it and from the scan at it
        on, held as loosely as a jump found when its keyframe was made (:meth:`_extend`); the
        motion across the jump itself is taken as none (one scan's, centimetres: within the jump
        edge's sigma — the odometry of scans already sent is not kept). One already held stays."""
        if not late or len(self.kf_scan) < 2:
            return
        kf = np.asarray(self.kf_scan, int)
        for scan, before, at in late:
            n = int(np.searchsorted(kf, int(scan)))  # the first keyframe at or after the jump
            if n == 0 or n >= len(kf) or self.kf_id[n] in self._jump_edges:
                continue
            self._jump_edges[self.kf_id[n]] = compose(relative(f[n - 1], before), relative(at, f[n]))
            self.stats["late_jumps"] = self.stats.get("late_jumps", 0) + 1

    def _add(self, track: Track, t: int, points_of, arc_m: float) -> None:
        i = int(track.scan[t])
        self.kf_arc.append(float(arc_m))
        self.kf_id.append(self.kf_id[-1] + 1 if self.kf_id else 0)
        self.kf_scan.append(i)
        self.kf_stamp.append(float(track.stamps_s[t]))
        self.kf_points.append(voxel_thin(points_of(i), self.cfg.voxel_m))

    def _hinted(self, f, kf, track: Track, stamps, i: int, pose: np.ndarray) -> list[Loop]:
        """A relocalization of the filter: scan ``i`` was found at ``pose`` among old elements.
        The search starts there: the drift it bridged is more than the window around the path."""
        t = int(np.searchsorted(track.scan, i))
        if t >= len(track.scan) or track.scan[t] != i:
            return []  # the path no longer holds that scan's pose (it fell out of the track)
        new = int(np.searchsorted(kf, i, side="right")) - 1  # the keyframe scan i hangs from
        est = f.copy()
        est[new] = compose(pose, relative(track.poses[t], f[new]))
        cand, d = near_old_keyframes(stamps, est, new, self.cfg)
        for old in cand[np.argsort(d[cand])][: self.cfg.candidates]:
            loop = match_loop(f, self.kf_points, int(old), new, self.cfg, self.stats, est)
            if loop is not None:
                self.stats["loops_hinted"] = self.stats.get("loops_hinted", 0) + 1
                return [loop]
        return []

    def _carry(self, f: np.ndarray, k_prev: int) -> np.ndarray:
        """The last solution on today's path: old keyframes keep their correction (their filter
        pose may have moved with a new lineage), new ones follow the last old one."""
        est = f.copy()
        if k_prev:
            est[:k_prev] = compose(self._x[:k_prev], relative(self._ref[:k_prev], f[:k_prev]))
            est[k_prev:] = compose(est[k_prev - 1], relative(f[k_prev - 1], f[k_prev:]))
        grow = len(f) - len(self._queried)
        self._queried = np.concatenate([self._queried, np.zeros(grow, bool)])
        self._queried_at = np.vstack([self._queried_at, np.zeros((grow, 3))])
        return est

    def _candidates(self, est, stamps, new, arc=None) -> list[int]:
        cfg = self.cfg
        cand, d = near_old_keyframes(stamps, est, new, cfg, arc)
        if len(cand) == 0:
            return []
        dth = np.abs(wrap_angle(est[cand, 2] - est[new, 2]))
        picked: list[int] = []
        for c in cand[np.argsort(d[cand] + 1.0 * dth)]:  # distinct places, not neighbours
            if all(abs(c - p) > 2 * cfg.cloud_neighbours for p in picked):
                picked.append(int(c))
            if len(picked) >= cfg.candidates:
                break
        return picked

    def _query(self, f, est, stamps, new, arc) -> list[Loop]:
        """A new keyframe: candidates near it, widened by the drift its estimate may hold, each
        searched that wide. First around the filter's path, as far as it may have drifted since
        the old keyframe (not around the correction so far: a wrong loop there would steer the
        search away from the right place). When that finds nothing and loops tie the path down:
        around the corrected path, as far as it may have drifted since the newest keyframe a
        loop ties — where the robot comes back to a place it passed long ago (drifted farther
        than the first search reaches) while loops since kept its estimate right."""
        self._queried[new], self._queried_at[new] = True, est[new]
        out = self._search(f, f, stamps, new, arc)
        tied = [lp.new for lp in self.loops if lp.new < new]
        if not out and tied:
            span = np.full(len(arc), arc[max(tied)])
            span[new] = arc[new]
            out = self._search(f, est, stamps, new, span)
        return out

    def _search(self, f, centre, stamps, new, span) -> list[Loop]:
        out = []
        for old in self._candidates(centre, stamps, new, span):
            drift = path_drift(span, old, new, self.cfg)
            loop = match_loop(f, self.kf_points, old, new, self.cfg, self.stats, centre, drift)
            if loop is not None:
                out.append(loop)
        return out

    def _requery(self, f, est, stamps, budget: int, deadline: float = np.inf) -> list[Loop]:
        """Moved keyframes without a loop searched again, the most moved first, at most
        ``budget`` of them (``-1``: all) and none after ``deadline`` (``time.perf_counter()``):
        those left wait for the next update."""
        cfg = self.cfg
        has_loop = np.zeros(len(f), bool)
        has_loop[[lp.new for lp in self.loops]] = True
        d = relative(self._queried_at, est)
        moved = (np.hypot(d[:, 0], d[:, 1]) >= cfg.pass_moved_m) | (np.abs(d[:, 2]) >= cfg.pass_moved_rad)
        idx = np.flatnonzero(self._queried & ~has_loop & moved)
        if budget >= 0 and len(idx) > budget:  # the most moved first
            size = np.hypot(d[idx, 0], d[idx, 1]) + np.abs(d[idx, 2])
            idx = idx[np.argsort(-size)[:budget]]
        out = []
        done = 0
        for new in idx:
            if time.perf_counter() > deadline:
                self.stats["requeries_deferred"] = self.stats.get("requeries_deferred", 0) + len(idx) - done
                break
            done += 1
            self._queried_at[new] = est[new]
            for old in self._candidates(est, stamps, int(new)):
                loop = match_loop(f, self.kf_points, old, int(new), cfg, self.stats, est)
                if loop is not None:
                    out.append(loop)
        self.stats["requeried"] = self.stats.get("requeried", 0) + done
        return out


def _rotated(m: np.ndarray, theta: float) -> np.ndarray:
    """A pose covariance or information ``(3,3)`` expressed in a frame turned by ``theta``."""
    rot = np.eye(3)
    c, s = np.cos(theta), np.sin(theta)
    rot[:2, :2] = [[c, -s], [s, c]]
    return rot @ m @ rot.T
