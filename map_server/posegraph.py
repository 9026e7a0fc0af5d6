"""The fleet's pose graph: every placed robot's keyframes optimized together, so that robots'
maps bend to agree where they overlap instead of only shifting as a whole.

A robot's map message carries its back end's graph (keyframes, their poses in its map frame,
its edges with their information: chain, jumps, loops) and the keyframe each map element moves
with (``shared/messages.py``, RobotMap). The server joins them:

- **nodes**: a fixed origin (the global frame) and every placed robot's keyframes. A robot
  without a graph (an agent without a back end, or an old one) is one keyframe at its map
  frame's origin, its whole map anchored there, held where its alignment placed it (as before
  the graph): the others bend against it.
- **each robot's own edges**, with the information its back end gave them, holding the relative
  poses of its own solution (its graph is taken as solved: alone, it stays as the robot put it).
  A robot whose map does not contradict its own free space (``consistent_self_m``) has its edges'
  information taken ``consistent_scale`` times: its back end's chain information (an odometry
  noise model) says its path may bend by decimetres where its solution is right within
  centimetres (simulated warehouse: 0.06 m at most over 184 keyframes), and a handful of
  constraints between robots, each within its own noise, bent the reference robot's path by
  0.43 m at a cost of 1 in chi-square. A map that stands in its own free space has a bent path
  (a real log's pieces: metres of it): the graph may bend it.
- **placement edges**: origin → the robot's first keyframe at its rigid placement
  (``alignment.py``). The reference robot's holds the gauge (stiff, as a rigid robot's); a
  prior's holds with the prior's sigma; an aligned robot's is weak — only what keeps a robot
  with no constraint yet where its verified placement put it.
- **constraints between robots by keyframe scans** (``GraphConfig.scans``): two robots that
  both send their keyframes' thinned scans (schema 7) are tied as an agent closes its own loops:
  a keyframe's scan with the two before it (the query) matched against the cloud of the other
  robot's nearest keyframe and its four neighbours each side, where the graph puts them, by
  correlative search over the cloud's likelihood field, its score surface's covariance and ICP
  (``shared/scanmatch.window_match``; ``scan_match``: the agents' defaults, but a best pose on
  the window's edge is searched again around it — keyframes the graph put a window's half width
  from their true places were tied with nothing known along one axis, and stayed there); the
  nearest of up to three keyframes that matches is tied, the keyframe to it, with the match's
  information. The segment maps summarize the scans (an Intel piece's submap constraints,
  fitted where a single robot's run put both keyframes, 0.067 m off that run at the median; the
  scans 0.038 m). Only
  a pair of which one map was found contradicting its own free space (a real log's piece, within
  seconds) is tied so; others are matched by submaps (``scans_always`` off: bench_merge's
  simulated robots tied by scans ended 15 of 39 over 0.05 m, by submaps 6 of 40).
- **constraints between robots by submaps** (robots without scans, or clean maps):
  around every few keyframes of a robot, the part of its map
  anchored to its neighbouring keyframes (a local submap, in that keyframe's frame; more of them
  when its map and the others' stand in none of their own free space: their rows anchored apart
  agree) is
  registered (registration.refine: point-to-line Gauss-Newton, shrinking gates) against the
  other robots' maps where the graph puts them now. The robot was placed by the rigid alignment
  first — the candidates, the verification by overlap, the refusal of ambiguous places are
  that module's; a constraint only says how a neighbourhood of an already verified placement
  fits, and is kept only when it moved the keyframe little, and enough of the submap lies on the
  others' walls. It ties the keyframe its own matched elements move with most (an agent anchors
  a wall to the keyframe that first saw it: a long wall moves with one keyframe, and the
  keyframes that pass it later have none of their own; ``tie_own_anchor``), carried there by the
  fit's correction, to the other robot's keyframe whose elements it matched most (the pose in
  that keyframe's frame), with the fit's information (floored: the submaps' own errors) —
  narrow across a corridor, nothing along it. A submap that meets enough wall of another robot
  besides is tied to it too, by a fit against that robot's walls alone (``each_robot``): two
  robots that overlap each other more than the reference were tied mostly to each other.
  **Held as walls** (``line_ties``, the default): the fit decides only which walls meet which; the
  solve holds each pair of walls met — two points on this robot's wall, in the frame of the
  keyframe it moves with, on the other's wall's line, in the frame of the keyframe that one moves
  with — and weighs their distance where the keyframes are at each iteration. A relative pose
  between two keyframes measured where the graph put the others' walls then carried the graph's
  error of that moment, and tied a submap's walls anchored across many keyframes to one of them;
  the walls tie each keyframe that holds them (a robot's first keyframe holds the walls of its
  first scan). The graph's test of a bent robot: 90th percentile 0.056 -> 0.0068 m.
  Constraints are kept by the keyframe tried and the other robot. A keyframe is tried again when
  the graph moved it; and when a robot arrives (placed, or placed again elsewhere), the others'
  keyframes tried near its map are due again: tried before it was there, they met none of its
  walls.
- **solve**: sparse Gauss-Newton (``shared/posegraph.py``), a Cauchy kernel on the constraints
  (narrower between two maps that agree with themselves: ``robust_k_consistent``),
  warm-started from the last solution; constraints that still disagree (normalized residual
  above ``max_chi``; held as walls: the root mean square of its walls' normalized distances, the
  kernel on each wall) are dropped and the graph solved again. When a robot leaves (the maps are
  final) the graph forgets its solution and constraints (:meth:`FleetGraph.reset`) and is
  matched and solved anew: constraints found on young maps, re-matched narrowly where the graph
  had put their keyframes, held the simulated warehouse's robots 0.12-0.14 m off where their
  final maps, placed on the reference's, are within 0.012 m. A robot placed while two are solved
  can make the graph rebuilt the same way (``rebuild_on_arrival``, off by default; otherwise the
  others' keyframes near it are matched again). A rebuild starts from the placements, or from the
  last solution when that bent robots placed by matching beyond a wide search's reach of their
  placements (their placements are then the bend's: ``_bent_far``). Meanwhile the maps keep the
  last whole bend (``held``; after a restart, the restored one), and the fused map says so.

Each element then moves with its keyframe: ``global = X[k] ∘ P[k]⁻¹ ∘ local`` (``X`` the solved
pose, ``P`` the robot's own).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import NamedTuple

import numpy as np
from scipy.spatial import cKDTree

from map_server.config import GraphConfig
from map_server.fusion import RobotLayer
from map_server.registration import MapIndex, Samples, refine
from shared import posegraph
from shared.geometry import compose, inverse, relative, segment_lengths, transform_points, wrap_angle
from shared.messages import RobotMap, info_matrices
from shared.scanmatch import likelihood_field, local_cloud, voxel_thin, window_match

PRUNE_SLACK = 64  # a robot's matched keyframes and constraints kept beyond its graph's size
MIN_SCAN_POINTS = 30  # a keyframe scan match needs this many points in the query and the cloud
_NO_POINTS = np.zeros((0, 2))


def _scan_points(g: RobotGraph) -> list[np.ndarray]:
    """A graph's keyframe scans, empty where none came (for shared.scanmatch.local_cloud)."""
    return [_NO_POINTS if q is None else q for q in g.points]


