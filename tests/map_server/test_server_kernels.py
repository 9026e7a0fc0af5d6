"""The map server's compiled kernels (shared/_kernels.c) against their references: the nearest-sample
index against scipy's k-d tree and numpy (shared/kernels.py) — the same answer bit for bit, and the
same registration —, and the merge's collinearity test against fusion.collinear's numpy code."""

from __future__ import annotations

import dataclasses
import shutil

import numpy as np
import pytest

from map_server.alignment import estimate_alignment
from map_server.config import AlignmentConfig
from map_server.fusion import FusionConfig, collinear
from map_server.registration import MapIndex, OutsideIndex, Samples
from shared import kernels
from shared.kernels import Lines, NearIndex

needs_kernel = pytest.mark.skipif(not kernels.AVAILABLE, reason="compiled kernel not built (no C compiler)")


def test_the_kernel_is_built_where_a_compiler_is():
    """The install builds it wherever a C compiler exists (setup.py: optional, so a failed build
    would otherwise pass unnoticed and the k-d tree would run)."""
    if shutil.which("cc") is None and shutil.which("gcc") is None:
        pytest.skip("no C compiler on this machine")
    assert kernels.AVAILABLE


def _lines(rng, n):
    f = rng.uniform(-4.0, 4.0, n)
    return Lines(f, np.cos(f), np.sin(f), rng.normal(size=n))


def _both(pts, cell_m, lines=None):
    return NearIndex(pts, cell_m, lines), NearIndex(pts, cell_m, lines, compiled=False)


@needs_kernel
@pytest.mark.parametrize("bound", [0.0, 0.1, 0.3, 0.65, 3.0])
@pytest.mark.parametrize("k", [1, 8, 20])
def test_same_neighbours_as_the_k_d_tree(bound, k):
    rng = np.random.default_rng(int(bound * 100) + k)
    pts = rng.uniform(-5.0, 15.0, (4000, 2))
    q = rng.uniform(-6.0, 16.0, (3000, 2))
    fast, ref = _both(pts, 0.3)
    a, b = fast.query(q, k, bound), ref.query(q, k, bound)
    assert np.array_equal(a.d, b.d) and np.array_equal(a.j, b.j)
    assert a.dang is None and a.perp is None
    found = a.j < len(pts)
    assert np.all(np.isinf(a.d[~found])) and np.all(a.d[found] < bound)
    assert found.sum() > 0 or bound == 0.0


@needs_kernel
def test_line_terms_and_the_box_as_numpy_computes_them():
    rng = np.random.default_rng(3)
    pts = rng.uniform(0.0, 10.0, (3000, 2))
    lines = _lines(rng, 3000)
    # facings all around the circle, wraps included: the kernel's wrap is numpy's to the bit
    qf = np.concatenate([rng.uniform(-9.0, 9.0, 1990), [np.pi, -np.pi, 0.0, -0.0, 2 * np.pi, -2 * np.pi,
                                                          3 * np.pi, 1e-300, -1e-300, 7.0]])  # fmt: skip
    q = rng.uniform(-0.5, 10.5, (2000, 2))
    fast, ref = _both(pts, 0.3, lines)
    for box in (
        None,
        (np.array([0.0, 0.0]), np.array([10.0, 10.0])),
        (np.array([-1.0, -1.0]), np.array([11.0, 11.0])),
    ):
        a, b = fast.query(q, 8, 0.4, qf, box), ref.query(q, 8, 0.4, qf, box)
        for x, y in zip(a[:4], b[:4], strict=True):
            assert np.array_equal(x, y)
        assert a.outside == b.outside == (box is not None and box[0][0] == 0.0)
    # the same index asked without facings: the neighbours alone (its rows read at their full width)
    a, b = fast.query(q, 8, 0.4), ref.query(q, 8, 0.4)
    assert np.array_equal(a.d, b.d) and np.array_equal(a.j, b.j) and a.dang is None


@needs_kernel
def test_ties_in_distance_come_by_index():
    """Points stacked on each other (two walls sampled at the same place): nearest first, and
    among equals the lower index first, whichever way the index was built."""
    base = np.array([[0.0, 0.0], [0.1, 0.0], [0.0, 0.1]])
    pts = np.concatenate([base, base, base])[[4, 0, 7, 2, 5, 1, 8, 3, 6]]
    fast, ref = _both(pts, 0.3)
    q = np.array([[0.0, 0.0], [0.05, 0.0], [1.0, 1.0]])
    a, b = fast.query(q, 9, 0.5), ref.query(q, 9, 0.5)
    assert np.array_equal(a.j, b.j) and np.array_equal(a.d, b.d)
    assert list(a.j[1, :6]) == sorted(a.j[1, :6])  # six points at 0.05 m: by index
    assert np.all(a.j[2] == len(pts))


