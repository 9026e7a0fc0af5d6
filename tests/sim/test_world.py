"""Built-in worlds keep their promises (size, loops, clearance); GeoJSON round trip and errors."""

from __future__ import annotations

import json
from functools import cache

import numpy as np
import pytest
import shapely
from shapely.geometry import LineString, Point, Polygon, box

from robot_agent.sim.robot import RobotConfig, RouteFollower, drive_route
from robot_agent.sim.world import (
    BUILTIN_WORLDS,
    WorldError,
    free_space,
    from_geojson,
    load_geojson,
    make_world,
    route_line,
    to_geojson,
    walls_from_geometries,
    walls_geometry,
)
from robot_agent.sim.worlds import BUILDERS, ROUTE_CLEARANCE_M, builtin_world


@cache
def world(name):
    return builtin_world(name)


@cache
def true_path(name, robot):
    """The simulated true path over one lap and a bit."""
    w, cfg = world(name), RobotConfig()
    lap_m = RouteFollower(w.routes[robot], w.starts[robot][:2], cfg).length_m
    poses, _ = drive_route(w.routes[robot], w.starts[robot], cfg, 2.0 * lap_m / cfg.max_v_mps)
    return poses


ROUTES = [(name, i) for name in BUILTIN_WORLDS for i in range(4)]


def test_builtin_names_and_unknown_name():
    assert set(BUILTIN_WORLDS) == set(BUILDERS)
    with pytest.raises(ValueError, match="office, warehouse, campus"):
        builtin_world("moon")


@pytest.mark.parametrize(
    "name, width, height", [("office", 30.0, 20.0), ("warehouse", 40.0, 25.0), ("campus", 120.0, 80.0)]
)
def test_world_sizes(name, width, height):
    w = world(name)
    assert w.name == name
    size = w.bounds[2:] - w.bounds[:2]
    np.testing.assert_allclose(size, [width, height], atol=0.5)
    assert w.walls.ndim == 3 and w.walls.shape[1:] == (2, 2)
    flat = w.walls.reshape(-1, 2)
    np.testing.assert_array_equal(w.bounds, np.r_[flat.min(0), flat.max(0)])


def test_campus_is_large_and_cluttered():
    w = world("campus")
    assert np.all(w.bounds[2:] - w.bounds[:2] >= [100.0, 60.0])
    small = [p for p in w.obstacles if p.area < 1.0]
    large = [p for p in w.obstacles if p.area > 50.0]
    assert len(small) >= 40  # trees, pillars, benches
    assert len(large) >= 6  # buildings (and the fence)


def test_warehouse_has_repetitive_aisles():
    shelves = [p for p in world("warehouse").obstacles if 30.0 < p.area < 40.0]
    assert 6 <= len(shelves) <= 8
    ys = sorted(p.centroid.y for p in shelves)
    np.testing.assert_allclose(np.diff(ys), np.diff(ys)[0])  # evenly spaced rows
    widths = {round(p.bounds[2] - p.bounds[0], 6) for p in shelves}
    assert len(widths) == 1  # identical rows


def test_office_ring_corridor_is_a_long_loop():
    w = world("office")
    ring = LineString([(4.5, 4.5), (25.5, 4.5), (25.5, 15.5), (4.5, 15.5), (4.5, 4.5)])
    assert ring.length >= 60.0
    assert free_space(w).buffer(-ROUTE_CLEARANCE_M).contains(ring)
    # the ring-patrolling routes (0: counter-clockwise, 2: clockwise) run all of it
    for robot in (0, 2):
        route = route_line(w.routes[robot])
        assert route.length >= 60.0
        assert route.buffer(0.01).contains(ring)


def test_office_rooms_have_doors_and_furniture():
    w = world("office")
    fs = free_space(w)
    room_centres = [(9.0, 1.75), (15.0, 18.25), (1.75, 6.75), (28.25, 13.25), (7.625, 7.75), (22.375, 12.25)]
    assert all(fs.contains(Point(c)) for c in room_centres)  # one connected navigable area
    furniture = [p for p in w.obstacles if p.area < 1.0]
    assert len(furniture) >= 20
    assert not any(fs.contains(p.centroid) for p in furniture)


@pytest.mark.parametrize("name", BUILTIN_WORLDS)
def test_routes_and_starts(name):
    w = world(name)
    assert w.num_robots == 4 and w.starts.shape == (4, 3)
    gaps = np.hypot(*(w.starts[:, None, :2] - w.starts[None, :, :2]).transpose(2, 0, 1))
    assert gaps[~np.eye(4, dtype=bool)].min() > 1.0  # distinct starts
    for route, start in zip(w.routes, w.starts, strict=True):
        line = route_line(route)
        assert line.is_closed and line.length > 40.0
        assert line.distance(Point(start[:2])) < 1e-9  # on the route
        heading = np.arctan2(*(route[0] - start[:2])[::-1])
        assert abs(np.angle(np.exp(1j * (heading - start[2])))) < 1e-9  # facing the first waypoint


@pytest.mark.parametrize("name, robot", ROUTES)
def test_route_clearance(name, robot):
    w = world(name)
    line = route_line(w.routes[robot])
    assert line.distance(walls_geometry(w)) >= ROUTE_CLEARANCE_M - 1e-9
    assert free_space(w).contains(line.buffer(ROUTE_CLEARANCE_M - 1e-6))