@dataclass(frozen=True, eq=False)
class RobotGraph:
    """One robot's graph: keyframe ids ``ids (K,)``, its poses ``pose (K,3)`` in its map frame,
    edges between keyframe positions ``a, b (E,)`` measuring ``z (E,3)`` with ``info (E,3,3)``,
    and each layer row's keyframe position ``row_kf (N,)``."""

    ids: np.ndarray
    pose: np.ndarray
    a: np.ndarray
    b: np.ndarray
    z: np.ndarray
    info: np.ndarray
    row_kf: np.ndarray
    rigid: bool = False  # no graph came: one keyframe at the origin, held where the alignment put it
    points: tuple = ()  # each keyframe's scan points (its frame), None where none came; () without

    @classmethod
    def of(cls, m: RobotMap, layer: RobotLayer) -> RobotGraph:
        """From a map message and its layer; one keyframe at the origin when it has no graph."""
        if not m.has_graph or layer.anchor is None:
            z3 = np.zeros((0, 3))
            e = np.zeros(0, np.int64)
            return cls(np.zeros(1, np.int64), np.zeros((1, 3)), e, e, z3, np.zeros((0, 3, 3)),
                       np.zeros(len(layer), np.int64), rigid=True)  # fmt: skip
        ids = np.asarray(m.kf_id, np.int64)
        pos = np.searchsorted(ids, m.edge_ids)
        pose = np.asarray(m.kf_pose, float)
        # the robot's own solution is taken as solved: each edge holds the relative pose that
        # solution gives (not the edge's measurement, which the robot's robust solve may have
        # outvoted), with the edge's information — alone, the graph stays where the robot put it
        z = relative(pose[pos[:, 0]], pose[pos[:, 1]])
        info = info_matrices(m.edge_info)
        scans = m.scans()
        points = tuple(scans.get(int(i)) for i in ids) if scans else ()
        return cls(
            ids, pose, pos[:, 0], pos[:, 1], z, info, np.searchsorted(ids, layer.anchor), points=points
        )

    def __len__(self) -> int:
        return len(self.ids)


@dataclass(frozen=True)
class Constraint:
    """Keyframe ``b_id`` of the robot seen at ``z`` in the frame of keyframe ``a_id`` of robot
    ``other``, with information ``info (3,3)``."""

    b_id: int
    other: str
    a_id: int
    z: np.ndarray
    info: np.ndarray
    by_scans: bool = False  # from matching keyframe scans (else a submap's fit)
    lines: Walls | None = None  # the fit's matched walls (GraphConfig.line_ties): held instead of z


class Walls(NamedTuple):
    """A fit's matched walls as point-on-line ties: points ``p (L,2)``, each in the frame of this
    robot's keyframe ``mine (L,)`` (ids), on the line ``n·q = d`` (``n (L,2)``, ``d (L,)``) in
    the frame of the other robot's keyframe ``theirs (L,)``, with information ``w (L,)``."""

    mine: np.ndarray
    theirs: np.ndarray
    p: np.ndarray
    n: np.ndarray
    d: np.ndarray
    w: np.ndarray


