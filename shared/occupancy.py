"""Free space as polygons, and the occupancy grid a navigation stack loads (pure).

Robots publish the space their lasers saw free per view (:class:`shared.messages.FreeSpace`); the
server unites them in the global frame (:class:`shared.messages.FusedFree`). A navigation stack
(nav2's ``map_server``, most planners) wants a grid: :func:`occupancy_grid` rasterizes the fused
segments as occupied over the fused free space, everything else unknown; ``shared/viz.py`` writes
it as the PGM + YAML pair ROS ``map_server`` defined.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import shapely
from shapely.geometry import MultiPolygon, Polygon

from shared.geometry import compose, sample_segments
from shared.messages import MAX_VERTICES, FreeSpace, FusedFree

FREE, UNKNOWN, OCCUPIED = 0, -1, 100  # cell values, as in a ROS OccupancyGrid


def place(rings: list[np.ndarray], pose: np.ndarray) -> list[np.ndarray]:
    """Rings ``(n,2)`` given in the frame whose pose is ``pose (3,)``, in the frame the pose is in."""
    c, s = np.cos(pose[2]), np.sin(pose[2])
    return [np.column_stack([c * v[:, 0] - s * v[:, 1] + pose[0], s * v[:, 0] + c * v[:, 1] + pose[1]])
            for v in rings]  # fmt: skip


def view_vertices(msg: FreeSpace, transform: np.ndarray | None = None) -> np.ndarray:
    """Every vertex ``(P,2)`` of a robot's free space in its map frame, or in the frame
    ``transform (3,)`` maps its map frame into (the global frame): each moved by its view's pose."""
    poses = msg.view_pose if transform is None else compose(np.asarray(transform, float), msg.view_pose)
    pose = poses[np.repeat(msg.ring_view, np.diff(msg.ring_offsets))]  # (P,3): each vertex's view
    c, s = np.cos(pose[:, 2]), np.sin(pose[:, 2])
    v = msg.vertices
    return np.column_stack([c * v[:, 0] - s * v[:, 1] + pose[:, 0], s * v[:, 0] + c * v[:, 1] + pose[:, 1]])


def view_rings(msg: FreeSpace, transform: np.ndarray | None = None) -> list[np.ndarray]:
    """Every ring of a robot's free space, placed as :func:`view_vertices` places them."""
    return np.split(view_vertices(msg, transform), msg.ring_offsets[1:-1])


def view_walls(
    msg: FreeSpace, transform: np.ndarray | None = None, vertices: np.ndarray | None = None
) -> np.ndarray:
    """The wall edges of a robot's views (the edges that run along hits) as segments ``(E,2,2)``,
    placed as :func:`view_vertices` places them (or given ``vertices`` so placed)."""
    v = view_vertices(msg, transform) if vertices is None else vertices
    o = msg.ring_offsets
    nxt = np.arange(len(v)) + 1  # the next vertex of its ring: the first after the last
    nxt[o[1:] - 1] = o[:-1]
    return np.stack([v[msg.wall], v[nxt[msg.wall]]], axis=1)


def unexplained(walls: np.ndarray, known, spacing_m: float = 0.05) -> np.ndarray:
    """The parts of wall segments ``(E,2,2)`` outside ``known`` (a shapely geometry: the segment
    map widened, and the free space): runs of samples ``spacing_m`` apart, as segments."""
    pts, owner, _ = sample_segments(walls, spacing_m, ends=True)
    if not len(pts):
        return np.zeros((0, 2, 2))
    out = np.ones(len(pts), bool)
    if known is not None and not known.is_empty:
        out = ~shapely.contains_xy(known, pts[:, 0], pts[:, 1])
    # runs of outside samples along one wall: a segment from the first to the last of each
    prev_out = np.concatenate([[False], out[:-1]])
    prev_same = np.concatenate([[False], owner[1:] == owner[:-1]])
    run = np.cumsum(out & ~(prev_out & prev_same))
    idx = np.nonzero(out)[0]
    if not len(idx):
        return np.zeros((0, 2, 2))
    r = run[idx]
    change = r[1:] != r[:-1]
    first, last = idx[np.concatenate([[True], change])], idx[np.concatenate([change, [True]])]
    seg = np.stack([pts[first], pts[last]], axis=1)
    return seg[np.linalg.norm(seg[:, 1] - seg[:, 0], axis=1) > spacing_m * 1.5]  # a sample or two: noise


