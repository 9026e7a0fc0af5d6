"""The map server's state, pure: robot maps and poses in, alignments and the fused map out.

Time is passed in (``now_s``, the server's clock); nothing here does I/O.

Global frame: if a robot's map carries a start-pose prior when the first robot is placed, the
priors define the global frame: every prior robot is placed by its prior and refined, within its
sigma, against the others as they move (so the maps settle on their consensus), and after each
round the whole placed set is moved by the rigid motion that balances the prior robots against
their priors (``prior_gauge``: one robot at a time fixes the robots relative to each other, not
where the set is); robots without a prior are matched against them. Otherwise the first robot to
publish a non-empty map becomes the *reference* (identity transform) and the others are matched
against the fused map of the robots already placed (never including themselves). While the
reference is the only placed robot, the others are also matched with each other: a pair that
matches (mature, verified, confirmed, as any placement) takes the frame over — the larger map
becomes the reference — and the old reference is matched against the two (placing.Placer.regroup:
which map comes first is chance, and a middle piece of a real log can overlap neither end). Priors that
arrive after a reference was chosen are in a frame nobody placed, so those robots are matched like
the others.

Matching is conservative at the fleet level too (alignment.py verifies one attempt, placing.py runs the
rounds of attempts, policy.py says what a verdict means):

- partial maps of a symmetric or repetitive building match their mirror image as well as the
  truth or better (office, 60-90 s: the half-turned placement scored up to 1.7x the truth, with
  exact maps too). An unplaced robot's verdict counts once its map and every placed robot's map
  are *mature* (grown by at most ``mature_growth`` over ``mature_window_s``), or before that
  when it is *quiet*: none of its walls where the other saw free space, over enough free space
  both saw (``young_*``; policy.quiet);
- of the unplaced robots that match in one round only the most decisive (highest rival ratio)
  is taken; the others are tried again against the grown placed map;
- a new place (a first alignment or a revision) counts after ``confirmations`` attempts in a row
  agree on it (a quiet verdict over ``young_once_seen_m2`` after ``young_confirmations``).

Attempts are repeated only when a robot's map grew enough, the map it is matched against changed,
or a candidate awaits confirmation; a placed robot (by prior or by matching) is refined where it
is whenever its map or the placed map changed, every ``retry_interval_s`` or at once when a robot
leaves (its agent published its final map, rebuilt by its back end, just before).
:meth:`Fleet.fuse` then merges the placed robots' cross-particle maps (fusion.py); the version
increases only when the content (segments, provenance, robot statuses — not the poses) changed.

A robot that restarts comes back as a new *session* in a new map frame. What the fused map held
of its old session is not dropped: the old session's last map becomes a *retired piece*, kept in
the fused map where it was placed (its transform frozen but for the prior frame's common motion,
its segments credited to the robot) and in the snapshot. The new session starts unaligned and is
placed like any robot — by its prior, or by matching against the fused map, which holds its own
old piece: a robot that re-maps the same place aligns to it. At most ``max_retired`` pieces are
kept per robot, the oldest dropped (logged); an old session that was never placed had nothing in
the fused map and is dropped (logged).

Cost: a fusion does what changed, not the whole fleet again (benchmarks/bench_fleet.py --only
fusion; README, "Operating it"). The merge across robots is kept per connected component
(incremental.py): a robot's new map or new transform re-merges the components its old and new
segments touch, a common motion of a prior frame moves the merged segments. A refinement looks
at the placed map near the robot only: the merge of the others is the fused map with the robot's
own components re-merged without it, cropped to the robot map's box (registration.MapIndex answers
exactly inside it; an attempt that strays out is done again on the whole map). Placed robots are
refined a few at a time (``refine_budget_segments``), not all at once every ``retry_interval_s``;
a robot is due again when its map or a placed map near it changed. Statuses and the change key's
parts are made again only for robots whose map, pose or alignment changed.
"""

from __future__ import annotations

import copy
import dataclasses
import logging
from collections.abc import Callable

import numpy as np

from map_server.alignment import (
    Alignment,
    floored_prior_sigma,
    prior_gauge,
)
from map_server.config import FleetConfig
from map_server.fusion import fuse_particles
from map_server.incremental import MergedMap, Source
from map_server.placing import Placer
from map_server.policy import agrees, contradicts_self
from map_server.posegraph import FleetGraph, Placed, RobotGraph
from map_server.state import RetiredPiece, RobotState
from map_server.trials import Trial, Trials
from shared.geometry import apply_segments, compose, inverse, relative, wrap_angle
from shared.messages import GRAPH_FIELDS, FusedMap, PoseUpdate, RobotMap, RobotPath, RobotStatus

log = logging.getLogger("fleet_slam.fleet")


