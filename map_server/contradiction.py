"""Negative evidence for a placement: walls where another robot's laser saw free space.

A matcher scores what agrees (overlap of walls); a building symmetric under a half turn, or with
identical aisles, offers a mirror image that agrees about as well as the truth — the simulated
warehouse's routes are half-turn images of each other, and only pallets a metre apart tell them
apart. What a wrong place cannot hide is the disagreement: under it, some of the robot's walls
land in space the placed robots' lasers saw through, or the placed walls in space the robot saw
through (the acceptance index of occupancy-grid merging, Birk and Carpin 2006, on segments and
free-space polygons).

Pure: the robots' free space comes in as shapely geometry in each map frame
(``freespace.FreeSpaces.area``) and is shrunk onto a grid (:func:`shrink_placed`, placed where
the maps are); nothing here does I/O.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from shared.geometry import apply_points, apply_segments, inverse, sample_segments
from shared.occupancy import cell_index, fill, ring_edges


@dataclass(frozen=True)
class ContradictionConfig:
    # On (2026-11-28, bench_merge.py 10 seeds, bench_demo.py --logs --splits 3): the simulated
    # warehouse's 14 half-turned merges in 20 robots and the office's one become 1 wrong merge,
    # undone later in the run (warehouse seed 2); 11 robots unplaced at the end (10 in the
    # warehouse, with alignment.MAX_VETOED = 20 distinct places checked); on Intel, ACES and
    # MIT-CSAIL cut in 3 no true place was vetoed (3/3, 1/3, 1/3 placed; off: 3/3, 2/3, 1/3 — the
    # runs differ by which piece became the reference, none was refused for contradiction). The
    # fixed threshold alone vetoed the real pieces' true places (28-89 m contradicted, 1/3 placed
    # each): the noise allowance below (Check) is what lets them through.
    enabled: bool = True
    margin_m: float = 0.3  # free space is shrunk by this much first (its edges are walls seen,
    # ranges and the maps' drift move them by centimetres to a decimetre)
    cell_m: float = 0.05  # ... onto cells this small (shrink_placed)
    max_cells: int = 4_000_000  # ... coarser where a free space's box would take more
    step_m: float = 0.1  # walls are sampled this densely
    # a placement is refused when this much wall (both ways) contradicts and this share of the
    # overlap matched (bench_merge.py, office and warehouse, 10 seeds: true places 0.0-2.1 m at
    # 48-251 m matched, the warehouse's half-turned ones 3.4-10 m at 100-230 m)
    max_m: float = 2.0
    max_share: float = 0.02
    # ... and this many times what the maps contradict themselves by where they meet (Check): a
    # real log's pieces at their truth contradict each other by up to 3.6 times that (ACES); the
    # simulated maps contradict themselves by 0-1 m, so a warehouse mirror image (3.4-10 m) can
    # pass where a robot's own map is noisy (warehouse seed 2 at 132 s; with 0: no wrong merge)
    noise_factor: float = 4.0
    # A close call decided by the free space seen (Check.outshone): a best place within
    # ``close_ratio`` of a distinct rival's net score, contradicted by more than ``max_m``, is set
    # aside when the rival's walls stand ``outshone_factor`` times less densely in free space seen
    # (metres of wall per m2 that both sides saw free; the rival's over at least
    # ``outshone_min_seen_m2``, the best's over at least that much). A real log's pieces are
    # contradicted at their truth by metres (their paths bend) and within the noise allowance
    # so is a mirror image: ACES in 3 pieces (78b5f0c, seed 0) merged its first piece half-turned
    # at 1.17x the truth's net score, 151 m of walls contradicted over 149 m2 (1.0 m/m2) against
    # the truth's 130 m over 314 m2 (0.41). Over 46 stored real-log final states (Intel, ACES,
    # MIT-CSAIL in 3 pieces, sessions 36-37; each piece searched again against the others where
    # they ended) no piece's final place with a distinct rival within 2x had over 1.4 times the
    # rival's density; the simulated maps' true places are contradicted by 0-2.1 m, mostly under
    # ``max_m``, so the rule rarely looks at them (bench_merge: every row the same with it)
    close_ratio: float = 2.0
    outshone_factor: float = 2.0
    outshone_min_seen_m2: float = 50.0

    @property
    def grid(self) -> tuple[float, float, int]:
        """:func:`shrink`'s arguments after the area: ``margin_m, cell_m, max_cells``."""
        return self.margin_m, self.cell_m, self.max_cells


