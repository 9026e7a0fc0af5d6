"""The built-in worlds: ``office``, ``warehouse``, ``campus``.

Every world is drawn as shapely polygons (walls are centre lines thickened into polygons, door
gaps left open; furniture, shelves, buildings, trees are footprints) and its walls are the
boundaries of those polygons. Routes run along corridor/aisle/path centre lines and keep at
least :data:`ROUTE_CLEARANCE_M` from every obstacle (``tests/sim/test_world.py`` checks it).
"""

from __future__ import annotations

import numpy as np
import shapely
from shapely import affinity
from shapely.geometry import LineString, MultiLineString, Polygon, box

from robot_agent.sim.world import BUILTIN_WORLDS, World, WorldError, make_world

ROUTE_CLEARANCE_M = 0.5  # promised free distance between any route line and any obstacle
WALL_THICKNESS_M = 0.15  # interior walls (office)
OUTER_WALL_THICKNESS_M = 0.2  # building shell / hall walls / campus fence
DOOR_GAP_M = 1.3  # door gap between wall centre lines; the clear opening is gap - thickness


def _thick(lines: list[LineString], thickness_m: float) -> list[Polygon]:
    """Centre lines → wall polygons; square caps close L and T junctions."""
    walls = shapely.buffer(
        np.asarray(lines, dtype=object), thickness_m / 2, cap_style="square", join_style="mitre"
    )
    return list(shapely.get_parts(shapely.union_all(walls)))