@pytest.mark.parametrize("name, robot", ROUTES)
def test_true_path_clearance(name, robot):
    w = world(name)
    path = true_path(name, robot)
    buffered = LineString(path[:, :2]).buffer(ROUTE_CLEARANCE_M - 0.05)  # 5 cm tracking tolerance
    assert not buffered.intersects(walls_geometry(w))
    assert free_space(w).contains(buffered)


def test_walls_from_geometries():
    hollow = Polygon([(0, 0), (4, 0), (4, 4), (0, 4)], [[(1, 1), (2, 1), (2, 2), (1, 2)]])
    polyline = LineString([(10, 0), (11, 0), (11, 1)])
    multi = shapely.MultiLineString([[(20, 0), (21, 0)], [(30, 0), (31, 0)]])
    walls = walls_from_geometries([hollow, polyline, multi])
    assert walls.shape == (4 + 4 + 2 + 2, 2, 2)  # no segment bridges two parts
    assert np.isclose(np.hypot(*(walls[:, 1] - walls[:, 0]).T).sum(), 16 + 4 + 2 + 2)
    assert walls_from_geometries([]).shape == (0, 2, 2)


def test_world_arrays_are_read_only():
    w = world("office")
    with pytest.raises(ValueError):
        w.walls[0, 0, 0] = 1.0
    with pytest.raises(ValueError):
        w.routes[0][0, 0] = 1.0


@pytest.mark.parametrize("name", BUILTIN_WORLDS)
def test_geojson_round_trip(name, tmp_path):
    w = world(name)
    path = tmp_path / f"{name}.geojson"
    path.write_text(json.dumps(to_geojson(w)))
    back = load_geojson(path)
    assert back.name == w.name
    np.testing.assert_array_equal(back.walls, w.walls)
    np.testing.assert_array_equal(back.starts, w.starts)
    np.testing.assert_array_equal(back.bounds, w.bounds)
    assert len(back.routes) == len(w.routes)
    for a, b in zip(back.routes, w.routes, strict=True):
        np.testing.assert_array_equal(a, b)
    assert len(back.obstacles) == len(w.obstacles)
    assert free_space(back).area == pytest.approx(free_space(w).area)


def test_geojson_user_file_with_polygon_walls_and_default_start():
    data = {
        "type": "FeatureCollection",
        "features": [
            {"type": "Feature", "properties": {}, "geometry": shapely.geometry.mapping(box(0, 0, 10, 6))},
            {
                "type": "Feature",
                "properties": {"kind": "route", "robot": 0},
                "geometry": {"type": "LineString", "coordinates": [[2, 2], [8, 2], [8, 4], [2, 4], [2, 2]]},
            },
        ],
    }
    w = from_geojson(data, default_name="tiny")
    assert w.name == "tiny" and len(w.walls) == 4
    assert w.routes[0].shape == (4, 2)  # the explicit closing point is dropped
    np.testing.assert_allclose(w.starts[0], [2.0, 3.0, -np.pi / 2])  # 1 m before route[0], facing it
    assert free_space(w).area == pytest.approx(60.0, rel=1e-4)


def feature(geometry, **props):
    return {"type": "Feature", "properties": props, "geometry": geometry}


WALL = {"type": "LineString", "coordinates": [[0, 0], [1, 0]]}
ROUTE = {"type": "LineString", "coordinates": [[0, 1], [1, 1], [1, 2]]}


@pytest.mark.parametrize(
    "data, message",
    [
        ([], "FeatureCollection"),
        ({"type": "FeatureCollection"}, "features"),
        ({"type": "FeatureCollection", "features": [{"type": "Nope"}]}, "feature 0"),
        (
            {"type": "FeatureCollection", "features": [feature({"type": "Point", "coordinates": [0, 0]})]},
            "feature 0 \\(wall\\): geometry type Point",
        ),
        (
            {
                "type": "FeatureCollection",
                "features": [feature({"type": "LineString", "coordinates": [[0]]})],
            },
            "feature 0: invalid geometry",
        ),
        ({"type": "FeatureCollection", "features": [feature(WALL, kind="door")]}, "unknown kind 'door'"),
        (
            {"type": "FeatureCollection", "features": [feature(ROUTE, kind="route", robot=1)]},
            "route robot indices",
        ),
        ({"type": "FeatureCollection", "features": [feature(ROUTE, kind="route", robot=-1)]}, "'robot'"),
        (
            {
                "type": "FeatureCollection",
                "features": [feature(ROUTE, kind="route", robot=0), feature(ROUTE, kind="route", robot=0)],
            },
            "robot 0 given twice",
        ),
        (
            {
                "type": "FeatureCollection",
                "features": [
                    feature(ROUTE, kind="route"),
                    feature({"type": "Point", "coordinates": [0, 1]}, kind="start"),
                ],
            },
            "'theta'",
        ),
        (
            {
                "type": "FeatureCollection",
                "features": [
                    feature({"type": "Point", "coordinates": [0, 1]}, kind="start", robot=3, theta=0.0)
                ],
            },
            "robots \\[3\\] have no route",
        ),
    ],
)
def test_malformed_geojson(data, message):
    with pytest.raises(WorldError, match=message):
        from_geojson(data)


def test_unreadable_file(tmp_path):
    bad = tmp_path / "bad.geojson"
    bad.write_text("{not json")
    with pytest.raises(WorldError, match=r"bad\.geojson"):
        load_geojson(bad)
    assert issubclass(WorldError, ValueError)


def test_make_world_checks_starts_against_routes():
    with pytest.raises(WorldError, match="2 start poses for 1 routes"):
        make_world("x", [box(0, 0, 5, 5)], routes=[[(1, 1), (4, 1), (4, 4)]], starts=np.zeros((2, 3)))