class Fleet:
    def __init__(self, cfg: FleetConfig, server_id: str):
        self.cfg, self.server_id = cfg, server_id
        self.robots: dict[str, RobotState] = {}
        self.retired: dict[str, list[RetiredPiece]] = {}  # per robot, oldest first
        self.reference: str | None = None
        self.frame: str | None = None  # "prior" or "reference", fixed when the first robot is placed
        self.version = 0
        self.epoch_s: float | None = None  # server time of the first message
        self._latest: FusedMap | None = None
        self._content: tuple | None = None
        self._arrivals = 0
        self._left = False  # a robot left since the last fusion: settle (not persisted)
        # a settle under way (not persisted): sweeps begun, robots left to refine in this sweep,
        # every placed robot's transform when it began
        self._settling: tuple[int, list[str], dict[str, np.ndarray]] | None = None
        self._merged = MergedMap(cfg.fusion)  # the merge of the placed layers, kept up to date
        self._rigid_merged = MergedMap(cfg.fusion)  # ... each placed as a whole (global_segments)
        self._statuses: dict[str, tuple] = {}  # robot -> (what its status is made of, status, key)
        self.graph = FleetGraph(cfg.graph)  # the placed robots' keyframes solved together
        self._graph_key: tuple | None = None  # what the graph's last solve held
        self._graph_moved = False  # the last bend matched or solved (keyframes may be due again)
        # a robot session's free space in its map frame (shapely, or None): the server gives
        # freespace.FreeSpaces.area; without it no placement is checked for contradiction
        self.free_of: Callable[[str, str], object] | None = None
        self.placer = Placer(self)  # the alignment rounds (placing.py)
        self._stiff: dict[str, tuple] = {}  # robot -> what Fleet._consistent measured
        self.trials = Trials()  # the graph's trials of robots at places (trials.py)
        self._defer_trials = False  # run after publishing (the server: fuse(bend=False))

    # -- inputs ------------------------------------------------------------------------------

    def _robot(self, robot: str, now_s: float | None) -> RobotState:
        if self.epoch_s is None and now_s is not None:
            self.epoch_s = now_s
        if robot not in self.robots:
            self.robots[robot] = RobotState(robot, order=self._arrivals)
            self._arrivals += 1
        return self.robots[robot]

    def put_map(self, m: RobotMap, now_s: float) -> None:
        """An assembled map (chunk 0 of 1). A new session replaces the old map and its alignment
        (the old map, if placed, lives on as a retired piece); an older or repeated ``seq`` of the
        current session is ignored."""
        r = self._robot(m.robot, now_s)
        if r.map is not None and m.session == r.map.session and m.seq <= r.map.seq:
            return
        if any(p.session == m.session for p in self.retired.get(m.robot, ())):
            return  # a late map of a replaced session (e.g. pulled from the state after a restart)
        if not m.has_graph and m.graph_seq is not None:
            m = self._with_graph(r, m)
        m = m.with_scans_of(r.map)  # (the keyframe scans came once each: the map kept is whole)
        if r.map is not None and m.session != r.map.session:
            self.trials.forget(m.robot)
            self._retire(r, now_s)
            r.new_session()
            if self.reference == m.robot:
                self.reference = None  # its old frame lives on only through the robots placed in it
        r.map, r.layer = m, None
        if r.first_map_s is None and len(m.seg):
            r.first_map_s = now_s

    @staticmethod
    def _with_graph(r: RobotState, m: RobotMap) -> RobotMap:
        """A map whose graph is unchanged since an earlier map carried it (``graph_seq``), with
        that graph (from the robot's map before: the stored map is whole). Missed (a lost message,
        a restart): the last graph the server has, if it holds every keyframe the anchors name;
        else the map is placed as a whole until the next graph comes (one back-end period)."""
        prev = r.map
        ok = prev is not None and prev.session == m.session and prev.has_graph
        if ok and prev.graph_seq != m.graph_seq and not np.isin(m.anchor, prev.kf_id).all():
            log.info(
                "%s: the graph of map %d was missed; map %d is placed as a whole", m.robot, m.graph_seq, m.seq
            )
            ok = False
        if not ok:
            return dataclasses.replace(m, anchor=None, graph_seq=None)
        graph = {f: getattr(prev, f) for f in GRAPH_FIELDS}
        return dataclasses.replace(m, **graph, graph_seq=prev.graph_seq)

    def _retire(self, r: RobotState, now_s: float) -> None:
        """Keep the replaced session's map in the fused map where it was placed (bounded)."""
        if not r.alignment.placed:
            if r.map is not None and len(r.map.seg):
                log.info("%s: session %s replaced unplaced; its map is dropped", r.robot, r.map.session)
            return
        layer = r.layer if r.layer is not None else fuse_particles(r.map, self.cfg.fusion)
        if len(layer) == 0:
            return
        t = now_s - (self.epoch_s if self.epoch_s is not None else now_s)
        pieces = self.retired.setdefault(r.robot, [])
        pieces.append(RetiredPiece(r.robot, r.map.session, r.map, layer, r.alignment, max(0.0, t)))
        while len(pieces) > self.cfg.max_retired:
            old = pieces.pop(0)
            log.info(
                "%s: more than %d retired sessions; the oldest (%s, %d segments) is dropped",
                r.robot, self.cfg.max_retired, old.session, len(old.layer),
            )  # fmt: skip

    def pieces(self) -> list[RetiredPiece]:
        return [p for name in sorted(self.retired) for p in self.retired[name]]

    def put_pose(self, p: PoseUpdate, now_s: float) -> None:
        r = self._robot(p.robot, now_s)
        if r.pose is None or p.session != r.pose.session or p.seq > r.pose.seq:
            r.pose = p

    def set_online(self, robot: str, online: bool) -> None:
        """Presence. A robot leaving has published its final map (an agent at the end of its run
        publishes the map rebuilt by its back end last): every placed robot is refined against
        the maps as they are now, without waiting for ``retry_interval_s``."""
        r = self._robot(robot, None)
        self._left |= r.online and not online
        r.online = bool(online)

    # -- fusion ------------------------------------------------------------------------------

    def fuse(self, now_s: float, bend: bool = True) -> FusedMap | None:
        """Recompute alignments where warranted, then the fused map; ``None`` if nothing changed.

        With ``bend`` false the fleet's graph is not matched and solved before the fused map is
        built: a robot's new map is bent by the graph's last solution (its new keyframes carried
        by their neighbours' correction), and the caller runs :meth:`bend` after publishing — the
        server does, so that the graph's work (most of a fusion at 16 robots) is not between a
        map's arrival and the fused map that holds it; its result goes out with the next fusion.
        The alignment rounds see the same state either way (they come before the graph)."""
        if self.epoch_s is None:
            self.epoch_s = now_s
        self._defer_trials = not bend
        self.placer.new_fusion()
        for r in self.robots.values():
            if r.map is not None and r.layer is None:
                r.layer = fuse_particles(r.map, self.cfg.fusion)
                r.graph = RobotGraph.of(r.map, r.layer)
                r.record_length(now_s, self.cfg.mature_window_s)
        self._choose_frame(now_s)
        while self.placer.round(now_s) or self.placer.regroup(now_s):
            pass
        if self._left:
            self._left = False
            self._settling = (0, [], {})  # a settle begins (again, if one was under way)
            # matched and solved anew on the final maps (from the bend when robots were placed
            # against it and it is far from their placements: FleetGraph._bent_far)
            self.graph.reset(aligned=any(r.alignment.status == "aligned" for r in self.placed()))
            log.info(
                "a robot left: the fleet graph is matched and solved anew (the last bend held meanwhile)"
            )
        if self._settling is not None:
            self._settle(now_s)
        if self.frame == "prior":
            self._hold_prior_gauge()
        if bend:
            self.bend()
        else:
            self._carry()
        return self._publish(now_s)

    @property
    def graph_stale(self) -> bool:
        """Whether :meth:`bend` has work: a placed robot's graph or placement changed since the
        graph's last solve, keyframes wait to be matched, or the last bend matched or moved
        keyframes (which may be due again where it moved them)."""
        if not self.cfg.graph.enabled:
            return False
        if self._graph_moved or self.graph.pending or self.graph.unsolved:
            return True
        return self._bend_key(self._bend_placed()) != self._graph_key

    def _bend_placed(self) -> list[RobotState]:
        return [r for r in self.placed() if r.map is not None and r.graph is not None]

    @staticmethod
    def _bend_key(placed: list[RobotState]) -> tuple:
        """What the graph's solve depends on besides its constraints."""
        return tuple(
            (r.robot, id(r.graph), r.alignment.transform.tobytes(), r.alignment.status) for r in placed
        )

    def graph_item(self, r: RobotState) -> Placed:
        """What the fleet's graph takes of placed robot ``r``, with its own-consistency verdicts."""
        return _graph_item(r, self._consistent(r), self._contradicts(r))

    def graph_items(self) -> list[Placed]:
        """:meth:`graph_item` of every robot the graph bends."""
        return [self.graph_item(r) for r in self._bend_placed()]

    def _consistent(self, r: RobotState) -> bool:
        """Whether a placed robot's walls stand in its own free space by at most
        ``consistent_self_m`` (not while its free space is not known): the graph takes its own
        edges' information ``consistent_scale`` times and matches wider submaps of it. Measured
        when the graph solves, again once its map grew by ``retry_growth_m`` since; a map once
        found contradicting itself stays so for its session (a real log's piece: metres within
        seconds — its free space, thousands of vertices, is not shrunk again for this)."""
        g, session = self.cfg.graph, r.map.session
        hit = self._stiff.get(r.robot)  # (session, map length measured at, own noise or None)
        stale = hit is None or hit[0] != session
        if not stale and not contradicts_self(hit[2], g.consistent_self_m):  # (else: for good)
            stale = abs(r.layer.length_m - hit[1]) >= self.cfg.retry_growth_m
        if stale:
            if len(self._stiff) > 2 * len(self.robots) + 8:  # (robots forgotten)
                self._stiff = {k: v for k, v in self._stiff.items() if k in self.robots}
            was = hit is not None and hit[0] == session and agrees(hit[2], g.consistent_self_m)
            hit = self._stiff[r.robot] = (session, r.layer.length_m, self.placer.own_noise_m(r))
            if hit[2] is not None and agrees(hit[2], g.consistent_self_m) != was:
                how = "bent as the others' walls say" if was else "held to its shape, wide submaps"
                log.info("%s: its walls stand %.1f m in its own free space: %s", r.robot, hit[2], how)
        return agrees(hit[2], g.consistent_self_m)

    def _contradicts(self, r: RobotState) -> bool:
        """Whether a placed robot's walls were found standing in its own free space by more than
        ``consistent_self_m`` (after :meth:`_consistent` measured it; not known: False)."""
        hit = self._stiff.get(r.robot)
        return (
            hit is not None
            and hit[0] == r.map.session
            and contradicts_self(hit[2], self.cfg.graph.consistent_self_m)
        )

    def _carry(self) -> None:
        """A bent robot whose map changed since the graph's last solve: its new layer moved by the
        last solution (:meth:`FleetGraph.poses`: new keyframes carried by their neighbours'
        correction) rather than its old layer kept, until the graph is solved again. One placed
        elsewhere since (undone and placed again, revised far: what the graph forgets) is
        merged rigidly where it is now, not bent where it was. While the graph is matched anew (a
        robot left) a new map is carried by the solution before (FleetGraph.carried)."""
        for r in self.placed():
            if r.bent is None or r.graph is None or r.graph.rigid:
                continue
            p = _graph_item(r)
            if self.graph.jumped(p):
                r.bent = r.bent_x = r.bent_of = None
                continue
            if r.bent_of is r.layer:
                continue
            x = self.graph.carried(p)
            r.bent = dataclasses.replace(r.layer, seg=self.graph.rows(p, x))
            r.bent_x, r.bent_of = x, r.layer

    def bend(self, stop: Callable[[], bool] | None = None) -> None:
        """The fleet's pose graph (posegraph.py) over the placed robots: constraints sought for
        this fusion's share of keyframes, the graph solved again when anything it holds changed,
        and each robot's rows moved with its keyframes where they moved (``moved_m`` /
        ``moved_rad``). Without a constraint between robots every map stays rigid. :meth:`fuse`
        runs it before building the fused map unless told not to (the server runs it after
        publishing: the next fusion publishes what it moved). ``stop()`` (the server: a map waits)
        cuts it short — one robot's keyframes matched and one iteration of the solve at least;
        the rest stays due (``graph_stale``)."""
        cfg = self.cfg.graph
        placed = self._bend_placed()
        items = [self.graph_item(r) for r in placed]
        rebuilding = self.graph.rebuilding
        for robot in self.graph.sync(items):  # what the graph found where the robot was would hold it
            log.info("%s: unplaced or moved far: the fleet graph forgets where it had it", robot)
        if self.graph.rebuilding and not rebuilding:
            log.info("a robot was placed: the fleet graph is matched and solved anew (the last bend held)")
        ids = {id(r) for r in placed if not r.graph.rigid}
        for r in self.robots.values():
            if id(r) not in ids:
                r.bent = r.bent_x = r.bent_of = None
        if not cfg.enabled or len(placed) < 2 or not ids:
            for r in placed:
                r.bent = r.bent_x = r.bent_of = None
            self._graph_key, self._graph_moved = self._bend_key(placed), False  # (nothing to solve)
            self.graph.rebuilt()  # (nor anything bent to hold)
            return
        tried = self.graph.match(items, stop)
        key = self._bend_key(placed)
        self._graph_moved = bool(tried) or key != self._graph_key or self.graph.unsolved
        if not self._graph_moved:
            return
        self._graph_key = key
        x = self.graph.solve(items, stop)
        if self.graph.rebuilding:  # the maps stay bent as the last whole solution had them until
            # every keyframe has been matched anew: a solution over the first few constraints would
            # bend them less for a few fusions (a real log's pieces: ~500 keyframes, 40 a fusion)
            if self.graph.pending:
                self._carry()  # (a map that came meanwhile is merged, bent as before)
                return
            self.graph.rebuilt()
            log.info("the fleet graph is matched and solved anew: its bend replaces the one held")
        if not self.graph.stats.get("constraints_kept"):
            for r in placed:
                r.bent = r.bent_x = r.bent_of = None
            return
        for r, p in zip(placed, items, strict=True):
            if r.graph.rigid:
                continue
            xr = x[r.robot]
            if r.bent is not None and r.bent_of is r.layer and len(r.bent_x) == len(xr):
                d = relative(r.bent_x, xr)
                if np.hypot(d[:, 0], d[:, 1]).max(initial=0.0) < cfg.moved_m and (
                    np.abs(d[:, 2]).max(initial=0.0) < cfg.moved_rad
                ):
                    continue
            r.bent = dataclasses.replace(r.layer, seg=self.graph.rows(p, xr))
            r.bent_x, r.bent_of = xr, r.layer

    def trial(self, r: RobotState, places: list[np.ndarray]) -> list[float] | None:
        """How much of ``r``'s walls [m] meets the others' walls once the fleet's graph has tried it
        at each of ``places`` (its map frame in the global frame): a copy of the graph with ``r``
        placed there, its keyframes matched (and the others' near it) and solved. A piece whose own
        path bent meets only part of the others' walls as a whole; at its true place the graph
        bends it into them, at a wrong one its keyframes meet nothing that holds (ACES in 3 pieces,
        final maps: 61-69 m at the truth against 29-30 m at the place the other search chose). The
        live graph is left as it is. Each trial matches every keyframe it has due (at most
        ``trial_keyframes`` in all); 0 for a place where nothing bends (no other robot bent).
        Run at once in a fusion with the graph inline (``fuse(bend=True)``); else (the server)
        queued and run after publishing (:meth:`try_places`, map_server/trials.py): None until it is
        done, then its answer for as long as it stands for the robot's places."""
        cfg = self.cfg.graph
        others = [x for x in self._bend_placed() if x is not r]
        items = [self.graph_item(x) for x in others]
        if not cfg.enabled or not items or r.graph is None or r.map is None:
            return [0.0 for _ in places]
        at = np.array(places, float).reshape(-1, 3)
        if self._defer_trials:
            asked = (r.robot, r.map.session, at, r.layer.length_m, self.cfg)
            met = self.trials.answer(*asked)
            if met is not None or self.trials.under_way(*asked):
                return met
        keep = {id(x.graph): x.graph for x in self.robots.values() if x.graph is not None}
        for p in self.pieces():
            keep[id(p.layer)] = p.layer
        pieces = [apply_segments(p.alignment.transform, p.layer.seg) for p in self.pieces()]
        fixed = np.concatenate([np.zeros((0, 2, 2)), *pieces])
        item = self.graph_item(r)
        base = copy.deepcopy(self.graph, dict(keep))
        t = Trial(r.robot, r.map.session, at, r.layer.length_m, item, items, fixed, base, keep)
        if not self._defer_trials:
            t.step(self.cfg)
            return t.met
        self.trials.request(t)
        log.info("%s: the fleet graph tries it at %d places after publishing", r.robot, len(at))
        return None

    def try_places(self, stop: Callable[[], bool] | None = None) -> None:
        """The trials under way (:meth:`trial`), until ``stop()`` says so; a robot whose trial is
        done is searched again at once (its attempt finds the trial's answer). A trial of a robot
        placed meanwhile, or of a session replaced, is dropped (every trial is of an unplaced one)."""
        for robot, t in list(self.trials.queue.items()):
            r = self.robots.get(robot)
            if r is None or r.map is None or r.map.session != t.session or r.alignment.placed:
                del self.trials.queue[robot]
        for robot in self.trials.step(self.cfg, stop):
            r, t = self.robots[robot], self.trials.finished[robot][-1]
            log.info("%s: tried at %d places: %s m of its walls on the others'", robot, len(t.met),
                     " / ".join(f"{m:.1f}" for m in t.met))  # fmt: skip
            r.attempt_len_m = None  # (due: RobotState.grew)

    def bent_transform(self, r: RobotState) -> np.ndarray | None:
        """Where the graph puts the robot's map frame now: its newest keyframe's correction."""
        if r.bent is None or r.graph is None:
            return None
        return compose(r.bent_x[-1], inverse(r.graph.pose[-1]))

    def _settle(self, now_s: float) -> None:
        """Refinement sweeps of every placed robot against the others until the frames stop
        moving (a robot left: the maps are final, and one sweep leaves each robot refined against
        where the others were before theirs), at most ``settle_rounds``; this fusion's share of
        it (``settle_budget_segments``, ``settle_refinements``), the rest in the next fusions."""
        c = self.cfg
        sweeps, todo, before = self._settling
        budget, count = c.settle_budget_segments, c.settle_refinements
        while True:
            if not todo:  # a sweep is done (or none begun yet)
                placed = self.placed()
                if sweeps >= c.settle_rounds or not placed or (before and self._still(before)):
                    self._settling = None
                    return
                sweeps += 1
                todo = [r.robot for r in placed]
                before = {r.robot: r.alignment.transform.copy() for r in placed}
            if budget <= 0 or count <= 0:
                self._settling = (sweeps, todo, before)
                return
            take: list[RobotState] = []
            while todo and count > 0:
                r = self.robots[todo[0]]
                if take and len(r.layer or ()) > budget:
                    break  # the first one is always taken
                todo.pop(0)
                if r.alignment.placed and r.layer is not None:
                    take.append(r)
                    budget -= len(r.layer)
                    count -= 1
            if take:
                only = {id(r) for r in take}
                while self.placer.round(now_s, urgent=True, only=only):
                    pass

    def _still(self, before: dict[str, np.ndarray]) -> bool:
        """Whether no placed robot moved from ``before`` (robot -> transform) by more than the
        settle thresholds."""
        moved = [(r.alignment.transform, before[r.robot]) for r in self.placed() if r.robot in before]
        if not moved:
            return True
        d = np.array([a - b for a, b in moved])
        return bool(np.hypot(d[:, 0], d[:, 1]).max() <= self.cfg.settle_m
                    and np.abs(wrap_angle(d[:, 2])).max() <= self.cfg.settle_rad)  # fmt: skip

    @property
    def pending_work(self) -> bool:
        """Whether a fusion now would do work without new input: a settle's sweeps are under way
        (spread over fusions: ``settle_refinements``) or about to begin (a robot left),
        keyframes wait to be matched for the fleet's graph (spread over fusions too), or a trial
        is under way (:meth:`try_places`: its robot is searched again when it is done)."""
        return self._settling is not None or self._left or self.graph.pending or self.trials.busy

    def latest(self) -> FusedMap | None:
        return self._latest

    def paths(self, version: int, session: str = "") -> list[RobotPath]:
        """Where each placed robot's keyframes are (the graph's solution, or its rigid placement;
        one keyframe at the map frame's origin for a map without a graph)."""
        out = []
        for r in self.placed():
            if r.map is None:
                continue
            g = r.graph
            if g is None or g.rigid:
                stamps, local, pose = np.zeros(1), np.zeros((1, 3)), r.alignment.transform[None]
            else:
                stamps, local = r.map.kf_stamp, g.pose
                pose = r.bent_x if r.bent is not None else compose(r.alignment.transform, g.pose)
            ids = (self.server_id, session, version, r.robot, r.map.session)
            out.append(RobotPath(*ids, stamps, local, pose))
        return out

    def placements(self) -> dict[tuple[str, str], np.ndarray]:
        """Where each placed map is: ``(robot, session) -> transform (3,)`` (its map frame in
        the global frame), for the robots' current sessions and the retired pieces."""
        out = {(r.robot, r.map.session): r.alignment.transform for r in self.placed() if r.map is not None}
        for p in self.pieces():
            out[(p.robot, p.session)] = p.alignment.transform
        return out

    def sessions(self) -> set[tuple[str, str]]:
        """Every (robot, session) whose map the fleet keeps, placed or not."""
        out = {(r.robot, r.map.session) for r in self.robots.values() if r.map is not None}
        return out | {(p.robot, p.session) for p in self.pieces()}

    def placed(self) -> list[RobotState]:
        return [r for r in self.ordered() if r.alignment.placed and r.layer is not None]

    def ordered(self) -> list[RobotState]:
        return sorted(self.robots.values(), key=lambda r: r.order)

    def _choose_frame(self, now_s: float) -> None:
        with_map = [r for r in self.ordered() if r.layer is not None and len(r.layer)]
        if self.frame is None and with_map:
            # (a joined robot's prior is its place in a fused map that exists: no frame of its own)
            framed = any(r.map.prior is not None and not r.map.joined for r in with_map)
            self.frame = "prior" if framed else "reference"
        if self.frame != "reference" or self.placed() or self.retired or not with_map:
            return  # priors define the frame (placing.Placer places them), or it is defined already
        first = min(with_map, key=lambda r: (r.first_map_s, r.order))
        self.reference = first.robot
        first.alignment = Alignment("reference", np.zeros(3), np.zeros(3), reason="first non-empty map")
        first.mark_placed(now_s - self.epoch_s)

    def _sources(self, rigid: bool = False) -> list[Source]:
        """What the fused map merges, in the order of the merge: the placed robots by name (as
        the fleet's graph bent them, unless ``rigid``), then the retired pieces."""
        robots = sorted(self.placed(), key=lambda r: r.robot)
        out = [
            Source(("robot", r.robot), r.robot, r.layer, r.alignment.transform)
            if r.bent is None or rigid
            else Source(("robot", r.robot), r.robot, r.bent, np.zeros(3))
            for r in robots
        ]
        pieces = self.pieces()
        return out + [
            Source(("piece", p.robot, p.session), p.robot, p.layer, p.alignment.transform) for p in pieces
        ]

    def _synced(self, hold: str | None = None) -> MergedMap:
        """The merge brought up to date (but for robot ``hold``'s own layer: see global_segments)."""
        self._merged.update(self._sources(), hold=None if hold is None else ("robot", hold))
        return self._merged

    def global_segments(
        self, exclude: str, lo: np.ndarray | None = None, hi: np.ndarray | None = None, rigid: bool = False
    ):
        """The fused map of the placed robots except ``exclude``, with every retired piece (its
        own too): what a robot is aligned to (only the segments whose box meets ``lo``-``hi``
        when given). ``rigid``: every placed map where its alignment put it as a whole, not as
        the fleet's graph bent it — what a robot not placed yet is searched against: the graph
        bends the placed maps towards each other where they disagree, which a newcomer that agrees
        with one of them as it was cannot follow before it is placed (and in the graph itself)."""
        # the robot's own changes need not be merged for this: the next merge takes them with its
        # new place at once
        hold = ("robot", exclude)
        if rigid and any(r.bent is not None for r in self.robots.values()):
            self._rigid_merged.update(self._sources(rigid=True), hold=hold)
            return self._rigid_merged.without(hold, lo, hi)
        return self._synced(hold=exclude).without(hold, lo, hi)

    def _hold_prior_gauge(self) -> None:
        """Move every placed frame (robots and retired pieces) by the common rigid motion that
        balances the prior-placed ones against their priors (alignment.prior_gauge): each prior
        robot is refined against the others, which fixes where they are relative to each other
        but not where the whole set is. A motion below a millimetre is left alone."""
        placed = self.placed() + self.pieces()
        held = [x for x in placed if x.alignment.status == "prior" and x.map.prior is not None]
        if not held:
            return
        t = np.array([x.alignment.transform for x in held])
        g = prior_gauge(
            t, np.array([x.map.prior for x in held]),
            floored_prior_sigma([x.map.prior_sigma for x in held], self.cfg.alignment),
        )  # fmt: skip
        moved = np.linalg.norm(compose(g, t)[:, :2] - t[:, :2], axis=1).max()
        if moved < 1e-3 and abs(g[2]) < 1e-4:
            return
        self._synced()
        relaid = set()
        for r in placed:
            a = dataclasses.replace(r.alignment, transform=compose(g, r.alignment.transform))
            if isinstance(r, RetiredPiece):
                pieces = self.retired[r.robot]
                pieces[pieces.index(r)] = dataclasses.replace(r, alignment=a)
            else:
                r.alignment = a
                if r.bent is not None:  # the graph's solution moves along
                    r.bent = dataclasses.replace(r.bent, seg=apply_segments(g, r.bent.seg))
                    r.bent_x = compose(g, r.bent_x)
                    self.graph.shift(r.robot, g)
                    relaid.add(("robot", r.robot))
        # (the merge moves as a whole: a bent robot's rows moved by g are its new layer; merged
        # again, every bent robot's layer was — 7 ms of a fusion at 16 robots with priors)
        self._merged.moved(g, self._sources(), relaid=frozenset(relaid))

    # -- output --------------------------------------------------------------------------------

    def _status(self, r: RobotState) -> RobotStatus | None:
        session = r.map.session if r.map is not None else (r.pose.session if r.pose is not None else None)
        if session is None:
            return None
        a = r.alignment
        transform = a.transform if a.placed else np.zeros(3)
        bent = self.bent_transform(r) if a.placed else None
        if bent is not None:
            transform = bent
        sigma = a.sigma if a.placed else np.zeros(3)
        local, stamp = None, 0.0
        if r.pose is not None and r.pose.session == session:
            local, stamp = r.pose.pose, r.pose.stamp_s
        elif r.map is not None:
            local, stamp = r.map.particle_poses[int(np.argmax(r.map.particle_weights))], r.map.stamp_s
        pose = compose(transform, local) if a.placed and local is not None else None
        return RobotStatus(
            r.robot, a.status, r.online, session, r.map.seq if r.map is not None else 0,
            len(r.layer) if r.layer is not None else 0, transform, sigma, pose, stamp, r.aligned_at_s,
        )  # fmt: skip

    def _status_row(self, r: RobotState) -> tuple[RobotStatus | None, tuple]:
        """The robot's status and its part of the content key, made again only when what they are
        made of changed (those objects are replaced on a change, never modified)."""
        made_of = (r.map, r.pose, r.alignment, r.layer, r.online, r.aligned_at_s, r.bent)
        cached = self._statuses.get(r.robot)
        if cached is not None and all(a is b for a, b in zip(cached[0], made_of, strict=True)):
            return cached[1], cached[2]
        s = self._status(r)
        key = () if s is None else (
            s.robot, s.status, s.online, s.session, s.map_seq, s.n_elements, s.transform.tobytes(),
            s.sigma.tobytes(), s.aligned_at_s,
        )  # fmt: skip
        self._statuses[r.robot] = (made_of, s, key)
        return s, key

    def _build(self) -> tuple[tuple, tuple, dict]:
        """The fused content: robot table, merged arrays, and the key that says if it changed."""
        rows = [self._status_row(r) for _, r in sorted(self.robots.items())]
        table = [s for s, _ in rows if s is not None]
        row = {s.robot: i for i, s in enumerate(table)}
        merged = self._synced()
        arrays = merged.result(row)
        key = tuple(a.tobytes() for a in arrays) + tuple(k for s, k in rows if s is not None)
        key += (self.graph.rebuilding,)  # (a rebuild's start and end are published: a subscriber
        # taking "no new map for a while" as settled would take the held bend as the last word)
        extra = {
            "robots_merged": float(len(self.placed())), "segments_in": float(len(merged)),
            "retired_pieces": float(len(self.pieces())), "graph_rebuilding": float(self.graph.rebuilding),
        }  # fmt: skip
        return tuple(table), arrays, {"key": key, "extra": extra}

    def _publish(self, now_s: float) -> FusedMap | None:
        built = self._build()
        if not built[0] or built[2]["key"] == self._content:
            return None
        self.version += 1
        return self._keep(built, now_s)

    def republish(self, now_s: float) -> FusedMap | None:
        """The latest fused map as the next version, stamped ``now_s`` (its maps unchanged: the
        server's figures in it are what changed), or None before the first."""
        if self._latest is None:
            return None
        self.version += 1
        self._latest = dataclasses.replace(self._latest, version=self.version, stamp_s=max(0.0, now_s))
        return self._latest

    def _keep(self, built: tuple, stamp_s: float) -> FusedMap:
        """Make ``built`` (from :meth:`_build`) the latest fused map, at the current version."""
        table, (seg, support, off, prov), info = built
        self._content = info["key"]
        self._latest = FusedMap(
            self.server_id,
            self.version,
            max(0.0, stamp_s),
            0,
            1,
            table,
            seg,
            support,
            off,
            prov,
            info["extra"],
        )
        return self._latest

    # -- persistence ---------------------------------------------------------------------------

    def _restore_graph(self, graph: dict[str, tuple[str, int, np.ndarray]] | None) -> None:
        """The bent robots as the graph left them (see :meth:`graph_state`); a robot whose map
        is not the one its solution was of stays rigid until the graph is solved again. The
        constraints are not kept: every keyframe is matched again (from the restored solution),
        and the restored bend is held meanwhile, as after a departure (FleetGraph.held)."""
        for robot, (session, seq, x) in (graph or {}).items():
            r = self.robots.get(robot)
            if r is None or r.map is None or (r.map.session, r.map.seq) != (session, seq) or r.graph is None:
                continue
            x = np.asarray(x, float).reshape(-1, 3)
            if len(x) != len(r.graph) or not r.alignment.placed:
                continue
            p = _graph_item(r)
            self.graph.solution[robot] = (r.graph, x)
            self.graph.placed_at(robot, r.alignment.transform)
            r.bent = dataclasses.replace(r.layer, seg=self.graph.rows(p, x))
            r.bent_x, r.bent_of = x, r.layer
        self.graph.hold(self.graph.solution)

    def snapshot(self) -> tuple[dict, dict[str, RobotMap]]:
        """Everything needed to resume: a JSON-able dict and the latest map of every robot."""
        meta = dict(
            version=self.version, epoch_s=self.epoch_s, reference=self.reference, frame=self.frame,
            arrivals=self._arrivals, stamp_s=None if self._latest is None else self._latest.stamp_s,
            robots={name: r.to_dict() for name, r in self.robots.items()},
            retired={name: [p.to_dict() for p in pieces] for name, pieces in self.retired.items()},
        )  # fmt: skip
        maps = {name: r.map for name, r in self.robots.items() if r.map is not None}
        maps.update((p.blob, p.map) for p in self.pieces())
        return meta, maps

    def graph_state(self) -> dict[str, tuple[str, int, np.ndarray]]:
        """Where the fleet's graph put each bent robot's keyframes (robot -> the session and seq
        of the map solved, (K, 3) poses): restored with the maps, the same fused map comes back."""
        return {
            r.robot: (r.map.session, r.map.seq, np.asarray(r.bent_x, float))
            for r in self.robots.values()
            if r.bent is not None and r.map is not None
        }

    @classmethod
    def restore(
        cls,
        meta: dict,
        maps: dict[str, RobotMap],
        cfg: FleetConfig,
        server_id: str,
        graph: dict[str, tuple[str, int, np.ndarray]] | None = None,
    ) -> Fleet:
        """A fleet that fuses to the same map, same version (no alignment is re-attempted until
        a map changes). ``maps`` holds the robots' maps and the retired pieces' (see snapshot);
        ``graph`` the graph's solution (:meth:`graph_state`)."""
        f = cls(cfg, server_id)
        f.version, f.epoch_s, f.reference = int(meta["version"]), meta["epoch_s"], meta["reference"]
        f.frame, f._arrivals = meta["frame"], int(meta["arrivals"])
        for name, d in meta["robots"].items():
            r = f.robots[name] = RobotState.from_dict(name, d, maps.get(name))
            if r.map is not None:
                r.layer = fuse_particles(r.map, cfg.fusion)
                r.graph = RobotGraph.of(r.map, r.layer)
        for name, pieces in meta.get("retired", {}).items():
            f.retired[name] = [RetiredPiece.from_dict(name, d, maps, cfg.fusion) for d in pieces]
        f._restore_graph(graph)
        built = f._build()
        if built[0] and meta["stamp_s"] is not None:
            f._keep(built, meta["stamp_s"])
        return f


def _graph_item(r: RobotState, consistent: bool = False, contradicts: bool = False) -> Placed:
    """What the fleet's graph takes of a placed robot (``consistent``: Fleet._consistent,
    ``contradicts``: Fleet._contradicts)."""
    a = r.alignment
    return Placed(
        r.robot, r.graph, r.layer, a.transform, a.status, r.map.prior_sigma, consistent, contradicts
    )