def _wall_with_doors(a, b, doors=(), gap_m: float = DOOR_GAP_M) -> list[LineString]:
    """Straight wall centre line ``a → b`` with door gaps centred at distances ``doors`` from ``a``."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    length = float(np.hypot(*(b - a)))
    cuts = [0.0]
    for d in sorted(doors):
        cuts += [d - gap_m / 2, d + gap_m / 2]
    cuts.append(length)
    unit = (b - a) / length
    return [
        LineString([a + unit * s0, a + unit * s1])
        for s0, s1 in zip(cuts[::2], cuts[1::2], strict=True)
        if s1 - s0 > 1e-9
    ]


def _hwall(y, x0, x1, doors_x=()) -> list[LineString]:
    return _wall_with_doors((x0, y), (x1, y), [x - x0 for x in doors_x])


def _vwall(x, y0, y1, doors_y=()) -> list[LineString]:
    return _wall_with_doors((x, y0), (x, y1), [y - y0 for y in doors_y])


def _rect_lines(x0, y0, x1, y1) -> LineString:
    return LineString([(x0, y0), (x1, y0), (x1, y1), (x0, y1), (x0, y0)])


def _octagon(cx: float, cy: float, r: float) -> Polygon:
    ang = np.arange(8) * np.pi / 4 + np.pi / 8
    return Polygon(np.c_[cx + r * np.cos(ang), cy + r * np.sin(ang)])


def _oriented_box(cx, cy, length, width, angle_rad) -> Polygon:
    return affinity.rotate(
        box(cx - length / 2, cy - width / 2, cx + length / 2, cy + width / 2),
        angle_rad,
        origin=(cx, cy),
        use_radians=True,
    )


def _finish(name: str, polygons: list[Polygon], routes: list) -> World:
    """Union the footprints (so no wall face hides inside another wall) and build the world."""
    obstacles = list(shapely.get_parts(shapely.union_all(np.asarray(polygons, dtype=object))))
    return make_world(name, obstacles, obstacles, routes)


# --- office ------------------------------------------------------------------------------------
# 30 m × 20 m building. A ring corridor (2 m between wall centre lines, centre line the rectangle
# (4.5, 4.5)–(25.5, 15.5), 64 m around) with a cross corridor at x = 15 (so corridors form two
# loops and a figure eight); 14 outer rooms between ring and shell, 8 inner rooms in two blocks.

_OFFICE_SOUTH_DOORS_X = (4.5, 9.0, 15.0, 21.0, 25.5)
_OFFICE_SIDE_DOORS_Y = (6.75, 13.25)
_OFFICE_INNER_DOORS_X = (7.625, 11.875, 18.125, 22.375)


def office() -> World:
    lines = [_rect_lines(0, 0, 30, 20)]
    shell = _thick(lines, OUTER_WALL_THICKNESS_M)
    inner = [
        *_hwall(3.5, 0, 30, _OFFICE_SOUTH_DOORS_X),  # ring, outer side (also splits room bands)
        *_hwall(16.5, 0, 30, _OFFICE_SOUTH_DOORS_X),
        *_vwall(3.5, 3.5, 16.5, _OFFICE_SIDE_DOORS_Y),
        *_vwall(26.5, 3.5, 16.5, _OFFICE_SIDE_DOORS_Y),
        *(seg for x in (6, 12, 18, 24) for seg in (*_vwall(x, 0, 3.5), *_vwall(x, 16.5, 20))),
        *_hwall(10, 0, 3.5),
        *_hwall(10, 26.5, 30),  # west / east room bands split in two
        *_hwall(5.5, 5.5, 14, _OFFICE_INNER_DOORS_X[:2]),
        *_hwall(5.5, 16, 24.5, _OFFICE_INNER_DOORS_X[2:]),
        *_hwall(14.5, 5.5, 14, _OFFICE_INNER_DOORS_X[:2]),
        *_hwall(14.5, 16, 24.5, _OFFICE_INNER_DOORS_X[2:]),
        *(_vwall(x, 5.5, 14.5)[0] for x in (5.5, 9.75, 14, 16, 20.25, 24.5)),
        *_hwall(10, 5.5, 14),
        *_hwall(10, 16, 24.5),
    ]
    walls = _thick(inner, WALL_THICKNESS_M)
    furniture = []
    for x0 in (0, 6, 12, 18, 24):  # outer south/north rooms: desk and cabinet against the shell
        furniture += [box(x0 + 0.5, 0.3, x0 + 1.7, 0.9), box(x0 + 4.8, 0.3, x0 + 5.6, 0.8)]
        furniture += [box(x0 + 0.5, 19.1, x0 + 1.7, 19.7), box(x0 + 4.8, 19.2, x0 + 5.6, 19.7)]
    for y0 in (3.5, 10.0):  # west / east rooms
        furniture += [box(0.3, y0 + 0.5, 0.9, y0 + 1.7), box(29.1, y0 + 0.5, 29.7, y0 + 1.7)]
    for x0 in (5.5, 9.75, 16, 20.25):  # inner rooms: a table at the back wall
        furniture += [box(x0 + 0.4, 9.0, x0 + 1.2, 9.7), box(x0 + 0.4, 10.3, x0 + 1.2, 11.0)]
    routes = [
        # ring counter-clockwise, into south room 3 and north room 2
        [
            (10, 4.5),
            (15, 4.5),
            (15, 1.75),
            (15, 4.5),
            (25.5, 4.5),
            (25.5, 15.5),
            (9, 15.5),
            (9, 18.25),
            (9, 15.5),
            (4.5, 15.5),
            (4.5, 4.5),
        ],
        # figure eight through the cross corridor, into the north-east inner room
        [
            (15, 4.5),
            (25.5, 4.5),
            (25.5, 15.5),
            (22.375, 15.5),
            (22.375, 12.25),
            (22.375, 15.5),
            (15, 15.5),
            (15, 4.5),
            (4.5, 4.5),
            (4.5, 15.5),
            (15, 15.5),
        ],
        # ring clockwise, into the upper east room and the south-west inner room
        [
            (8, 15.5),
            (25.5, 15.5),
            (25.5, 13.25),
            (28.25, 13.25),
            (25.5, 13.25),
            (25.5, 4.5),
            (7.625, 4.5),
            (7.625, 7.75),
            (7.625, 4.5),
            (4.5, 4.5),
            (4.5, 15.5),
        ],
        # west loop clockwise, into the lower west room
        [(4.5, 10), (4.5, 15.5), (15, 15.5), (15, 4.5), (4.5, 4.5), (4.5, 6.75), (1.75, 6.75), (4.5, 6.75)],
    ]
    return _finish("office", shell + walls + furniture, routes)


# --- warehouse ---------------------------------------------------------------------------------
# 40 m × 25 m hall, six identical 28 m shelf rows (1.2 m deep) with 2.5 m aisles between them,
# 6 m cross aisles at both ends: every aisle looks like every other one (data association trap).
# Wall pillars every 10 m and pallets in the end aisles are the only landmarks.

_SHELF_DEPTH_M = 1.2
_AISLE_WIDTH_M = 2.5
_SHELF_ROWS = 6
_SHELF_X_M = (6.0, 34.0)


def warehouse() -> World:
    shell = _thick([_rect_lines(0, 0, 40, 25)], OUTER_WALL_THICKNESS_M)
    pitch = _SHELF_DEPTH_M + _AISLE_WIDTH_M
    y0 = (25 - (_SHELF_ROWS * _SHELF_DEPTH_M + (_SHELF_ROWS - 1) * _AISLE_WIDTH_M)) / 2
    shelves = [
        box(_SHELF_X_M[0], y0 + i * pitch, _SHELF_X_M[1], y0 + i * pitch + _SHELF_DEPTH_M)
        for i in range(_SHELF_ROWS)
    ]
    pillars = [box(x - 0.2, y, x + 0.2, y + 0.4) for x in (10, 20, 30) for y in (0.0, 24.6)]
    pallets = [
        box(0.4, 3.0, 1.6, 4.0),
        box(0.4, 4.3, 1.6, 5.3),
        box(0.4, 14.0, 1.6, 15.0),
        box(38.4, 9.0, 39.6, 10.0),
        box(38.4, 20.0, 39.6, 21.2),
    ]
    a = [y0 + _SHELF_DEPTH_M + _AISLE_WIDTH_M / 2 + i * pitch for i in range(_SHELF_ROWS - 1)]
    west, east, low, high = 3.0, 37.0, y0 / 2 + 0.1, 25 - y0 / 2 - 0.1  # end and side aisles
    routes = [
        [
            (west, a[0]),
            (east, a[0]),
            (east, a[1]),
            (west, a[1]),
            (west, a[2]),
            (east, a[2]),
            (east, a[4]),
            (west, a[4]),
        ],
        [
            (east, a[3]),
            (west, a[3]),
            (west, high),
            (east, high),
            (east, a[4]),
            (west, a[4]),
            (west, a[2]),
            (east, a[2]),
        ],
        [
            (west, low),
            (east, low),
            (east, a[2]),
            (west, a[2]),
            (west, a[1]),
            (east, a[1]),
            (east, a[0]),
            (west, a[0]),
        ],
        [
            (east, a[4]),
            (west, a[4]),
            (west, a[3]),
            (east, a[3]),
            (east, a[0]),
            (west, a[0]),
            (west, low),
            (east, low),
        ],
    ]
    return _finish("warehouse", shell + shelves + pillars + pallets, routes)


# --- campus ------------------------------------------------------------------------------------
# 120 m × 80 m fenced site: paths on a grid (x = 8, 45, 80, 112; y = 8, 40, 72) between six
# building blocks of varied shape (L, portico of pillars, twin blocks, U with courtyard, rotated
# block, notched block); trees (octagons) and benches line the paths.

_CAMPUS_PATH_X = (8.0, 45.0, 80.0, 112.0)
_CAMPUS_PATH_Y = (8.0, 40.0, 72.0)
_CAMPUS_SIZE_M = (120.0, 80.0)
_TREE_RADIUS_M = 0.35
_TREE_OFFSET_M = 4.0  # from the path centre line
_TREE_SPACING_M = 7.0
_CLUTTER_GAP_PROB = 0.25  # share of clutter slots left empty
_BENCH_PROB = 0.15  # share of clutter slots holding a bench instead of a tree
_CLUTTER_SEED = 7  # fixed: the world must be the same on every call


def _campus_buildings() -> list[Polygon]:
    notch = Polygon([(87, 47), (105, 47), (105, 58), (99, 58), (99, 65), (87, 65)])
    return [
        box(15, 15, 38, 33).difference(box(28, 24, 38.5, 33.5)),  # L
        box(52, 18, 73, 33),
        *[box(x - 0.25, 15.5, x + 0.25, 16.0) for x in np.arange(53.0, 73.0, 3.0)],  # portico
        box(87, 15, 95, 33),
        box(98, 15, 105, 26),  # twin blocks
        box(15, 47, 38, 65).difference(box(22, 54, 31, 65.5)),  # U, courtyard open to the north
        _oriented_box(62.5, 56.0, 16.0, 10.0, np.deg2rad(15.0)),
        notch,
    ]


def _campus_clutter(paths: MultiLineString, buildings: list[Polygon]) -> list[Polygon]:
    """Trees along both sides of every path and benches beside some of them; nothing within
    3 m of a path centre line (crossings) or 1 m of a building."""
    rng = np.random.default_rng(_CLUTTER_SEED)
    blocked = shapely.union_all([paths.buffer(_TREE_OFFSET_M - 1.0), *(b.buffer(1.0) for b in buildings)])
    site = box(1.0, 1.0, _CAMPUS_SIZE_M[0] - 1.0, _CAMPUS_SIZE_M[1] - 1.0)
    clutter = []
    for line in paths.geoms:
        (x0, y0), (x1, y1) = line.coords
        n = int(line.length // _TREE_SPACING_M)
        s = (np.arange(n) + 0.5 + rng.uniform(-0.2, 0.2, n)) / n
        along = np.c_[x0 + s * (x1 - x0), y0 + s * (y1 - y0)]
        normal = np.array([-(y1 - y0), x1 - x0]) / line.length
        angle = np.arctan2(y1 - y0, x1 - x0)
        for side in (-1.0, 1.0):
            centres = along + side * _TREE_OFFSET_M * normal
            probs = [_CLUTTER_GAP_PROB, 1 - _CLUTTER_GAP_PROB - _BENCH_PROB, _BENCH_PROB]
            kinds = rng.choice(3, size=n, p=probs)  # 0 nothing, 1 tree, 2 bench
            for (cx, cy), kind in zip(centres, kinds, strict=True):
                if kind == 0:
                    continue
                shape = (
                    _oriented_box(cx, cy, 1.6, 0.45, angle)
                    if kind == 2
                    else _octagon(cx, cy, _TREE_RADIUS_M * rng.uniform(0.8, 1.3))
                )
                if not shape.intersects(blocked) and shape.within(site):
                    clutter.append(shape)
    return clutter


def campus() -> World:
    w, h = _CAMPUS_SIZE_M
    fence = _thick([_rect_lines(0, 0, w, h)], OUTER_WALL_THICKNESS_M)
    px, py = _CAMPUS_PATH_X, _CAMPUS_PATH_Y
    paths = MultiLineString([[(x, py[0]), (x, py[-1])] for x in px] + [[(px[0], y), (px[-1], y)] for y in py])
    buildings = _campus_buildings()
    routes = [
        [(px[0], py[0]), (px[1], py[0]), (px[1], py[1]), (px[0], py[1])],
        [(px[2], py[1]), (px[2], py[2]), (px[1], py[2]), (px[1], py[1])],
        [(px[3], py[0]), (px[3], py[1]), (px[2], py[1]), (px[2], py[0])],
        [(px[1], py[1]), (px[3], py[1]), (px[3], py[2]), (px[0], py[2]), (px[0], py[1])],
    ]
    return _finish("campus", fence + buildings + _campus_clutter(paths, buildings), routes)


BUILDERS = {"office": office, "warehouse": warehouse, "campus": campus}


def builtin_world(name: str) -> World:
    """One of :data:`~robot_agent.sim.world.BUILTIN_WORLDS`, built fresh (worlds are immutable;
    build once and reuse)."""
    if name not in BUILDERS:
        raise WorldError(f"unknown world {name!r}; valid names: {', '.join(BUILTIN_WORLDS)}")
    return BUILDERS[name]()
