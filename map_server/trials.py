"""The fleet graph's trials of a robot at several places (placing.Placer: a bent piece's place
against its rivals, the two searches that placed apart, a place refused for its share), run at
once or stepped after publishing.

A trial copies the fleet's graph with the robot placed at one place, matches its keyframes (and
the others' near it: at most ``trial_keyframes`` in all), solves, and measures how much of the
robot's walls meets the others' there (:meth:`fleet.Fleet.trial`). On a real log's pieces that is
2.5-3 s a place (ACES in 3 pieces), and a trial tries up to four: run inside a fusion it would
stall every robot's merge by 8-10 s. The server therefore runs trials after publishing, in steps
cut short when a map waits (as the graph's bend: :meth:`fleet.Fleet.try_places`), and a robot
whose placement waits on one stays unplaced, saying so, until it is in; :class:`Trials` keeps what
is under way and what came out. Tests and benchmarks that fuse with the graph inline
(``Fleet.fuse(bend=True)``) run each trial at once, as before.

A finished trial stands for a later search of the same robot session whose places are the same
(each within ``trial_same_m`` of the trial's, mean displacement of the robot's walls) while its map
grew by less than ``trial_growth_share`` (or ``4 * retry_growth_m``) since the trial began; anything
else asks for a new one, which replaces a queued or running trial of that robot. One trial runs at a
time, the others wait in request order: at most one of each robot queued, and its last few kept.
"""

from __future__ import annotations

import copy
import dataclasses
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from map_server.candidates import mean_displacement
from map_server.config import FleetConfig
from map_server.posegraph import FleetGraph, Placed
from map_server.registration import MapIndex, Samples
from shared.geometry import apply_segments

SOLVE_CUTS = 3  # a trial's solve cut short this many times runs whole the next time
FINISHED_KEPT = 4  # finished trials kept per robot (each answers its places)


@dataclass(eq=False)
class Trial:
    """One robot tried at ``places (P,3)`` against a snapshot of the fleet: ``item`` the robot,
    ``items`` the others placed (as the graph takes them), ``fixed`` the retired pieces' segments in
    the global frame, ``base`` a copy of the fleet's graph when it began (``keep``: what copies of
    it share rather than copy: the robots' graphs and the pieces' layers, never modified); a
    finished trial keeps none of these (Trials.finished). ``met`` fills as places are tried;
    ``graph`` is the current place's copy, ``tried`` its keyframes matched so far."""

    robot: str
    session: str
    places: np.ndarray
    length_m: float
    item: Placed
    items: list[Placed]
    fixed: np.ndarray
    base: FleetGraph | None
    keep: dict
    met: list[float] = field(default_factory=list)
    graph: FleetGraph | None = None
    now: list[Placed] = field(default_factory=list)
    tried: int = 0
    matching: bool = True
    cuts: int = 0

    @property
    def done(self) -> bool:
        return len(self.met) == len(self.places)

    def step(self, cfg: FleetConfig, stop: Callable[[], bool] | None = None) -> bool:
        """Work on the trial until it is done (True) or ``stop()`` says so (False: the rest in the
        next step). Each step matches one robot's share of keyframes, or runs one iteration of the
        solve at least (the whole solve after ``SOLVE_CUTS`` cut short)."""
        while not self.done:
            if self.graph is None:
                place = self.places[len(self.met)]
                self.graph = copy.deepcopy(self.base, dict(self.keep))
                self.now = [*self.items, dataclasses.replace(self.item, transform=place, status="aligned")]
                self.graph.sync(self.now)
                self.tried, self.matching, self.cuts = 0, True, 0
            g = self.graph
            while self.matching:
                if self.tried >= cfg.trial_keyframes:
                    self.matching = False
                    break
                n = g.match(self.now, stop)
                self.tried += n
                if not g.pending or not n:
                    self.matching = False
                elif stop is not None and stop():
                    return False
            # cut short, the solve goes on from there in the next step; after SOLVE_CUTS cuts it
            # runs whole (cut at each iteration it would never drop a constraint that disagrees)
            x = g.solve(self.now, stop if self.cuts < SOLVE_CUTS else None)
            if g.unsolved:
                self.cuts += 1
                return False
            self.met.append(self._met(g, x, cfg))
            self.graph, self.now = None, []
            if not self.done and stop is not None and stop():
                return False
        return True

    def _met(self, g: FleetGraph, x: dict, cfg: FleetConfig) -> float:
        """How much of the robot's walls [m] meets the others' where the solve ``x`` put them."""
        c = cfg.graph
        mine = self.now[-1]

        def where(p: Placed) -> np.ndarray:
            return g.rows(p, x[p.robot]) if p.robot in x else apply_segments(p.transform, p.layer.seg)

        seg = np.concatenate([*map(where, self.items), self.fixed]).reshape(-1, 2, 2)
        walls = where(mine)
        index = MapIndex(seg, c.sample_step_m)
        return index.overlap(np.zeros(3), Samples.of(walls, c.sample_step_m), *c.stages[-1])

    def stands_for(self, session: str, places: np.ndarray, length_m: float, cfg: FleetConfig) -> bool:
        """Whether this trial answers a search of the robot's session ``session`` at ``places
        (P,3)`` with a map of ``length_m`` (the module's doc)."""
        if session != self.session or places.shape != self.places.shape:
            return False
        grown = abs(length_m - self.length_m)
        if grown >= max(4.0 * cfg.retry_growth_m, cfg.trial_growth_share * self.length_m):
            return False
        points = self.item.layer.seg.reshape(-1, 2)
        pairs = zip(places, self.places, strict=True)
        return all(mean_displacement(a, b, points) <= cfg.trial_same_m for a, b in pairs)