@needs_kernel
def test_points_that_are_not_finite_and_spread_out_maps():
    """A NaN point is nobody's neighbour; points kilometres apart get a coarser grid (bounded
    memory), not a wrong answer; queries that are not finite find nothing."""
    rng = np.random.default_rng(5)
    pts = np.concatenate(
        [rng.uniform(0.0, 5.0, (500, 2)), [[np.nan, 1.0]], rng.uniform(4000.0, 4005.0, (500, 2))]
    )
    q = np.concatenate(
        [rng.uniform(0.0, 5.0, (300, 2)), rng.uniform(4000.0, 4005.0, (300, 2)), [[np.nan, 0.0]]]
    )
    fast = NearIndex(pts, 0.3)
    assert fast._w * fast._h <= kernels.MAX_CELLS_PER_POINT * len(pts) + 65_536
    assert fast.cell_m > 0.3
    ref = NearIndex(np.where(np.isfinite(pts), pts, 1e9), 0.3, compiled=False)  # the tree takes no NaN
    a, b = fast.query(q, 8, 0.5), ref.query(q, 8, 0.5)
    assert np.array_equal(a.j, b.j) and np.array_equal(a.d, b.d)
    assert np.all(a.j[-1] == len(pts)) and not np.any(a.j == 500)


def test_bad_arguments_are_named():
    idx = NearIndex(np.zeros((3, 2)), 0.3)
    with pytest.raises(ValueError, match="k must be within"):
        idx.query(np.zeros((1, 2)), 0, 0.3)
    with pytest.raises(ValueError, match="no lines"):
        idx.query(np.zeros((1, 2)), 4, 0.3, facing=np.zeros(1))
    with pytest.raises(ValueError, match="lines"):
        NearIndex(np.zeros((3, 2)), 0.3, Lines(*(np.zeros(2),) * 4))
    if kernels.AVAILABLE:
        with pytest.raises(ValueError, match="cell_m"):
            NearIndex(np.zeros((3, 2)), 0.0)
        with pytest.raises(ValueError, match="starts must rise"):  # the kernel checks the grid it is given
            kernels._kernels.near(
                np.zeros((2, 2)), np.zeros(2, np.int64), np.array([0, 5], np.int64), np.zeros((1, 2)),
                np.zeros(0), np.zeros(0), np.zeros((1, 1)), np.zeros((1, 1), np.int64),
                np.zeros(0), np.zeros(0),
                2, 2, 2, 1, 1, 1, 1, 0, 0, 0.3, 0.3, False, 0.0, 0.0, 0.0, 0.0,
            )  # fmt: skip


def test_empty_index_and_empty_queries():
    for compiled in (True, False):
        idx = NearIndex(np.zeros((0, 2)), 0.3, compiled=compiled)
        a = idx.query(np.ones((4, 2)), 3, 1.0)
        assert a.d.shape == (4, 3) and np.all(np.isinf(a.d)) and np.all(a.j == 0)
        idx = NearIndex(np.ones((5, 2)), 0.3, compiled=compiled)
        a = idx.query(np.zeros((0, 2)), 3, 1.0, box=(np.zeros(2), np.ones(2)))
        assert a.d.shape == (0, 3) and not a.outside


