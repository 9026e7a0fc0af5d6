"""The merge across robots (fusion.merge_segments), kept up to date as maps and frames change.

A merged segment depends only on the connected component of collinear pairs it belongs to (its
members and their order): fusion.merge_groups. So the merged map is kept per component, and a
change re-merges only the components it touches:

- every *source* (a placed robot's or a retired piece's layer under its transform) keeps its
  segments in the global frame, recomputed only when its layer or its transform changes;
- a source that changed takes its old segments out — the components that held them are re-merged
  from their remaining members and the collinear pairs among them (kept per component: pairs
  between unchanged segments never change) — and brings its new segments in: their pairs with
  each other (the sweep of fusion._candidate_pairs) and with the segments already there (a sweep
  of one set against the other, over the segments whose boxes meet the new ones' extent) join the
  components they reach, which are re-merged with them;
- members are merged in the order of the full stack (sources in the given order, each source's
  segments in its layer's order), so a re-merged component comes out bit for bit as the full merge
  would make it (tests/map_server/test_incremental.py compares the two on random fleets).

A rigid motion of every source at once (a prior frame's common motion, Fleet._hold_prior_gauge)
moves the merged segments with them instead: collinearity does not depend on where the set is.
:meth:`MergedMap.without` is the merge of every source but one, near a region: what a robot is
refined against (the components the robot shares, re-merged without it; the others as they are).
"""

from __future__ import annotations

from collections.abc import Hashable
from dataclasses import dataclass

import numpy as np

from map_server.fusion import (
    FusionConfig,
    RobotLayer,
    _candidate_pairs,
    _ranges,
    box_pairs,
    collinear,
    components,
    merge_groups,
    pair_margin,
    unique_pairs,
)
from shared.geometry import apply_segments

EDGES_COMPACT_MIN = 4096  # pair rows taken out before the pair array is compacted (and half of them)


@dataclass(frozen=True, eq=False)
class Source:
    """One layer of the merge: ``layer``'s segments moved by ``transform (3,)``, owned by ``robot``
    (its provenance). ``key`` names it across updates (a changed layer object or transform is a
    changed source)."""

    key: Hashable
    robot: str
    layer: RobotLayer
    transform: np.ndarray


@dataclass
class _Entry:
    slot: int
    layer: RobotLayer
    transform: np.ndarray
    nodes: np.ndarray  # node ids of its segments, in the layer's order


