"""Free space on the wire and the occupancy grid: messages refuse what is malformed, the codec
round-trips them (schema 4; a schema-3 sender has no such kinds), the grid puts walls over free
space, and the nav2 pair reads back — with a YAML parser and an image library, by nav2's own
rule — as walls occupied, free free and the rest unknown."""

from __future__ import annotations

import msgpack
import numpy as np
import pytest
import yaml
from PIL import Image
from shapely.geometry import Polygon

from shared import codec
from shared.messages import FreeSpace, FusedFree, WireFormatError
from shared.occupancy import (
    FREE,
    OCCUPIED,
    UNKNOWN,
    fill,
    grid_quality,
    occupancy_grid,
    ring_edges,
    to_rings,
    unexplained,
    view_rings,
    view_walls,
)
from shared.viz import save_nav2

SQUARE = np.array([[0.0, 0.0], [2.0, 0.0], [2.0, 2.0], [0.0, 2.0]])


def free_space(seq=0, poses=None) -> FreeSpace:
    poses = np.array([[1.0, 2.0, 0.0], [3.0, 2.0, np.pi / 2]]) if poses is None else poses
    verts = np.concatenate([SQUARE, SQUARE + 0.5, SQUARE * 0.5])
    wall = np.array([1, 1, 0, 0] * 3, bool)
    offsets, ring_view = np.array([0, 4, 8, 12]), np.array([0, 1, 1])
    return FreeSpace("robot1", "s1", seq, 12.5, poses, offsets, ring_view, verts, wall)


def test_free_space_round_trips_in_centimetres_and_old_schemas_do_not_have_it():
    m = free_space()
    back = codec.decode(codec.encode(m), expect=FreeSpace)
    np.testing.assert_allclose(back.vertices, m.vertices, atol=0.005)
    np.testing.assert_allclose(back.view_pose, m.view_pose, atol=1e-6)  # float32 poses
    assert back.ring_view.tolist() == [0, 1, 1] and back.ring_offsets.tolist() == [0, 4, 8, 12]
    assert back.wall.tolist() == m.wall.tolist()  # bits on the wire
    assert len(codec.encode(m)) < 300  # 12 vertices, 2 views: compact
    fields = msgpack.unpackb(codec.encode(m), raw=False)
    with pytest.raises(WireFormatError, match="kind: free_space does not exist in schema 3"):
        codec.decode(msgpack.packb(dict(fields, schema=3), use_bin_type=True))
    walls = np.array([[[0.0, 0.0], [1.0, 0.0]]])
    f = FusedFree("server", "", 3, 7, 1.0, 0.05, np.array([0, 4, 8]), np.array([0, 1]),
                  np.concatenate([SQUARE * 3, SQUARE + 1.0]), walls)  # fmt: skip
    back = codec.decode(codec.encode(f), expect=FusedFree)
    assert back.version == 3 and back.map_version == 7 and back.ring_hole.tolist() == [0, 1]
    assert back.walls.shape == (1, 2, 2)
    ((outer, holes),) = back.polygons()
    assert Polygon(outer, holes).area == pytest.approx(36.0 - 4.0)


@pytest.mark.parametrize(
    "change, match",
    [
        (dict(ring_offsets=np.array([0, 2, 12])), "at least 3 vertices a ring"),
        (dict(ring_offsets=np.array([0, 4, 8, 11])), "must run from 0 to 12"),
        (dict(ring_view=np.array([0, 1, 2])), "ring_view: values out of range"),
        (dict(vertices=np.full((12, 2), 400.0)), "vertices: values out of range"),
        (dict(view_pose=np.array([[0.0, 0.0, np.nan], [0, 0, 0]])), "view_pose: contains NaN"),
        (dict(wall=np.ones(11, bool)), "wall: expected shape \\(12\\)"),
    ],
)
def test_a_malformed_free_space_is_refused_naming_the_field(change, match):
    m = free_space()
    fields = dict(robot=m.robot, session=m.session, seq=m.seq, stamp_s=m.stamp_s, view_pose=m.view_pose,
                  ring_offsets=m.ring_offsets, ring_view=m.ring_view, vertices=m.vertices,
                  wall=m.wall)  # fmt: skip
    with pytest.raises(WireFormatError, match=match):
        FreeSpace(**{**fields, **change})


def test_view_rings_follow_the_views_poses_and_a_transform():
    m = free_space()
    rings = view_rings(m)
    np.testing.assert_allclose(rings[0], SQUARE + np.array([1.0, 2.0]))
    np.testing.assert_allclose(rings[1][0], [3.0 - 0.5, 2.0 + 0.5])  # (0.5, 0.5) turned by 90°
    moved = view_rings(m, np.array([10.0, 0.0, 0.0]))
    np.testing.assert_allclose(moved[0], SQUARE + np.array([11.0, 2.0]))
    walls = view_walls(m)  # the edges marked: the first two of each ring
    assert walls.shape == (6, 2, 2)
    np.testing.assert_allclose(walls[0], [[1.0, 2.0], [3.0, 2.0]])


def test_unexplained_keeps_the_parts_of_walls_outside_what_is_known():
    walls = np.array([[[0.0, 0.0], [4.0, 0.0]], [[0.0, 1.0], [1.0, 1.0]]])
    known = Polygon([[1.0, -0.5], [3.0, -0.5], [3.0, 2.0], [1.0, 2.0]])
    known = known.union(Polygon(SQUARE + np.array([-0.5, 0.5])))
    out = unexplained(walls, known)
    assert len(out) == 2  # [0, 1) and (3, 4] of the first; the second is known
    np.testing.assert_allclose(out[:, :, 1], 0.0)
    assert out[0, 0, 0] == 0.0 and out[0, 1, 0] == pytest.approx(1.0) and out[1, 1, 0] == 4.0


