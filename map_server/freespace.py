"""The fleet's free space: every placed robot's views united in the global frame (pure).

Each robot publishes the space its laser saw free as polygons per view, anchored at the view's
pose in its own map frame, each edge marked as a wall seen or not (:class:`shared.messages.FreeSpace`,
``robot_agent/freespace.py``). The server keeps the latest of each (robot, session) whose map it
keeps — a robot's current session and its retired pieces — and places them where their maps are
placed. The union in the global frame, shrunk by ``wall_margin_m`` (free space keeps off every
wall seen, measured across the wall: the wall's cell stays a wall's even where the maps are a few
centimetres apart) and simplified by ``tolerance_m``, is a :class:`shared.messages.FusedFree`;
with it the wall edges the fused segment map does not hold within ``explained_m`` (a door jamb, a
wall seen once through a door), none inside the free space (someone walking by). A robot not placed
adds nothing (its frame is nowhere yet). Each (robot, session)'s own union is cached by its
``seq``, so a new placement costs one transform and one union across robots, not every view again.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import shapely
from shapely import affinity

from shared.geometry import apply_segments
from shared.messages import FreeSpace, FusedFree
from shared.occupancy import to_rings, unexplained, union, view_vertices, view_walls


@dataclass(frozen=True)
class FreeFusionConfig:
    tolerance_m: float = 0.02  # the fused polygons' simplification (a boundary moves at most this)
    wall_margin_m: float = 0.08  # free space keeps this far from every wall seen (> both tolerances)
    explained_m: float = 0.10  # a wall edge this close to a fused segment is the segment's
    min_gap_s: float = 2.0  # server time between fusions of free space (a union is not free) ...
    # ... and at least this many times what the last one took: the loop that fuses the maps runs
    # it, and a real log's three pieces (MIT-CSAIL: 19,000 vertices, 2,000 holes) take GEOS
    # 1.5-2.5 s to keep off the walls, which at every 2 s would hold the maps' fusions most of the time
    gap_per_cost: float = 5.0
    moved_m: float = 0.01  # a placement that moved this much (or moved_rad) re-fuses
    moved_rad: float = 0.001


Placements = dict[tuple[str, str], np.ndarray]  # (robot, session) -> its map frame in the global frame


def place_area(area, pose: np.ndarray):
    """A shapely ``area`` with its frame placed at ``pose (3,)``."""
    c, s = np.cos(pose[2]), np.sin(pose[2])
    return affinity.affine_transform(area, [c, -s, s, c, pose[0], pose[1]])


class FreeSpaces:
    def __init__(self, cfg: FreeFusionConfig = FreeFusionConfig()):
        self.cfg = cfg
        self.latest: dict[tuple[str, str], FreeSpace] = {}
        self._own_cache: dict[tuple[str, str], tuple[int, object, np.ndarray]] = {}  # seq, union, walls
        self._fused_with: tuple[frozenset, dict] | None = None  # what the last fusion used
        self.version = 0
        self.changed = False  # a new message since the last fusion
        self.fused: FusedFree | None = None
        self._last_fuse_s = -np.inf
        self.cost_s = 0.0  # what the last fusion took (wall clock: the caller times it)

    def put(self, m: FreeSpace) -> str:
        """Take ``m``: ``"kept"`` (newer than what its (robot, session) has: the whole of it, or
        the views it adds put together with the previous message's), ``"stale"`` (not newer), or
        ``"gap"`` (it adds to a message not received: the whole must be asked for)."""
        key = (m.robot, m.session)
        old = self.latest.get(key)
        if old is not None and m.seq <= old.seq:
            return "stale"
        whole = m if m.rings_from == 0 else (None if old is None else m.merged_onto(old))
        if whole is None:
            return "gap"
        self.latest[key] = whole
        self.changed = True
        return "kept"

    def keep_only(self, keys: set[tuple[str, str]]) -> None:
        """Forget the free space of sessions the fleet no longer keeps (bounded like the maps)."""
        for key in [k for k in self.latest if k not in keys]:
            del self.latest[key]
            self.changed = True
        for key in [k for k in list(self._own_cache) if k not in self.latest]:  # (a fusion on its
            self._own_cache.pop(key, None)  # thread may have cached a session dropped meanwhile)

    def area(self, robot: str, session: str):
        """The free space a robot session's views saw, united, in its map frame (shapely; None
        when none came)."""
        return self._own((robot, session))[0] if (robot, session) in self.latest else None

    def _own(self, key: tuple[str, str], m: FreeSpace | None = None) -> tuple[object, np.ndarray]:
        """A session's views united and its wall edges ``(E,2,2)``, in its map frame (of its
        latest message, or of ``m``)."""
        m = self.latest[key] if m is None else m
        cached = self._own_cache.get(key)
        if cached is None or cached[0] != m.seq:
            v = view_vertices(m)  # placed once, for the rings and their wall edges
            rings = np.split(v, m.ring_offsets[1:-1])
            cached = (m.seq, union(rings), view_walls(m, vertices=v))
            self._own_cache[key] = cached
        return cached[1], cached[2]

    def due(self, placements: Placements, now_s: float) -> bool:
        """Whether a fusion now would differ from the last one: new free space, or a placement
        added, dropped or moved; and the gap since the last has passed (``min_gap_s``, or
        ``gap_per_cost`` times what the last took)."""
        if now_s - self._last_fuse_s < max(self.cfg.min_gap_s, self.cfg.gap_per_cost * self.cost_s):
            return False
        if self.changed or self._fused_with is None:
            return bool(self.latest) or self._fused_with is not None
        keys, before = self._fused_with
        used = frozenset(k for k in placements if k in self.latest)
        if used != keys:
            return True
        for k in used:
            d = np.asarray(placements[k]) - before[k]
            turn = abs((d[2] + np.pi) % (2 * np.pi) - np.pi)
            if np.hypot(d[0], d[1]) >= self.cfg.moved_m or turn >= self.cfg.moved_rad:
                return True
        return False

    def begin(self, placements: Placements, now_s: float) -> list:
        """What a fusion now is made of — each placed session's latest message and its placement,
        ``[(key, message, pose)]`` — and the fusion counted as begun: a message that comes while it
        runs (:meth:`compute`, on another thread) makes the next one due."""
        used = {k: np.asarray(placements[k], float).copy() for k in sorted(placements) if k in self.latest}
        self._fused_with = (frozenset(used), used)
        self.changed = False
        self._last_fuse_s = now_s
        return [(k, self.latest[k], t) for k, t in used.items()]

    def compute(self, parts: list, segments: np.ndarray | None = None) -> tuple:
        """The free space of ``parts`` (:meth:`begin`) in the global frame, kept off the walls, and
        the walls seen that ``segments (M,2,2)`` (the fused map) lacks: ``FusedFree``'s arrays.
        Reads only what it is given and the sessions' unions (cached by their
        message): another thread may run it while messages come (GEOS releases the GIL)."""
        areas, walls = [], []
        for key, m, t in parts:
            own, own_walls = self._own(key, m)
            if own.is_empty:
                continue
            areas.append(place_area(own, t))
            walls.append(apply_segments(t, own_walls))
        seen = shapely.union_all(areas) if areas else shapely.MultiPolygon()
        free = seen.buffer(-self.cfg.wall_margin_m, join_style="mitre") if not seen.is_empty else seen
        offsets, hole, vertices, tol = to_rings(free, self.cfg.tolerance_m)
        known = free
        if segments is not None and len(segments):
            lines = shapely.multilinestrings(np.asarray(segments, float).reshape(-1, 2, 2))
            known = shapely.union(free, lines.buffer(self.cfg.explained_m, cap_style="flat"))
        extra = unexplained(np.concatenate(walls) if walls else np.zeros((0, 2, 2)), known)
        return tol, offsets, hole, vertices, extra

    def finish(self, computed: tuple, server: str, map_version: int, now_s: float) -> FusedFree:
        """The fused free space :meth:`compute` gave, as a new version (``now_s``: when it began)."""
        tol, offsets, hole, vertices, extra = computed
        self.version += 1
        self.fused = FusedFree(server, "", self.version, int(map_version), max(now_s, 0.0), tol, offsets,
                               hole, vertices, extra)  # fmt: skip
        return self.fused

    def fuse(
        self, placements: Placements, server: str, map_version: int, now_s: float,
        segments: np.ndarray | None = None,
    ) -> FusedFree:  # fmt: skip
        """The placed sessions' free space in the global frame, kept off the walls, and the walls
        seen that ``segments (M,2,2)`` (the fused map) lacks (a new version): :meth:`begin`,
        :meth:`compute` and :meth:`finish` at once."""
        return self.finish(self.compute(self.begin(placements, now_s), segments), server, map_version, now_s)
