"""Segment fusion on the server: across the particles of one robot, then across robots.

*Across particles* (report §5, moved to the server): a robot sends the trusted elements of its
top ``K`` particles; an element (one identity, ``RobotMap.element``) may exist in several
versions. Like the agent's consensus map, the version with the highest weight wins — the sum of
the weights of the particles holding it, times its trust (report §5.2 ii) — and an element is
kept only if enough of the particle weight holds it at all (any version) and it is trusted.

*Across robots*: segments already in the global frame that lie on one line, face the same way
and overlap (or nearly touch) become one segment, refitted by weighted total least squares over
all members (each member a uniform density of points along it, weighted by its evidence), its
extent the union of the members' projections. Support counts the members, provenance lists the
robots. Segments are directed (facing = left normal of ``p0 → p1``, shared/messages.py), so the
two faces of a thin wall never merge.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from shared import kernels
from shared.geometry import segment_lengths
from shared.messages import RobotMap

# Pairs tested at once when looking for merge candidates (bounds the temporaries to ~50 MB).
PAIR_CHUNK_ELEMENTS = 2_000_000


@dataclass(frozen=True)
class FusionConfig:
    # across particles (report §5)
    min_support: float = 0.5  # share of the sent particle weight whose map must hold the element:
    # an element only a minority of the weight believes in is a particle's private mistake
    min_trust: float = 0.15  # the winning version's trust; the agent publishes from 0.15 (consensus.py)
    # across robots: two segments are one wall when, seen from the longer one's line, ...
    merge_angle_rad: float = np.radians(5.0)  # ... their directions differ by at most this ...
    merge_perp_m: float = 0.10  # ... the shorter one's endpoints are this close to the line ...
    merge_gap_m: float = 0.30  # ... and they overlap or leave at most this gap (< door openings)
    outlier_perp_m: float = 0.15  # a member farther than this from its group's fitted line
    # (a chain of small tolerances can bend a group) is split off and kept on its own
    # the collinearity test of segment pairs in the compiled kernel (shared/kernels.py; False, or
    # not built: numpy, the same answer)
    compiled: bool = True


@dataclass(frozen=True, eq=False)
class RobotLayer:
    """One robot's fused elements in its own map frame: ``seg (N,2,2)`` directed, ``weight (N,)``
    winning version's share of particle weight × trust, ``support (N,)`` share of particle weight
    holding the element, ``trust (N,)``, ``hits (N,)``, ``element (N,)`` identities."""

    seg: np.ndarray
    weight: np.ndarray
    support: np.ndarray
    trust: np.ndarray
    hits: np.ndarray
    element: np.ndarray
    anchor: np.ndarray | None = None  # (N,) the keyframe id each row moves with (None: rigid map)

    def __len__(self) -> int:
        return len(self.seg)

    @classmethod
    def empty(cls) -> RobotLayer:
        z = np.zeros(0)
        return cls(np.zeros((0, 2, 2)), z, z, z, np.zeros(0, np.int64), np.zeros(0, np.int64))

    @cached_property
    def length_m(self) -> float:
        return float(segment_lengths(self.seg).sum())

    @cached_property
    def bounds(self) -> np.ndarray:
        """``(4,)`` x0, y0, x1, y1 of the segments' bounding box in the map frame (zeros if none)."""
        if len(self.seg) == 0:
            return np.zeros(4)
        pts = self.seg.reshape(-1, 2)
        return np.r_[pts.min(axis=0), pts.max(axis=0)]


def _bits(masks: np.ndarray, k: int) -> np.ndarray:
    """Bit matrix ``(N,K)`` of bitmasks ``(N,)``."""
    return ((masks[:, None] >> np.arange(k, dtype=np.int64)) & 1).astype(float)


def fuse_particles(m: RobotMap, cfg: FusionConfig) -> RobotLayer:
    """The cross-particle map of one assembled RobotMap (report §5 at the server)."""
    w = m.particle_weights
    k, n = len(w), len(m.seg)
    total = float(w.sum())
    if n == 0:
        return RobotLayer.empty()
    if total <= 0.0:  # no weights given: the particles count alike
        w, total = np.ones(k), float(k)
    held = _bits(m.members, k) @ w  # (N,) weight of the particles holding each version
    score = held * m.trust
    ids, group = np.unique(m.element, return_inverse=True)
    union = np.zeros(len(ids), np.int64)
    np.bitwise_or.at(union, group, m.members)
    support = (_bits(union, k) @ w) / total
    # per element the version of highest score (ties: the first row)
    order = np.lexsort((np.arange(n), -score, group))
    starts = np.flatnonzero(np.r_[True, np.diff(group[order]) != 0])
    win = order[starts]
    keep = (support >= cfg.min_support) & (m.trust[win] >= cfg.min_trust)
    win = win[keep]
    return RobotLayer(
        seg=m.seg[win],
        weight=score[win] / total,
        support=support[keep],
        trust=m.trust[win],
        hits=m.hits[win],
        element=ids[keep],
        anchor=None if m.anchor is None else m.anchor[win],
    )


