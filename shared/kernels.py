"""The map server's compiled kernels (``_kernels.c``): points indexed for "the k nearest within a
distance" (map_server/registration.py's placed-map samples), and the merge's collinearity test
(map_server/fusion.collinear). ``AVAILABLE`` is False when the extension was not built (no C
compiler at install); :class:`NearIndex` then answers with scipy's k-d tree and numpy, and
fusion.collinear runs its numpy code — the same answers (tests/map_server/test_server_kernels.py),
ties in distance ordered by index either way."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from scipy.spatial import cKDTree

from shared.geometry import wrap_angle

try:
    from shared import _kernels
except ImportError:  # built without a C compiler: the k-d tree answers
    _kernels = None

AVAILABLE = _kernels is not None

MAX_K = 64  # the kernel holds at most this many neighbours per query
MAX_CELLS_PER_POINT = 4  # a sparse map's grid grows its cells instead of its memory
_EMPTY = np.zeros(0)


class Lines(NamedTuple):
    """What the indexed points sample: directed lines, per point ``(N,)``: facing [rad], unit
    facing normal ``nx``, ``ny`` and offset (``nx x + ny y = offset`` on the line)."""

    facing: np.ndarray
    nx: np.ndarray
    ny: np.ndarray
    offset: np.ndarray


class Near(NamedTuple):
    """A query's answer, ``(Q,k)`` each: distances (inf where missing), indices (N where
    missing); with lines the facing difference ``|wrap(query facing - point facing)|`` and the
    signed distance of the query to the point's line (point 0's where missing); and whether
    any query lay outside the box asked about."""

    d: np.ndarray
    j: np.ndarray
    dang: np.ndarray | None
    perp: np.ndarray | None
    outside: bool


class NearIndex:
    """Points ``(N,2)`` (samples of ``lines`` when given) and :meth:`query`, which answers like
    ``cKDTree.query(q, k, distance_upper_bound=bound)`` with ties in distance ordered by index.
    Compiled (``compiled`` and the kernel built): the points sorted by cell of a grid of
    ``cell_m`` (larger when the points' box would need more than ``MAX_CELLS_PER_POINT`` cells a
    point, plus 65,536), each query looking in the cells within its bound; else a k-d tree."""

    def __init__(self, points: np.ndarray, cell_m: float, lines: Lines | None = None, compiled: bool = True):
        pts = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 2)
        self.n = len(pts)
        self.lines = (
            None if lines is None else Lines(*(np.ascontiguousarray(a, dtype=np.float64) for a in lines))
        )
        if self.lines is not None and any(len(a) != self.n for a in self.lines):
            raise ValueError(f"lines: {[len(a) for a in self.lines]} values for {self.n} points")
        self.compiled = bool(compiled and AVAILABLE)
        if not self.compiled:
            self._tree = cKDTree(pts) if self.n else None
            return
        if not (np.isfinite(cell_m) and cell_m > 0):
            raise ValueError(f"cell_m must be finite and > 0, got {cell_m}")
        # the points' values column by column: x, y and (lines) facing, nx, ny, offset
        cols = np.stack([pts[:, 0], pts[:, 1]] + ([] if self.lines is None else list(self.lines)))
        x, y = cols[0], cols[1]
        finite = np.isfinite(x) & np.isfinite(y)  # a point not finite is nobody's neighbour
        w = h = 0
        origin = np.zeros(2, np.int64)
        if finite.any():
            room = MAX_CELLS_PER_POINT * int(finite.sum()) + 65_536
            xf, yf = (x, y) if finite.all() else (x[finite], y[finite])
            x0, x1, y0, y1 = xf.min(), xf.max(), yf.min(), yf.max()
            while True:  # cells this large or larger: a box of at most ``room`` of them
                w = int(np.floor(x1 / cell_m) - np.floor(x0 / cell_m)) + 1
                h = int(np.floor(y1 / cell_m) - np.floor(y0 / cell_m)) + 1
                if w * h <= room:
                    break
                cell_m *= max(1.01, float(np.sqrt(w * h / room)))
            origin = np.array([np.floor(x0 / cell_m), np.floor(y0 / cell_m)]).astype(np.int64)
        # the points' rows in cell order (x, y, ... side by side), their indices, each cell's first
        data, order = np.empty((self.n, len(cols))), np.empty(self.n, np.int64)
        self._start = np.empty(w * h + 1, np.int64)
        x0, y0 = int(origin[0]), int(origin[1])
        kept = _kernels.grid(cols, data, order, self._start, len(cols), self.n, w, h, x0, y0, float(cell_m))
        self._data, self._order = data[:kept], order[:kept]
        self._line0 = np.array([a[0] for a in self.lines]) if self.lines is not None and self.n else _EMPTY
        self._origin, self._w, self._h, self.cell_m = origin, int(w), int(h), float(cell_m)

    def query(
        self,
        q: np.ndarray,
        k: int,
        bound: float,
        facing: np.ndarray | None = None,
        box: tuple[np.ndarray, np.ndarray] | None = None,
    ) -> Near:
        """The ``k`` nearest points nearer than ``bound`` to each of ``q (Q,2)``; with the
        queries' ``facing (Q,)`` (the index has lines) what :class:`Near` says of their lines;
        ``box (lo (2,), hi (2,))``: whether a query lies outside it."""
        q = np.ascontiguousarray(q, dtype=np.float64).reshape(-1, 2)
        if not 1 <= k <= MAX_K:
            raise ValueError(f"k must be within 1..{MAX_K}, got {k}")
        if facing is not None and (self.lines is None or self.n == 0):
            raise ValueError("facing given, but the index holds no lines (or no points)")
        lo, hi = (np.full(2, -np.inf), np.full(2, np.inf)) if box is None else box
        if not self.compiled:
            return self._reference(q, k, bound, facing, lo, hi)
        nq = len(q)
        d, j = np.empty((nq, k)), np.empty((nq, k), dtype=np.int64)
        if facing is None:
            qf, dang, perp = _EMPTY, _EMPTY, _EMPTY
        else:
            qf = np.ascontiguousarray(facing, dtype=np.float64)
            dang, perp = np.empty((nq, k)), np.empty((nq, k))
        x0, y0 = (int(v) for v in self._origin)
        n_grid, stride = self._data.shape
        outside = _kernels.near(
            self._data, self._order, self._start, q, qf, self._line0 if facing is not None else _EMPTY,
            d, j, dang, perp, n_grid, stride, self.n, self._w, self._h, nq, int(k), x0, y0, self.cell_m,
            float(bound), facing is not None, float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1]),
        )  # fmt: skip
        return Near(d, j, None if facing is None else dang, None if facing is None else perp, outside > 0)

    def _reference(self, q, k, bound, facing, lo, hi) -> Near:
        """The numpy answer: a k-d tree, its ties reordered by index."""
        nq = len(q)
        outside = bool(nq) and bool((q.min(axis=0) < lo).any() or (q.max(axis=0) > hi).any())
        if self._tree is None:
            d, j = np.full((nq, k), np.inf), np.zeros((nq, k), dtype=np.int64)
        else:  # (the tree refuses a query that is not finite: it finds nothing)
            d, j = np.full((nq, k), np.inf), np.full((nq, k), self.n, dtype=np.int64)
            ok = np.isfinite(q).all(axis=1)
            dk, jk = self._tree.query(q[ok], k=k, distance_upper_bound=bound)
            d[ok], j[ok] = _ties_by_index(dk.reshape(-1, k), jk.reshape(-1, k).astype(np.int64))
        if facing is None:
            return Near(d, j, None, None, outside)
        j0 = np.where(j < self.n, j, 0)
        ln = self.lines
        dang = np.abs(wrap_angle(np.asarray(facing, float)[:, None] - ln.facing[j0]))
        perp = ln.nx[j0] * q[:, None, 0] + ln.ny[j0] * q[:, None, 1] - ln.offset[j0]
        return Near(d, j, dang, perp, outside)


def _ties_by_index(d: np.ndarray, j: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rows of a k-d tree answer with equal distances reordered by index (the tree leaves them in
    the order it met them)."""
    tie = np.flatnonzero(((d[:, 1:] == d[:, :-1]) & np.isfinite(d[:, 1:])).any(axis=1))
    if len(tie):
        o = np.lexsort((j[tie], d[tie]), axis=-1)
        d[tie], j[tie] = np.take_along_axis(d[tie], o, 1), np.take_along_axis(j[tie], o, 1)
    return d, j