def union(rings: list[np.ndarray]):
    """The union of polygons given as outer rings (a shapely geometry)."""
    polys = [Polygon(v) for v in rings if len(v) >= 3]
    return shapely.union_all([p if p.is_valid else shapely.make_valid(p) for p in polys])


def polygons(geom) -> list[Polygon]:
    """The polygons in any shapely geometry."""
    if geom is None or geom.is_empty:
        return []
    if geom.geom_type == "Polygon":
        return [geom]
    if hasattr(geom, "geoms"):
        return [p for g in geom.geoms for p in polygons(g)]
    return []


def cell_index(xy: np.ndarray, x0: float, y0: float, cell_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Row and column of the cells (cell (0,0)'s lower-left corner at ``(x0, y0)``, square cells
    of ``cell_m``) holding points ``(N,2)``; they may fall outside the grid."""
    xy = np.asarray(xy, float).reshape(-1, 2)
    col = np.floor((xy[:, 0] - x0) / cell_m).astype(np.int64)
    row = np.floor((xy[:, 1] - y0) / cell_m).astype(np.int64)
    return row, col


def ring_edges(geom) -> np.ndarray:
    """Every ring's edges ``(E,2,2)`` (outer rings and holes) of the polygons in ``geom``."""
    polys = polygons(geom)
    if not polys:
        return np.zeros((0, 2, 2))
    xy, ring = shapely.get_coordinates(shapely.get_rings(np.array(polys, dtype=object)), return_index=True)
    same = ring[1:] == ring[:-1]  # (a ring's coordinates close on its first: no edge across rings)
    return np.stack([xy[:-1][same], xy[1:][same]], axis=1)


def fill(
    edges: np.ndarray, x0: float, y0: float, cell_m: float, shape: tuple[int, int], chunk: int = 20_000
) -> np.ndarray:
    """The cells ``(H,W)`` bool of a grid (cell (0,0)'s lower-left corner at ``(x0, y0)``) whose
    centre lies inside the rings whose edges are ``edges (E,2,2)``, by the even-odd rule (outer
    rings and their holes; polygons that do not overlap): a scanline fill, each edge's crossings
    of the rows' centre lines toggling the cells right of them, summed along each row (``chunk``
    edges at a time: bounded memory)."""
    h, w = shape
    toggles = np.zeros(h * (w + 1), np.uint8)
    edges = np.asarray(edges, float).reshape(-1, 2, 2)
    for c0 in range(0, len(edges), chunk):
        e = (edges[c0 : c0 + chunk] - (x0, y0)) / cell_m - 0.5  # (cell centres at whole numbers)
        ya, yb = e[:, 0, 1], e[:, 1, 1]
        lo = np.clip(np.ceil(np.minimum(ya, yb)), 0, h).astype(np.int64)  # rows lo <= r < hi cross
        hi = np.clip(np.ceil(np.maximum(ya, yb)), 0, h).astype(np.int64)
        n = hi - lo
        k = np.flatnonzero(n > 0)
        owner = np.repeat(k, n[k])
        row = lo[owner] + np.arange(len(owner)) - np.repeat(np.cumsum(n[k]) - n[k], n[k])
        t = (row - ya[owner]) / (yb[owner] - ya[owner])
        x = e[owner, 0, 0] + t * (e[owner, 1, 0] - e[owner, 0, 0])
        col = np.clip(np.ceil(x), 0, w).astype(np.int64)  # the first cell centre right of the crossing
        at, count = np.unique(row * (w + 1) + col, return_counts=True)
        toggles[at] ^= (count & 1).astype(np.uint8)
    # (a uint8 sum wraps at 256: its parity stays right)
    return (np.cumsum(toggles.reshape(h, w + 1), axis=1, dtype=np.uint8)[:, :w] & 1).astype(bool)


def to_rings(geom, tolerance_m: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """``geom`` simplified by ``tolerance_m`` as ``ring_offsets, ring_hole, vertices`` (the arrays
    of a :class:`FusedFree`) and the tolerance used: doubled until the vertices fit one message."""
    tol = tolerance_m
    while True:
        rings, holes = [], []
        for p in polygons(geom.simplify(tol, preserve_topology=True) if tol > 0 else geom):
            rings.append(np.asarray(p.exterior.coords)[:-1])
            holes.append(0)
            for hole in p.interiors:
                rings.append(np.asarray(hole.coords)[:-1])
                holes.append(1)
        keep = [i for i, r in enumerate(rings) if len(r) >= 3]
        rings, holes = [rings[i] for i in keep], [holes[i] for i in keep]
        while holes and holes[0] == 1:  # (a hole whose outer ring collapsed)
            rings, holes = rings[1:], holes[1:]
        n = sum(len(r) for r in rings)
        if n <= MAX_VERTICES:
            break
        tol = max(2 * tol, 0.05)
    offsets = np.concatenate([[0], np.cumsum([len(r) for r in rings])]).astype(np.int64)
    vertices = np.concatenate(rings) if rings else np.zeros((0, 2))
    return offsets, np.array(holes, np.int64), vertices, tol


def grid_walls(seg: np.ndarray, f: FusedFree | None) -> np.ndarray:
    """What a grid marks occupied: the fused segments ``(M,2,2)`` and the walls seen that they
    lack (:attr:`FusedFree.walls`)."""
    seg = np.asarray(seg, float).reshape(-1, 2, 2)
    return seg if f is None or not len(f.walls) else np.concatenate([seg, f.walls])


def fused_geometry(f: FusedFree | None):
    """The fused free space as a shapely geometry (empty for ``None``)."""
    if f is None:
        return MultiPolygon()
    return shapely.union_all([Polygon(outer, holes) for outer, holes in f.polygons()])


@dataclass(frozen=True)
class Grid:
    """An occupancy grid: ``cells (H,W)`` int8 (``FREE``, ``UNKNOWN``, ``OCCUPIED``), row 0 at
    ``origin_y``, column 0 at ``origin_x`` (the lower-left corner of cell (0,0)), square cells of
    ``resolution_m``."""

    cells: np.ndarray
    resolution_m: float
    origin_x: float
    origin_y: float

    def centres(self) -> tuple[np.ndarray, np.ndarray]:
        h, w = self.cells.shape
        xs = self.origin_x + (np.arange(w) + 0.5) * self.resolution_m
        ys = self.origin_y + (np.arange(h) + 0.5) * self.resolution_m
        return xs, ys

    def index(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Row and column of the cells holding points ``(N,2)`` (may fall outside)."""
        return cell_index(xy, self.origin_x, self.origin_y, self.resolution_m)


def occupancy_grid(seg: np.ndarray, free, resolution_m: float = 0.05, margin_m: float = 0.5) -> Grid:
    """The grid of fused segments ``(M,2,2)`` (occupied) over the free space ``free`` (a shapely
    geometry: cells whose centre lies in it are free), the rest unknown; it spans both, plus
    ``margin_m``. A wall wins over free space in its cells."""
    if resolution_m <= 0:
        raise ValueError(f"resolution must be positive, got {resolution_m}")
    seg = np.asarray(seg, float).reshape(-1, 2, 2)
    boxes = []
    if len(seg):
        boxes.append((*seg.reshape(-1, 2).min(axis=0), *seg.reshape(-1, 2).max(axis=0)))
    if free is not None and not free.is_empty:
        boxes.append(free.bounds)
    if not boxes:
        return Grid(np.full((1, 1), UNKNOWN, np.int8), resolution_m, 0.0, 0.0)
    b = np.array(boxes)
    x0, y0 = b[:, 0].min() - margin_m, b[:, 1].min() - margin_m
    x1, y1 = b[:, 2].max() + margin_m, b[:, 3].max() + margin_m
    x0, y0 = np.floor(x0 / resolution_m) * resolution_m, np.floor(y0 / resolution_m) * resolution_m
    w = int(np.ceil((x1 - x0) / resolution_m))
    h = int(np.ceil((y1 - y0) / resolution_m))
    if w * h > 200_000_000:
        raise ValueError(f"a {w} x {h} grid at {resolution_m} m is too large: choose a coarser resolution")
    grid = Grid(np.full((h, w), UNKNOWN, np.int8), resolution_m, float(x0), float(y0))
    if free is not None and not free.is_empty:
        xs, ys = grid.centres()
        shapely.prepare(free)
        for r0 in range(0, h, 256):  # rows in blocks: bounded memory on big maps
            yy, xx = np.meshgrid(ys[r0 : r0 + 256], xs, indexing="ij")
            inside = shapely.contains_xy(free, xx, yy)
            grid.cells[r0 : r0 + 256][inside] = FREE
    pts = sample_segments(seg, resolution_m / 4, ends=True)[0]
    row, col = grid.index(pts)
    ok = (row >= 0) & (row < h) & (col >= 0) & (col < w)
    grid.cells[row[ok], col[ok]] = OCCUPIED
    return grid


@dataclass(frozen=True)
class GridQuality:
    """An occupancy grid against the truth (a simulated world), cell by cell.

    ``wall_occupied``: share of the true wall cells with an occupied cell within one cell (of
    ``wall_cells``); ``seen_*`` the same over the wall cells a true beam hit (within one cell);
    ``covered_free``: share of the cells true beams crossed (short of their hit by one cell, no
    wall in them) that are free (of ``covered_cells``); ``wall_free``: share of the true wall cells
    marked free; ``free_cells`` / ``occupied_cells`` as exported."""

    wall_cells: int
    wall_occupied: float
    seen_wall_cells: int
    seen_wall_occupied: float
    covered_cells: int
    covered_free: float
    wall_free: float
    free_cells: int
    occupied_cells: int


def _mark(grid: Grid, pts: np.ndarray, mask: np.ndarray) -> None:
    row, col = grid.index(pts)
    h, w = grid.cells.shape
    ok = (row >= 0) & (row < h) & (col >= 0) & (col < w)
    mask[row[ok], col[ok]] = True


def _grow(mask: np.ndarray) -> np.ndarray:
    """``mask`` and its 8 neighbours."""
    out = mask.copy()
    p = np.pad(mask, 1)
    for dr in (-1, 0, 1):
        for dc in (-1, 0, 1):
            out |= p[1 + dr : p.shape[0] - 1 + dr, 1 + dc : p.shape[1] - 1 + dc]
    return out


def grid_quality(grid: Grid, true_walls: np.ndarray, origins: np.ndarray, ends: np.ndarray,
                 hit: np.ndarray) -> GridQuality:  # fmt: skip
    """``grid`` against true walls ``(W,2,2)`` and true beams from ``origins (N,2)`` to ``ends
    (N,2)`` (``hit (N,)``: the beam ended on a wall), all in the grid's frame."""
    res = grid.resolution_m
    shape = grid.cells.shape
    walls = np.zeros(shape, bool)
    _mark(grid, sample_segments(true_walls, res / 4, ends=True)[0], walls)
    seen = np.zeros(shape, bool)
    _mark(grid, np.asarray(ends)[np.asarray(hit, bool)], seen)
    seen_walls = walls & _grow(seen)
    covered = np.zeros(shape, bool)
    origins, ends = np.asarray(origins, float), np.asarray(ends, float)
    length = np.linalg.norm(ends - origins, axis=1)
    reach = np.maximum(length - res, 0.0)
    rays = np.stack([origins, origins + (ends - origins) * (reach / np.maximum(length, 1e-12))[:, None]], 1)
    for a in range(0, len(rays), 2000):  # beams in blocks: bounded memory
        _mark(grid, sample_segments(rays[a : a + 2000], res / 2, ends=True)[0], covered)
    covered &= ~walls
    occupied = grid.cells == OCCUPIED
    free = grid.cells == FREE
    near_occupied = _grow(occupied)

    def share(sel: np.ndarray, of: np.ndarray) -> float:
        return float(np.count_nonzero(sel & of) / max(np.count_nonzero(of), 1))

    return GridQuality(
        wall_cells=int(walls.sum()),
        wall_occupied=share(near_occupied, walls),
        seen_wall_cells=int(seen_walls.sum()),
        seen_wall_occupied=share(near_occupied, seen_walls),
        covered_cells=int(covered.sum()),
        covered_free=share(free, covered),
        wall_free=share(free, walls),
        free_cells=int(free.sum()),
        occupied_cells=int(occupied.sum()),
    )