# --- across robots ------------------------------------------------------------------------------


def _candidate_pairs(seg: np.ndarray, margin_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Pairs ``i < j`` whose bounding boxes, grown by ``margin_m``, intersect, in ``(i, j)`` order.

    A sweep along x: boxes sorted by their x-min; box ``a`` can only meet the boxes that start
    before its x-max (``searchsorted``); those are tested in y, in chunks of at most
    ``PAIR_CHUNK_ELEMENTS`` candidate pairs. (All pairs took 1.2 s for 7,300 segments, the sweep
    9 ms, same pairs: benchmarks/bench_fleet.py.)"""
    n = len(seg)
    lo = seg.min(axis=1) - margin_m
    hi = seg.max(axis=1) + margin_m
    order = np.argsort(lo[:, 0], kind="stable")
    lo_s, hi_s = lo[order], hi[order]
    end = np.searchsorted(lo_s[:, 0], hi_s[:, 0], side="right")  # sorted boxes k < end[a] start in time
    count = np.maximum(end - np.arange(n) - 1, 0)  # candidates k in (a, end[a])
    out_i, out_j = [np.zeros(0, np.int64)], [np.zeros(0, np.int64)]
    cum = np.cumsum(count)
    s = 0
    while s < n:
        e = max(
            s + 1, int(np.searchsorted(cum, (cum[s - 1] if s else 0) + PAIR_CHUNK_ELEMENTS, side="right"))
        )
        e = min(e, n)
        c = count[s:e]
        a = np.repeat(np.arange(s, e), c)
        k = np.arange(c.sum()) - np.repeat(np.cumsum(c) - c, c) + a + 1
        ok = (lo_s[k, 1] <= hi_s[a, 1]) & (lo_s[a, 1] <= hi_s[k, 1])
        i, j = order[a[ok]], order[k[ok]]
        out_i.append(np.minimum(i, j))
        out_j.append(np.maximum(i, j))
        s = e
    i, j = np.concatenate(out_i), np.concatenate(out_j)
    idx = np.lexsort((j, i))
    return i[idx], j[idx]


def _ranges(start: np.ndarray, end: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(row, k)`` for every ``k`` in ``[start[row], end[row])``."""
    cnt = np.maximum(end - start, 0)
    row = np.repeat(np.arange(len(start)), cnt)
    k = np.arange(cnt.sum()) - np.repeat(np.cumsum(cnt) - cnt, cnt) + np.repeat(start, cnt)
    return row, k


def box_pairs(a_box: np.ndarray, b_box: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pairs ``(ia, jb)`` of boxes ``(x0, y0, x1, y1)`` of two sets that meet (edges included): one
    sweep per side — ``b`` starts (in x) within ``a``, or ``a`` starts strictly after ``b`` does and
    within it."""
    ob = np.argsort(b_box[:, 0], kind="stable")
    bx = b_box[ob, 0]
    ia1, k = _ranges(np.searchsorted(bx, a_box[:, 0], "left"), np.searchsorted(bx, a_box[:, 2], "right"))
    jb1 = ob[k]
    oa = np.argsort(a_box[:, 0], kind="stable")
    ax = a_box[oa, 0]
    jb2, k = _ranges(np.searchsorted(ax, b_box[:, 0], "right"), np.searchsorted(ax, b_box[:, 2], "right"))
    ia2 = oa[k]
    ia, jb = np.concatenate([ia1, ia2]), np.concatenate([jb1, jb2])
    ok = (a_box[ia, 1] <= b_box[jb, 3]) & (b_box[jb, 1] <= a_box[ia, 3])
    return ia[ok], jb[ok]


def collinear_pairs(seg: np.ndarray, cfg: FusionConfig) -> tuple[np.ndarray, np.ndarray]:
    """Pairs ``(i, j)`` of directed segments that are one wall (see :class:`FusionConfig`)."""
    i, j = _candidate_pairs(seg, pair_margin(cfg))
    ok = collinear(seg, i, j, cfg)
    return i[ok], j[ok]


def pair_margin(cfg: FusionConfig) -> float:
    """Two segments that are one wall have bounding boxes that meet once grown by this much."""
    return cfg.merge_gap_m + cfg.merge_perp_m


def collinear(seg: np.ndarray, i: np.ndarray, j: np.ndarray, cfg: FusionConfig) -> np.ndarray:
    """Mask ``(K,)``: whether segments ``i (K,)`` and ``j (K,)`` of ``seg`` are one wall."""
    if cfg.compiled and kernels.AVAILABLE:
        return kernels.collinear(seg, i, j, np.cos(cfg.merge_angle_rad), cfg.merge_perp_m, cfg.merge_gap_m)
    length = segment_lengths(seg[i]), segment_lengths(seg[j])
    swap = length[1] > length[0]  # a = the longer one, b = the shorter ...
    tie = np.flatnonzero(length[1] == length[0])  # ... of equal ones the first by coordinates,
    if len(tie):  # so that the test does not depend on which one comes first
        d = (seg[j[tie]] - seg[i[tie]]).reshape(-1, 4)
        swap[tie] = d[np.arange(len(tie)), np.argmax(d != 0, axis=1)] < 0
    a, b = np.where(swap, j, i), np.where(swap, i, j)
    la_raw, lb = np.where(swap, length[1], length[0]), np.where(swap, length[0], length[1])
    da = seg[a, 1] - seg[a, 0]
    la = np.maximum(la_raw, 1e-12)
    u = da / la[:, None]  # unit direction of the longer segment
    rel = seg[b] - seg[a, None, 0]  # (K,2,2) the shorter one's endpoints from a's start
    t = np.sum(rel * u[:, None, :], axis=-1)  # along a
    perp = u[:, None, 0] * rel[..., 1] - u[:, None, 1] * rel[..., 0]  # left of a
    db = seg[b, 1] - seg[b, 0]
    cos_ab = np.sum(u * db, axis=-1) / np.maximum(lb, 1e-12)
    gap = np.maximum(t.min(axis=1) - la, -t.max(axis=1))  # < 0: they overlap
    ok = (cos_ab >= np.cos(cfg.merge_angle_rad)) & (np.abs(perp).max(axis=1) <= cfg.merge_perp_m)
    ok &= gap <= cfg.merge_gap_m
    return ok


def _group_lines(seg: np.ndarray, weight: np.ndarray, group: np.ndarray, n_groups: int) -> tuple:
    """Weighted TLS line of every group: centroid ``(G,2)`` and unit direction ``(G,2)`` oriented
    like the members. A member is a uniform point density along it, weight × length in total:
    its second moment about its midpoint is ``L²/12`` along its direction."""
    d = seg[:, 1] - seg[:, 0]
    mass = np.maximum(weight, 1e-9) * np.maximum(segment_lengths(seg), 1e-9)
    mid = 0.5 * (seg[:, 0] + seg[:, 1])

    def gsum(v: np.ndarray) -> np.ndarray:
        return np.bincount(group, weights=v, minlength=n_groups)

    m0 = gsum(mass)
    cx, cy = gsum(mass * mid[:, 0]) / m0, gsum(mass * mid[:, 1]) / m0
    sxx = gsum(mass * (mid[:, 0] ** 2 + d[:, 0] ** 2 / 12.0)) - m0 * cx * cx
    sxy = gsum(mass * (mid[:, 0] * mid[:, 1] + d[:, 0] * d[:, 1] / 12.0)) - m0 * cx * cy
    syy = gsum(mass * (mid[:, 1] ** 2 + d[:, 1] ** 2 / 12.0)) - m0 * cy * cy
    phi = 0.5 * np.arctan2(2.0 * sxy, sxx - syy)  # major axis of the scatter
    u = np.stack([np.cos(phi), np.sin(phi)], axis=-1)
    along = np.stack([gsum(mass * d[:, 0]), gsum(mass * d[:, 1])], axis=-1)
    u = np.where(np.sum(u * along, axis=-1, keepdims=True) < 0, -u, u)
    return np.stack([cx, cy], axis=-1), u


def _split_outliers(seg: np.ndarray, group: np.ndarray, centre, u, cfg: FusionConfig) -> np.ndarray:
    """Groups with members farther than ``outlier_perp_m`` from the fitted line: those members
    get groups of their own (new labels after the existing ones), labels then renumbered densely
    in the same order (``np.unique``'s inverse, without the sort)."""
    cx, cy, ux, uy = centre[group, 0], centre[group, 1], u[group, 0], u[group, 1]
    p0 = np.abs(ux * (seg[:, 0, 1] - cy) - uy * (seg[:, 0, 0] - cx))
    p1 = np.abs(ux * (seg[:, 1, 1] - cy) - uy * (seg[:, 1, 0] - cx))
    out = np.maximum(p0, p1) > cfg.outlier_perp_m
    new = group.copy()
    new[out] = group.max(initial=-1) + 1 + np.arange(int(out.sum()))
    present = np.bincount(new) > 0
    return (np.cumsum(present) - 1)[new]


def merge_segments(
    seg: np.ndarray, weight: np.ndarray, robot: np.ndarray, cfg: FusionConfig
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Merge directed global-frame segments ``seg (N,2,2)`` (evidence ``weight (N,)``, owner
    ``robot (N,)``) into ``seg (M,2,2)``, ``support (M,)`` members per segment, and provenance
    as CSR: ``prov_offsets (M+1,)``, ``prov_robot (L,)`` sorted unique robots per segment. The
    merged segments come in the order of their first member."""
    seg = np.asarray(seg, float).reshape(-1, 2, 2)
    n = len(seg)
    if n == 0:
        return np.zeros((0, 2, 2)), np.zeros(0, np.int64), np.zeros(1, np.int64), np.zeros(0, np.int64)
    i, j = collinear_pairs(seg, cfg)
    n_comp, comp = components(n, i, j)
    group, out = merge_groups(seg, weight, comp, n_comp, cfg)
    support, offsets, prov = provenance(group, robot, len(out))
    return out, support, offsets, prov


def components(n: int, i: np.ndarray, j: np.ndarray) -> tuple[int, np.ndarray]:
    """Connected components of ``n`` nodes joined by the pairs ``(i, j)``: count and labels."""
    graph = coo_matrix((np.ones(len(i)), (i, j)), shape=(n, n))
    n_comp, comp = connected_components(graph, directed=False)
    return int(n_comp), comp


def merge_groups(
    seg: np.ndarray, weight: np.ndarray, comp: np.ndarray, n_comp: int, cfg: FusionConfig
) -> tuple[np.ndarray, np.ndarray]:
    """Each connected component of collinear pairs (``comp (N,)`` labels) as one segment, refitted;
    members too far from their component's line (:func:`_split_outliers`) on their own. Returns
    every member's group ``(N,)`` and the groups' segments ``(G,2,2)``, groups numbered in the order
    of their first member. A group depends only on its members and their order, not on the other
    components (map_server/incremental.py merges components apart)."""
    n = len(seg)
    centre, u = _group_lines(seg, weight, comp, n_comp)
    group = _split_outliers(seg, comp, centre, u, cfg)
    n_groups = int(group.max()) + 1
    first = np.full(n_groups, n)
    np.minimum.at(first, group, np.arange(n))
    rank = np.empty(n_groups, np.int64)
    rank[np.argsort(first)] = np.arange(n_groups)
    group = rank[group]
    centre, u = _group_lines(seg, weight, group, n_groups)
    # extent: the union of the members' endpoint projections on the group's line
    cx, cy, ux, uy = centre[group, 0], centre[group, 1], u[group, 0], u[group, 1]
    t0 = (seg[:, 0, 0] - cx) * ux + (seg[:, 0, 1] - cy) * uy
    t1 = (seg[:, 1, 0] - cx) * ux + (seg[:, 1, 1] - cy) * uy
    lo = np.full(n_groups, np.inf)
    hi = np.full(n_groups, -np.inf)
    np.minimum.at(lo, group, np.minimum(t0, t1))
    np.maximum.at(hi, group, np.maximum(t0, t1))
    return group, np.stack([centre + lo[:, None] * u, centre + hi[:, None] * u], axis=1)


def provenance(group: np.ndarray, robot: np.ndarray, n_groups: int) -> tuple:
    """Members per group ``(G,)`` and the sorted unique robots per group as CSR."""
    support = np.bincount(group, minlength=n_groups).astype(np.int64)
    pairs = unique_pairs(group, np.asarray(robot, np.int64))  # sorted
    offsets = np.r_[0, np.cumsum(np.bincount(pairs[:, 0], minlength=n_groups))].astype(np.int64)
    return support, offsets, pairs[:, 1].copy()


def unique_pairs(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The distinct pairs ``(a, b)`` of non-negative integers, sorted, as ``(P,2)``
    (``np.unique(..., axis=0)`` on one integer key)."""
    if len(a) == 0:
        return np.zeros((0, 2), np.int64)
    span = int(b.max()) + 1
    key = np.unique(a.astype(np.int64) * span + b)
    return np.column_stack([key // span, key % span])
