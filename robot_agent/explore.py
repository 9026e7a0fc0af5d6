"""Exploration controller: velocity commands from the SLAM estimate and global segment map.

Frontier exploration (Yamauchi 1997) on a coarse grid kept in the map frame, with a reactive
safety layer on the latest scan. Per call of :meth:`Explorer.command`:

1. grow the grid to cover the robot and the map;
2. mark cells seen along the scan's beams, each cut at its measured range, at the first mapped
   segment and at the sensing radius; stamp the cells around the robot as visited;
3. replan now and then (period, goal reached or no longer a frontier, stuck): rasterize the map
   into a clearance grid, block cells too close to a wall, Dijkstra from the robot over seen
   free cells, pick the nearest frontier by path cost (with hysteresis) or, once none is left,
   the least recently visited reachable place (so loops get driven again and closed);
4. pure pursuit along the path;
5. safety: the command's stopping arc must keep clear of the scan's points and nearby mapped
   segments; otherwise the closest safe command is taken (slower, swerving, or turning in place).

Everything is in the SLAM map frame: the filter's estimate, never the ground truth.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import ndimage
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import dijkstra

from shared.geometry import (
    apply_segments,
    compose,
    inverse,
    point_segment_distance,
    transform_points,
    wrap_angle,
)

# Undirected 8-neighbourhood: four offsets, the other four are their reverses.
_STEPS = np.array([[1, 0], [0, 1], [1, 1], [1, -1]])
_STEP_LEN = np.hypot(_STEPS[:, 0], _STEPS[:, 1])


class ExploreInputError(ValueError):
    """An input of the exploration controller has the wrong shape or non-finite values."""


@dataclass(frozen=True)
class ExploreConfig:
    """Exploration parameters (metres, radians, seconds).

    cell_m: grid cell size. sense_radius_m: beams mark cells seen up to this range.
    robot_radius_m / block_margin_m: cells closer than their sum to a mapped segment are blocked.
    comfort_clearance_m / clearance_cost: a cell's path cost grows linearly from 1 (at the comfort
        clearance) to ``1 + clearance_cost`` (at the blocking distance): paths keep to the middle.
    min_frontier_cells: a frontier cell needs this many frontier cells in its 3×3 block (no specks).
    min_goal_dist_m: frontier goals nearer than this to the robot are ignored (it would "reach"
        them without looking). goal_tol_m: a goal this close is reached.
    goal_clear_radius_m: cells this close to a reached or abandoned frontier goal count as seen.
    hysteresis_m: the current goal is kept while its path cost is at most this above the best.
    replan_period_s: periodic replanning. stuck_timeout_s / stuck_progress_m: a goal whose path
        cost has not dropped by the progress within the timeout is abandoned.
    visit_radius_m: cells this close to the robot are stamped visited. revisit_s_per_m: in
        revisit mode a place must be this much staler per metre of extra path to be preferred.
        revisit_min_dist_m: the nearest revisit goal. revisit_min_clearance_m: revisit goals
        keep at least this clearance.
    max_v_mps / max_w_radps / accel_mps2: commanded limits and the robot's braking ability.
    command_period_s: time until the next command (the latency the safety layer allows for).
    lookahead_m / turn_in_place_rad / turn_gain_per_s: pure pursuit; above the heading error the
        robot turns in place.
    safety_margin_m: the stopping arc keeps ``robot_radius_m + safety_margin_m`` from obstacles.
    safety_window_m: scan points and map segments farther than this are ignored by the safety layer.
    spin_w_radps: turn rate when nothing is reachable (look around, the map may grow).
    obstacle_memory_s: scan points that stopped the robot are blocked for planning this long.
    map_window_m: the grid grows to cover the map only this far from the robot.
    grid_chunk_m / max_grid_cells: grid growth step and the largest grid allowed.
    """

    cell_m: float = 0.25
    sense_radius_m: float = 3.0
    robot_radius_m: float = 0.2
    block_margin_m: float = 0.1
    comfort_clearance_m: float = 0.8
    clearance_cost: float = 3.0
    min_frontier_cells: int = 3
    min_goal_dist_m: float = 1.0
    goal_tol_m: float = 0.35
    goal_clear_radius_m: float = 0.75
    hysteresis_m: float = 1.5
    replan_period_s: float = 1.0
    stuck_timeout_s: float = 10.0
    stuck_progress_m: float = 0.3
    visit_radius_m: float = 1.0
    revisit_s_per_m: float = 2.0
    revisit_min_dist_m: float = 2.0
    revisit_min_clearance_m: float = 0.5
    max_v_mps: float = 0.6
    max_w_radps: float = 1.0
    accel_mps2: float = 0.5
    command_period_s: float = 0.2
    lookahead_m: float = 0.6
    turn_in_place_rad: float = 0.6
    turn_gain_per_s: float = 1.5
    safety_margin_m: float = 0.1
    safety_window_m: float = 2.5
    spin_w_radps: float = 0.5
    obstacle_memory_s: float = 20.0
    map_window_m: float = 100.0
    grid_chunk_m: float = 5.0
    max_grid_cells: int = 4_000_000

    def __post_init__(self) -> None:
        for name in ("cell_m", "sense_radius_m", "max_v_mps", "max_w_radps", "accel_mps2", "lookahead_m"):
            if not getattr(self, name) > 0:
                raise ValueError(f"ExploreConfig.{name} must be > 0, got {getattr(self, name)}")
        chunks = self.grid_chunk_m / self.cell_m
        if abs(chunks - round(chunks)) > 1e-9 or round(chunks) < 1:
            raise ValueError(
                f"ExploreConfig.grid_chunk_m ({self.grid_chunk_m}) must be a whole multiple of "
                f"cell_m ({self.cell_m})"
            )


# --- kernels ------------------------------------------------------------------------------------


def clearance_grid(
    seg: np.ndarray,
    origin: np.ndarray,
    shape: tuple[int, int],
    cell_m: float,
    extra: np.ndarray | None = None,
) -> np.ndarray:
    """Distance ``(NX, NY)`` from each cell centre to the nearest segment ``(G,2,2)``, on the grid:
    segments are sampled every quarter cell into occupied cells (plus the ``extra`` mask), the
    Euclidean distance transform measures centre to centre, and half a cell is taken off. The
    result overestimates the true distance by at most ``(sqrt(2)/2 - 1/2 + 1/8) cell`` (< cell/3:
    the wall may lie in a corner of its cell, the samples an eighth of a cell off it) and
    underestimates it by at most ``(sqrt(2)/2 + 1/2) cell``. inf when nothing is occupied."""
    occ = np.zeros(shape, bool) if extra is None else extra.copy()
    if len(seg):
        d = seg[:, 1] - seg[:, 0]
        n = np.maximum(np.ceil(np.hypot(d[:, 0], d[:, 1]) / (0.25 * cell_m)).astype(int), 1) + 1
        owner = np.repeat(np.arange(len(seg)), n)
        t = np.arange(n.sum()) - np.repeat(np.cumsum(n) - n, n)
        pts = seg[owner, 0] + d[owner] * (t / (n[owner] - 1))[:, None]
        ij = np.floor((pts - origin) / cell_m).astype(int)
        inside = np.all((ij >= 0) & (ij < shape), axis=1)
        occ[ij[inside, 0], ij[inside, 1]] = True
    if not occ.any():
        return np.full(shape, np.inf)
    return np.maximum(ndimage.distance_transform_edt(~occ) * cell_m - 0.5 * cell_m, 0.0)


def ray_lengths(origin: np.ndarray, dirs_rad: np.ndarray, seg: np.ndarray, max_m: np.ndarray) -> np.ndarray:
    """Length ``(B,)`` of rays from ``origin (2,)`` at ``dirs_rad (B,)`` up to the first segment
    of ``seg (G,2,2)``, at most ``max_m (B,)``. Ray ``o + t d`` meets ``a + u e`` at
    ``t = (p × e)/(d × e)``, ``u = (p × d)/(d × e)``, ``p = a - o``; a hit needs ``t > 0``, ``u in [0,1]``."""
    if len(seg) == 0:
        return max_m
    c, s = np.cos(dirs_rad)[:, None], np.sin(dirs_rad)[:, None]
    p = seg[None, :, 0] - origin
    e = seg[None, :, 1] - seg[None, :, 0]
    denom = c * e[..., 1] - s * e[..., 0]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (p[..., 0] * e[..., 1] - p[..., 1] * e[..., 0]) / denom
        u = (p[..., 0] * s - p[..., 1] * c) / denom
    hit = (t > 0) & (u >= 0) & (u <= 1)
    return np.minimum(np.where(hit, t, np.inf).min(axis=1), max_m)


def frontier_mask(seen: np.ndarray, blocked: np.ndarray, min_cells: int) -> np.ndarray:
    """Seen free cells with an unseen free 4-neighbour, kept where the 3×3 block holds at least
    ``min_cells`` of them."""
    unknown = np.pad(~seen & ~blocked, 1)
    near_unknown = unknown[:-2, 1:-1] | unknown[2:, 1:-1] | unknown[1:-1, :-2] | unknown[1:-1, 2:]
    front = seen & ~blocked & near_unknown
    count = ndimage.correlate(front.astype(np.int16), np.ones((3, 3), np.int16), mode="constant")
    return front & (count >= min_cells)


def shortest_paths(cost: np.ndarray, traversable: np.ndarray, source: tuple[int, int]):
    """Dijkstra over traversable cells (8-neighbours; an edge costs its length in cells times the
    mean cost of its two cells). Returns path cost ``(NX, NY)`` in cells (inf: unreachable) and
    the predecessor ``(NX, NY)`` flat index (-1 at the source and unreachable cells)."""
    nx, ny = cost.shape
    node = np.full(cost.shape, -1)
    flat = np.flatnonzero(traversable)
    node.flat[flat] = np.arange(len(flat))
    rows, cols, weights = [], [], []
    for (dx, dy), length in zip(_STEPS, _STEP_LEN, strict=True):
        here = (slice(max(0, -dx), nx - max(0, dx)), slice(max(0, -dy), ny - max(0, dy)))
        there = (slice(max(0, dx), nx + min(0, dx)), slice(max(0, dy), ny + min(0, dy)))
        a, b = node[here], node[there]
        ok = (a >= 0) & (b >= 0)
        rows.append(a[ok])
        cols.append(b[ok])
        weights.append(0.5 * length * (cost[here][ok] + cost[there][ok]))
    n = len(flat)
    graph = coo_matrix((np.concatenate(weights), (np.concatenate(rows), np.concatenate(cols))), (n, n))
    dist_c, pred_c = dijkstra(graph.tocsr(), directed=False, indices=node[source], return_predecessors=True)
    dist = np.full(cost.shape, np.inf)
    dist.flat[flat] = dist_c
    pred = np.full(cost.shape, -1)
    pred.flat[flat] = np.where(pred_c >= 0, flat[np.maximum(pred_c, 0)], -1)
    return dist, pred


def arc_points(v_mps: np.ndarray, w_radps: np.ndarray, length_m: np.ndarray, samples: int) -> np.ndarray:
    """Points ``(C, S, 2)`` in the robot frame along the arcs of curvature ``w/v`` driven forward
    for ``length_m`` (C,), ``S`` samples each, the last at the full length."""
    s = length_m[:, None] * np.linspace(1.0 / samples, 1.0, samples)
    k = (w_radps / np.maximum(v_mps, 1e-3))[:, None]
    with np.errstate(divide="ignore", invalid="ignore"):
        straight = np.abs(k) < 1e-6
        x = np.where(straight, s, np.sin(k * s) / k)
        y = np.where(straight, 0.0, (1.0 - np.cos(k * s)) / k)
    return np.stack([x, y], axis=-1)


def safe_command(
    v_des: float,
    w_des: float,
    v_now: float,
    points: np.ndarray,
    seg: np.ndarray,
    cfg: ExploreConfig,
) -> tuple[float, float, bool]:
    """The safe command nearest to ``(v_des, w_des)``, and whether forward motion was refused.

    ``points (N,2)`` obstacle points and ``seg (G,2,2)`` obstacle segments, robot frame. A
    candidate is driven for one command period, then braked: it sweeps ``v T + v²/2a`` along its
    arc (``v`` the larger of the candidate and the current speed). It is safe when that arc keeps
    ``robot_radius_m + safety_margin_m`` of clearance, or at least does not lose clearance
    where the robot is already closer (so it can always move away from a wall).
    """
    w_max = cfg.max_w_radps
    v = np.repeat([v_des, 0.5 * v_des, 0.0], 10)
    w = np.tile(np.append(np.linspace(-w_max, w_max, 9), w_des), 3)
    v_hi = np.maximum(v, v_now)
    length = v_hi * cfg.command_period_s + v_hi**2 / (2.0 * cfg.accel_mps2)
    arc = np.concatenate([np.zeros((len(v), 1, 2)), arc_points(v_hi, w, length, 8)], axis=1)
    stop_m = cfg.robot_radius_m + cfg.safety_margin_m
    reach = length.max() + stop_m + 0.05  # anything farther can neither be hit nor be the nearest
    points = points[np.hypot(points[:, 0], points[:, 1]) < reach]
    if len(seg):
        seg = seg[point_segment_distance(np.zeros(2), seg) < reach]
    clear = np.full(arc.shape[:2], np.inf)
    if len(points):
        diff = arc[:, :, None, :] - points[None, None]
        clear = np.minimum(clear, np.sqrt(np.min(np.sum(diff * diff, axis=-1), axis=-1)))
    if len(seg):
        clear = np.minimum(clear, point_segment_distance(arc[:, :, None, :], seg[None, None]).min(axis=-1))
    need = np.minimum(stop_m, clear[:, 0] - 1e-3)
    safe = clear[:, 1:].min(axis=1) >= need
    penalty = 2.0 * np.abs(v - v_des) / cfg.max_v_mps + np.abs(w - w_des) / w_max
    if safe.any():
        best = int(np.argmin(np.where(safe, penalty, np.inf)))
    else:  # no stop fits: brake, turning the way that keeps the most clearance
        best = int(np.argmax(np.where(v == 0.0, clear.min(axis=1), -np.inf)))
    return float(v[best]), float(w[best]), bool(v_des > 0.0 and v[best] == 0.0)


def _checked(name: str, value, shape: tuple[int | None, ...], finite: bool = True) -> np.ndarray:
    arr = np.asarray(value, dtype=float)
    if arr.ndim != len(shape) or any(s is not None and s != a for s, a in zip(shape, arr.shape, strict=True)):
        want = "(" + ", ".join("N" if s is None else str(s) for s in shape) + ")"
        raise ExploreInputError(f"{name}: expected shape {want}, got {arr.shape}")
    if finite and not np.all(np.isfinite(arr)):
        raise ExploreInputError(f"{name}: contains non-finite values")
    return arr


# --- the controller -----------------------------------------------------------------------------


class Explorer:
    """Frontier exploration on the SLAM map; :meth:`command` turns one scan into ``(v, w)``.

    State kept between calls (all in the map frame): the grid ``origin (2,)``, ``seen (NX,NY)``,
    ``visited_s (NX,NY)`` last time the robot was near each cell, the current ``goal (2,)`` and
    ``path (K,2)``, ``mode`` (``"frontier"``, ``"revisit"`` or ``"spin"``), and from the last
    plan ``blocked``, ``frontier`` and ``clearance_m`` grids.
    """

    def __init__(self, cfg: ExploreConfig = ExploreConfig()):  # frozen, so a shared default is safe
        self.cfg = cfg
        self.origin = np.zeros(2)
        self.seen = np.zeros((0, 0), bool)
        self.visited_s = np.zeros((0, 0))
        self.memory_s = np.zeros((0, 0))  # until when a cell holds a remembered scan obstacle
        self.blocked = np.zeros((0, 0), bool)
        self.frontier = np.zeros((0, 0), bool)
        self.clearance_m = np.zeros((0, 0))
        self.goal: np.ndarray | None = None
        self.path: np.ndarray | None = None
        self.mode = "spin"
        self.stats = {"replans": 0, "goals": 0, "abandoned": 0, "safety_stops": 0}
        self._t0: float | None = None
        self._last_s = -np.inf
        self._plan_s = -np.inf
        self._replan_now = True
        self._k = 0  # path index the robot has progressed to
        self._goal_cost = np.inf  # best path cost to the goal so far, and when it was reached
        self._progress_s = 0.0
        self._v_now = self._v_cmd = 0.0

    # -- grid ----------------------------------------------------------------------------------

    def cell_of(self, xy: np.ndarray) -> np.ndarray:
        """Integer cell indices ``(..., 2)`` of map points ``(..., 2)`` (may lie off the grid)."""
        return np.floor((np.asarray(xy) - self.origin) / self.cfg.cell_m).astype(int)

    def centre_of(self, ij: np.ndarray) -> np.ndarray:
        return self.origin + (np.asarray(ij) + 0.5) * self.cfg.cell_m

    def _ensure(self, lo: np.ndarray, hi: np.ndarray) -> None:
        """Grow the grid (in whole chunks) to cover the box ``lo..hi``; seen/visited are kept."""
        cfg = self.cfg
        old_hi = self.origin + np.array(self.seen.shape) * cfg.cell_m
        if self.seen.size and np.all(lo >= self.origin) and np.all(hi <= old_hi):
            return
        if self.seen.size:
            lo, hi = np.minimum(lo, self.origin), np.maximum(hi, old_hi)
        new_lo = np.floor(lo / cfg.grid_chunk_m) * cfg.grid_chunk_m
        shape = np.ceil((np.ceil(hi / cfg.grid_chunk_m) * cfg.grid_chunk_m - new_lo) / cfg.cell_m - 1e-9)
        shape = tuple(int(n) for n in shape)
        if shape[0] * shape[1] > cfg.max_grid_cells:
            raise ExploreInputError(
                f"map extent {lo.round(1).tolist()}..{hi.round(1).tolist()} m needs a grid of {shape} "
                f"cells, more than max_grid_cells={cfg.max_grid_cells}"
            )
        off = np.round((self.origin - new_lo) / cfg.cell_m).astype(int)
        grids = []
        for old, fill in ((self.seen, False), (self.visited_s, self._t0), (self.memory_s, -np.inf)):
            new = np.full(shape, fill, dtype=old.dtype)
            new[off[0] : off[0] + old.shape[0], off[1] : off[1] + old.shape[1]] = old
            grids.append(new)
        self.seen, self.visited_s, self.memory_s = grids
        self.origin = new_lo
        self._replan_now = True

    def _disk(self, centre: np.ndarray, radius_m: float) -> tuple[tuple[slice, slice], np.ndarray]:
        """Grid window and mask of the cells whose centres lie within ``radius_m`` of ``centre``."""
        lo = np.maximum(self.cell_of(centre - radius_m), 0)
        hi = np.minimum(self.cell_of(centre + radius_m) + 1, self.seen.shape)
        ii, jj = np.mgrid[lo[0] : hi[0], lo[1] : hi[1]]
        c = self.centre_of(np.stack([ii, jj], axis=-1))
        window = (slice(lo[0], hi[0]), slice(lo[1], hi[1]))
        return window, np.hypot(*(c - centre).transpose(2, 0, 1)) <= radius_m

    # -- the loop ------------------------------------------------------------------------------

    def command(
        self,
        stamp_s: float,
        pose: np.ndarray,
        map_segments: np.ndarray,
        ranges_m: np.ndarray,
        angles_rad: np.ndarray,
        laser_offset: np.ndarray,
        range_max_m: float = np.inf,
    ) -> tuple[float, float]:
        """Velocity command ``(v_mps, w_radps)`` for the robot at ``pose (3,)`` (map frame) given
        the map ``map_segments (G,2,2)`` and the latest scan: ``ranges_m (B,)`` (non-finite or
        ``>= range_max_m``: no return) at ``angles_rad (B,)`` from a laser at ``laser_offset (3,)``
        in the robot frame. ``stamp_s`` is the scan time."""
        cfg = self.cfg
        stamp_s = float(_checked("stamp_s", stamp_s, ()))
        pose = _checked("pose", pose, (3,))
        seg = _checked("map_segments", map_segments, (None, 2, 2))
        ranges = _checked("ranges_m", ranges_m, (None,), finite=False)
        angles = _checked("angles_rad", angles_rad, (len(ranges),))
        offset = _checked("laser_offset", laser_offset, (3,))
        if self._t0 is None:
            self._t0 = stamp_s
        dt = min(max(stamp_s - self._last_s, 0.0), 1.0)
        self._last_s = stamp_s
        step = cfg.accel_mps2 * dt  # the robot's speed now, from the last command (acceleration-limited)
        self._v_now = float(np.clip(self._v_cmd, self._v_now - step, self._v_now + step))

        # 1. grid covering the robot's surroundings and the map
        pad = cfg.sense_radius_m + 1.0
        lo, hi = pose[:2] - pad, pose[:2] + pad
        if len(seg):  # the map, but not a stray far-off element: within map_window_m of the robot
            flat = np.clip(seg.reshape(-1, 2), pose[:2] - cfg.map_window_m, pose[:2] + cfg.map_window_m)
            lo, hi = np.minimum(lo, flat.min(0) - 1.0), np.maximum(hi, flat.max(0) + 1.0)
        self._ensure(lo, hi)
        # 2. seen along the beams (cut by the scan, the map and the sensing radius), visited around
        laser = compose(pose, offset)
        dirs = laser[2] + angles
        hit = np.isfinite(ranges) & (ranges > 0.0) & (ranges < range_max_m)
        reach = np.minimum(np.where(hit, ranges, np.inf), cfg.sense_radius_m)
        near = point_segment_distance(laser[:2], seg) < cfg.sense_radius_m
        reach = ray_lengths(laser[:2], dirs, seg[near], reach)
        self._mark_seen(laser[:2], dirs, reach)
        window, disk = self._disk(pose[:2], cfg.visit_radius_m)
        self.visited_s[window][disk] = stamp_s
        # 3. plan
        if self.goal is not None and np.hypot(*(self.goal - pose[:2])) < cfg.goal_tol_m:
            self._finish_goal(stamp_s, abandoned=False)
        elif self.mode == "frontier" and self.goal is not None and not self._frontier_near(self.goal):
            self._replan_now = True
        if self._replan_now or stamp_s - self._plan_s >= cfg.replan_period_s:
            self._replan(stamp_s, pose, seg)
        # 4. pure pursuit, 5. safety on the scan and the nearby map
        v_des, w_des = self._pursue(pose)
        close = hit & (ranges < cfg.safety_window_m)
        pts = transform_points(
            offset, np.c_[np.cos(angles[close]), np.sin(angles[close])] * ranges[close, None]
        )
        local = apply_segments(
            inverse(pose), seg[point_segment_distance(pose[:2], seg) < cfg.safety_window_m]
        )
        v, w, refused = safe_command(v_des, w_des, self._v_now, pts, local, cfg)
        if refused:  # turn towards the freer side; remember what stopped us, plan around it
            self.stats["safety_stops"] += 1
            free = np.where(hit, ranges, cfg.safety_window_m)
            left, right = free[angles > 0].sum(), free[angles < 0].sum()
            if abs(w) < 0.2 * cfg.max_w_radps:
                w = 0.5 * cfg.max_w_radps * (1.0 if left >= right else -1.0)
            self._remember(pose, pts, stamp_s)
            self._replan_now = True
        self._v_cmd = v
        return v, w

    # -- parts ---------------------------------------------------------------------------------

    def _mark_seen(self, origin: np.ndarray, dirs: np.ndarray, reach: np.ndarray) -> None:
        """Cells along each ray ``origin + t (cos, sin)(dirs)``, ``t <= reach``, sampled at half a cell."""
        t = np.arange(0.0, self.cfg.sense_radius_m + 1e-9, 0.5 * self.cfg.cell_m)
        ok = t[None, :] <= reach[:, None]
        xy = origin + t[None, :, None] * np.stack([np.cos(dirs), np.sin(dirs)], -1)[:, None, :]
        ij = self.cell_of(xy[ok])
        inside = np.all((ij >= 0) & (ij < self.seen.shape), axis=1)
        self.seen[ij[inside, 0], ij[inside, 1]] = True

    def _remember(self, pose: np.ndarray, points_robot: np.ndarray, stamp_s: float) -> None:
        ij = self.cell_of(transform_points(pose, points_robot))
        inside = np.all((ij >= 0) & (ij < self.seen.shape), axis=1)
        self.memory_s[ij[inside, 0], ij[inside, 1]] = stamp_s + self.cfg.obstacle_memory_s

    def _frontier_near(self, xy: np.ndarray) -> bool:
        """Whether a frontier cell (on the current seen grid, last plan's blocking) is within one
        cell of ``xy``."""
        i, j = self.cell_of(xy)
        if (
            self.blocked.shape != self.seen.shape
            or not (2 <= i < self.seen.shape[0] - 2)
            or not (2 <= j < self.seen.shape[1] - 2)
        ):
            return False
        window = (slice(i - 2, i + 3), slice(j - 2, j + 3))
        return bool(frontier_mask(self.seen[window], self.blocked[window], 1)[1:4, 1:4].any())

    def _finish_goal(self, stamp_s: float, abandoned: bool) -> None:
        """A goal was reached or given up: its surroundings count as seen (and visited), so it is
        not chosen again."""
        window, disk = self._disk(self.goal, self.cfg.goal_clear_radius_m)
        self.seen[window] |= disk
        if abandoned:
            self.visited_s[window][disk] = stamp_s
        self.stats["abandoned" if abandoned else "goals"] += 1
        self.goal = self.path = None
        self._replan_now = True

    def _replan(self, stamp_s: float, pose: np.ndarray, seg: np.ndarray) -> None:
        cfg = self.cfg
        self.stats["replans"] += 1
        self._plan_s, self._replan_now = stamp_s, False
        # clearance and blocking from the map (and remembered scan obstacles); cost for the middle
        self.clearance_m = clearance_grid(
            seg, self.origin, self.seen.shape, cfg.cell_m, self.memory_s > stamp_s
        )
        block_m = cfg.robot_radius_m + cfg.block_margin_m
        self.blocked = self.clearance_m < block_m
        excess = np.clip(
            (cfg.comfort_clearance_m - self.clearance_m) / (cfg.comfort_clearance_m - block_m), 0, 1
        )
        cost = 1.0 + cfg.clearance_cost * excess
        traversable = ~self.blocked & ndimage.binary_dilation(self.seen, np.ones((3, 3), bool))
        source = self._source(pose[:2], traversable)
        if source is None:
            self.mode, self.goal, self.path = "spin", None, None
            return
        dist, pred = shortest_paths(cost, traversable, source)
        dist *= cfg.cell_m
        self.frontier = frontier_mask(self.seen, self.blocked, cfg.min_frontier_cells)
        goal = self._frontier_goal(pose, dist)
        mode = "frontier"
        if goal is None:
            goal, mode = self._revisit_goal(stamp_s, pose, dist, traversable), "revisit"
        if goal is None:
            self.mode, self.goal, self.path = "spin", None, None
            return
        new_goal = self.goal is None or mode != self.mode or np.any(self.cell_of(self.goal) != goal)
        if new_goal or dist[tuple(goal)] < self._goal_cost - cfg.stuck_progress_m:
            self._goal_cost, self._progress_s = dist[tuple(goal)], stamp_s
        elif stamp_s - self._progress_s > cfg.stuck_timeout_s:
            self._finish_goal(stamp_s, abandoned=True)
            return self._replan(stamp_s, pose, seg)
        self.mode, self.goal = mode, self.centre_of(goal)
        back, chain = pred.ravel().tolist(), [int(np.ravel_multi_index(tuple(goal), pred.shape))]
        while back[chain[-1]] >= 0:
            chain.append(back[chain[-1]])
        cells = np.stack(np.unravel_index(chain[::-1], pred.shape), axis=-1)
        self.path = np.vstack([pose[:2], self.centre_of(cells)])
        self._k = 0

    def _source(self, xy: np.ndarray, traversable: np.ndarray) -> tuple[int, int] | None:
        """The robot's cell, or the nearest traversable cell within a metre when it is blocked."""
        window, disk = self._disk(xy, 1.0)
        ok = disk & traversable[window]
        if not ok.any():
            return None
        ii, jj = np.nonzero(ok)
        ij = np.c_[ii + window[0].start, jj + window[1].start]
        best = np.argmin(np.hypot(*(self.centre_of(ij) - xy).T))
        return int(ij[best, 0]), int(ij[best, 1])

    def _frontier_goal(self, pose: np.ndarray, dist: np.ndarray) -> np.ndarray | None:
        """Nearest reachable frontier cell by path cost; the current goal is kept while it is
        still a frontier and not more than ``hysteresis_m`` costlier (no dithering)."""
        cfg = self.cfg
        ij = np.argwhere(self.frontier & np.isfinite(dist))
        ij = ij[np.hypot(*(self.centre_of(ij) - pose[:2]).T) >= cfg.min_goal_dist_m]
        if len(ij) == 0:
            return None
        best = ij[np.argmin(dist[ij[:, 0], ij[:, 1]])]
        if self.mode == "frontier" and self.goal is not None and self._frontier_near(self.goal):
            cur = self.cell_of(self.goal)
            if dist[tuple(cur)] <= dist[tuple(best)] + cfg.hysteresis_m:
                return cur
        return best

    def _revisit_goal(self, stamp_s, pose, dist, traversable) -> np.ndarray | None:
        """No frontier left: the least recently visited reachable open place (staleness traded
        against path cost), so the robot drives its loops again and the filter closes them."""
        cfg = self.cfg
        if (
            self.mode == "revisit"
            and self.goal is not None
            and np.isfinite(dist[tuple(self.cell_of(self.goal))])
        ):
            return self.cell_of(self.goal)
        ok = traversable & self.seen & np.isfinite(dist) & (dist >= cfg.revisit_min_dist_m)
        ok &= self.clearance_m >= cfg.revisit_min_clearance_m
        if not ok.any():
            return None
        score = np.where(ok, (stamp_s - self.visited_s) - cfg.revisit_s_per_m * dist, -np.inf)
        return np.array(np.unravel_index(np.argmax(score), score.shape))

    def _pursue(self, pose: np.ndarray) -> tuple[float, float]:
        """Pure pursuit towards the path point ``lookahead_m`` ahead of the nearest one; turn in
        place when the heading error is large. Spin when there is no path."""
        cfg = self.cfg
        if self.path is None:
            return 0.0, cfg.spin_w_radps
        ahead = self.path[self._k : self._k + 40]
        self._k += int(np.argmin(np.hypot(*(ahead - pose[:2]).T)))
        along = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(self.path[self._k :], axis=0).T))])
        target = self.path[self._k + min(int(np.searchsorted(along, cfg.lookahead_m)), len(along) - 1)]
        to = target - pose[:2]
        alpha = float(wrap_angle(math.atan2(to[1], to[0]) - pose[2]))
        if abs(alpha) > cfg.turn_in_place_rad:
            return 0.0, float(np.clip(cfg.turn_gain_per_s * alpha, -cfg.max_w_radps, cfg.max_w_radps))
        curvature = 2.0 * math.sin(alpha) / max(math.hypot(to[0], to[1]), 1e-6)
        v = cfg.max_v_mps * (1.0 - 0.5 * abs(alpha) / cfg.turn_in_place_rad)
        if abs(curvature) * v > cfg.max_w_radps:
            v = cfg.max_w_radps / abs(curvature)
        return v, curvature * v