def collinear(
    seg: np.ndarray, i: np.ndarray, j: np.ndarray, cos_min: float, perp_max_m: float, gap_max_m: float
) -> np.ndarray:
    """map_server/fusion.collinear's mask ``(K,)`` for the pairs ``(i, j)`` of ``seg (N,2,2)``."""
    seg = np.ascontiguousarray(seg, dtype=np.float64)
    i, j = np.ascontiguousarray(i, dtype=np.int64), np.ascontiguousarray(j, dtype=np.int64)
    if seg.ndim != 3 or seg.shape[1:] != (2, 2) or i.shape != j.shape or i.ndim != 1:
        raise ValueError(
            f"collinear: segments (N,2,2) and pairs (K,) each; got {seg.shape}, {i.shape}, {j.shape}"
        )
    ok = np.empty(len(i), dtype=np.bool_)
    _kernels.collinear(
        seg, i, j, ok.view(np.uint8), len(seg), len(i), float(cos_min), float(perp_max_m), float(gap_max_m)
    )
    return ok


def require(module):
    """A compiled extension ``module``, or a RuntimeError when the install did not build it
    (None); robot_agent/slam/kernels.py's too."""
    if module is None:
        raise RuntimeError("the compiled kernels are not built (no C compiler at install)")
    return module


def f64(a: np.ndarray) -> np.ndarray:
    """``a`` as the kernels take it: C-contiguous float64 (a view when it is already)."""
    return np.ascontiguousarray(a, dtype=np.float64)


def i64(a: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(a, dtype=np.int64)


def window_sums(values: np.ndarray, cells: np.ndarray, ox: np.ndarray, oy: np.ndarray) -> np.ndarray:
    """Mean of ``values (W,H)`` (0 off the grid) over the cells ``(A,N,2)`` moved by each offset
    ``(ox, oy) (T,)``: ``(A,T)`` — scanmatch.window_scores."""
    lib = require(_kernels)
    a, n = cells.shape[:2]
    out = np.empty((a, len(ox)))
    lib.window_sums(
        f64(values), i64(cells), i64(ox), i64(oy), out,
        values.shape[0], values.shape[1], a, n, len(ox),
    )  # fmt: skip
    return out


def block_sums(
    level: np.ndarray, cells: np.ndarray, a: np.ndarray, ox: np.ndarray, oy: np.ndarray
) -> np.ndarray:
    """Mean of ``level (W,H)`` (float32; 0 off the grid) over the cells ``(A,N,2)`` of angle ``a``
    moved by ``(ox, oy)``, for every block ``(M,)`` — scanmatch.branch_and_bound's scores."""
    lib = require(_kernels)
    lv = np.ascontiguousarray(level, dtype=np.float32)
    out = np.empty(len(a))
    lib.block_sums(
        lv, i64(cells), i64(a), i64(ox),
        i64(oy), out, lv.shape[0], lv.shape[1], cells.shape[0], cells.shape[1], len(a),
    )  # fmt: skip
    return out
