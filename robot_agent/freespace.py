"""The space a robot's laser saw free, kept per *view* and published beside its segment map.

A navigation stack wants an occupancy grid: walls (the fused segments) and, as important, the
space known to be free. Each scan's free region is the fan from the laser to its readings:

- a beam that hit something is free up to the hit; between two beams the nearer bounds it (at a
  depth step the chord from a near hit to a far one would cut behind the near wall);
- a beam with no return (at or beyond the laser's range) is free up to ``no_return_m`` only —
  glass, black and far surfaces return nothing, and an open view is no proof of long free space;
- an unusable reading (NaN, zero, below the minimum) is unknown: the fan goes back to the laser.

The fan is a polygon in the robot's frame, simplified (Douglas-Peucker, ``tolerance_m``: how far
a boundary may move); each of its edges says whether it runs along hits — a wall seen — or along
a beam or the no-return reach (the server keeps free space off the walls, and marks walls the
segment map lacks: ``map_server/freespace.py``). A scan
becomes a *view* (a keyframe of free space) when the robot moved at least ``every_m`` or
``every_rad`` since the last candidate and its region adds at least ``min_new_area_m2`` to what
the kept views cover — so the views grow with the area explored, not with time, and a robot that
patrols a known building adds none. The view is anchored to the pose of its scan: the agent
publishes every view with that pose as the path it publishes puts it (the back end's latest
correction, or the path rebuilt at the end), so corrections move free space as they move walls.

Pure: scans and poses in, arrays out (shapely for the polygons).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
import shapely
from shapely.geometry import Polygon

from shared.geometry import point_segment_distance, sample_segments
from shared.messages import MAX_VERTICES, MAX_VIEW_REACH_M, MAX_VIEWS
from shared.occupancy import place, polygons

log = logging.getLogger("fleet_slam.freespace")


@dataclass(frozen=True)
class FreeSpaceConfig:
    enabled: bool = True
    every_m: float = 0.5  # a new candidate view after this much travel ...
    every_rad: float = 0.5  # ... or this much turn
    min_new_area_m2: float = 1.0  # kept only when it adds this much free area to the kept views
    tolerance_m: float = 0.03  # simplification: a boundary moves at most this much
    no_return_m: float = 5.0  # a beam with no return is free this far
    # two neighbouring hits are one wall (the edge between them is a wall edge) when their ranges
    # differ by at most this much plus step_share of the range (else a depth step)
    step_m: float = 0.15
    step_share: float = 0.1
    max_views: int = 2000  # at most this many views (bounded: at most MAX_VIEWS on the wire)


def scan_region(
    ranges_m: np.ndarray,
    angles_rad: np.ndarray,
    laser_offset: np.ndarray,
    range_max_m: float,
    cfg: FreeSpaceConfig = FreeSpaceConfig(),
) -> list[tuple[np.ndarray, np.ndarray]]:
    """The region one scan saw free, in the robot's frame: per simplified polygon its outer ring
    ``(n,2)`` (open, no holes) and ``wall (n,)``: whether the edge from vertex ``i`` to the next
    runs along hits (a wall seen), not along a beam or the no-return reach. Empty: saw nothing."""
    r = np.asarray(ranges_m, float)
    a = np.asarray(angles_rad, float)
    usable = np.isfinite(r) & (r > 0.0)
    hit = usable & (r < range_max_m)
    reach = np.where(hit, r, 0.0)
    reach = np.where(usable & ~hit, min(cfg.no_return_m, range_max_m), reach)
    reach = np.minimum(reach, MAX_VIEW_REACH_M - 1.0)
    if not np.any(reach > 2 * cfg.tolerance_m):
        return []
    order = np.argsort(a, kind="stable")
    a, reach, hit = a[order], reach[order], hit[order]
    if a[-1] - a[0] >= 2 * np.pi - 1e-9:  # a full turn: the last beam repeats the first
        keep = a < a[0] + 2 * np.pi - 1e-9
        a, reach, hit = a[keep], reach[keep], hit[keep]
    # between two beams the nearer one bounds what was seen: at a depth step (a door, a wall's
    # end) the straight chord from the near hit to the far one would cut behind the near wall
    full_turn = a[-1] - a[0] > np.pi * 1.98
    a_all = np.empty(2 * len(a) - 1)
    a_all[0::2], a_all[1::2] = a, (a[:-1] + a[1:]) / 2
    r_all = np.empty_like(a_all)
    r_all[0::2], r_all[1::2] = reach, np.minimum(reach[:-1], reach[1:])
    ox, oy, oth = (float(v) for v in laser_offset)
    th = oth + a_all
    pts = np.column_stack([ox + r_all * np.cos(th), oy + r_all * np.sin(th)])
    ring = pts if full_turn else np.vstack([[ox, oy], pts])
    poly = shapely.make_valid(Polygon(ring)).simplify(cfg.tolerance_m, preserve_topology=True)
    # the walls seen: neighbouring hits without a depth step between them
    ends = pts[0::2]
    same = hit[:-1] & hit[1:] & (np.abs(np.diff(reach)) <= cfg.step_m + cfg.step_share * reach[:-1])
    out = []
    for p in polygons(poly):
        if p.area <= cfg.tolerance_m**2:
            continue
        v = np.asarray(p.exterior.coords)[:-1]
        out.append((v, _wall_edges(v, ends, same, a, (ox, oy, oth), cfg.tolerance_m + 0.02)))
    return out


def _wall_edges(ring: np.ndarray, ends: np.ndarray, same: np.ndarray, angles: np.ndarray, laser,
                within_m: float, step_m: float = 0.05) -> np.ndarray:  # fmt: skip
    """Per edge of ``ring`` (from vertex i to the next): every point of it within ``within_m`` of
    a wall seen — the segment between hits ``ends[k]``, ``ends[k+1]`` where ``same[k]``. The fan
    is star-shaped from the laser: a point's bearing tells which beams' segment it may lie on."""
    if not same.any():
        return np.zeros(len(ring), bool)
    edges = np.stack([ring, np.roll(ring, -1, axis=0)], axis=1)
    pts, owner, _ = sample_segments(edges, step_m, ends=True)
    starts = np.searchsorted(owner, np.arange(len(ring)))  # each edge's first point
    ox, oy, oth = laser
    bearing = np.arctan2(pts[:, 1] - oy, pts[:, 0] - ox) - oth
    bearing = angles[0] + (bearing - angles[0]) % (2 * np.pi)
    k = np.searchsorted(angles, bearing) - 1
    best = np.full(len(pts), np.inf)
    for dk in (-1, 0, 1):
        kk = np.clip(k + dk, 0, len(ends) - 2)
        dist = point_segment_distance(pts, np.stack([ends[kk], ends[kk + 1]], axis=1))
        best = np.where(same[kk], np.minimum(best, dist), best)
    return np.logical_and.reduceat(best <= within_m, starts)


class FreeSpaceViews:
    """The kept views of one session: per view its scan (trajectory index), pose in the map
    frame (as captured, then as the published path puts it: :meth:`refresh`) and rings in the
    robot frame."""

    def __init__(self, cfg: FreeSpaceConfig = FreeSpaceConfig()):
        self.cfg = cfg
        self.scan: list[int] = []
        self.pose: list[np.ndarray] = []
        self.rings: list[list[np.ndarray]] = []
        self.walls: list[list[np.ndarray]] = []  # per ring: its wall edges (bool per vertex)
        self._covered = Polygon()  # the kept views' union (as captured), for the area test
        self._last: np.ndarray | None = None
        self._vertices = 0
        self.full = False  # max_views (or the wire's vertex limit) reached: no more views

    def __len__(self) -> int:
        return len(self.scan)

    def add(self, scan: int, pose: np.ndarray, ranges_m, angles_rad, laser_offset,
            range_max_m: float) -> bool:  # fmt: skip
        """The scan with trajectory index ``scan`` seen from ``pose (3,)`` (map frame):
        kept as a view if it is a candidate and adds free area. Returns whether it was kept."""
        cfg = self.cfg
        if not cfg.enabled or self.full:
            return False
        pose = np.asarray(pose, float)
        if self._last is not None:
            d = self._last - pose
            turn = abs((d[2] + np.pi) % (2 * np.pi) - np.pi)
            if np.hypot(d[0], d[1]) < cfg.every_m and turn < cfg.every_rad:
                return False
        self._last = pose.copy()
        seen = scan_region(ranges_m, angles_rad, laser_offset, range_max_m, cfg)
        if not seen:
            return False
        rings = [v for v, _ in seen]
        region = shapely.union_all([Polygon(v) for v in place(rings, pose)])
        if region.difference(self._covered).area < cfg.min_new_area_m2:
            return False
        n = sum(len(v) for v in rings)
        if len(self.scan) >= min(cfg.max_views, MAX_VIEWS) or self._vertices + n > MAX_VERTICES:
            self.full = True
            log.warning("free space: %d views kept, no more (max_views)", len(self.scan))
            return False
        self._covered = self._covered.union(region).simplify(cfg.tolerance_m)
        self.scan.append(int(scan))
        self.pose.append(pose.copy())
        self.rings.append(rings)
        self.walls.append([w for _, w in seen])
        self._vertices += n
        return True

    def drop_from(self, scan: int) -> int:
        """Forget the views from trajectory index ``scan`` on (scans the filter no longer trusts:
        a doubt about odometry); returns how many."""
        keep = [i for i, s in enumerate(self.scan) if s < scan]
        gone = len(self.scan) - len(keep)
        if gone:
            self.scan = [self.scan[i] for i in keep]
            self.pose = [self.pose[i] for i in keep]
            self.rings = [self.rings[i] for i in keep]
            self.walls = [self.walls[i] for i in keep]
            self._vertices = sum(len(v) for r in self.rings for v in r)
            self.full = False
            self._last = None  # the next scan is a candidate again
            self._covered = shapely.union_all(
                [Polygon(v) for p, r in zip(self.pose, self.rings, strict=True) for v in place(r, p)]
            )
        return gone

    def refresh(self, path: np.ndarray, first_scan: int = 0) -> np.ndarray:
        """The views' poses taken from the path as published now (``path (S,3)``: trajectory
        index ``first_scan + i`` is ``path[i]``); a view older than the path keeps its last pose.
        Returns the poses ``(V,3)``."""
        poses = self.poses()
        at = np.asarray(self.scan, dtype=int) - first_scan
        inside = (at >= 0) & (at < len(path))
        poses[inside] = np.asarray(path, float)[at[inside]]
        self.pose = list(poses)
        return poses

    def poses(self) -> np.ndarray:
        return np.array(self.pose, float).reshape(-1, 3)

    def arrays(self, poses: np.ndarray | None = None) -> tuple[np.ndarray, ...]:
        """``view_pose (V,3)`` (``poses`` or the views' own), ``ring_offsets (R+1,)``,
        ``ring_view (R,)``, ``vertices (P,2)``, ``wall (P,)``: the arrays of a
        :class:`shared.messages.FreeSpace`."""
        view_pose = self.poses() if poses is None else np.asarray(poses, float).reshape(-1, 3)
        flat = [(i, v) for i, rings in enumerate(self.rings) for v in rings]
        lengths = np.array([len(v) for _, v in flat], np.int64)
        offsets = np.concatenate([[0], np.cumsum(lengths)]).astype(np.int64)
        ring_view = np.array([i for i, _ in flat], np.int64)
        vertices = np.concatenate([v for _, v in flat]) if flat else np.zeros((0, 2))
        wall = np.concatenate([w for ws in self.walls for w in ws]) if flat else np.zeros(0, bool)
        return view_pose, offsets, ring_view, vertices, wall