def test_to_rings_keeps_holes_and_coarsens_only_to_fit():
    geom = Polygon(SQUARE * 5, [SQUARE + 1.0])
    offsets, hole, _, tol = to_rings(geom, 0.05)
    assert hole.tolist() == [0, 1] and tol == 0.05 and offsets.tolist() == [0, 4, 8]


def room_grid(res=0.1):
    walls = np.array([[[0, 0], [4, 0]], [[4, 0], [4, 3]], [[4, 3], [0, 3]], [[0, 3], [0, 0]]], float)
    free = Polygon([[0.02, 0.02], [3.98, 0.02], [3.98, 2.98], [0.02, 2.98]])
    return walls, occupancy_grid(walls, free, res, margin_m=0.5)


def test_the_grid_puts_walls_over_free_space_and_leaves_the_rest_unknown():
    walls, g = room_grid()
    assert g.cells.shape == (40, 50) and g.resolution_m == 0.1
    row, col = g.index(np.array([[2.0, 1.5], [4.0, 1.5], [-0.3, 1.5], [2.0, 0.0]]))
    assert [g.cells[r, c] for r, c in zip(row, col, strict=True)] == [FREE, OCCUPIED, UNKNOWN, OCCUPIED]
    origins = np.array([[2.0, 1.5]] * 4)
    ends = np.array([[4.0, 1.5], [0.0, 1.5], [2.0, 3.0], [2.0, 0.0]])
    q = grid_quality(g, walls, origins, ends, np.ones(4, bool))
    assert q.wall_occupied == 1.0 and q.wall_free == 0.0 and q.covered_free == 1.0
    assert q.seen_wall_cells < q.wall_cells and q.seen_wall_occupied == 1.0
    # a free polygon through a wall leaves the wall occupied
    leaky = occupancy_grid(walls, Polygon([[-1, -1], [5, -1], [5, 4], [-1, 4]]), 0.1)
    assert grid_quality(leaky, walls, origins, ends, np.ones(4, bool)).wall_free == 0.0


def test_the_nav2_pair_reads_back_with_an_independent_reader(tmp_path):
    _, g = room_grid(0.05)
    pgm, yml = save_nav2(tmp_path / "map.yaml", g)
    meta = yaml.safe_load(yml.read_text())
    assert meta["image"] == "map.pgm" and meta["mode"] == "trinary" and meta["negate"] == 0
    assert meta["resolution"] == 0.05 and len(meta["origin"]) == 3
    img = np.asarray(Image.open(pgm))
    assert img.dtype == np.uint8 and img.shape == g.cells.shape
    # nav2's map_io for a trinary map: occ = (255 - value) / 255; > occupied_thresh occupied,
    # < free_thresh free, else unknown
    occ = (255.0 - img) / 255.0
    cell = np.where(occ > meta["occupied_thresh"], 100, np.where(occ < meta["free_thresh"], 0, -1))
    assert set(np.unique(cell)) == {100, 0, -1}

    def at(x, y):  # the image's row 0 is the top; origin is the lower-left pixel's corner
        col = int((x - meta["origin"][0]) / meta["resolution"])
        row = img.shape[0] - 1 - int((y - meta["origin"][1]) / meta["resolution"])
        return cell[row, col]

    assert at(2.0, 1.5) == 0 and at(1.0, 2.5) == 0  # inside: free
    assert at(4.0, 1.5) == 100 and at(2.0, 3.0) == 100 and at(0.0, 0.5) == 100  # walls
    assert at(-0.3, 1.0) == -1 and at(4.3, 2.0) == -1  # outside: unknown
    with pytest.raises(ValueError, match=r"named \*\.yaml"):
        save_nav2(tmp_path / "map.pgm", g)


@pytest.mark.parametrize("x0, y0", [(-1.0, -1.0), (3.01, 1.52), (-7.0, -6.0)])
def test_a_scanline_fill_holds_the_cells_whose_centre_lies_in_the_polygon(x0, y0):
    """``fill`` (the contradiction check's grid) against shapely's own point test, cell by cell: a
    room with a pillar and a sliver hole, a jagged star of 400 vertices, and windows that cut
    them (a part filled in its box of a larger grid)."""
    import shapely

    rng = np.random.default_rng(3)
    a = np.sort(rng.uniform(0.0, 2 * np.pi, 400))
    r = rng.uniform(1.0, 5.0, 400)
    star = shapely.Polygon(np.column_stack([12.0 + r * np.cos(a), 3.0 + r * np.sin(a)])).buffer(0)
    room = shapely.box(0.0, 0.0, 10.0, 6.0).difference(shapely.box(2.0, 2.0, 4.0, 4.0))
    room = room.difference(shapely.box(6.0, 1.0, 6.03, 5.0))  # thinner than a cell
    geom = shapely.union_all([room, star])
    cell, shape = 0.05, (200, 380)
    cells = fill(ring_edges(geom), x0, y0, cell, shape)
    xx, yy = np.meshgrid(x0 + (np.arange(shape[1]) + 0.5) * cell, y0 + (np.arange(shape[0]) + 0.5) * cell)
    truth = shapely.contains_xy(geom, xx, yy)
    assert truth.sum() > 5000 and (cells == truth).all()
    assert not fill(np.zeros((0, 2, 2)), x0, y0, cell, shape).any()
