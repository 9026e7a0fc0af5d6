"""A simulated world: wall segments for the lidar, polygons for export and free-space checks.

Worlds are drawn with shapely (outer boundary, walls as thin polygons or linestrings, obstacle
footprints) and converted ONCE to a ``(W, 2, 2)`` segment array by :func:`walls_from_geometries`;
ray casting only ever sees that array.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import shapely
from shapely.geometry import LineString, MultiLineString, Point, Polygon, box

BUILTIN_WORLDS: tuple[str, ...] = ("office", "warehouse", "campus")

# Thickness given to wall lines when free space is cut out of the bounding box; only needs to be
# large enough for shapely to split regions along a line, far below any clearance we check.
WALL_CUT_WIDTH_M = 1e-6


class WorldError(ValueError):
    """A world description is malformed (bad geometry, routes, starts or file content)."""


@dataclass(frozen=True, eq=False)
class World:
    """A 2D world.

    ``walls`` (W, 2, 2) wall segments in metres — the only thing ray casting uses.
    ``obstacles`` footprints (thick walls, furniture, trees), kept for export and free-space
    checks. ``routes`` one closed patrol route ``(K, 2)`` per robot (the robot drives
    ``route[0] → … → route[K-1] → route[0]`` cyclically). ``starts`` (R, 3) start poses, one per
    route, on the route's closing leg and facing ``route[0]``. ``bounds`` (4,) is
    ``(min_x, min_y, max_x, max_y)`` of the walls.
    """

    name: str
    walls: np.ndarray
    obstacles: tuple[Polygon, ...] = ()
    routes: tuple[np.ndarray, ...] = ()
    starts: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    bounds: np.ndarray = field(default_factory=lambda: np.zeros(4))

    def __post_init__(self) -> None:
        walls = np.asarray(self.walls, dtype=float).reshape(-1, 2, 2)
        starts = np.asarray(self.starts, dtype=float).reshape(-1, 3)
        routes = tuple(np.asarray(r, dtype=float) for r in self.routes)
        for i, r in enumerate(routes):
            if r.ndim != 2 or r.shape[1] != 2 or len(r) < 2:
                raise WorldError(f"route {i}: expected shape (K>=2, 2), got {r.shape}")
        if len(starts) != len(routes):
            raise WorldError(f"{len(starts)} start poses for {len(routes)} routes")
        if not np.all(np.isfinite(walls)):
            raise WorldError("walls contain non-finite coordinates")
        bounds = np.asarray(self.bounds, dtype=float).reshape(4)
        for name, value in (("walls", walls), ("starts", starts), ("bounds", bounds)):
            value.flags.writeable = False
            object.__setattr__(self, name, value)
        for r in routes:
            r.flags.writeable = False
        object.__setattr__(self, "routes", routes)
        object.__setattr__(self, "obstacles", tuple(self.obstacles))

    @property
    def num_robots(self) -> int:
        """How many robots the world has routes for."""
        return len(self.routes)


def walls_from_geometries(geometries) -> np.ndarray:
    """Wall segments ``(W, 2, 2)`` from shapely geometries, converted once.

    Polygons contribute their boundary rings (so a thin polygon gives both faces of a wall),
    linestrings their consecutive vertex pairs; multi-part geometries are split first.
    Zero-length segments are dropped.
    """
    parts = shapely.get_parts(np.asarray(list(geometries), dtype=object))
    is_poly = shapely.get_type_id(parts) == shapely.GeometryType.POLYGON
    rings = shapely.get_parts(shapely.boundary(parts[is_poly]))
    lines = np.concatenate([rings, parts[~is_poly]])
    line_types = (shapely.GeometryType.LINESTRING, shapely.GeometryType.LINEARRING)
    lines = lines[np.isin(shapely.get_type_id(lines), line_types) & ~shapely.is_empty(lines)]
    if len(lines) == 0:
        return np.zeros((0, 2, 2))
    coords, index = shapely.get_coordinates(lines, return_index=True)
    same_line = index[:-1] == index[1:]  # consecutive vertices of one line form a segment
    segments = np.stack([coords[:-1][same_line], coords[1:][same_line]], axis=1)
    return segments[np.any(segments[:, 0] != segments[:, 1], axis=1)]


def start_on_route(route: np.ndarray, back_m: float = 1.0) -> np.ndarray:
    """A start pose ``(3,)`` on the route's closing leg, ``back_m`` before ``route[0]``, facing it.

    ``back_m`` is capped at half the closing leg so the start stays on the route.
    """
    route = np.asarray(route, dtype=float)
    leg = route[0] - route[-1]
    length = float(np.hypot(*leg))
    if length == 0.0:
        raise WorldError("route's last waypoint equals its first: no closing leg to start on")
    xy = route[0] - leg / length * min(back_m, 0.5 * length)
    return np.array([xy[0], xy[1], np.arctan2(leg[1], leg[0])])


def make_world(
    name: str,
    wall_geometries,
    obstacles=(),
    routes=(),
    starts: np.ndarray | None = None,
) -> World:
    """Build a :class:`World`: walls from ``wall_geometries`` (polygons and/or lines), bounds from
    the walls, and start poses from :func:`start_on_route` where ``starts`` is not given."""
    walls = walls_from_geometries(list(wall_geometries))
    routes = tuple(np.asarray(r, dtype=float) for r in routes)
    if starts is None:
        starts = np.array([start_on_route(r) for r in routes]).reshape(-1, 3)
    if len(walls):
        flat = walls.reshape(-1, 2)
        bounds = np.concatenate([flat.min(axis=0), flat.max(axis=0)])
    else:
        bounds = np.zeros(4)
    return World(
        name=name, walls=walls, obstacles=tuple(obstacles), routes=routes, starts=starts, bounds=bounds
    )


def route_line(route: np.ndarray) -> LineString:
    """The closed route as a shapely line (last waypoint joined back to the first)."""
    route = np.asarray(route, dtype=float)
    return LineString(np.vstack([route, route[:1]]))


def walls_geometry(world: World) -> MultiLineString:
    """All wall segments as one shapely geometry (for distance and clearance checks)."""
    return MultiLineString(list(world.walls))


def free_space(world: World):
    """Shapely geometry of the navigable area.

    The bounding box minus obstacle footprints and the (hairline-thick) wall lines; of the pieces
    this leaves, those holding a route waypoint or a start pose are kept (the inside of a closed
    wall outline without routes is not navigable). Without routes, every piece is kept.
    """
    cut = shapely.union_all([*world.obstacles, walls_geometry(world).buffer(WALL_CUT_WIDTH_M)])
    pieces = shapely.get_parts(box(*world.bounds).difference(cut))
    seeds = [Point(p) for r in world.routes for p in r] + [Point(s[:2]) for s in world.starts]
    if seeds:
        seed_geom = shapely.MultiPoint(seeds)
        pieces = pieces[shapely.intersects(pieces, seed_geom)]
    return shapely.union_all(pieces)


# --- GeoJSON ------------------------------------------------------------------------------------

_WALL_TYPES = ("LineString", "MultiLineString", "Polygon", "MultiPolygon")


def to_geojson(world: World) -> dict:
    """A GeoJSON FeatureCollection: one ``"kind": "wall"`` LineString per wall segment,
    ``"obstacle"`` footprint polygons, ``"route"`` LineStrings and ``"start"`` Points."""
    features = [_feature({"kind": "wall"}, LineString(seg)) for seg in world.walls]
    features += [_feature({"kind": "obstacle"}, poly) for poly in world.obstacles]
    features += [_feature({"kind": "route", "robot": i}, LineString(r)) for i, r in enumerate(world.routes)]
    features += [
        _feature({"kind": "start", "robot": i, "theta": float(s[2])}, Point(s[:2]))
        for i, s in enumerate(world.starts)
    ]
    return {"type": "FeatureCollection", "name": world.name, "features": features}


def _feature(properties: dict, geometry) -> dict:
    return {"type": "Feature", "properties": properties, "geometry": shapely.geometry.mapping(geometry)}


def load_geojson(path) -> World:
    """Read a world from a GeoJSON file (see :func:`from_geojson`); the name defaults to the
    file's stem."""
    import json
    from pathlib import Path

    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise WorldError(f"{path}: cannot read GeoJSON: {exc}") from exc
    return from_geojson(data, default_name=path.name.split(".")[0])