class MergedMap:
    """fusion.merge_segments of the sources given to :meth:`update`, kept per component."""

    def __init__(self, cfg: FusionConfig):
        self.cfg = cfg
        self._margin = pair_margin(cfg)
        # nodes: one per source segment (ids reused once freed)
        self._cap = 0
        self._seg = np.zeros((0, 2, 2))
        self._w = np.zeros(0)
        self._box = np.zeros((0, 4))
        self._slot = np.zeros(0, np.int64)
        self._local = np.zeros(0, np.int64)
        self._comp = np.zeros(0, np.int64)
        self._alive = np.zeros(0, bool)
        self._free = np.zeros(0, np.int64)
        self._top = 0  # node ids below this were used
        # sources
        self._entries: dict[Hashable, _Entry] = {}
        self._order: list[Hashable] = []
        self._free_slots: list[int] = []
        self._slot_robot = np.zeros(0, np.int64)  # robot id of each slot
        self._offset = np.zeros(0, np.int64)  # first stack position of each slot
        self._robots: dict[str, int] = {}
        # components: a component's id is its smallest member node id (``_comp`` per node, -1: none
        # yet); the collinear pairs (node ids) and their component (-1: taken out; the rows are
        # compacted once half of them are), ``_e_top`` rows used, a component's pairs in the rows
        # ``_c_start[c]`` to ``_c_end[c]`` (by component id)
        self._c_start = np.zeros(0, np.int64)
        self._c_end = np.zeros(0, np.int64)
        self._edges = np.zeros((0, 2), np.int64)
        self._e_comp = np.zeros(0, np.int64)
        self._e_top = 0
        self._e_dead = 0
        self.compactions = 0  # of the pair array (a count for tests)
        # merged groups, rows in the order made (uid ascending); provenance pairs (uid, robot id)
        self._g_seg = np.zeros((0, 2, 2))
        self._g_support = np.zeros(0, np.int64)
        self._g_first = np.zeros(0, np.int64)  # node of its first member
        self._g_comp = np.zeros(0, np.int64)
        self._g_uid = np.zeros(0, np.int64)
        self._p_uid = np.zeros(0, np.int64)
        self._p_robot = np.zeros(0, np.int64)
        self._p_comp = np.zeros(0, np.int64)
        self._next_uid = 0

    # -- sources -------------------------------------------------------------------------------

    def __len__(self) -> int:
        """Source segments merged."""
        return int(sum(len(e.nodes) for e in self._entries.values()))

    def update(self, sources: list[Source], hold: Hashable = None) -> bool:
        """Merge ``sources`` (stack order: the order of the full merge); False if nothing changed.
        The source ``hold`` is left as it was (as it is not there, if it was not): for
        :meth:`without` that source, which it would not change, before it changes again."""
        if hold in self._entries and any(s.key == hold for s in sources):
            e = self._entries[hold]
            sources = [Source(hold, s.robot, e.layer, e.transform) if s.key == hold else s for s in sources]
        elif hold is not None:
            sources = [s for s in sources if s.key != hold]  # not merged yet: it stays out
        keys = [s.key for s in sources]
        given = dict(zip(keys, sources, strict=True))
        changed = [
            s for s in sources
            if (e := self._entries.get(s.key)) is None or e.layer is not s.layer
            or not np.array_equal(e.transform, s.transform)
        ]  # fmt: skip
        gone = [k for k in self._entries if k not in given]
        if not changed and not gone and keys == self._order:
            return False
        old = [self._drop(k) for k in gone + [s.key for s in changed if s.key in self._entries]]
        new = [self._add(s) for s in changed]
        self._order = keys
        self._restack()
        empty = np.zeros(0, np.int64)
        self._edit(np.concatenate([empty, *old]), np.concatenate([empty, *new]))
        return True

    def moved(self, g: np.ndarray, sources: list[Source], relaid: frozenset = frozenset()) -> None:
        """Every source moved by the same rigid motion ``g (3,)`` to the transforms ``sources``
        give (same layers; those named in ``relaid`` may come as new layers of the same rows,
        moved by ``g`` themselves): the components stay, the merged segments move by ``g``."""
        for s in sources:
            e = self._entries[s.key]
            if e.layer is not s.layer and (s.key not in relaid or len(e.layer) != len(s.layer)):
                raise ValueError(f"{s.key}: moved() takes the same layers (or their rows moved: relaid)")
            e.layer = s.layer
            e.transform = np.array(s.transform, float)
            self._place(e.nodes, s)
        self._g_seg = apply_segments(g, self._g_seg)

    def _drop(self, key: Hashable) -> np.ndarray:
        e = self._entries.pop(key)
        self._alive[e.nodes] = False
        self._free_slots.append(e.slot)
        return e.nodes

    def _add(self, s: Source) -> np.ndarray:
        n = len(s.layer)
        ids = self._alloc(n)
        slot = self._free_slots.pop() if self._free_slots else len(self._slot_robot)
        if slot == len(self._slot_robot):
            self._slot_robot = np.r_[self._slot_robot, 0]
            self._offset = np.r_[self._offset, 0]
        self._slot_robot[slot] = self._robots.setdefault(s.robot, len(self._robots))
        self._entries[s.key] = _Entry(slot, s.layer, np.array(s.transform, float), ids)
        self._place(ids, s)
        self._w[ids] = s.layer.weight
        self._slot[ids] = slot
        self._local[ids] = np.arange(n)
        self._comp[ids] = -1
        self._alive[ids] = True
        return ids

    def _place(self, ids: np.ndarray, s: Source) -> None:
        seg = apply_segments(s.transform, s.layer.seg) if len(ids) else np.zeros((0, 2, 2))
        self._seg[ids] = seg
        self._box[ids, :2] = seg.min(axis=1) - self._margin
        self._box[ids, 2:] = seg.max(axis=1) + self._margin

    def _alloc(self, n: int) -> np.ndarray:
        take = min(n, len(self._free))
        ids, self._free = self._free[:take], self._free[take:]
        more = n - take
        if self._top + more > self._cap:
            self._grow(max(2 * self._cap, self._top + more, 1024))
        ids = np.concatenate([ids, np.arange(self._top, self._top + more)])
        self._top += more
        return ids

    def _grow(self, cap: int) -> None:
        def grown(a: np.ndarray, fill=0) -> np.ndarray:
            out = np.full((cap, *a.shape[1:]), fill, a.dtype)
            out[: len(a)] = a
            return out

        self._seg, self._w, self._box = grown(self._seg), grown(self._w), grown(self._box)
        self._slot, self._local, self._comp = grown(self._slot), grown(self._local), grown(self._comp, -1)
        self._alive = grown(self._alive, False)
        self._c_start, self._c_end = grown(self._c_start), grown(self._c_end)
        self._cap = cap

    def _restack(self) -> None:
        """Stack positions: the sources in the given order, each in its layer's order."""
        at = 0
        for k in self._order:
            e = self._entries[k]
            self._offset[e.slot] = at
            at += len(e.nodes)

    def _position(self, nodes: np.ndarray) -> np.ndarray:
        return self._offset[self._slot[nodes]] + self._local[nodes]

    # -- components ----------------------------------------------------------------------------

    def _marks(self, comps: np.ndarray) -> np.ndarray:
        """A table over component ids + 1 (index 0: no component) marking ``comps``."""
        mark = np.zeros(self._top + 1, bool)
        mark[np.asarray(comps, np.int64) + 1] = True
        mark[0] = False
        return mark

    def _members(self, mark: np.ndarray, comps: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The nodes of the components ``comps`` (marked in ``mark``) and the rows of their pairs."""
        nodes = np.flatnonzero(mark[self._comp[: self._top] + 1])
        return nodes, _ranges(self._c_start[comps], self._c_end[comps])[1]

    def _add_edges(self, edges: np.ndarray, edge_comp: np.ndarray, comps: np.ndarray) -> None:
        """Store the pairs ``edges`` of the new components ``comps`` (each pair's: ``edge_comp``),
        each component's pairs in consecutive rows."""
        if self._e_dead > max(self._e_top // 2, EDGES_COMPACT_MIN):  # compact, the rows kept in order
            live = np.flatnonzero(self._e_comp[: self._e_top] >= 0)
            self._edges[: len(live)], self._e_comp[: len(live)] = self._edges[live], self._e_comp[live]
            self._e_top, self._e_dead = len(live), 0
            c, first, count = np.unique(self._e_comp[: len(live)], return_index=True, return_counts=True)
            self._c_start[c], self._c_end[c] = first, first + count
            self.compactions += 1
        top = self._e_top + len(edges)
        if top > len(self._edges):
            more = max(2 * len(self._edges), top, 4096) - self._e_top
            self._edges = np.concatenate([self._edges[: self._e_top], np.zeros((more, 2), np.int64)])
            self._e_comp = np.concatenate([self._e_comp[: self._e_top], np.full(more, -1, np.int64)])
        order = np.argsort(edge_comp, kind="stable")
        self._edges[self._e_top : top], self._e_comp[self._e_top : top] = edges[order], edge_comp[order]
        self._c_start[comps] = self._c_end[comps] = self._e_top  # none, unless ...
        c, first, count = np.unique(edge_comp[order], return_index=True, return_counts=True)
        self._c_start[c], self._c_end[c] = self._e_top + first, self._e_top + first + count
        self._e_top = top

    def _edit(self, old: np.ndarray, new: np.ndarray) -> None:
        """Take the nodes ``old`` (already dead) out and bring ``new`` in: re-merge what they touch."""
        touched = [self._comp[old]]
        edges = [np.zeros((0, 2), np.int64)]
        if len(new):
            seg = self._seg
            i, j = _candidate_pairs(seg[new], self._margin)
            ok = collinear(seg, new[i], new[j], self.cfg)
            edges.append(np.column_stack([new[i[ok]], new[j[ok]]]))
            lo, hi = self._box[new, :2].min(axis=0), self._box[new, 2:].max(axis=0)
            box = self._box[: self._top]
            near = self._alive[: self._top] & (self._comp[: self._top] >= 0)
            near &= (box[:, 0] <= hi[0]) & (box[:, 2] >= lo[0]) & (box[:, 1] <= hi[1]) & (box[:, 3] >= lo[1])
            b = np.flatnonzero(near)
            ia, jb = box_pairs(self._box[new], self._box[b])
            ok = collinear(seg, new[ia], b[jb], self.cfg)
            edges.append(np.column_stack([new[ia[ok]], b[jb[ok]]]))
            touched.append(self._comp[b[jb[ok]]])
        t = np.unique(np.concatenate(touched))
        t = t[t >= 0]
        mark = self._marks(t)
        self._comp[old] = -1
        nodes, theirs = self._members(mark, t)  # alive: the old nodes are out of their components now
        nodes = np.concatenate([nodes, new])
        kept = self._edges[theirs]
        kept = kept[self._alive[kept[:, 0]] & self._alive[kept[:, 1]]]
        self._e_comp[theirs] = -1
        self._e_dead += len(theirs)
        if len(t):
            keep = ~mark[self._g_comp + 1]
            self._g_seg, self._g_support = self._g_seg[keep], self._g_support[keep]
            self._g_first, self._g_comp, self._g_uid = (
                self._g_first[keep],
                self._g_comp[keep],
                self._g_uid[keep],
            )
            keep = ~mark[self._p_comp + 1]
            self._p_uid, self._p_robot, self._p_comp = (
                self._p_uid[keep],
                self._p_robot[keep],
                self._p_comp[keep],
            )
        self._free = np.concatenate([self._free, old])
        if len(nodes):
            self._merge(nodes, np.concatenate([kept, *edges[1:]]))

    def _local_graph(self, nodes: np.ndarray, edges: np.ndarray) -> tuple:
        """``nodes`` in stack order, their components (count, labels) and the edges' first ends'
        index into them."""
        nodes = nodes[np.argsort(self._position(nodes), kind="stable")]
        index = np.full(self._top, -1, np.int64)
        index[nodes] = np.arange(len(nodes))
        i, j = index[edges[:, 0]], index[edges[:, 1]]
        n_comp, comp = components(len(nodes), i, j)
        return nodes, n_comp, comp, i

    def _merge(self, nodes: np.ndarray, edges: np.ndarray) -> None:
        nodes, n_comp, comp, first_end = self._local_graph(nodes, edges)
        group, out = merge_groups(self._seg[nodes], self._w[nodes], comp, n_comp, self.cfg)
        smallest = np.full(n_comp, self._top, np.int64)  # a component's id: its smallest node id
        np.minimum.at(smallest, comp, nodes)
        cid = smallest[comp]
        self._comp[nodes] = cid
        self._add_edges(edges, cid[first_end], smallest)
        g = len(out)
        first = np.full(g, len(nodes))
        np.minimum.at(first, group, np.arange(len(nodes)))
        uid = self._next_uid + np.arange(g)
        self._next_uid += g
        g_comp = cid[first]
        self._g_seg = np.concatenate([self._g_seg, out])
        self._g_support = np.concatenate([self._g_support, np.bincount(group, minlength=g)])
        self._g_first = np.concatenate([self._g_first, nodes[first]])
        self._g_comp = np.concatenate([self._g_comp, g_comp])
        self._g_uid = np.concatenate([self._g_uid, uid])
        pairs = unique_pairs(group, self._slot_robot[self._slot[nodes]])
        self._p_uid = np.concatenate([self._p_uid, uid[pairs[:, 0]]])
        self._p_robot = np.concatenate([self._p_robot, pairs[:, 1]])
        self._p_comp = np.concatenate([self._p_comp, g_comp[pairs[:, 0]]])

    # -- results -------------------------------------------------------------------------------

    def result(self, rows: dict[str, int]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """As fusion.merge_segments of the stacked sources, provenance as ``rows[robot]``."""
        g = len(self._g_seg)
        order = np.argsort(self._position(self._g_first), kind="stable")
        rank = np.empty(g, np.int64)
        rank[order] = np.arange(g)
        gi = rank[np.searchsorted(self._g_uid, self._p_uid)]
        to_row = np.full(max(len(self._robots), 1), -1, np.int64)
        for name, k in self._robots.items():
            to_row[k] = rows.get(name, -1)
        row = to_row[self._p_robot]
        o = np.lexsort((row, gi))
        offsets = np.r_[0, np.cumsum(np.bincount(gi, minlength=g))].astype(np.int64)
        return self._g_seg[order], self._g_support[order].astype(np.int64), offsets, row[o]

    def without(
        self, key: Hashable, lo: np.ndarray | None = None, hi: np.ndarray | None = None
    ) -> np.ndarray:
        """The merged segments of every source but ``key`` (all of them if it is not one), only
        those whose bounding box meets the box ``lo``-``hi`` when given; in no particular order."""
        e = self._entries.get(key)
        keep = np.ones(len(self._g_seg), bool)
        parts = []
        if e is not None and len(e.nodes):
            touched = np.unique(self._comp[e.nodes])
            mark = self._marks(touched)
            keep = ~mark[self._g_comp + 1]
            nodes, theirs = self._members(mark, touched)
            nodes = nodes[self._slot[nodes] != e.slot]
            edges = self._edges[theirs]
            edges = edges[(self._slot[edges[:, 0]] != e.slot) & (self._slot[edges[:, 1]] != e.slot)]
            if len(nodes):
                nodes, n_comp, comp, _ = self._local_graph(nodes, edges)
                parts.append(merge_groups(self._seg[nodes], self._w[nodes], comp, n_comp, self.cfg)[1])
        out = np.concatenate([self._g_seg[keep], *parts])
        if lo is None or hi is None:
            return out
        a, b = out.min(axis=1), out.max(axis=1)
        inside = (a[:, 0] <= hi[0]) & (b[:, 0] >= lo[0]) & (a[:, 1] <= hi[1]) & (b[:, 1] >= lo[1])
        return out[inside]