@dataclass(frozen=True)
class Shrunk:
    """Free space shrunk, as cells: ``cells (H,W)`` bool, cell (0,0)'s lower-left corner at
    ``(x0, y0)``, square cells of ``cell_m`` — what :func:`shrink` gives, for point queries."""

    cells: np.ndarray
    cell_m: float
    x0: float
    y0: float

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        h, w = self.cells.shape
        return self.x0, self.y0, self.x0 + w * self.cell_m, self.y0 + h * self.cell_m

    @property
    def area(self) -> float:
        return float(self.cells.sum()) * self.cell_m**2

    def contains_xy(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Whether each point lies in a cell kept."""
        x = np.asarray(x, float)
        row, col = cell_index(np.column_stack([x.ravel(), np.ravel(y)]), self.x0, self.y0, self.cell_m)
        h, w = self.cells.shape
        ok = (row >= 0) & (row < h) & (col >= 0) & (col < w)
        out = np.zeros(len(ok), bool)
        out[ok] = self.cells[row[ok], col[ok]]
        return out.reshape(x.shape)

    def centres(self) -> np.ndarray:
        """The centres ``(K,2)`` of the cells kept."""
        row, col = np.nonzero(self.cells)
        return np.column_stack([self.x0 + (col + 0.5) * self.cell_m, self.y0 + (row + 0.5) * self.cell_m])


def shrink(
    area,
    margin_m: float,
    cell_m: float = ContradictionConfig.cell_m,
    max_cells: int = ContradictionConfig.max_cells,
) -> Shrunk | None:
    """``area`` (shapely) shrunk by ``margin_m`` (:func:`shrink_placed` of it alone)."""
    return shrink_placed([(area, None)], margin_m, cell_m, max_cells)


def shrink_placed(
    parts: list,
    margin_m: float,
    cell_m: float = ContradictionConfig.cell_m,
    max_cells: int = ContradictionConfig.max_cells,
) -> Shrunk | None:
    """The union of ``parts`` — ``(area, pose)``, a shapely area in a frame placed at ``pose (3,)``
    (None: as it is) — shrunk by ``margin_m``, as cells of ``cell_m`` (coarser where the union's
    box would take more than ``max_cells``): the cells whose centre lies in the union farther than
    ``margin_m`` from its edge (a disk's erosion, to within a cell). None when
    nothing is left. A grid, not a polygon buffer: a real log's free space (7,000-12,000 vertices,
    up to 1,300 holes) took GEOS 1-5 s and 200 MB to shrink, searched again at every new map."""
    edges, boxes = [], []  # each part's edges, and their box (lo, hi)
    for area, pose in parts:
        if area is None or area.is_empty:
            continue
        e = ring_edges(area)
        if pose is not None and len(e):
            e = apply_segments(np.asarray(pose, float), e)
        if len(e):
            edges.append(e)
            boxes.append((e.reshape(-1, 2).min(axis=0), e.reshape(-1, 2).max(axis=0)))
    if not edges:
        return None
    lo, hi = np.min([b[0] for b in boxes], axis=0), np.max([b[1] for b in boxes], axis=0)
    cell = max(cell_m, float(np.sqrt(np.prod(hi - lo + 2 * cell_m) / max_cells)))
    x0, y0 = np.floor(lo / cell) * cell - cell  # (a cell outside every edge: the border is not free)
    w, h = (np.ceil((hi - (x0, y0)) / cell) + 1).astype(int)
    free = np.zeros((h, w), bool)
    for e, (e_lo, e_hi) in zip(edges, boxes, strict=True):  # each part in its own box (the parts
        c0, r0 = np.floor((e_lo - (x0, y0)) / cell).astype(int)  # overlap: even-odd holds in one)
        c1, r1 = np.minimum(np.ceil((e_hi - (x0, y0)) / cell).astype(int) + 1, (w, h))
        px, py = x0 + c0 * cell, y0 + r0 * cell
        part = fill(e, px, py, cell, (r1 - r0, c1 - c0))
        # the cells its edges cross are its edge's, not free: a hole narrower than a cell (a gap
        # between views either side of a wall) holds no cell's centre and would vanish
        for k in range(0, len(e), 20_000):  # (in chunks: bounded memory; indexed as the grid is)
            row, col = cell_index(sample_segments(e[k : k + 20_000], cell / 2, ends=True)[0], x0, y0, cell)
            part[row - r0, col - c0] = False
        free[r0:r1, c0:c1] |= part
    # (measured from the centres of the cells its edges cross, up to 0.7 of a cell inside the
    # edge; a quarter of a cell more errs on shrinking more, as GEOS's mitred buffer did: a 10 x 6 m
    # room shrunk by 0.3 m keeps 49.6 m2 of 9.4 x 5.4 = 50.8, an office robot's free space 151 m2
    # where the mitred buffer kept 154 and a round one 157)
    keep = _eroded(free, margin_m / cell + 0.25)
    rows, cols = np.flatnonzero(keep.any(axis=1)), np.flatnonzero(keep.any(axis=0))
    if not len(rows):
        return None
    keep = keep[rows[0] : rows[-1] + 1, cols[0] : cols[-1] + 1]
    return Shrunk(keep, cell, float(x0 + cols[0] * cell), float(y0 + rows[0] * cell))


def _eroded(free: np.ndarray, radius: float, band: int = 256) -> np.ndarray:
    """The cells of ``free (H,W)`` farther than ``radius`` cells (centre to centre) from every
    cell not free — its first and last columns are not — by a Euclidean distance transform in
    bands of ``band`` rows, each with the rows within ``radius`` either side (bounded memory: the
    transform keeps 16 bytes a cell)."""
    h, pad = free.shape[0], int(np.ceil(radius)) + 1
    out = np.empty_like(free)
    for r0 in range(0, h, band):
        r1 = min(h, r0 + band)
        a, b = max(0, r0 - pad), min(h, r1 + pad)
        out[r0:r1] = ndimage.distance_transform_edt(free[a:b])[r0 - a : r1 - a] > radius
    return out


def inside_m(area, seg: np.ndarray, step_m: float) -> float:
    """Length of ``seg (N,2,2)`` inside (prepared) ``area``, sampled every ``step_m``."""
    if area is None or not len(seg):
        return 0.0
    pts, _, w = sample_segments(seg, step_m)
    return float(w[area.contains_xy(pts[:, 0], pts[:, 1])].sum())


def contradiction_m(
    pose: np.ndarray,
    robot_seg: np.ndarray,
    robot_free,
    placed_seg: np.ndarray,
    placed_free,
    cfg: ContradictionConfig,
) -> float:
    """Metres of wall that contradict the robot's map frame at ``pose``: the robot's walls
    ``robot_seg`` (its frame) inside the placed robots' free space ``placed_free`` (global), plus
    the placed walls ``placed_seg`` (global) inside the robot's free space ``robot_free`` (its
    frame) — each as :func:`shrink` gives it. Either may be None (not known: no evidence)."""
    pose = np.asarray(pose, float)
    out = inside_m(placed_free, apply_segments(pose, robot_seg), cfg.step_m)
    if robot_free is not None and len(placed_seg):
        local = apply_segments(inverse(pose), placed_seg)
        lo, hi = np.array(robot_free.bounds[:2]), np.array(robot_free.bounds[2:])
        near = ((local.max(axis=1) >= lo) & (local.min(axis=1) <= hi)).all(axis=1)
        out += inside_m(robot_free, local[near], cfg.step_m)
    return out


def refused(contradicted_m: float, matched_m: float, cfg: ContradictionConfig, noise_m: float = 0.0) -> bool:
    """Whether that much contradiction refuses a placement that matched ``matched_m``, where the
    two sides' own maps contradict their own free space by ``noise_m`` (:class:`Check`)."""
    return contradicted_m > max(cfg.max_m, cfg.max_share * matched_m, cfg.noise_factor * noise_m)