def from_geojson(data: dict, default_name: str = "geojson") -> World:
    """A world from a GeoJSON FeatureCollection.

    Features without ``kind`` or with ``"kind": "wall"`` are walls (Polygon, MultiPolygon,
    LineString, MultiLineString; polygons contribute their boundaries). ``"kind": "obstacle"``
    polygons are footprints only (no walls: give those separately). ``"kind": "route"``
    LineStrings with an integer ``"robot"`` are patrol routes; ``"kind": "start"`` Points with
    ``"robot"`` and ``"theta"`` are start poses (a missing start is put on the route).
    """
    if not isinstance(data, dict) or data.get("type") != "FeatureCollection":
        raise WorldError("GeoJSON: top level must be an object with type 'FeatureCollection'")
    features = data.get("features")
    if not isinstance(features, list):
        raise WorldError("GeoJSON: 'features' must be a list")
    walls, obstacles, routes, starts = [], [], {}, {}
    for i, feat in enumerate(features):
        kind, props, geom = _parse_feature(i, feat)
        if kind == "wall":
            _expect_type(i, kind, geom, _WALL_TYPES)
            walls.append(geom)
        elif kind == "obstacle":
            _expect_type(i, kind, geom, ("Polygon", "MultiPolygon"))
            obstacles.extend(shapely.get_parts(geom))
        elif kind == "route":
            _expect_type(i, kind, geom, ("LineString",))
            coords = np.asarray(geom.coords)[:, :2]
            if len(coords) > 2 and np.array_equal(coords[0], coords[-1]):
                coords = coords[:-1]  # an explicitly closed route
            routes[_robot_index(i, props, routes)] = coords
        elif kind == "start":
            _expect_type(i, kind, geom, ("Point",))
            theta = props.get("theta", None)
            if not isinstance(theta, int | float) or not np.isfinite(theta):
                raise WorldError(f"feature {i} (start): 'theta' must be a finite number, got {theta!r}")
            starts[_robot_index(i, props, starts)] = np.array([geom.x, geom.y, float(theta)])
        else:
            raise WorldError(f"feature {i}: unknown kind {kind!r} (wall, obstacle, route, start)")
    if sorted(routes) != list(range(len(routes))):
        raise WorldError(f"route robot indices must be 0..{len(routes) - 1}, got {sorted(routes)}")
    orphans = sorted(set(starts) - set(routes))
    if orphans:
        raise WorldError(f"start poses for robots {orphans} have no route")
    route_list = [routes[k] for k in range(len(routes))]
    start_arr = np.array(
        [starts[k] if k in starts else start_on_route(routes[k]) for k in range(len(routes))]
    )
    name = data.get("name", default_name)
    return make_world(str(name), walls, obstacles, route_list, start_arr.reshape(-1, 3))