def _office_pair():
    rng = np.random.default_rng(11)
    # a placed map of rooms (walls both ways) and a robot map: part of it, moved and noisy
    walls = []
    for x0 in range(0, 40, 5):
        for y0 in range(0, 20, 5):
            box = np.array([[x0, y0], [x0 + 4.0, y0], [x0 + 4.0, y0 + 4.0], [x0, y0 + 4.0]])
            walls += [[box[i], box[(i + 1) % 4]] for i in range(4) if rng.random() < 0.8]
    placed = np.array(walls, float)
    truth = np.array([1.2, -0.7, 0.05])
    c, s = np.cos(truth[2]), np.sin(truth[2])
    inv = np.array([[c, s], [-s, c]])
    robot = (placed[: len(placed) * 2 // 3] - truth[:2]) @ inv.T + rng.normal(
        0, 0.01, (len(placed) * 2 // 3, 2, 2)
    )
    return placed, robot, truth


@needs_kernel
def test_registration_gives_the_same_result_either_way():
    """Refinement, strict score and the contradiction checks of one alignment from a prior, and
    an index over a crop: the compiled index and the k-d tree agree to the bit."""
    placed, robot, truth = _office_pair()
    prior = truth + np.array([0.08, -0.05, 0.01])
    out = []
    for compiled in (True, False):
        cfg = AlignmentConfig(compiled=compiled)
        out.append(
            estimate_alignment(robot, placed, cfg, prior=prior, prior_sigma=np.array([0.2, 0.2, 0.05]))
        )
    a, b = out
    assert a.status == b.status == "prior", a.reason
    assert np.array_equal(a.transform, b.transform) and a.score_m == b.score_m and a.reason == b.reason
    assert np.hypot(*(a.transform[:2] - truth[:2])) < 0.02
    # a crop: queries outside its inner box are refused either way
    robot_s = Samples.of(robot, 0.1)
    for compiled in (True, False):
        index = MapIndex(placed, 0.1, inner=(np.array([0.0, 0.0]), np.array([20.0, 20.0])), compiled=compiled)
        with pytest.raises(OutsideIndex):
            index.match(truth, robot_s, 0.3, 0.1)
        with pytest.raises(OutsideIndex):
            index.evidence(truth, robot_s, 0.1, 0.1, 0.3)


@needs_kernel
def test_collinearity_as_numpy_decides_it():
    """fusion.collinear in C and in numpy, pair for pair: near-collinear pairs around every
    threshold, equal lengths (the tie rule), zero-length and reversed segments, segments that are
    not finite."""
    rng = np.random.default_rng(7)
    n = 6000
    base = rng.uniform(-20.0, 20.0, (n, 2))
    ang = rng.uniform(-np.pi, np.pi, n)
    length = rng.choice([0.0, 0.5, 1.0, 2.0, 3.7], n)  # many equal lengths
    seg = np.stack([base, base + length[:, None] * np.stack([np.cos(ang), np.sin(ang)], -1)], axis=1)
    # a second copy nudged along, across and turned by about the thresholds: most pairs decide near them
    m = n // 2
    shift = rng.normal(0.0, 0.1, (m, 1, 2)) + rng.normal(0.0, 0.2, (m, 1, 1)) * (seg[:m, 1:] - seg[:m, :1])
    twin = seg[:m] + shift
    twin[: m // 4] = twin[: m // 4, ::-1]  # reversed: opposite facing
    seg = np.concatenate([seg, twin])
    seg[5] = np.nan
    seg[6, 1, 0] = np.inf
    i = np.concatenate([np.arange(m), rng.integers(0, len(seg), 20_000), [5, 0, 6, 7]])
    j = np.concatenate([np.arange(n, n + m), rng.integers(0, len(seg), 20_000), [0, 5, 7, 6]])
    cfg = FusionConfig()
    fast = collinear(seg, i, j, cfg)
    with np.errstate(invalid="ignore"):  # numpy's inf / inf on the way to its False
        ref = collinear(seg, i, j, dataclasses.replace(cfg, compiled=False))
    assert np.array_equal(fast, ref)
    assert 0.1 < fast[:m].mean() < 0.9  # the twins straddle the thresholds
    assert not fast[-4:].any()  # nothing that is not finite is one wall
    assert np.array_equal(collinear(seg, j, i, cfg), fast)  # the order within a pair does not matter


@needs_kernel
def test_collinearity_arguments_are_checked():
    seg = np.zeros((3, 2, 2))
    with pytest.raises(IndexError, match="outside"):
        kernels.collinear(seg, np.array([0]), np.array([3]), 0.99, 0.1, 0.3)
    with pytest.raises(ValueError, match="segments"):
        kernels.collinear(np.zeros((3, 4)), np.array([0]), np.array([1]), 0.99, 0.1, 0.3)


@needs_kernel
def test_the_grid_refuses_points_outside_its_extent():
    """The grid's counting sort writes where each point's cell says: a cell outside the extent
    it was given is an error, not a write past the arrays."""
    cols = np.array([[0.0, 1.0, 5.0], [0.0, 1.0, 0.5]])
    data, order, start = np.empty((3, 2)), np.empty(3, np.int64), np.empty(2 * 2 + 1, np.int64)
    with pytest.raises(ValueError, match="outside the grid"):
        kernels._kernels.grid(cols, data, order, start, 2, 3, 2, 2, 0, 0, 1.0)
    # within it: the points in cell order, stable, and each cell's first
    cols = np.array([[1.5, 0.2, 1.1, np.nan], [0.5, 0.5, 1.5, 0.0]])
    data, order, start = np.empty((4, 2)), np.empty(4, np.int64), np.empty(2 * 2 + 1, np.int64)
    kept = kernels._kernels.grid(cols, data, order, start, 2, 4, 2, 2, 0, 0, 1.0)
    assert kept == 3
    assert list(order[:kept]) == [1, 0, 2] and list(start) == [0, 1, 1, 2, 3]
    assert np.array_equal(data[:kept], cols[:, [1, 0, 2]].T)