class Trials:
    """The trials under way (``queue``, request order, the first running; one per robot) and the
    last ``FINISHED_KEPT`` finished of each robot (``finished``, oldest first): a robot's attempt
    can ask for two — the two searches' places, then its place's own rivals
    (Placer._search, Placer._rival_trial) — and each must answer the next attempt."""

    def __init__(self) -> None:
        self.queue: dict[str, Trial] = {}
        self.finished: dict[str, list[Trial]] = {}

    @property
    def busy(self) -> bool:
        return bool(self.queue)

    def answer(
        self, robot: str, session: str, places: np.ndarray, length_m: float, cfg: FleetConfig
    ) -> list[float] | None:
        """What a finished trial of ``robot`` met at each of ``places``, the newest that stands for
        them (Trial.stands_for); None if none does."""
        for t in reversed(self.finished.get(robot, ())):
            if t.stands_for(session, places, length_m, cfg):
                return list(t.met)
        return None

    def under_way(
        self, robot: str, session: str, places: np.ndarray, length_m: float, cfg: FleetConfig
    ) -> bool:
        """Whether the trial of ``robot`` queued or running will stand for ``places``."""
        t = self.queue.get(robot)
        return t is not None and t.stands_for(session, places, length_m, cfg)

    def request(self, t: Trial) -> None:
        """Queue ``t``, in place of any trial of its robot queued or running."""
        self.queue.pop(t.robot, None)
        self.queue[t.robot] = t

    def step(self, cfg: FleetConfig, stop: Callable[[], bool] | None = None) -> list[str]:
        """Work on the queue in order until it is empty or ``stop()`` says so (each step does some
        work at least); the robots whose trial finished."""
        out = []
        while self.queue:
            robot, t = next(iter(self.queue.items()))
            if not t.step(cfg, stop):
                break
            del self.queue[robot]
            kept = self.finished.setdefault(robot, [])
            kept.append(dataclasses.replace(t, items=[], fixed=t.fixed[:0], base=None, keep={}))
            del kept[:-FINISHED_KEPT]
            out.append(robot)
            if stop is not None and stop():
                break
        return out

    def forget(self, robot: str) -> None:
        """Drop ``robot``'s trials (a new session)."""
        self.queue.pop(robot, None)
        self.finished.pop(robot, None)
