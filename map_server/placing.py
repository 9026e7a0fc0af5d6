"""The alignment rounds: which robots get an attempt in a fusion, against what, and what is done
with the verdict (policy.py says what a verdict means; alignment.py makes one attempt).

A round goes over the robots in arrival order. An unplaced robot without a prior is tried only
once its map and every placed robot's map are mature; a robot that joined the fused map (its
agent found itself in it: ``RobotMap.joined``) has its claim verified and is placed at once if it
holds. Of the unplaced robots that matched in one round only the most decisive (highest rival
ratio) is taken; the others are tried again against the grown placed map. Placed robots are
refined where they are when due (state.RobotState.due: their map or the maps near them changed,
or ``retry_interval_s`` passed), a few per fusion (``refine_budget_segments``). A place found by a
search is checked against the free space the robots saw (contradiction.py).

Fleet (fleet.py) owns the robots, the merge and the frame; :class:`Placer` keeps what the rounds
cache between fusions (each robot's samples, the placed robots' free space and its noise, the
parts of the keys that say an attempt is due).
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Callable
from typing import Protocol

import numpy as np

from map_server import candidates, contradiction, policy
from map_server.alignment import JOIN_REFUTED, Alignment, estimate_alignment, query_reach, verify_join
from map_server.config import FleetConfig
from map_server.registration import MapIndex, OutsideIndex, Samples
from map_server.schedule import Around, PlacedKey, global_box
from map_server.state import RetiredPiece, RobotState
from shared.geometry import relative

log = logging.getLogger("fleet_slam.fleet")

SHARE_TRIAL_MATCHED = 2  # the search's most matched places a share trial tries besides its best and rival


class FleetView(Protocol):
    """What the rounds read of the fleet (fleet.Fleet)."""

    cfg: FleetConfig
    robots: dict[str, RobotState]
    frame: str | None
    reference: str | None
    epoch_s: float | None
    free_of: Callable[[str, str], object] | None

    def placed(self) -> list[RobotState]: ...

    def pieces(self) -> list[RetiredPiece]: ...

    def ordered(self) -> list[RobotState]: ...

    def global_segments(
        self, exclude: str, lo: np.ndarray | None = None, hi: np.ndarray | None = None, rigid: bool = False
    ) -> np.ndarray: ...

    def trial(self, r: RobotState, places: list[np.ndarray]) -> list[float] | None: ...


class Placer:
    def __init__(self, fleet: FleetView):
        self.fleet = fleet
        self._budget = fleet.cfg.refine_budget_segments  # layer segments left to refine in this fusion
        self._entries: dict[tuple, tuple] = {}  # parts of schedule.placed_key, per robot or retired piece
        self._samples: dict[str, tuple] = {}  # robot -> (layer, its samples for alignment attempts)
        self._placed_free: tuple | None = None  # (what it was made of, area, noise)
        self._noise_cache: dict[tuple[int, int], tuple] = {}  # Placer._own_noise
        self._shrunk: dict[int, tuple] = {}  # Placer._shrink: id(area) -> (area, shrunk)
        # regroup(): per pair of unplaced robots (names), what its last attempt was made of (the
        # two maps' seqs), when, and the place awaiting confirmation with its count and first time
        self._pairs: dict[tuple[str, str], tuple] = {}

    @property
    def cfg(self) -> FleetConfig:
        return self.fleet.cfg

    def new_fusion(self) -> None:
        """A fusion begins: its refinement budget is whole again."""
        self._budget = self.cfg.refine_budget_segments

    def _turns(self, placed: list[RobotState], key_of, now_s: float) -> set[int]:
        """Which placed robots due for a refinement get it in this fusion: first those waiting
        twice ``retry_interval_s`` or more, then those whose own map changed, the newest map first
        (a robot whose map just came: its new layer and its new place are merged in one go), then
        in arrival order; until their layers add up to ``refine_budget_segments`` (the first
        always)."""
        overdue = 2.0 * self.cfg.retry_interval_s

        def rank(r: RobotState) -> tuple:
            newest = -r.lengths[-1][0] if r.lengths else 0.0
            return now_s - r.attempt_s < overdue, r.map.seq == r.attempt_seq, newest, r.order

        turn: set[int] = set()
        for r in sorted((r for r in placed if r.alignment.status != "reference"), key=rank):
            spent = self._budget < self.cfg.refine_budget_segments  # in this round or an earlier one
            if spent and len(r.layer) > self._budget:
                continue  # (before asking whether it is due: that looks at the maps around it)
            if r.due(self.cfg, *key_of(r), now_s):
                turn.add(id(r))
                self._budget -= len(r.layer)
        return turn

    def estimate(
        self, r: RobotState, prior, sigma, current: Alignment | None, search: bool, join: bool = False
    ) -> Alignment:
        """An alignment attempt. A refinement where the robot is (from its prior, from its claim
        of its place in the fused map when ``join``, or from its current place without a search)
        looks at the placed map near the robot map only: every query stays within ``query_reach``
        of the robot map's samples, and the index is a crop that answers exactly there
        (registration.MapIndex); one that strays out of it is done again against the whole map."""
        c = self.cfg.alignment
        start = prior if prior is not None else (None if search or current is None else current.transform)
        samples = self._samples.get(r.robot)
        if samples is None or samples[0] is not r.layer:
            fine, coarse = Samples.of(r.layer.seg, c.sample_step_m), Samples.of(r.layer.seg, c.coarse_step_m)
            samples = self._samples[r.robot] = (r.layer, (fine, coarse))
        kw = {"robot_samples": samples[1]}

        def attempt(placed_map: np.ndarray, index: MapIndex | None = None, **more) -> Alignment:
            if join:  # a place contradicted by the free space seen is not verified
                veto = self.veto(r, placed_map)
                return verify_join(r.layer.seg, placed_map, c, prior, sigma, index, veto=veto, **kw)
            return estimate_alignment(
                r.layer.seg, placed_map, c, prior, sigma, current, search, index=index, **kw, **more
            )

        if start is not None and len(r.layer):
            box = global_box(r.layer.bounds[None], np.asarray(start, float)[None])[0]
            reach = query_reach(c)
            lo, hi = box[:2] - self.cfg.refine_margin_m, box[2:] + self.cfg.refine_margin_m
            near = self.fleet.global_segments(r.robot, lo - reach, hi + reach, rigid=not r.alignment.placed)
            if len(near):
                index = MapIndex(near, c.sample_step_m, inner=(lo, hi), compiled=c.compiled)
                try:
                    return attempt(near, index)
                except OutsideIndex:
                    log.debug("%s: refinement left its crop; done against the whole placed map", r.robot)
        placed_map = self.fleet.global_segments(r.robot, rigid=not r.alignment.placed)
        if prior is None and (current is None or search):  # a search: a place contradicted by the
            # free space seen is set aside (and a current one undone)
            v, tried = self._search(r, placed_map, attempt)
            if not r.alignment.placed and not tried:
                v = self._rival_trial(r, v) if v.placed else self._share_trial(r, v, placed_map)
            return v
        return attempt(placed_map)

    def _search(self, r: RobotState, placed_map: np.ndarray, attempt) -> tuple[Alignment, bool]:
        """A search of ``r`` (``attempt``: Placer.estimate's) against the placed maps, rigid and,
        for a robot not placed while the graph bends them, bent; and whether the fleet's graph
        tried it (Fleet.trial) to settle between the two."""
        a = attempt(placed_map, veto=self.veto(r, placed_map))
        if r.alignment.placed or not any(x.bent is not None for x in self.fleet.placed()):
            return a, False
        # Searched again against the placed maps as the fleet's graph bent them. Either can
        # hide a true overlap — the bend pulls two placed maps toward each other where they
        # disagree, away from a third that agrees with one as it was (Intel in 3 pieces); a
        # placed map held rigidly by its overlap with the reference is off where it bends on
        # its own, and the newcomer meets it there (MIT-CSAIL in 3 pieces: 50 m matched bent,
        # 10 m rigid). A bent piece placed rigidly misleads too (ACES's first piece, half-turned):
        # a place found against the rigid maps stands where the bent maps' best place (placed
        # or not) is the same place (FleetConfig.search_agree_m). Where it is not, neither
        # stands (the search is ambiguous): each search has placed a piece wrongly where the
        # other found its truth — ACES's first piece half-turned against the rigid maps (1.57x)
        # where the bent maps put its truth first (1.10x); its third piece 18.8 m off against
        # the bent maps (1.59x) where the rigid maps placed its truth (1.18x). The bent maps
        # place alone only where the rigid maps place nothing; where both place apart, the graph
        # tries the robot at each (FleetConfig.trial_ratio).
        bent_map = self.fleet.global_segments(r.robot)
        b = attempt(bent_map, veto=self.veto(r, bent_map))
        if not a.placed:
            if b.placed:
                return dataclasses.replace(
                    b, reason=f"{b.reason} (the placed maps as the graph bent them)"
                ), False
            return a, False
        apart = self._apart(r, a, b)
        if apart is None:
            return a, False
        why = f"{a.reason}; but the best place against the maps as bent lies {apart:.1f} m away"
        if b.placed:
            why += f" and is placed there ({b.reason})"
        met = self.fleet.trial(r, [a.transform, b.transform])  # the graph tries it at each
        if met is None:
            return self._awaiting(a, f"{why}; the fleet's graph tries it at each"), True
        tried = f"a trial bend puts {met[0]:.1f} m of its walls on the others' there, {met[1]:.1f} m"
        ratio, settled = self.cfg.trial_ratio, None
        for v, mine, other in ((a, met[0], met[1]), (b, met[1], met[0])):
            if v.placed and mine >= ratio * other and mine > 0.0:
                settled = dataclasses.replace(v, reason=f"{v.reason} (settled by {tried} at the other place)")
        settled = settled or self._settle_unplaced(r, b, bent_map, met[1], met[0])
        if settled is None and not b.placed and met[1] * self.cfg.alignment.min_rival_ratio < met[0]:
            # the other search placed nothing, and once tried this place meets the others' walls
            # by a search's margin (min_rival_ratio) more than its best: a rival of this place, as
            # Placer._rival_trial's (which tries this place's own rivals next). MIT-CSAIL's middle
            # piece, live at cb2dc5e: 42.4 m at its place (2.26x its rival), 31.5 m at the bent
            # maps' best 25.8 m away, which its search refused — left "ambiguous" and unplaced
            why = f"{tried} at the bent maps' best, which their search refused"
            log.info("%s: the two searches placed %.1f m apart; %s: it stands", r.robot, apart, why)
            return dataclasses.replace(a, reason=f"{a.reason} (stands: {why})"), False
        if settled is None:
            why += f"; {tried} at the other"
            return dataclasses.replace(a, status="unaligned", reason=f"rejected: ambiguous ({why})"), True
        log.info("%s: the two searches placed %.1f m apart; %s", r.robot, apart, tried)
        return settled, True

    def _settle_unplaced(
        self,
        r: RobotState,
        v: Alignment,
        placed_map: np.ndarray,
        mine: float,
        other: float,
        rival_tried: bool = False,
        at: str | None = None,
        against: str | None = None,
    ) -> Alignment | None:
        """The bent maps' best place ``v``, refused by its search, where a trial bend puts
        ``trial_ratio`` times as much of the robot's walls on the others' there (``mine``) as at the
        rigid maps' place (``other``), and as much as a merge needs (``min_overlap_m`` and
        ``min_share`` of its map): verified again where it is against the maps as bent (every check
        of a search's best but the share, which a bent piece placed whole cannot reach — the trial
        is its fit; and the free space seen), ahead of its best distinct rival by
        ``min_rival_ratio`` (unless ``rival_tried``: ``other`` is that rival's trial). None if
        not. ``at``: which of the search's places other than its best ``v`` is (its best distinct
        rival, a most matched place: Placer._share_trial); ``against``: which place ``other`` was
        met at, when not the rigid maps' (or, ``rival_tried``, its best rival's). ACES's first
        piece (of 3), live at edd65b8: 12 % of its map on the bent maps whole (2.0 m from its
        truth), 69.4 m once tried against 36.1 m at the rigid maps' place (16.6 m off)."""
        c = self.cfg.alignment
        total = float(self._samples[r.robot][1][0].length.sum())
        if (
            v.placed
            or (v.rival_ratio < c.min_rival_ratio and not rival_tried)
            or mine < self.cfg.trial_ratio * other
            or mine < max(c.min_overlap_m, c.min_share * total)
        ):
            return None
        whole = dataclasses.replace(c, join_min_overlap_m=c.min_overlap_m, join_min_share=0.0)
        w = verify_join(
            r.layer.seg, placed_map, whole, v.transform, v.sigma, veto=self.veto(r, placed_map),
            robot_samples=self._samples[r.robot][1],
        )  # fmt: skip
        if not w.placed:
            return None
        whole = f"{v.score_m:.1f} m ({v.inlier_share:.0%})"
        if at is not None:
            against, whole = against or "the search's best", f"{at}; the best whole {whole}"
        else:
            against = against or ("its best rival's" if rival_tried else "the rigid maps'")
            whole = f"whole {whole}, {v.rival_ratio:.2f}x the best rival"
        why = (
            f"matched once tried: a trial bend puts {mine:.1f} m of its walls on the others' there"
            f" ({mine / max(total, 1e-9):.0%}), {other:.1f} m at {against} place; {whole}"
        )
        return dataclasses.replace(w, rival_ratio=v.rival_ratio, reason=why)

    def _share_trial(self, r: RobotState, v: Alignment, placed_map: np.ndarray) -> Alignment:
        """A search's best place refused for a robot whose map contradicts itself, on as much wall
        as a merge needs (``min_overlap_m``) but not on ``min_share`` of its map — a bent piece
        placed whole (ACES's first piece: 10-14 %, in 3 of 8 live runs at 2447fbe): the fleet's
        graph tries it there, at the best distinct rival and at the search's two most matched
        places (Placer._matched_rivals), each farther than ``search_agree_m`` from the others
        (Fleet.trial), and a place stands where the trial puts ``trial_ratio`` times as much of
        its walls on the others' as at every other place tried, and a merge's worth
        (Placer._settle_unplaced: verified again, every check but the share; the trial stands for
        the rival ratio, the rivals tried themselves). Else ``v``. ACES's first piece, on a live
        run's final maps at 610156e: its best place 34.7 m off and its best rival 22.7 m, its
        truth the second most matched place (44.0 m, the best 43.2 m) and sixth by net score."""
        c = self.cfg.alignment
        if v.score_m < c.min_overlap_m or not self._contradicts_self(r):
            return v
        # the place, else a rival: the rigid scores of a bent piece mislead both ways (ACES's
        # first piece, live at 80d0893: its best place 36 m off, 1.07x its rival 1.9 m from its
        # truth; tried, 39.3 m against 64.7 m)
        places = self._trial_places(r, v, self._far_rival(r, v), SHARE_TRIAL_MATCHED, self.cfg.search_agree_m)
        if len(places) < 2:
            return v
        met = self.fleet.trial(r, [q for q, _, _ in places])
        if met is None:
            return self._awaiting(v, f"{v.reason}; the fleet's graph tries it at {len(places)} places")
        return self._settle_by_trial(r, v, places, met, placed_map) or v

    def _trial_places(
        self, r: RobotState, v: Alignment, rival: bool, matched: int, apart_m: float
    ) -> list[tuple[np.ndarray, str | None, str]]:
        """The places a trial of ``r`` tries: its search's best, its best distinct rival (if
        ``rival``) and up to ``matched`` of the search's most matched places (Placer._matched_rivals)
        each farther than ``apart_m`` from those before it; each as (where, what it is — None for
        the best —, what it is called)."""
        places = [(np.asarray(v.transform, float), None, "the search's best")]
        if rival:
            places.append((np.array(v.rival, float), "the search's best rival place", "its best rival's"))
        for p in self._matched_rivals(r, v, matched):
            if all(self._moved_m(r, p, q) > apart_m for q, _, _ in places):
                places.append((p, "a place the search matched most", "its most matched rival's"))
        return places

    def _settle_by_trial(
        self,
        r: RobotState,
        v: Alignment,
        places: list,
        met: list[float],
        placed_map: np.ndarray,
        start: int = 0,
    ) -> Alignment | None:
        """The first of ``places`` (Placer._trial_places) from ``start`` whose trial ``met`` puts
        ``trial_ratio`` times as much of the robot's walls on the others' as at every other place
        tried, verified again there (Placer._settle_unplaced); None if none. A place other than
        the search's best ``v`` stands with ``v`` as its rival."""
        for i in range(start, len(places)):
            q, at, _ = places[i]
            k = max((j for j in range(len(places)) if j != i), key=lambda j: met[j])  # the best other
            place = v
            if i:
                place = dataclasses.replace(
                    v, status="unaligned", transform=q, rival=np.array(v.transform, float),
                    rival_ratio=1.0 / max(v.rival_ratio, 1e-9),
                )  # fmt: skip
            settled = self._settle_unplaced(
                r, place, placed_map, met[i], met[k], rival_tried=True, at=at, against=places[k][2]
            )
            if settled is not None:
                log.info("%s: %s", r.robot, settled.reason)
                return settled
        return None

    @staticmethod
    def _awaiting(v: Alignment, why: str) -> Alignment:
        """``v`` unplaced while the fleet's graph tries it after publishing (Fleet.trial): the
        robot is searched again when the trial is done."""
        return dataclasses.replace(v, status="unaligned", reason=f"waiting for a trial: {why}")

    def _far_rival(self, r: RobotState, v: Alignment) -> bool:
        """Whether the search's best distinct rival lies farther than ``search_agree_m`` from its
        place: nearer, it is the same place where the robot's bent map fits otherwise (ACES's first
        piece: its place 0.2 m from its truth and its rival 2.0 m, the rival meeting 1.11x as much
        once tried) — no contest for a trial."""
        return v.rival is not None and self._moved_m(r, v.transform, v.rival) > self.cfg.search_agree_m

    def _moved_m(self, r: RobotState, a: np.ndarray, b: np.ndarray) -> float:
        """How far [m] ``r``'s map lies at place ``b`` from place ``a`` (mean displacement of its
        coarse samples)."""
        return candidates.mean_displacement(a, b, self._samples[r.robot][1][1].points)

    def _contradicts_self(self, r: RobotState) -> bool:
        """Whether ``r``'s walls stand in its own free space by more than
        ``graph.consistent_self_m`` (policy.contradicts_self; not known: False)."""
        return policy.contradicts_self(self.own_noise_m(r), self.cfg.graph.consistent_self_m)

    def _rival_trial(self, r: RobotState, v: Alignment) -> Alignment:
        """A search's place for a robot whose map contradicts itself (its walls stand in its own
        free space by more than ``graph.consistent_self_m``: a real log's piece, its path bent),
        tried by the fleet's graph (Fleet.trial) at its place and at its rivals farther than
        ``search_agree_m``: its best distinct rival when within ``trial_rival_ratio`` of its net
        score, and the search's most matched place when within ``trial_rival_ratio`` of its matched
        length (Placer._matched_rivals). The place stands if its walls then meet the others' at
        least as much there as at the rival (a rival a metre or two off is bent to the same place,
        and both meet the same); the rival's place is taken (verified) if it meets
        ``alignment.min_rival_ratio`` times as much (the margin a search places by); between the
        two the robot waits: ACES's third piece, live, was placed half-turned at 1.48x the rival by
        the search, tried 66.7 m there against 70.5 m at its truth (20 m off across the pieces). A bent
        piece's rigid scores mislead both ways: ACES's middle piece (of 3) was merged half-turned
        at 1.18x the rival (its truth), 72.6 m matched; tried, 70.5 m there and 98.2 m at the
        truth. Over 13 true best places of pieces on 8 runs' final maps the rival met 0.14-0.95
        times as much. The net score's rival can be the same wrong place a metre and a half off
        while the truth stands fourth by net score, first by matched length: ACES's third piece,
        live at f7cdc54, merged half-turned at 1.83x (73.3 m matched; its truth 70.8 m, net 24.5
        against 46.0 — its walls near the others' but not on them)."""
        if not self._contradicts_self(r):
            return v
        near_rival = v.rival_ratio < self.cfg.trial_rival_ratio and self._far_rival(r, v)
        places = self._trial_places(r, v, near_rival, 1, self.cfg.alignment.distinct_m)
        if len(places) < 2:
            return v
        met = self.fleet.trial(r, [q for q, _, _ in places])
        if met is None:
            n = len(places) - 1
            why = f"its place ({v.reason.removeprefix('matched: ')}) against {n} rival place{'s' * (n > 1)}"
            return self._awaiting(v, f"the fleet's graph tries {why}")
        here = met[0]
        k = 1 + int(np.argmax(met[1:]))
        there, which = met[k], f"{places[k][2]} place"
        if there <= here or there == 0.0:
            log.info("%s: a trial bend puts %.1f m of its walls on the others' at its place, %.1f m at"
                     " %s: it stands", r.robot, here, there, which)  # fmt: skip
            return v
        if there < self.cfg.alignment.min_rival_ratio * here:  # the rival ahead, by less than a margin
            why = (
                f"rejected: a trial bend puts {here:.1f} m of its walls on the others' at its place"
                f" ({v.reason.removeprefix('matched: ')}), {there:.1f} m at {which}: not told apart yet"
            )
            log.info("%s: %s", r.robot, why)
            return dataclasses.replace(v, status="unaligned", reason=why)
        why = (
            f"rejected: a trial bend puts {there:.1f} m of its walls on the others' at {which},"
            f" {here:.1f} m at the best ({v.reason.removeprefix('matched: ')})"
        )
        log.info("%s: %s", r.robot, why)
        refused = dataclasses.replace(v, status="unaligned", reason=why)
        # a rival, where the trial put ``trial_ratio`` times as much there as at every other place
        # (verified again there, as Placer._share_trial's): ACES's middle piece against the two
        # others, on the final maps of a run at f7cdc54, 128.7 m at its truth (its best rival)
        # against 83.8 m at its best
        bent_map = self.fleet.global_segments(r.robot)
        return self._settle_by_trial(r, v, places, met, bent_map, start=1) or refused

    def _matched_rivals(self, r: RobotState, v: Alignment, limit: int = 1) -> list[np.ndarray]:
        """The search's most matched places (Alignment.others) farther than ``search_agree_m`` from
        its best that matched over 1 / ``trial_rival_ratio`` of the best's length, at most
        ``limit``, most matched first."""
        out: list[np.ndarray] = []
        for row in [] if v.others is None else v.others:
            if len(out) == limit or row[3] * self.cfg.trial_rival_ratio < v.score_m:
                break  # (most matched first)
            if self._moved_m(r, v.transform, row[:3]) > self.cfg.search_agree_m:
                out.append(np.array(row[:3], float))
        return out

    def _apart(self, r: RobotState, v: Alignment, other: Alignment) -> float | None:
        """How far [m] (mean displacement of ``r``'s map) the other search's best place lies from
        ``v``'s when it is farther than ``search_agree_m`` and stands on as much wall as a merge
        needs (``min_overlap_m``: a best place of a few metres is no rival — MIT-CSAIL's middle
        piece against the bent maps, 7 m); else None."""
        if other.score_m < self.cfg.alignment.min_overlap_m:
            return None
        d = self._moved_m(r, v.transform, other.transform)
        return d if d > self.cfg.search_agree_m else None

    def veto(self, r: RobotState, placed_map: np.ndarray) -> Callable[[np.ndarray, float], str | None] | None:
        """Why a place found for ``r`` is contradicted — its walls where the placed robots saw
        free space, or theirs where it did (contradiction.py) — or None."""
        cc = self.cfg.contradiction
        if self.fleet.free_of is None or not cc.enabled:
            return None
        free_of = self.fleet.free_of
        own = self._shrink(free_of(r.robot, r.map.session))
        others = [x for x in self.fleet.placed() if x is not r]
        placed = [(x.robot, x.map.session, x.layer, x.alignment.transform) for x in others]
        placed += [(p.robot, p.session, p.layer, p.alignment.transform) for p in self.fleet.pieces()]
        parts = [(a, lay, t) for robot, ses, lay, t in placed if (a := free_of(robot, ses)) is not None]
        made_of = tuple((id(a), id(lay), *np.round(t, 4)) for a, lay, t in parts)
        if self._placed_free is None or self._placed_free[0] != made_of:
            noise = contradiction.placed_noise(
                [(n, t) for n, (_, _, t) in zip(self._own_noise(parts), parts, strict=True)]
            )
            # (the ids it is known by stay theirs: _noise_cache holds the parts)
            self._placed_free = (
                made_of,
                contradiction.shrink_placed([(a, t) for a, _, t in parts], *cc.grid),
                noise,
            )
        theirs, noise = self._placed_free[1:]
        if own is None and theirs is None:
            return None
        return contradiction.Check(r.layer.seg, own, placed_map, theirs, cc, noise)

    def own_noise_m(self, r: RobotState) -> float | None:
        """How much of ``r``'s walls stand in its own free space (contradiction.own_noise), or None
        when its free space is not known (or the check is off)."""
        if self.fleet.free_of is None or not self.cfg.contradiction.enabled:
            return None
        area = self.fleet.free_of(r.robot, r.map.session)
        own = self._shrink(area)
        if own is None:
            return None
        hit = self._noise_cache.get((id(area), id(r.layer)))  # (a placed robot's, from a veto)
        if hit is not None and hit[0] is area and hit[1] is r.layer:
            return float(hit[2][1].sum())
        return float(contradiction.own_noise(r.layer.seg, own, self.cfg.contradiction.step_m)[1].sum())

    def _shrink(self, area):
        """contradiction.shrink of a robot's free space, kept while it is the same object (a free
        space of a real log's 361-beam scans, 7,000-12,000 vertices, takes a tenth of a second to
        put on the grid; it took GEOS 2-10 s to buffer, at every search of an unplaced robot).
        The newest few are kept (the robots' and retired pieces' current free spaces)."""
        if area is None:
            return None
        hit = self._shrunk.get(id(area))
        if hit is None or hit[0] is not area:
            hit = self._shrunk[id(area)] = (area, contradiction.shrink(area, *self.cfg.contradiction.grid))
            while len(self._shrunk) > 2 * (len(self.fleet.robots) + len(self.fleet.pieces())) + 8:
                del self._shrunk[next(iter(self._shrunk))]  # (the oldest first)
        return hit[1]

    def _own_noise(self, parts: list) -> list[tuple[np.ndarray, np.ndarray]]:
        """contradiction.own_noise of each placed ``(free area, layer, pose)``, in its own frame:
        kept while the area and the layer are the same objects (a placement that moves needs only
        its transform, not the area shrunk again)."""
        cc, out, keep = self.cfg.contradiction, [], {}
        for a, lay, _ in parts:
            hit = self._noise_cache.get((id(a), id(lay)))
            if hit is None or hit[0] is not a or hit[1] is not lay:
                hit = (
                    a,
                    lay,
                    contradiction.own_noise(lay.seg, self._shrink(a), cc.step_m),
                )
            keep[(id(a), id(lay))] = hit
            out.append(hit[2])
        self._noise_cache = keep  # (only the current parts: bounded by the placed robots)
        return out

    def round(self, now_s: float, urgent: bool = False, only: set[int] | None = None) -> bool:
        """One pass over the robots that deserve an attempt; True if a robot got placed.

        Of the unplaced robots that matched, only the most decisive one (highest rival ratio)
        is taken this round; the others are tried again against the grown placed map — a robot
        matched against more of the fleet has fewer mirror images to fall for."""
        fresh: list[tuple[RobotState, Alignment, float, str, bool]] = []
        pieces, robots = self.fleet.pieces(), self.fleet.robots.values()
        if len(self._entries) > 2 * (len(robots) + len(pieces)) + 16:  # forget replaced pieces
            self._entries = {(r.robot, None): self._entries[(r.robot, None)] for r in robots
                             if (r.robot, None) in self._entries}  # fmt: skip
        placed = self.fleet.placed()
        around = Around(placed + pieces, self.cfg.refine_margin_m)
        pieces_m = sum(p.layer.length_m for p in pieces)
        keys: dict[int, tuple[float, PlacedKey]] = {}
        placed_total = sum(p.layer.length_m for p in placed)
        placed_ids = {id(p) for p in placed}

        def key_of(r: RobotState) -> tuple[float, PlacedKey]:
            if id(r) not in keys:
                if id(r) in placed_ids:
                    placed_m = placed_total - r.layer.length_m + pieces_m
                else:
                    placed_m = placed_total + pieces_m
                keys[id(r)] = (
                    placed_m,
                    PlacedKey(r, lambda: [p for p in placed if p is not r] + pieces, around, self._entries),
                )
            return keys[id(r)]

        def now_placed() -> None:  # a robot got placed in this round: the others see it
            nonlocal placed, placed_total, placed_ids
            placed = self.fleet.placed()
            placed_total = sum(p.layer.length_m for p in placed)
            placed_ids = {id(p) for p in placed}

        # which placed robots are refined: a settle's share (``only``), every due one (urgent), or
        # those whose turn it is
        turn = only if only is not None else (None if urgent else self._turns(placed, key_of, now_s))
        for r in self.fleet.ordered():
            if r.layer is None or r.alignment.status == "reference":
                continue
            if turn is not None and r.alignment.placed and id(r) not in turn:
                continue  # a refinement whose turn comes in a later fusion (or not due)
            prior = r.map.prior if self.fleet.frame == "prior" and not r.map.joined else None
            placed_m, key = key_of(r)
            young = (
                prior is None
                and not r.alignment.placed
                and not policy.mature([r, *(p for p in placed if p is not r)], now_s, self.cfg)
            )
            matured = r.young_s is not None and not young  # (attempted young: at once when mature)
            if not r.due(self.cfg, placed_m, key, now_s, urgent) and not matured:
                continue
            key = key()
            # it found itself in the fused map: its claim is checked, unless refuted before (a
            # claim placed, then undone, was verified again and again until the overlap's share
            # allowance let its contradiction through: bench_join, warehouse 3 -> 0, 2026-12-05)
            joining = r.map.joined and not r.alignment.placed and placed and not r.claim_refuted()
            if joining:
                a = self.estimate(r, r.map.prior, r.map.prior_sigma, None, search=False, join=True)
                log.info("%s: join at %.1f s: %s (%s)", r.robot, now_s, a.status, a.reason)
                r.alignment = a
                if a.placed:  # verified: placed at once, no maturity, no confirmation (its own evidence)
                    r.attempted(placed_m, key, now_s)
                    r.pending, r.pending_count = None, 0
                    r.mark_placed(now_s - self.fleet.epoch_s)
                    now_placed()
                    continue
                if a.reason.startswith(JOIN_REFUTED):
                    r.refute_claim()
                # not verified: matched as any robot (below)
            if young and (self.cfg.young_max_contradicted_m < 0.0 or (
                r.young_s is not None and now_s - r.young_s < self.cfg.young_retry_s
            )):  # fmt: skip
                if r.alignment.score_m == 0.0 and r.young_s is None and not joining:  # say why it waits
                    r.alignment = Alignment(
                        "unaligned", np.zeros(3), np.zeros(3), reason=policy.waiting(self.cfg)
                    )
                continue  # a young map's match is not evidence yet (unless quiet: below)
            if young and ((noisy := self.own_noise_m(r)) is None or noisy > self.cfg.young_max_self_m):
                r.young_s = now_s  # (looked at again after young_retry_s)
                why = (
                    "its free space is not known"
                    if noisy is None
                    else f"its map contradicts itself by {noisy:.1f} m"
                )
                if not joining:  # (a claim refused says why itself)
                    r.alignment = dataclasses.replace(
                        r.alignment, reason=f"{policy.waiting(self.cfg)}; {why}"
                    )
                continue  # it would not be quiet: searched once the maps are mature
            current = r.alignment if r.alignment.status == "aligned" else None
            sigma = r.map.prior_sigma if prior is not None else None
            a = self.estimate(r, prior, sigma, current, search=current is None or r.grew(self.cfg))
            r.young_s = now_s if young else None
            if young:  # a young map's match is not evidence yet, unless nothing contradicts it
                a = policy.young(a, self.cfg)
            if not r.alignment.placed or a.status != r.alignment.status:  # why a robot is (not) placed
                log.info("%s: attempt at %.1f s: %s (%s)", r.robot, now_s, a.status, a.reason)
            if a.status == "aligned" and not r.alignment.placed:  # (a young one is quiet)
                fresh.append((r, a, placed_m, key, young))
                continue
            r.attempted(placed_m, key, now_s)
            revised = a.status == "aligned" and current is not None and policy.moved(r, current, a, self.cfg)
            if revised:
                a = policy.confirm(r, a, current, self.cfg, now_s)  # a revision: not before it is confirmed
            else:
                r.pending, r.pending_count = None, 0
            was_placed = r.alignment.placed
            if was_placed and (not a.placed or (revised and r.pending is None)):
                r.refute_claim()  # (a joined robot: the place its claim gave is gone)
            if revised and r.pending is None:  # confirmed: the robot moves (say so)
                d = relative(current.transform, a.transform)
                log.info(
                    "%s: placed again at %.1f s, %.2f m and %.1f° from where it was (%s)",
                    r.robot, now_s, np.hypot(d[0], d[1]), np.degrees(abs(d[2])), a.reason,
                )  # fmt: skip
            r.alignment = a
            if a.placed and not was_placed:
                r.mark_placed(now_s - self.fleet.epoch_s)
                now_placed()
        if not fresh:
            return False
        for f in fresh:
            f[0].attempted(f[2], f[3], now_s)
        r, a, _, _, young = max(fresh, key=lambda f: f[1].rival_ratio)
        r.alignment = policy.confirm(r, a, None, self.cfg, now_s, young)
        if r.alignment.placed:
            r.mark_placed(now_s - self.fleet.epoch_s)
            return True
        return False

    def regroup(self, now_s: float) -> bool:
        """While the reference is the only placed robot, the unplaced robots are matched with each
        other; a pair that matches hands the frame over: the larger map of the two becomes the
        reference, the other is placed in it, and the old reference is matched as any robot
        (against the two). True if it did.

        Which robot becomes the reference is chance (the first map to arrive), and a real log cut
        in three shows it: MIT-CSAIL's middle piece meets the others by 7-15 m of wall, while the
        first and the last share 115 m — with the middle one as reference nothing was ever placed.
        The pair is held to what any placement is: mature maps, a search verified by the same
        checks (the free space both saw included), and ``confirmations`` attempts in a row at
        the same place. Only robots whose current map was tried against the reference and not
        placed take part; at most ``regroup_pairs`` pair attempts a fusion, each pair again when
        one of its maps changed (or its place awaits confirmation) and ``retry_interval_s`` passed."""
        f, cfg = self.fleet, self.cfg
        placed = f.placed()
        if f.frame != "reference" or len(placed) != 1 or f.pieces():
            return False
        ref = placed[0]
        waiting = [
            r for r in f.ordered()
            if r is not ref and r.layer is not None and len(r.layer) and not r.map.joined
            and r.attempt_seq == r.map.seq and r.pending is None
        ]  # fmt: skip
        if len(waiting) < 2 or not policy.mature([ref, *waiting], now_s, cfg):
            return False
        names = {r.robot for r in waiting}
        self._pairs = {k: v for k, v in self._pairs.items() if k[0] in names and k[1] in names}
        pairs = [(x, y) for i, x in enumerate(waiting) for y in waiting[i + 1 :]]
        found, tried = [], 0
        for x, y in pairs:
            if tried == cfg.regroup_pairs:
                break
            a, b = (x, y) if x.layer.length_m >= y.layer.length_m else (y, x)  # b searched in a
            key, seqs = (x.robot, y.robot), (a.robot, a.map.seq, b.robot, b.map.seq)
            last = self._pairs.get(key)
            if last is not None and (
                now_s - last[1] < cfg.retry_interval_s or (last[0] == seqs and last[2] is None)
            ):  # (a place awaiting its confirmation is attempted again on the same maps, as a robot's)
                continue
            tried += 1
            v = self._pair_attempt(a, b)
            if v.status != "aligned":
                self._pairs[key] = (seqs, now_s, None, 0, now_s)
                continue
            log.info("%s in %s: pair attempt at %.1f s: %s (%s)", b.robot, a.robot, now_s, v.status, v.reason)
            held = last is not None and last[2] is not None and last[2][0] is a
            if held and not policy.moved(b, last[2][1], v, cfg):
                count, first_s = last[3] + 1, last[4]
            else:
                count, first_s = 1, now_s
            self._pairs[key] = (seqs, now_s, (a, v), count, first_s)
            if count >= cfg.confirmations and now_s - first_s >= cfg.confirm_s:
                found.append((a, b, v))
        if not found:
            return False
        a, b, v = max(found, key=lambda x: x[2].rival_ratio)
        self._hand_over(ref, a, b, v, now_s)
        return True

    def _pair_attempt(self, a: RobotState, b: RobotState) -> Alignment:
        """``b``'s map searched in ``a``'s (in ``a``'s frame), checked against the free space
        both saw (contradiction.Check, with what ``a``'s map contradicts itself by)."""
        c, cc = self.cfg.alignment, self.cfg.contradiction
        veto = None
        if self.fleet.free_of is not None and cc.enabled:
            own = self._shrink(self.fleet.free_of(b.robot, b.map.session))
            theirs = self._shrink(self.fleet.free_of(a.robot, a.map.session))
            if own is not None or theirs is not None:
                noise = (
                    contradiction.own_noise(a.layer.seg, theirs, cc.step_m) if theirs is not None else None
                )
                veto = contradiction.Check(b.layer.seg, own, a.layer.seg, theirs, cc, noise)
        return estimate_alignment(b.layer.seg, a.layer.seg, c, veto=veto)

    def _hand_over(self, old: RobotState, a: RobotState, b: RobotState, v: Alignment, now_s: float) -> None:
        f = self.fleet
        log.info(
            "the frame is handed over from %s to %s: %s matched %s (%s), neither matched %s",
            old.robot, a.robot, b.robot, a.robot, v.reason, old.robot,
        )  # fmt: skip
        f.reference = a.robot
        a.alignment = Alignment(
            "reference", np.zeros(3), np.zeros(3), reason=f"the frame handed over from {old.robot}"
        )
        a.mark_placed(now_s - f.epoch_s)
        b.alignment = dataclasses.replace(v, reason=f"{v.reason} (with {a.robot}: the frame handed over)")
        b.mark_placed(now_s - f.epoch_s)
        old.alignment = Alignment(
            "unaligned", np.zeros(3), np.zeros(3),
            reason=f"the frame handed over to {a.robot} (this map matched neither {a.robot} nor {b.robot})",
        )  # fmt: skip
        old.aligned_at_s = None
        old.attempt_len_m, old.attempt_seq = None, -1  # due at once against the two
        self._pairs.clear()
