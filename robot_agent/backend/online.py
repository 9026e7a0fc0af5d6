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
from dataclasses import dataclass, field

import numpy as np

from robot_agent.slam.backend import (
    BackendConfig,
    Loop,
    follow_keyframes,
    match_loop,
    near_old_keyframes,
    optimize,
    path_drift,
)
from robot_agent.slam.extraction import voxel_thin
from shared.geometry import compose, relative, wrap_angle


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
class Correction:
    """What the back end says about the path: scans ``kf_scan (K,)`` were at ``filter (K,3)`` on
    the filter's path and are at ``corrected (K,3)``. Every scan moves rigidly with the last
    keyframe at or before it (scans after the last keyframe with the last)."""

    kf_scan: np.ndarray
    filter: np.ndarray
    corrected: np.ndarray
    loops: int = 0

    def apply(self, poses: np.ndarray) -> np.ndarray:
        """The corrected path ``(S,3)`` of the filter's path ``poses (S,3)`` (of this run: scan
        ``i`` is ``poses[i]``), which may reach past the last keyframe."""
        if len(self.kf_scan) == 0:
            return np.array(poses, dtype=float, copy=True)
        return follow_keyframes(poses, self.kf_scan, self.filter, self.corrected)

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
    _jump_edges: dict = field(default_factory=dict)  # chain edge -> motion across a jump
    _surprises: list[Loop] = field(default_factory=list)  # loops the estimate contradicts, waiting
    _waiting: int = 0

    @property
    def keyframes(self) -> int:
        return len(self.kf_scan)

    def correction(self) -> Correction:
        return Correction(np.asarray(self.kf_scan, int), self._ref.copy(), self._x.copy(), len(self.loops))

    def update(
        self,
        track: Track,
        points_of: Callable[[int], np.ndarray],
        kf_poses: np.ndarray | None = None,
        hints: list[tuple[int, np.ndarray]] | None = None,
        requeries: int | None = None,
    ) -> Correction:
        """One step over the filter's best path as it is now. ``track``: that path over the scans
        from the last keyframe on (or the whole path); ``points_of(i)`` scan ``i``'s points in
        the robot frame (asked once per new keyframe); ``kf_poses (K,3)``: the path's poses at the
        keyframes so far (default: looked up in ``track``, which must then hold them);
        ``hints``: the filter's relocalizations since the last update (``(scan, pose)``).
        ``requeries``: at most this many moved keyframes are searched again (default
        ``cfg.online_requeries``; ``-1``: all)."""
        t0 = time.perf_counter()
        cfg = self.cfg
        if len(track.scan) == 0:
            return self.correction()
        k_prev = len(self.kf_scan)
        old = kf_poses if kf_poses is not None else track.at(np.asarray(self.kf_scan, int))
        if len(old) != k_prev:
            raise ValueError(f"kf_poses: {len(old)} poses for {k_prev} keyframes")
        f = np.vstack([old.reshape(-1, 3), self._extend(track, points_of)])
        kf = np.asarray(self.kf_scan, int)
        est = self._carry(f, k_prev)
        stamps = np.asarray(self.kf_stamp)
        step = relative(f[:-1], f[1:])
        arc = np.concatenate([[0.0], np.cumsum(np.hypot(step[:, 0], step[:, 1]))])

        found: list[Loop] = []
        for i, pose in hints or []:
            found += self._hinted(f, kf, track, stamps, int(i), pose)
        for new in range(k_prev, len(kf)):  # the new keyframes, searched as wide as they may drift
            if new % cfg.check_every:
                continue
            found += self._query(f, est, stamps, new, arc)
        accepted = self._admit(found, est, final=requeries == -1)
        changed = accepted > 0 or len(self._jump_edges) != self.stats.get("jumps", 0)
        self.stats["jumps"] = len(self._jump_edges)
        if changed:
            est = optimize(f, self.loops, cfg, self.stats, self._jump_edges, x0=est)
            self.stats["optimizations"] = self.stats.get("optimizations", 0) + 1
        budget = cfg.online_requeries if requeries is None else requeries
        passes = 0
        while changed and passes < (cfg.passes if budget < 0 else 1):
            # keyframes without a loop that the correction moved: searched again, narrow
            passes += 1
            more = self._requery(f, est, stamps, budget)
            if not self._admit(more, est, final=budget < 0):
                break
            est = optimize(f, self.loops, cfg, self.stats, self._jump_edges, x0=est)
            if budget < 0 and len(more) < cfg.min_pass_loops:
                break
        self._ref, self._x = f, est
        self.stats["keyframes"] = len(kf)
        self.stats["loops"] = len(self.loops)
        self.stats["updates"] = self.stats.get("updates", 0) + 1
        dt = time.perf_counter() - t0
        self.stats["update_s_total"] = self.stats.get("update_s_total", 0.0) + dt
        self.stats["update_s_max"] = max(self.stats.get("update_s_max", 0.0), dt)
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
        if self._surprises and (final or len(self._surprises) >= self.cfg.online_surprises):
            self.loops += self._surprises
            admitted += len(self._surprises)
            self._surprises = []
        self._waiting = len(self._surprises)
        self.stats["surprises_waiting"] = self._waiting
        return admitted

    def _extend(self, track: Track, points_of) -> np.ndarray:
        """New keyframes from ``track`` after the last one (one every keyframe_m / keyframe_rad
        of the path, one at each of the filter's jumps, whose chain edge is then the path up to
        the scan before it and odometry across it); their poses ``(N,3)``."""
        cfg = self.cfg
        added: list[np.ndarray] = []
        t0 = 0
        if not self.kf_scan:
            self._add(track, 0, points_of)
            added.append(track.poses[0])
        else:
            t0 = int(np.searchsorted(track.scan, self.kf_scan[-1]))
            if t0 >= len(track.scan) or track.scan[t0] != self.kf_scan[-1]:
                raise ValueError(f"track: starts after the last keyframe (scan {self.kf_scan[-1]})")
        last_t = t0
        for t in range(t0 + 1, len(track.scan)):
            d = relative(track.poses[last_t], track.poses[t])
            jump = bool(track.jumps[t])
            if jump or np.hypot(d[0], d[1]) >= cfg.keyframe_m or abs(d[2]) >= cfg.keyframe_rad:
                if jump:  # chain edge (previous keyframe -> this one)
                    across = relative(track.odometry[t - 1], track.odometry[t])
                    self._jump_edges[len(self.kf_scan) - 1] = compose(
                        relative(track.poses[last_t], track.poses[t - 1]), across
                    )
                self._add(track, t, points_of)
                added.append(track.poses[t])
                last_t = t
        return np.array(added).reshape(-1, 3)

    def _add(self, track: Track, t: int, points_of) -> None:
        i = int(track.scan[t])
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
        """A new keyframe: candidates near it on the filter's path, widened by the drift that path
        may hold since them, each searched that wide around the filter's path (not around the
        correction so far: a wrong loop there would steer the search away from the right place)."""
        self._queried[new], self._queried_at[new] = True, est[new]
        out = []
        for old in self._candidates(f, stamps, new, arc):
            drift = path_drift(arc, old, new, self.cfg)
            loop = match_loop(f, self.kf_points, old, new, self.cfg, self.stats, None, drift)
            if loop is not None:
                out.append(loop)
        return out

    def _requery(self, f, est, stamps, budget: int) -> list[Loop]:
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
        for new in idx:
            self._queried_at[new] = est[new]
            for old in self._candidates(est, stamps, int(new)):
                loop = match_loop(f, self.kf_points, old, int(new), cfg, self.stats, est)
                if loop is not None:
                    out.append(loop)
        self.stats["requeried"] = self.stats.get("requeried", 0) + len(idx)
        return out