def own_noise(seg: np.ndarray, free, step_m: float) -> tuple[np.ndarray, np.ndarray]:
    """The samples ``(N,2)`` of a map's walls ``seg`` inside its own free space ``free`` (as
    :func:`shrink` gives it; the map's frame) and their lengths ``(N,)``: what its laser and path
    contradict themselves by, and where."""
    if free is None or not len(seg):
        return np.zeros((0, 2)), np.zeros(0)
    pts, _, w = sample_segments(seg, step_m)
    inside = free.contains_xy(pts[:, 0], pts[:, 1])
    return pts[inside], w[inside]


def placed_noise(noises: list) -> tuple[np.ndarray, np.ndarray]:
    """Each placed map's :func:`own_noise` ``((pts, w), pose)`` — in its frame — placed at its
    ``pose``, all together in the global frame."""
    pts = [np.zeros((0, 2))] + [apply_points(pose, p) for (p, _), pose in noises]
    return np.concatenate(pts), np.concatenate([np.zeros(0)] + [w for (_, w), _ in noises])


class Check:
    """The contradiction test of one robot's search against the placed robots, prepared once:
    what ``alignment.estimate_alignment`` takes as ``veto`` — ``(pose, matched_m)`` -> why the
    place is contradicted, or None. Free spaces as :func:`shrink` gives them (None: not known).

    Real lasers and paths disagree with themselves: a door open in one pass and shut in another,
    people, a wall joined across a doorway, the drift a back end left — a real log's map has 3-10 %
    of its walls inside its own free space (Intel, ACES, MIT-CSAIL cut in 3, 2026-11-28), and two
    of its pieces placed rigidly at the truth contradict each other by up to 3.6 times what each
    contradicts itself (their paths bend differently). A simulated map contradicts itself by next
    to nothing. So the noise is measured, not assumed: the robot's own walls in its own free space
    (:func:`own_noise`), plus each placed robot's own (``placed_noise``: its samples placed in the
    global frame, and their lengths) within the robot's reach at the pose. Not the placed maps
    against each other's free space: that is where a wrong merge among them would show."""

    def __init__(
        self,
        robot_seg: np.ndarray,
        robot_free,
        placed_seg: np.ndarray,
        placed_free,
        cfg: ContradictionConfig,
        placed_noise: tuple[np.ndarray, np.ndarray] | None = None,
    ):
        self.robot_seg, self.robot_free = robot_seg, robot_free
        self.placed_seg, self.placed_free, self.cfg = placed_seg, placed_free, cfg
        self.robot_self_m = float(own_noise(robot_seg, robot_free, cfg.step_m)[1].sum())
        self._noise_pts, self._noise_w = (
            placed_noise if placed_noise is not None else (np.zeros((0, 2)), np.zeros(0))
        )
        self._reach = None  # the robot's map and free space: its box in its frame
        # each place measured, by its pose's bytes: a search measures the best again, and a close
        # call the best and its rival in turn (bounded: a Check lives for one search)
        self._contradicted: dict[bytes, float] = {}
        self._seen: dict[bytes, float] = {}
        self._centres = None  # the robot's free cells' centres (its frame), once seen_m2 asks
        boxes = [robot_seg.reshape(-1, 2)] if len(robot_seg) else []
        if robot_free is not None:
            boxes.append(np.reshape(robot_free.bounds, (2, 2)))
        if boxes:
            b = np.concatenate(boxes)
            (x0, y0), (x1, y1) = b.min(axis=0), b.max(axis=0)
            self._reach = np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]])

    def contradicted_m(self, pose: np.ndarray) -> float:
        pose = np.asarray(pose, float)
        key = pose.tobytes()
        if key not in self._contradicted:
            self._contradicted[key] = contradiction_m(
                pose, self.robot_seg, self.robot_free, self.placed_seg, self.placed_free, self.cfg
            )
        return self._contradicted[key]

    def seen_m2(self, pose: np.ndarray) -> float:
        """The area both sides saw free (as :func:`shrink` gives it) with the robot's map frame at
        ``pose``: where a wrong place could have been contradicted at all (0: either is unknown)."""
        if self.robot_free is None or self.placed_free is None:
            return 0.0
        key = np.asarray(pose, float).tobytes()
        if key not in self._seen:
            if self._centres is None:
                self._centres = self.robot_free.centres()
            inside = self.placed_free.contains_xy(*apply_points(np.asarray(pose, float), self._centres).T)
            self._seen[key] = float(inside.sum()) * self.robot_free.cell_m**2
        return self._seen[key]

    def noise_m(self, pose: np.ndarray) -> float:
        """What the robot and the placed robots within its reach at ``pose`` contradict
        themselves by."""
        if self._reach is None or not len(self._noise_w):
            return self.robot_self_m
        pose = np.asarray(pose, float)
        c, s = np.cos(pose[2]), np.sin(pose[2])
        corners = self._reach @ np.array([[c, s], [-s, c]]) + pose[:2]
        lo, hi = corners.min(axis=0), corners.max(axis=0)
        near = ((self._noise_pts >= lo) & (self._noise_pts <= hi)).all(axis=1)
        return self.robot_self_m + float(self._noise_w[near].sum())

    def outshone(self, pose: np.ndarray, rival: np.ndarray) -> str | None:
        """Why the place ``pose`` yields to the distinct place ``rival`` (a close call, the caller
        decides which is close): its walls stand in the free space both sides saw
        ``outshone_factor`` times more densely than the rival's (contradicted metres per m2 seen),
        itself contradicted by more than ``max_m`` — or None. An agreement with the free space
        seen over too little of it (``outshone_min_seen_m2``) says nothing: no rival then."""
        cfg = self.cfg
        m = self.contradicted_m(pose)
        if m <= cfg.max_m:
            return None
        seen_r = self.seen_m2(rival)
        if seen_r < cfg.outshone_min_seen_m2:
            return None
        dens = m / max(self.seen_m2(pose), cfg.outshone_min_seen_m2)
        dens_r = self.contradicted_m(rival) / seen_r
        if dens < cfg.outshone_factor * dens_r:
            return None
        return (
            f"{m:.1f} m of walls where free space was seen, {dens:.2f} m per m2 seen by both, against"
            f" {dens_r:.2f} at a rival place"
        )

    def __call__(self, pose: np.ndarray, matched_m: float) -> str | None:
        m = self.contradicted_m(pose)
        if not refused(m, matched_m, self.cfg):
            return None  # (the noise is not even needed)
        noise = self.noise_m(pose)
        if not refused(m, matched_m, self.cfg, noise):
            return None
        return (
            f"{m:.1f} m of walls where free space was seen (the maps contradict themselves by {noise:.1f} m)"
        )