@dataclass
class Matched:
    """A robot's keyframes tried for a constraint: ids ``ids (M,)`` sorted, and for each its poses
    when tried ``at (M,6)``: where the graph put it, where the robot put it in its own frame."""

    ids: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    at: np.ndarray = field(default_factory=lambda: np.zeros((0, 6)))

    def __len__(self) -> int:
        return len(self.ids)

    def put(self, ids: np.ndarray, at: np.ndarray) -> None:
        """Note keyframes ``ids`` tried at ``at`` (replacing what was noted of them)."""
        ids = np.asarray(ids, np.int64)
        old = ~np.isin(self.ids, ids)
        both = np.concatenate([self.ids[old], ids])
        order = np.argsort(both, kind="stable")
        self.ids, self.at = both[order], np.concatenate([self.at[old], at])[order]

    def keep(self, mask: np.ndarray) -> None:
        self.ids, self.at = self.ids[mask], self.at[mask]

    def lookup(self, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Whether each of ``ids`` was tried, and its poses then (zeros where not)."""
        found, at = _among(self.ids, ids)
        if not len(self.ids):
            return found, np.zeros((len(ids), 6))
        return found, np.where(found[:, None], self.at[at], 0.0)


def _among(keys: np.ndarray, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Whether each of ``ids`` is in the sorted ``keys``, and where (np.isin costs ~35 µs a call
    on a robot's few dozen keyframes; this ~6)."""
    if not len(keys):
        return np.zeros(len(ids), bool), np.zeros(len(ids), np.int64)
    at = np.minimum(np.searchsorted(keys, ids), len(keys) - 1)
    return keys[at] == ids, at


def _wall_ties(
    c: Constraint, g: RobotGraph, og: RobotGraph, start: int, other_start: int, width: float
) -> posegraph.LineTies | None:
    """Constraint ``c``'s walls (``Constraint.lines``) as the solve's line ties, its robot's
    keyframes (graph ``g``) numbered from ``start``, the other's (``og``) from ``other_start``,
    each with the Cauchy kernel ``width``. None when none of its keyframes is left in both graphs."""
    t = c.lines
    found_b, at_b = _among(g.ids, t.mine)
    found_a, at_a = _among(og.ids, t.theirs)
    use = found_a & found_b
    if not use.any():
        return None
    return posegraph.LineTies(
        other_start + at_a[use], start + at_b[use], t.p[use], t.n[use], t.d[use], t.w[use],
        np.full(int(use.sum()), width),
    )  # fmt: skip


@dataclass
class Placed:
    """What the graph needs of a placed robot."""

    robot: str
    graph: RobotGraph
    layer: RobotLayer
    transform: np.ndarray  # its rigid placement
    status: str  # reference / prior / aligned
    sigma: np.ndarray | None = None  # a prior's sigma (status prior)
    consistent: bool = False  # its walls stand in none of its own free space (Fleet._consistent): its
    # own edges' information taken GraphConfig.consistent_scale times, its submaps wider
    contradicts: bool = False  # its walls were found standing in its own free space (a real log's
    # piece): it is tied by keyframe scans (GraphConfig.scans)


@dataclass
class FleetGraph:
    cfg: GraphConfig = field(default_factory=GraphConfig)
    solution: dict = field(default_factory=dict)  # robot -> (graph, X (K,3)): the last solve
    constraints: dict = field(default_factory=dict)  # robot -> {(keyframe id, other robot): Constraint}
    stats: dict = field(default_factory=dict)
    pending: bool = False  # keyframes wait to be matched (more than one fusion's budget, or cut short)
    unsolved: bool = False  # the last solve was cut short (``stop``): solve again
    _matched: dict = field(default_factory=dict)  # robot -> Matched: its keyframes tried
    _placed_at: dict = field(default_factory=dict)  # robot -> its rigid placement at the last solve
    held: dict = field(default_factory=dict)  # robot -> (graph, X): the solution before a reset (or
    # the one restored after a restart: the constraints are not persisted) ...
    rebuilding: bool = False  # ... kept out while every keyframe is matched anew (:meth:`rebuilt`)
    _from_bend: bool = False  # ... matched from the held bend rather than the placements (_bent_far)
    # robot -> (graph, placement, X (K,3)): where a robot new to the graph starts, until it is solved
    # (:meth:`_carry_in`)
    _start: dict = field(default_factory=dict)

    def sync(self, placed: list[Placed]) -> list[str]:
        """Forget what the graph holds of a robot that is no longer placed, or whose placement
        jumped since the last solve by more than twice its placement edge's sigma (undone and
        placed elsewhere, or revised): its last solution and the constraints found where it was
        (its own, and the others' on it) would hold it there. Returns the robots forgotten. Called
        before :meth:`match` and :meth:`solve` with the same robots (they hold nothing of others).
        With ``rebuild_on_arrival`` (off by default: see its comment), a robot new to the graph
        (placed, or placed again elsewhere) with two robots solved already makes it matched and
        solved anew, as a departure does (:meth:`reset`): going on from the last solution, only the
        keyframes near it matched again, left Intel's pieces 0.041 m over the log where a rebuild
        on the same maps gives 0.032-0.038 m. One that arrives during a rebuild joins it
        (:meth:`_arrived`), and so does one that arrives while the bend is beyond a wide search's
        reach of the placements (:meth:`_bent_far`): it was placed against the unbent maps, the
        others would be matched from their bend (ACES in 3 pieces, the reference bent by 2.3 m at
        the median: the new piece ended 3 m off its place); its keyframes start where the bend
        moved the others' around it (:meth:`_carry_in`)."""
        now = {p.robot: p for p in placed}

        def kept(robot: str) -> bool:
            p = now.get(robot)
            return p is not None and not self.jumped(p)

        held = (
            set(self.solution)
            | set(self.constraints)
            | set(self._matched)
            | set(self._placed_at)
            | set(self.held)
        )
        out = sorted(robot for robot in held if not kept(robot))
        for robot in out:
            self.forget(robot)
        new = [p for p in placed if p.robot not in self._placed_at and len(p.layer)]
        if (
            new
            and self.cfg.rebuild_on_arrival
            and len(self.solution) >= 2
            and not self.rebuilding
            and not self._bent_far(self.solution)
        ):
            self.reset(aligned=any(p.status == "aligned" for p in placed))
            self.stats["rebuilds_on_arrival"] = self.stats.get("rebuilds_on_arrival", 0) + 1
        else:
            for p in new:
                others = [o for o in placed if o.robot != p.robot]
                if self.cfg.carry_arrivals:
                    self._carry_in(p, others)
                self._arrived(p, others)
        return out

    def _carry_in(self, p: Placed, others: list[Placed]) -> None:
        """Where a robot new to the graph starts (matched from, and solved from): each of its
        keyframes moved as the bend moved the others' nearest keyframe from their placement, when
        that agrees with more of the others' walls where the bend put them than its placement does.
        A robot placed by a search against the unbent maps (Placer.estimate) meets the others'
        walls there; matched from its placement against their bend, the keyframes the bend moved
        beyond a first match's reach are met by nothing, or by the wrong walls (Intel in 3 pieces:
        the last piece tied by 8 submaps, 2 m off, where the bend had moved the second 2.4 m). One
        placed against the bent maps (or refined against them since) agrees with them as it is."""
        self._start.pop(p.robot, None)
        if p.graph.rigid:
            return
        rigid, correction, walls = [], [], []
        for o in others:  # where the graph has their keyframes (solved, held while rebuilt from
            # the bend, or carried) against where their placements put them
            if o.graph.rigid or o.robot not in self._placed_at:
                continue
            x, r = self.poses(o), compose(o.transform, o.graph.pose)
            rigid.append(r)
            correction.append(compose(x, inverse(r)))
            walls.append(self.rows(o, x))
        if not rigid:
            return
        rigid, correction = np.concatenate(rigid), np.concatenate(correction)
        y = compose(p.transform, p.graph.pose)
        _, near = cKDTree(rigid[:, :2]).query(y[:, :2])
        x = compose(correction[near], y)
        step = np.hypot(*(x[:, :2] - y[:, :2]).T)
        if np.median(step) < self.cfg.stages[-1][0]:  # (within the narrowest match's gate: as it is)
            return
        index = MapIndex(np.concatenate(walls).reshape(-1, 2, 2), self.cfg.sample_step_m)

        def met_m(xs: np.ndarray) -> float:  # (its walls, moved with its keyframes, on theirs)
            return index.overlap(
                np.zeros(3), Samples.of(self.rows(p, xs), self.cfg.sample_step_m), *self.cfg.stages[-1]
            )

        if met_m(x) > met_m(y):
            self._start[p.robot] = (p.graph, np.array(p.transform, float), x)
            self.stats["carried_arrivals"] = self.stats.get("carried_arrivals", 0) + 1

    def _arrived(self, p: Placed, others: list[Placed]) -> None:
        """A robot new to the graph (placed, or placed again elsewhere): the others' keyframes
        tried near its map are due again — tried before it was there, they met none of its walls
        (Intel in 3 pieces, the last piece placed after the rebuild that followed the last
        departure: its overlap tied from its own side only, 0.041 m over the log against 0.033 m
        with both sides). With ``rebuild_on_arrival``, an arrival while nothing is being rebuilt
        rebuilds the graph instead (:meth:`sync`)."""
        rows = self.rows(p).reshape(-1, 2)
        lo, hi = rows.min(axis=0) - self.cfg.crop_radius_m, rows.max(axis=0) + self.cfg.crop_radius_m
        for o in others:
            seen = self._matched.get(o.robot)
            if seen is None or not len(seen):
                continue
            found, at = _among(o.graph.ids, seen.ids)
            x = self.poses(o)[at]
            near = found & np.all((x[:, :2] >= lo) & (x[:, :2] <= hi), axis=1)
            if near.any():
                seen.keep(~near)

    def jumped(self, p: Placed) -> bool:
        """Whether the robot's placement moved since the last solve by more than twice its
        placement edge's sigma (False if not solved yet: nothing held of it)."""
        was = self._placed_at.get(p.robot)
        if was is None:
            return False
        d = relative(was, p.transform)
        near = np.hypot(d[0], d[1]) <= 2.0 * self.cfg.placement_sigma_m
        return not (near and abs(d[2]) <= 2.0 * self.cfg.placement_sigma_rad)

    def forget(self, robot: str) -> None:
        """Drop the robot's solution, its constraints and the others' constraints on it (their
        keyframes are matched again)."""
        for held in (self.solution, self.constraints, self._matched, self._placed_at, self.held, self._start):
            held.pop(robot, None)
        for other, cons in self.constraints.items():
            gone = [k for k, c in cons.items() if c.other == robot]
            for k in gone:
                cons.pop(k)
            if gone and other in self._matched:
                self._matched[other].keep(~np.isin(self._matched[other].ids, [k[0] for k in gone]))

    def reset(self, aligned: bool = False) -> None:
        """Forget every robot's solution and constraints: every keyframe is due again, searched
        wide from the robots' placements (from the solution before, when it bent a robot far from
        its placement and ``aligned`` — some robot was placed by matching, against the maps as
        the graph bent them: :meth:`_bent_far`), and the graph solved from there (a robot left:
        the maps are final; or one was placed, with ``rebuild_on_arrival``: :meth:`sync`). The
        solution before is ``held`` until :meth:`rebuilt` (new maps are carried by it:
        :meth:`carried`; a reset during a rebuild keeps the one before the first), and where each
        robot was placed is kept (one that jumps meanwhile is forgotten: :meth:`jumped`)."""
        self.hold(self.held if self.rebuilding else self.solution)
        self._from_bend = aligned and self.rebuilding and self._bent_far(self.held)
        self.solution = {}
        self.constraints.clear()
        self._matched.clear()
        self._start.clear()

    def _bent_far(self, solution: dict) -> bool:
        """Whether ``solution`` put more than ``rebuild_from_bend_share`` of some robot's keyframes
        further from its rigid placement than a wide search reaches (``first_shift_m``): a
        rebuild then matches them from the bend rather than from the placements, when robots were
        placed by matching (:meth:`reset`) — placed, and refined, against the maps as the graph
        bent them, they are placed where the bend put the others (Intel in 3 pieces, one run: the
        reference piece bent by up to 2.5 m, another piece's keyframes 2.5 m from its placement at
        the median; from the placements the wide searches fell short: 0.41 m over the log, two
        pairs of pieces 2 m apart, against 0.045 m from the bend). Within reach a rebuild from
        the placements is better: a bend is matched again where it went astray (Intel, other
        runs, bent up to 1.5 m: 0.033-0.041 m from the placements, 0.041 m from the bend; the
        graph's bent test robot: 0.038 m at the 90th percentile from the placements, 0.13 m from
        its bend) — but not always: an Intel run whose pieces were placed after the departures,
        13 % of one piece's keyframes beyond reach (its median 1.26 m from its placement), was
        rebuilt from the placements to 0.41 m, from the bend to 0.051 m (the share: GraphConfig)."""
        for robot, (g, x) in solution.items():
            at = self._placed_at.get(robot)
            if at is None:
                continue
            d = compose(at, g.pose)[:, :2] - x[:, :2]
            beyond = np.hypot(d[:, 0], d[:, 1]) > self.cfg.first_shift_m
            if np.mean(beyond) > self.cfg.rebuild_from_bend_share:
                return True
        return False

    def hold(self, solution: dict) -> None:
        """Keep ``solution``'s bend out of the fused map while every keyframe is matched anew
        (:meth:`reset`; a restart, whose constraints are not persisted) — when it is a bend: two
        robots solved together at least. (A departure while only the reference was placed held
        nothing, and the robots placed after it stayed rigid until every keyframe had been
        matched: Intel in 3 pieces ended 0.10 m, the pieces unbent.)"""
        self.rebuilding = len(solution) >= 2
        self.held = dict(solution) if self.rebuilding else {}

    def rebuilt(self) -> None:
        """The rebuild since :meth:`reset` is whole (or there is nothing to rebuild): the
        solution before is let go."""
        self.rebuilding, self.held, self._from_bend = False, {}, False

    def placed_at(self, robot: str, transform: np.ndarray) -> None:
        """The placement the robot's solution was solved with (a solution restored after a
        restart: :meth:`jumped` and :meth:`reset` judge from it)."""
        self._placed_at[robot] = np.array(transform, float)

    def shift(self, robot: str, g: np.ndarray) -> None:
        """The robot's solution moved by the rigid motion ``g`` (the prior gauge moved every frame)."""
        for sol in (self.solution, self.held):
            if robot in sol:
                graph, x = sol[robot]
                sol[robot] = (graph, compose(g, x))
        if robot in self._placed_at:
            self._placed_at[robot] = compose(g, self._placed_at[robot])
        if robot in self._matched:
            seen = self._matched[robot]
            seen.at = np.concatenate([compose(g, seen.at[:, :3]), seen.at[:, 3:]], axis=1)

    def carried(self, p: Placed) -> np.ndarray:
        """Where the robot's keyframes are carried for its fused map: :meth:`poses`, from the
        solution before the reset while a rebuild is under way."""
        return self.poses(p, self.held if self.rebuilding else None)

    def poses(self, p: Placed, solution: dict | None = None) -> np.ndarray:
        """The robot's keyframes in the global frame: solved, or (new ones) carried from the last
        solution (or ``solution``) by the nearest solved keyframe's correction, or at its rigid
        placement."""
        if solution is None and self._from_bend and p.robot in self.held:  # (only while rebuilding)
            solution = self.held  # (matched, and solved from, where the bend had it until rebuilt)
        old = (self.solution if solution is None else solution).get(p.robot)
        g = p.graph
        if old is None:
            start = self._start.get(p.robot)  # (a robot new to the graph: _carry_in)
            if start is not None and start[0] is g and np.array_equal(start[1], p.transform):
                return start[2]
            return compose(p.transform, g.pose)
        og, ox = old
        if og is g:
            return ox
        at = np.clip(np.searchsorted(og.ids, g.ids), 0, len(og.ids) - 1)
        prev = np.clip(at - 1, 0, len(og.ids) - 1)
        closer = np.abs(og.ids[prev] - g.ids) < np.abs(og.ids[at] - g.ids)
        at = np.where(closer, prev, at)
        correction = compose(ox[at], inverse(og.pose[at]))
        return compose(correction, g.pose)

    def rows(self, p: Placed, x: np.ndarray | None = None) -> np.ndarray:
        """The robot's layer rows in the global frame, each moved with its keyframe."""
        x = self.poses(p) if x is None else x
        move = compose(x, inverse(p.graph.pose))[p.graph.row_kf]  # (N,3)
        return transform_points(move[:, None, :], p.layer.seg)

    # -- constraints ---------------------------------------------------------------------------

    def _due(self, placed: list[Placed]) -> list[tuple[np.ndarray, np.ndarray]]:
        """Each robot's keyframes (positions) due for matching: never tried first, then those the
        graph moved since they were tried, the most moved first; and whether each is searched
        wide (it has no constraint yet: never tried, or refused — the graph may have brought it
        within reach since). All robots at once (a robot at a time cost ~4 ms a fusion at 16)."""
        cfg = self.cfg
        parts, out = [], []
        for p in placed:
            g = p.graph
            cand = np.arange(0, len(g), cfg.every_keyframes)
            if g.rigid or not len(cand):
                parts.append(None)
                continue
            seen = self._matched.setdefault(p.robot, Matched())
            cons = self.constraints.get(p.robot, {})
            if len(seen) > len(g) + PRUNE_SLACK or len(cons) > len(g) + PRUNE_SLACK:  # keyframes that
                # left the robot's graph (retired, thinned) leave these too: bounded by its size
                seen.keep(np.isin(seen.ids, g.ids))
                ids = set(g.ids.tolist())
                cons = self.constraints[p.robot] = {k: c for k, c in cons.items() if k[0] in ids}
            found, before = seen.lookup(g.ids[cand])
            parts.append((cand, found, before, self.poses(p)[cand], g.pose[cand]))
        live = [x for x in parts if x is not None]
        if live:
            before = np.concatenate([x[2] for x in live])
            size = np.zeros(len(before))
            for d in (relative(before[:, :3], np.concatenate([x[3] for x in live])),
                      relative(before[:, 3:], np.concatenate([x[4] for x in live]))):  # fmt: skip
                # where the graph put it, where the robot itself put it (its own correction moved it)
                size = np.maximum(
                    size, np.hypot(d[:, 0], d[:, 1]) / cfg.rematch_m + np.abs(d[:, 2]) / cfg.rematch_rad
                )
            sizes = np.split(size, np.cumsum([len(x[0]) for x in live])[:-1])
        at = 0
        for p, x in zip(placed, parts, strict=True):
            if x is None:
                out.append((np.zeros(0, int), np.zeros(0, bool)))
                continue
            cand, found, _, _, _ = x
            sz, at = sizes[at], at + 1
            moved = found & (sz >= 1.0)
            order = np.concatenate([np.flatnonzero(~found), np.flatnonzero(moved)[np.argsort(-sz[moved])]])
            cons = self.constraints.get(p.robot, {})
            held = np.unique(np.fromiter((k[0] for k in cons), np.int64, len(cons)))
            out.append((cand[order], ~_among(held, p.graph.ids[cand[order]])[0]))
        return out

    def match(self, placed: list[Placed], stop: Callable[[], bool] | None = None) -> int:
        """Seek constraints for the keyframes due (:meth:`_due`), at most ``budget_keyframes``
        of them, the robots in turn (no robot after the first once ``stop()`` says so: the rest
        stay due); how many were tried."""
        cfg = self.cfg
        self.pending = False
        if len(placed) < 2:
            return 0
        due = [(p, *d) for p, d in zip(placed, self._due(placed), strict=True)]
        total = sum(len(k) for _, k, _ in due)
        if not total:
            return 0
        share = max(1, cfg.budget_keyframes // max(1, sum(1 for _, k, _ in due if len(k))))
        tried = 0
        where: dict[str, tuple[np.ndarray, np.ndarray]] = {}  # robot -> (keyframes, rows) where
        # the graph puts them: the same for every robot matched here (nothing is solved meanwhile)
        for p, ks, first in due:
            if not len(ks):
                continue
            ks, first = ks[:share], first[:share]
            others = [o for o in placed if o.robot != p.robot]
            x = self._where(p, where)[0]
            found = self._match_robot(p, ks, first, others, where)
            cons = self.constraints.setdefault(p.robot, {})
            tried_ids = set(p.graph.ids[ks].tolist())
            for key in [key for key in cons if key[0] in tried_ids]:
                cons.pop(key)
            self._matched[p.robot].put(p.graph.ids[ks], np.concatenate([x[ks], p.graph.pose[ks]], axis=1))
            for kid, c in found:
                cons[kid, c.other] = c
            tried += len(ks)
            if stop is not None and stop():
                break
        self.pending = tried < total
        self.stats["matched_keyframes"] = self.stats.get("matched_keyframes", 0) + tried
        return tried

    def _where(self, p: Placed, where: dict) -> tuple[np.ndarray, np.ndarray]:
        """The robot's keyframes and layer rows in the global frame, kept in ``where``."""
        if p.robot not in where:
            x = self.poses(p)
            where[p.robot] = (x, self.rows(p, x))
        return where[p.robot]

    def _match_robot(
        self, p: Placed, ks: np.ndarray, first: np.ndarray, others: list[Placed], where: dict
    ) -> list[tuple[int, Constraint]]:
        """Constraints for keyframes ``ks`` of robot ``p`` against the ``others``, each with the
        keyframe tried: by keyframe scans against the robots that, like ``p``, sent them
        (``GraphConfig.scans``), by submaps against the rest (``where``: see :meth:`_where`)."""
        scans = [o for o in others if self._by_scans(p, o)]
        rest = [o for o in others if not any(o is s for s in scans)]
        out = self._match_scans(p, ks, scans, where) if scans else []
        if scans and self.cfg.scan_fallback:  # a pair the scans have not tied yet: by submaps
            untied = [o for o in scans if not self._tied_by_scans(p.robot, o.robot, out)]
            out += self._match_segments(p, ks, first, untied, where) if untied else []
        return out + (self._match_segments(p, ks, first, rest, where) if rest else [])

    def _tied_by_scans(self, a: str, b: str, found: list[tuple[int, Constraint]]) -> bool:
        """Whether a constraint by scans ties robots ``a`` and ``b`` (kept, or in ``found``)."""
        if any(c.by_scans and c.other == b for _, c in found):
            return True
        mine, theirs = self.constraints.get(a, {}).values(), self.constraints.get(b, {}).values()
        return any(c.by_scans and c.other == b for c in mine) or any(
            c.by_scans and c.other == a for c in theirs
        )

    def _by_scans(self, p: Placed, o: Placed) -> bool:
        """Whether robots ``p`` and ``o`` are tied by their keyframe scans: both sent them, and
        one of them was found contradicting its own free space (``scans_always``: whatever their
        maps; else clean maps are matched by submaps, which the scans do not beat there)."""
        cfg = self.cfg
        if not (cfg.scans and len(p.graph.points) and len(o.graph.points)):
            return False
        return cfg.scans_always or p.contradicts or o.contradicts

    def _match_scans(
        self, p: Placed, ks: np.ndarray, others: list[Placed], where: dict
    ) -> list[tuple[int, Constraint]]:
        """Each of keyframes ``ks``: its scan with the ones before it matched against the cloud
        of each other robot's nearest keyframes (and their neighbours) where the graph puts them,
        the nearest that matches tied (its pose in that keyframe's frame, the match's information)."""
        cfg, mc = self.cfg, self.cfg.scan_match
        x = self._where(p, where)[0]
        mine = _scan_points(p.graph)
        queries = {}  # keyframe -> its query (its scan and the ones before it), once for every robot
        for k in ks:
            if p.graph.points[k] is None:
                continue
            q = cfg.scan_query_neighbours
            query = voxel_thin(local_cloud(p.graph.pose, mine, k, k - q, k), cfg.scan_voxel_m)
            if len(query) > cfg.scan_query_points:
                query = query[np.linspace(0, len(query) - 1, cfg.scan_query_points).astype(int)]
            if len(query) < MIN_SCAN_POINTS:
                self._count("scan_small")
                continue
            queries[k] = query
        out, refused = [], {}
        for o in others:
            xo, theirs = self._where(o, where)[0], _scan_points(o.graph)
            for k, query in queries.items():
                d = np.hypot(*(xo[:, :2] - x[k, :2]).T)
                near = np.flatnonzero(
                    (d <= cfg.scan_radius_m)
                    & (np.abs(wrap_angle(xo[:, 2] - x[k, 2])) <= cfg.scan_max_turn_rad)
                )
                near = near[np.argsort(d[near], kind="stable")][: cfg.scan_candidates]
                if not len(near):
                    continue
                for a in near:
                    w = cfg.scan_cloud_neighbours
                    cloud = voxel_thin(local_cloud(o.graph.pose, theirs, a, a - w, a + w), cfg.scan_voxel_m)
                    if len(cloud) < MIN_SCAN_POINTS:
                        continue
                    fld = likelihood_field(cloud, mc.search_step_m, mc.field_sigma_m, 4.0 * mc.field_sigma_m)
                    found = window_match(fld, cloud, query, relative(xo[a], x[k]), mc, refused)
                    if found is not None:
                        kid = int(p.graph.ids[k])
                        c = Constraint(kid, o.robot, int(o.graph.ids[a]), found[0], found[2], by_scans=True)
                        out.append((kid, c))
                        break
                else:
                    self._count("scan_unmatched")
        recentred = refused.pop("recentred", 0)
        if recentred:
            self.stats["scan_recentred"] = self.stats.get("scan_recentred", 0) + recentred
        for why, n in refused.items():
            self.stats[f"refused_scan_{why}"] = self.stats.get(f"refused_scan_{why}", 0) + n
        return out

    def _match_segments(
        self, p: Placed, ks: np.ndarray, first: np.ndarray, others: list[Placed], where: dict
    ) -> list[tuple[int, Constraint]]:
        """Constraints for keyframes ``ks`` of robot ``p`` against the ``others``' walls, each with
        the keyframe tried: its submap searched wide where ``first``, narrow otherwise."""
        cfg = self.cfg
        x, mine = self._where(p, where)
        if not len(mine):
            return []
        # the others' rows where the graph puts them, near this robot's
        lo, hi = mine.reshape(-1, 2).min(axis=0) - 2.0, mine.reshape(-1, 2).max(axis=0) + 2.0
        segs, owner_robot, owner_kf = [], [], []
        for j, o in enumerate(others):
            if not len(o.layer):
                continue
            rows = self._where(o, where)[1]
            near = np.all((rows.max(axis=1) >= lo) & (rows.min(axis=1) <= hi), axis=1)
            segs.append(rows[near])
            owner_robot.append(np.full(int(near.sum()), j))
            owner_kf.append(o.graph.row_kf[near])
        if not segs or not sum(len(s) for s in segs):
            return []
        seg = np.concatenate(segs)
        own_r, own_k = np.concatenate(owner_robot), np.concatenate(owner_kf)
        index = MapIndex(seg, cfg.sample_step_m)
        g = p.graph
        out = []
        mid = cKDTree(0.5 * (mine[:, 0] + mine[:, 1]))
        alone: dict[int, tuple[MapIndex, np.ndarray]] = {}  # another robot's rows alone, indexed
        # (a wide submap is fitted rigidly: to walls that agree with each other as widely — a bent
        # robot's do not, even where the graph put them: the exact robot of the graph's test ended
        # 0.21 m off, matched widely against a bent one, against 0.09 m)
        wide_ok = p.consistent and all(o.consistent for o in others)
        window = cfg.window_consistent_keyframes if wide_ok else cfg.window_keyframes
        for k, wide in zip(ks, first, strict=True):
            stages = cfg.first_stages if wide else cfg.stages
            shift_m, turn_rad = (
                (cfg.first_shift_m, cfg.first_turn_rad) if wide else (cfg.max_shift_m, cfg.max_turn_rad)
            )
            near = np.asarray(mid.query_ball_point(x[k, :2], cfg.crop_radius_m), int)
            near = near[np.abs(g.row_kf[near] - k) <= window]  # (those moving with it)
            if not len(near):
                self._count("small")
                continue
            local = transform_points(inverse(x[k])[None, None, :], mine[near])
            if segment_lengths(local).sum() < cfg.min_submap_m:
                self._count("small")
                continue
            sub = Samples.of(local, cfg.sample_step_m)
            fit = refine(index, sub, x[k], stages, cfg.point_sigma_m, cfg.correlation_m)
            d = fit.pose - x[k]
            if np.hypot(d[0], d[1]) > shift_m or abs(wrap_angle(d[2])) > turn_rad:
                self._count("moved")
                continue
            gate, angle = cfg.stages[-1]
            ok, idx, perp = index.match(fit.pose, sub, gate, angle)
            ok &= np.abs(perp) <= gate
            need = max(cfg.min_matched_m, cfg.min_matched_share * float(sub.length.sum()))
            if float(sub.length[ok].sum()) < need:
                self._count("unmatched")
                continue
            rows = index.samples.owner[idx]  # (the row each sample met, and whose it is)
            met = own_r[rows]
            j = np.bincount(met[ok]).argmax()  # the robot most of the matched walls are of
            a = int(np.bincount(own_k[rows[ok & (met == j)]]).argmax())
            kid = int(g.ids[k])
            tie = self._tie(p, k, x, near, sub, fit, ok, others[j], a, where)
            if cfg.line_ties:
                sel = ok & (met == j)
                tie = self._lines(tie, p, k, x, near, sub, sel, index.samples, idx, own_k, others[j], where)
            out.append((kid, tie))
            if not cfg.each_robot:
                continue
            for jj in np.unique(met[ok]):  # a robot met here besides: its own fit, its own tie
                if jj == j or float(sub.length[ok & (met == jj)].sum()) < need:
                    continue
                if jj not in alone:
                    mine_j = np.flatnonzero(own_r == jj)
                    alone[jj] = (MapIndex(seg[mine_j], cfg.sample_step_m), own_k[mine_j])
                index_j, kf_j = alone[jj]
                fit_j = refine(index_j, sub, fit.pose, cfg.stages, cfg.point_sigma_m, cfg.correlation_m)
                d = fit_j.pose - x[k]
                if np.hypot(d[0], d[1]) > shift_m or abs(wrap_angle(d[2])) > turn_rad:
                    continue
                ok_j, idx_j, perp_j = index_j.match(fit_j.pose, sub, gate, angle)
                ok_j &= np.abs(perp_j) <= gate
                if float(sub.length[ok_j].sum()) < need:
                    continue
                a_j = int(np.bincount(kf_j[index_j.samples.owner[idx_j[ok_j]]]).argmax())
                tie = self._tie(p, k, x, near, sub, fit_j, ok_j, others[jj], a_j, where)
                if cfg.line_ties:
                    tie = self._lines(
                        tie, p, k, x, near, sub, ok_j, index_j.samples, idx_j, kf_j, others[jj], where
                    )
                out.append((kid, tie))
        return out

    def _tie(
        self, p: Placed, k: int, x: np.ndarray, near: np.ndarray, sub: Samples, fit, ok: np.ndarray,
        o: Placed, a: int, where: dict,
    ) -> Constraint:  # fmt: skip
        """The constraint a fit of keyframe ``k``'s submap (rows ``near``, samples ``sub``; ``ok``:
        those matched) makes with keyframe position ``a`` of robot ``o``: its own side tied to the
        keyframe its matched rows move with (``tie_own_anchor``), its information the fit's (carried
        there) plus the floor, turned into ``a``'s frame."""
        cfg, g = self.cfg, p.graph
        xa = self._where(o, where)[0][a]
        cov = np.linalg.inv(fit.info + 1e-9 * np.eye(3))
        b, pose_b = k, fit.pose
        if cfg.tie_own_anchor:  # the keyframe the matched rows of this robot move with
            b = int(np.bincount(g.row_kf[near][sub.owner[ok]]).argmax())
            if b != k:
                pose_b = compose(fit.pose, relative(x[k], x[b]))
                arm = pose_b[:2] - fit.pose[:2]  # (the fit's turn moves the anchor across it)
                jac = np.array([[1.0, 0.0, -arm[1]], [0.0, 1.0, arm[0]], [0.0, 0.0, 1.0]])
                cov = jac @ cov @ jac.T
        cov = cov + np.diag([cfg.floor_sigma_m**2, cfg.floor_sigma_m**2, cfg.floor_sigma_rad**2])
        rot = np.eye(3)
        c, s = np.cos(xa[2]), np.sin(xa[2])
        rot[:2, :2] = [[c, -s], [s, c]]
        info = rot.T @ np.linalg.inv(cov) @ rot
        info = 0.5 * (info + info.T)
        return Constraint(int(g.ids[b]), o.robot, int(o.graph.ids[a]), relative(xa, pose_b), info)

    def _lines(
        self, tie: Constraint, p: Placed, k: int, x: np.ndarray, near: np.ndarray, sub: Samples,
        ok: np.ndarray, theirs: Samples, idx: np.ndarray, their_kf: np.ndarray, o: Placed, where: dict,
    ) -> Constraint:  # fmt: skip
        """``tie`` with the fit's matched walls as point-on-line ties (``GraphConfig.line_ties``):
        samples ``ok`` of keyframe ``k``'s submap (rows ``near``) met ``theirs[idx]`` (the other
        robot's samples, their rows' keyframes ``their_kf``). Each pair of rows met becomes two
        points on this robot's row, in the frame of the keyframe it moves with, on the other's
        line in the frame of the keyframe that one moves with — their placements taken out, the
        tie holds only the walls' shapes, and the solve weighs them where the keyframes are then.
        The two points (the matched samples' mean ± their spread along the row) sum the samples'
        squared distances exactly for any rigid motion; their information is the samples'
        (``line_sigma_m``, a sample counting ``step / correlation_m``) floored by
        ``line_floor_m`` (a wall's own error, the same for all its samples)."""
        cfg, g = self.cfg, p.graph
        if ok.sum() < 2:
            return tie
        xo = self._where(o, where)[0]
        mine_row = sub.owner[ok]  # (positions in ``near``)
        their_row = theirs.owner[idx[ok]]
        ba = g.row_kf[near][mine_row]
        ab = their_kf[their_row]
        pts = transform_points(x[k], sub.points[ok])  # (global, where the graph puts them)
        q = transform_points(inverse(x[ba]), pts)  # ... in the frame of the keyframe they move with
        nw, cw = theirs.normal[idx[ok]], theirs.offset[idx[ok]]
        c, s = np.cos(xo[ab, 2]), np.sin(xo[ab, 2])
        n = np.column_stack([c * nw[:, 0] + s * nw[:, 1], -s * nw[:, 0] + c * nw[:, 1]])
        d = cw - np.sum(nw * xo[ab, :2], axis=1)
        key = mine_row.astype(np.int64) * (int(their_row.max()) + 1) + their_row
        _, first, pair = np.unique(key, return_index=True, return_inverse=True)
        pair, m = pair.ravel(), len(first)
        wl = sub.length[ok]
        tot = np.bincount(pair, wl, m)
        centre = np.column_stack([np.bincount(pair, wl * q[:, 0], m), np.bincount(pair, wl * q[:, 1], m)])
        centre /= tot[:, None]
        row = self._where(p, where)[1][near[mine_row[first]]]  # (this robot's rows, global)
        phi = np.arctan2(row[:, 1, 1] - row[:, 0, 1], row[:, 1, 0] - row[:, 0, 0]) - x[ba[first], 2]
        e = np.column_stack([np.cos(phi), np.sin(phi)])
        along = np.sum((q - centre[pair]) * e[pair], axis=1)
        spread = np.sqrt(np.bincount(pair, wl * along**2, m) / tot)
        var = cfg.line_sigma_m**2 * cfg.correlation_m / tot + cfg.line_floor_m**2
        both = np.tile  # (the pair's two points: the first half, then the second)
        walls = Walls(
            both(g.ids[ba[first]], 2), both(o.graph.ids[ab[first]], 2),
            np.concatenate([centre + spread[:, None] * e, centre - spread[:, None] * e]),
            both(n[first], (2, 1)), both(d[first], 2), both(0.5 / var, 2),
        )  # fmt: skip
        return replace(tie, lines=walls)

    def _count(self, why: str) -> None:
        self.stats[f"refused_{why}"] = self.stats.get(f"refused_{why}", 0) + 1

    # -- the solve -----------------------------------------------------------------------------

    def solve(self, placed: list[Placed], stop: Callable[[], bool] | None = None) -> dict[str, np.ndarray]:
        """Every placed robot's keyframes in the global frame (robot -> X (K,3)), solved together;
        one Gauss-Newton iteration at least, no further one once ``stop()`` says so (``unsolved``:
        the next solve goes on from there)."""
        cfg = self.cfg
        start, x0 = {}, [np.zeros((1, 3))]
        n = 1
        for p in placed:
            start[p.robot] = n
            x0.append(self.poses(p))
            n += len(p.graph)
        x0 = np.vstack(x0)
        a, b, z, info = [], [], [], []
        for p in placed:  # each robot's own edges
            s, g = start[p.robot], p.graph
            a.append(g.a + s)
            b.append(g.b + s)
            z.append(g.z)
            info.append(g.info * (cfg.consistent_scale if p.consistent else 1.0))
        for p in placed:  # placement edges: origin -> first keyframe
            if p.status == "reference" or p.graph.rigid:  # the gauge, or a map placed as a whole
                sig = np.array([cfg.reference_sigma_m, cfg.reference_sigma_m, cfg.reference_sigma_rad])
            elif p.status == "prior" and p.sigma is not None:
                sig = np.maximum(p.sigma, [1e-3, 1e-3, 1e-4])
            else:
                sig = np.array([cfg.placement_sigma_m, cfg.placement_sigma_m, cfg.placement_sigma_rad])
            a.append(np.array([0]))
            b.append(np.array([start[p.robot]]))
            z.append(compose(p.transform, p.graph.pose[0])[None])
            info.append(np.diag(1.0 / sig**2)[None])
        robust_from = sum(len(v) for v in a)
        cons, width = [], []  # (each constraint's kernel width: both robots' maps agree with themselves)
        line_parts, groups = [], []  # (constraints held as point-on-line ties: line_ties)
        by_robot = {p.robot: p for p in placed}
        for p in placed:
            for c in self.constraints.get(p.robot, {}).values():
                if c.other not in start:
                    continue
                og = by_robot[c.other].graph
                ai, bi = int(np.searchsorted(og.ids, c.a_id)), int(np.searchsorted(p.graph.ids, c.b_id))
                if ai >= len(og.ids) or og.ids[ai] != c.a_id:
                    continue  # (that keyframe left the other robot's graph)
                if bi >= len(p.graph.ids) or p.graph.ids[bi] != c.b_id:
                    continue
                both = p.consistent and by_robot[c.other].consistent
                k = cfg.robust_k_consistent if both else cfg.robust_k
                if c.lines is not None and cfg.line_ties:
                    part = _wall_ties(c, p.graph, og, start[p.robot], start[c.other], k)
                    if part is not None:
                        groups.append(np.full(len(part.a), len(groups)))
                        line_parts.append(part)
                    continue
                cons.append((start[c.other] + ai, start[p.robot] + bi, c.z, c.info))
                width.append(k)
        self.stats["constraints"] = len(cons) + len(groups)
        lines = None
        if line_parts:
            lines = posegraph.LineTies(*(np.concatenate(col) for col in zip(*line_parts, strict=True)))
            group = np.concatenate(groups)
            line_keep = np.ones(len(groups), bool)
        if cons:
            ca, cb, ci = (
                np.array([c[0] for c in cons]),
                np.array([c[1] for c in cons]),
                np.array([c[3] for c in cons]),
            )
            if cfg.share_pairs:  # constraints on one pair of keyframes share its information
                _, inv, count = np.unique(
                    np.column_stack([ca, cb]), axis=0, return_inverse=True, return_counts=True
                )
                ci = ci / count[inv.ravel()][:, None, None]
            a.append(ca)
            b.append(cb)
            z.append(np.array([c[2] for c in cons]))
            info.append(ci)
        a, b = np.concatenate(a).astype(int), np.concatenate(b).astype(int)
        width = np.array(width, float)
        z, info = np.vstack(z), np.concatenate(info)
        keep = np.ones(len(a), bool)
        x = x0
        self.unsolved = False
        for _round in range(3):
            held = None if lines is None else posegraph.LineTies(*(col[line_keep[group]] for col in lines))
            x = posegraph.optimize(
                x0, a[keep], b[keep], z[keep], info[keep], iterations=cfg.iterations, tol=cfg.tol,
                robust_from=int(keep[:robust_from].sum()), robust_k=width[keep[robust_from:]], stop=stop,
                lines=held,
            )  # fmt: skip
            if stop is not None and stop():
                self.unsolved = True  # (maybe converged: the next solve says so cheaply)
                break
            if not cons and lines is None:
                break
            r = relative(x[a[robust_from:]], x[b[robust_from:]]) - z[robust_from:]
            r[:, 2] = wrap_angle(r[:, 2])
            chi = np.sqrt(posegraph.mahalanobis2(r, info[robust_from:]) / 3.0)
            new = np.concatenate([np.ones(robust_from, bool), chi <= cfg.max_chi])
            same = np.array_equal(new, keep)
            if lines is not None:  # a line constraint's chi: over its lines
                lr = posegraph.line_residuals(x, lines)[0]
                n_lines = np.bincount(group, minlength=len(line_keep))
                line_chi = np.sqrt(np.bincount(group, lines.w * lr**2, len(line_keep)) / n_lines)
                new_lines = line_chi <= cfg.max_chi
                same = same and np.array_equal(new_lines, line_keep)
                line_keep = new_lines
            if same:
                break
            keep = new
        kept_lines = 0 if lines is None else int(line_keep.sum())
        self.stats["constraints_kept"] = int(keep[robust_from:].sum()) + kept_lines
        out = {}
        for p in placed:
            s = start[p.robot]
            out[p.robot] = x[s : s + len(p.graph)]
            self.solution[p.robot] = (p.graph, out[p.robot])
            self._placed_at[p.robot] = np.array(p.transform, float)
            self._start.pop(p.robot, None)
        return out