def _parse_feature(i: int, feat) -> tuple[str, dict, object]:
    if not isinstance(feat, dict) or feat.get("type") != "Feature":
        raise WorldError(f"feature {i}: expected an object with type 'Feature'")
    props = feat.get("properties") or {}
    if not isinstance(props, dict):
        raise WorldError(f"feature {i}: 'properties' must be an object")
    try:
        geom = shapely.geometry.shape(feat.get("geometry"))
    except Exception as exc:  # shapely raises several types for bad coordinates
        raise WorldError(f"feature {i}: invalid geometry: {exc}") from exc
    if geom.is_empty:
        raise WorldError(f"feature {i}: empty geometry")
    if not np.all(np.isfinite(shapely.get_coordinates(geom))):
        raise WorldError(f"feature {i}: non-finite coordinates")
    return str(props.get("kind", "wall")), props, geom


def _expect_type(i: int, kind: str, geom, allowed: tuple[str, ...]) -> None:
    if geom.geom_type not in allowed:
        raise WorldError(f"feature {i} ({kind}): geometry type {geom.geom_type} not in {allowed}")


def _robot_index(i: int, props: dict, seen: dict) -> int:
    robot = props.get("robot", len(seen))
    if not isinstance(robot, int) or isinstance(robot, bool) or robot < 0:
        raise WorldError(f"feature {i}: 'robot' must be a non-negative integer, got {robot!r}")
    if robot in seen:
        raise WorldError(f"feature {i}: robot {robot} given twice")
    return robot
