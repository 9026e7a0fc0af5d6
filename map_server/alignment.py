"""Robot map frame → global frame: from a start-pose prior, or by geometric map matching, with a
verdict that says why.

Without a prior (the usual case) candidates come from corner correspondences between the robot
map and the placed (fused) map, voted, refined by point-to-line least squares and scored by their
*net* evidence: robot-map length lying on placed walls minus length lying next to placed walls
but not on them (candidates.py, registration.py). The best is accepted only after verification —
conservative, since a wrong merge ruins the fused map while "unaligned" only delays it:

- enough absolute overlap (m) and enough of the robot map's length;
- a clear margin over the best *distinct* rival (a different place for the robot map): repetitive
  and symmetric buildings score alike (the office is 89 % self-similar under a half turn about
  its centre; only furniture and tables tell the halves apart);
- contradictions within limits: conflicting length, robot walls facing the other way on a placed
  wall, robot walls crossing placed walls. The limits are loose on purpose: the maps of three
  pieces of the real Intel log disagree with each other for 40-77 % of the matched length at
  their true placement (each piece's own SLAM drift), and a tight limit refused them all;
- a well-conditioned fit (sigma from the least-squares information matrix): a corridor alone
  leaves the position along it free.

Verification is per attempt; the fleet adds more (fleet.py: mature maps, confirmations, the most
decisive robot first), since a single attempt between partial maps of a symmetric building can
pass every check here and still be the mirror image.

With a prior the prior is refined by matching within its sigma (a MAP estimate with the prior as
a Gaussian term) and kept as is when the evidence is thin. A robot that is already aligned keeps
its alignment (re-refined as the maps change) unless a distinct place passes every check and the
current one lost support (fails a check now, or is beaten by ``revise_ratio`` where the free space
seen does not prefer it); only a map that grew enough is searched for such a place (fleet.py), a
changed one is refined where it is.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from map_server import candidates as cand
from map_server.candidates import Scored
from map_server.config import AlignmentConfig
from map_server.contradiction import Check
from map_server.registration import MapIndex, Samples, refine
from shared.geometry import compose, segment_lengths, transform_points, wrap_angle
from shared.messages import ALIGNMENT_STATUSES

RATIO_CAP = 1000.0  # rival ratio reported when there is no rival at all


@dataclass(frozen=True, eq=False)
class Alignment:
    """A verdict on one robot's frame. ``transform (3,)`` maps its map frame into the global frame
    (for ``unaligned``: the rejected best candidate, for diagnostics), ``sigma (3,)`` [m, m, rad],
    ``score_m`` verified overlap length, ``inlier_share`` its share of the robot map's length,
    ``rival_ratio`` net score over the best distinct rival's, ``reason`` why accepted or rejected.
    A search's place checked against the free space seen (``veto``: contradiction.Check) carries
    ``contradicted_m``, its walls where free space was seen (both ways), and ``seen_m2``, the
    free space both sides saw there (policy.quiet); None and 0 when not checked."""

    status: str
    transform: np.ndarray
    sigma: np.ndarray
    score_m: float = 0.0
    inlier_share: float = 0.0
    rival_ratio: float = 0.0
    reason: str = ""
    contradicted_m: float | None = None
    seen_m2: float = 0.0
    rival: np.ndarray | None = None  # a search's best distinct rival place (None: none, or no search)
    # a search's other places, each distinct from the best and from each other, most matched wall
    # first (K,4): x, y, theta, matched m — a bent map loses net score at its truth to walls near
    # the others' but not on them, and its truth can stand behind nearer rivals by net score
    others: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.status not in ALIGNMENT_STATUSES:
            raise ValueError(f"status: {self.status!r} is not one of {ALIGNMENT_STATUSES}")
        object.__setattr__(self, "transform", np.asarray(self.transform, float).reshape(3))
        object.__setattr__(self, "sigma", np.asarray(self.sigma, float).reshape(3))

    @property
    def placed(self) -> bool:
        return self.status != "unaligned"


def _sigma(info: np.ndarray) -> np.ndarray:
    try:
        cov = np.linalg.inv(info)
    except np.linalg.LinAlgError:
        return np.full(3, 1.0e3)
    return np.sqrt(np.clip(np.diag(cov), 0.0, 1.0e6))


def _problems(s: Scored, total_m: float, index: MapIndex, robot: Samples, robot_seg, cfg) -> list[str]:
    """What keeps candidate ``s`` from being accepted, rivals aside (empty: nothing)."""
    out = []
    if s.matched_m < cfg.min_overlap_m:
        out.append(f"overlap {s.matched_m:.1f} m < {cfg.min_overlap_m:g} m")
    if s.matched_m < cfg.min_share * total_m:
        out.append(f"share {s.matched_m / max(total_m, 1e-9):.2f} < {cfg.min_share:g}")
    if out:
        return out
    if s.conflict_m > cfg.max_conflict_share * s.matched_m:
        out.append(f"{s.conflict_m:.1f} m next to placed walls but not on them")
    opposed = index.opposed(s.pose, robot, cfg.opposed_perp_m)
    if opposed > cfg.max_opposed_share * s.matched_m:
        out.append(f"{opposed:.1f} m facing placed walls the other way")
    cross = index.crossings(transform_points(s.pose, robot_seg), cfg.cross_margin_m, cfg.cross_min_angle_rad)
    crossing = float(segment_lengths(robot_seg)[cross].sum())
    if crossing > cfg.max_crossing_share * s.matched_m:
        out.append(f"{crossing:.1f} m crossing placed walls")
    sig = _sigma(s.refined.info) if s.refined is not None else np.full(3, np.inf)
    if max(sig[0], sig[1]) > cfg.max_sigma_m or sig[2] > cfg.max_sigma_rad:
        out.append(f"ill-conditioned fit (sigma {sig[0]:.2f}, {sig[1]:.2f} m, {np.degrees(sig[2]):.2f} deg)")
    return out


def _verdict(status: str, s: Scored, total_m: float, ratio: float, reason: str) -> Alignment:
    sigma = _sigma(s.refined.info) if s.refined is not None else np.zeros(3)
    share = s.matched_m / total_m if total_m > 0 else 0.0
    return Alignment(status, s.pose, sigma, s.matched_m, share, min(ratio, RATIO_CAP), reason)


def estimate_alignment(
    robot_seg: np.ndarray,
    placed_seg: np.ndarray,
    cfg: AlignmentConfig,
    prior: np.ndarray | None = None,
    prior_sigma: np.ndarray | None = None,
    current: Alignment | None = None,
    search: bool = True,
    index: MapIndex | None = None,
    robot_samples: tuple[Samples, Samples] | None = None,
    veto: Callable[[np.ndarray, float], str | None] | None = None,
) -> Alignment:
    """The robot's map frame in the global frame, from its directed segments ``robot_seg (N,2,2)``
    (its map frame) and the placed robots' fused map ``placed_seg (M,2,2)`` (global frame).
    ``search=False`` with a ``current`` alignment only refines it where it is (no candidate
    search, so no revision to a distinct place): the maps changed shape, not size. ``index``: the
    placed map's index when the caller has one (a crop, registration.MapIndex; without a search
    only the index is used); ``robot_samples``: ``robot_seg``'s samples at ``cfg.sample_step_m``
    and ``cfg.coarse_step_m`` when the caller keeps them. ``veto(pose, matched_m)``: why a found
    place is contradicted (contradiction.py: walls in free space), or None — a contradicted place
    is set aside, as the best and as a rival (a search only)."""
    robot_seg = np.asarray(robot_seg, float).reshape(-1, 2, 2)
    placed_seg = np.asarray(placed_seg, float).reshape(-1, 2, 2)
    if robot_samples is None:
        robot_samples = Samples.of(robot_seg, cfg.sample_step_m), Samples.of(robot_seg, cfg.coarse_step_m)
    robot, coarse = robot_samples
    index = MapIndex(placed_seg, cfg.sample_step_m, compiled=cfg.compiled) if index is None else index
    total = float(robot.length.sum())
    if prior is not None:
        sigma = np.zeros(3) if prior_sigma is None else np.asarray(prior_sigma, float)
        return _from_prior(robot_seg, index, robot, coarse, np.asarray(prior, float), sigma, cfg)
    keep = current is not None and current.status == "aligned"
    if total < cfg.min_overlap_m or len(index.samples) == 0:
        if keep:
            return current
        why = "nothing placed yet" if len(index.samples) == 0 else f"robot map only {total:.1f} m long"
        return Alignment("unaligned", np.zeros(3), np.zeros(3), reason=why)
    cands = cand.search(robot_seg, placed_seg, index, robot, coarse, cfg) if search or not keep else []
    if keep:
        cur = cand.refine_and_score(index, robot, coarse, current.transform, cfg)
        return _revise(current, cur, cands, robot_seg, index, robot, total, cfg, veto)
    if not cands:
        return Alignment("unaligned", np.zeros(3), np.zeros(3), reason="no corner correspondences")
    a = _accept_best(cands, robot_seg, index, robot, total, cfg, veto, coarse)
    if a.placed or a.score_m >= cfg.min_overlap_m or cfg.deep_peaks <= cfg.max_peaks:
        return a
    # no place stands on as much wall as a merge needs among the densest vote peaks: deeper (a
    # piece that overlaps the others little has few corners in common with them)
    deep = cand.search(
        robot_seg, placed_seg, index, robot, coarse, dataclasses.replace(cfg, max_peaks=cfg.deep_peaks)
    )
    d = _accept_best(deep, robot_seg, index, robot, total, cfg, veto, coarse)
    if not d.placed:
        return a
    return dataclasses.replace(d, reason=f"{d.reason} (among the {cfg.deep_peaks} densest vote peaks)")


MAX_VETOED = 20  # distinct places checked for contradiction, best first, before the search gives up
# (bench_merge.py, warehouse, 10 seeds: 11 of 20 robots placed, 6 with 6 places checked, the same
# 1 wrong merge either way; 50 places as 20)


def _set_aside(
    cands: list[Scored],
    veto,
    points: np.ndarray,
    distinct_m: float,
    top: Callable[[list[Scored]], list[Scored]] | None = None,
) -> tuple[list[Scored], list[tuple[Scored, str]], int]:
    """The places ``veto`` contradicts, best first, up to the first it does not (at most
    MAX_VETOED distinct places checked), and the candidates without them. A candidate that is
    the same place as a contradicted one (within ``distinct_m``, as rivals are told apart) goes
    with it unchecked: a mirror image found six times over is one place, not six. ``top``: the
    candidates with the best scored strictly (:func:`_best_refined`), before each is looked at.
    Returns the candidates left, those set aside with why, and how many distinct places were
    contradicted."""
    aside, contradicted, checked = [], [], 0
    left = list(cands)
    while left:
        if top is not None:
            left = top(left)
        s = max(left, key=lambda s: s.net)
        same = next(
            (w for c, w in contradicted if cand.mean_displacement(s.pose, c.pose, points) <= distinct_m), None
        )
        if same is None:
            if checked == MAX_VETOED:
                break
            checked += 1
            same = veto(s.pose, s.matched_m)
            if same is None:
                break
            contradicted.append((s, same))
        aside.append((s, same))
        left = [c for c in left if c is not s]
    return left, aside, len(contradicted)


def _rivals_aside(
    best: Scored,
    cands: list[Scored],
    veto,
    points: np.ndarray,
    cfg: AlignmentConfig,
    budget: int,
    strict: Callable[[Scored, list[Scored], float], list[Scored]] | None = None,
) -> tuple[list[Scored], list[tuple[Scored, str]]]:
    """While the best distinct rival keeps ``best`` below ``min_rival_ratio``, the rival is checked
    by ``veto``; a contradicted one (and the candidates at its place) is set aside, at most
    ``budget`` places checked. A symmetric building's true place often ties with a mirror image
    that the free space seen rules out (the simulated warehouse: rival ratios 1.000-1.02 at the end
    of a run, the rival half-turned). A rival the free space seen prefers less than the best
    (``Check.outshone``) is no rival either. Returns the candidates left and those set aside with
    why. ``strict``: the candidates with the close rivals only pre-scored scored strictly
    (:func:`_rivals_refined`), before each rival is looked at."""
    aside = []
    for _ in range(max(budget, 0)):
        if strict is not None:
            cands = strict(best, cands, cfg.min_rival_ratio)
        r = cand.best_rival(best, cands, points, cfg.distinct_m)
        if r is None or best.net >= cfg.min_rival_ratio * r.net:
            break
        why = veto(r.pose, r.matched_m)
        if why is None and isinstance(veto, Check):  # ... or outshone by the best (a close call)
            why = veto.outshone(r.pose, best.pose)
        if why is None:
            break
        cands, gone = cand.without_place(cands, r.pose, points, cfg.distinct_m)
        aside += [(c, why) for c in gone]
    return cands, aside


def _rivals_refined(
    best: Scored, cands: list[Scored], index: MapIndex, robot: Samples, coarse: Samples, cfg, ratio: float
) -> list[Scored]:
    """``cands`` with the distinct rivals that keep ``best`` below ``ratio`` of their net score
    scored as strictly as ``best``: while the best distinct rival is one only pre-scored (generous
    tolerances, candidates.search refines the best ``max_refined``), it is refined and scored and
    takes its place, at most ``max_refined`` of them. A close call is made between strict scores:
    a pre-score has no conflict term, and a real log's piece loses a third of its net score to it
    at its true place (ACES in 3 pieces: the truth 29.1 net against a half turn in place pre-scored
    27.8 and -2.7 refined)."""
    for _ in range(cfg.max_refined):
        r = cand.best_rival(best, cands, robot.points, cfg.distinct_m)
        if r is None or r.refined is not None or best.net >= ratio * r.net:
            break
        s = cand.refine_and_score(index, robot, coarse, r.pose, cfg)
        cands = [s if c is r else c for c in cands]
    return cands


def _best_refined(
    cands: list[Scored], index: MapIndex, robot: Samples, coarse: Samples, cfg: AlignmentConfig
) -> list[Scored]:
    """``cands`` with the best scored strictly: while the best (net) is one only pre-scored (its
    generous pre-score has no conflict term), it is refined and scored and takes its place, at
    most ``max_refined`` of them (a candidate is refined once: over a verdict, at most the
    search's unrefined peaks). Once the refined candidates at the true place are set aside or
    lose their conflicting length, an unrefined peak can lead; it used to decide the verdict
    unrefined — rejected as an ill-conditioned fit (no refinement, no sigma)."""
    for _ in range(cfg.max_refined):
        best = max(cands, key=lambda s: s.net)
        if best.refined is not None:
            break
        s = cand.refine_and_score(index, robot, coarse, best.pose, cfg)
        cands = [s if c is best else c for c in cands]
    return cands


def _outshone_aside(
    cands: list[Scored],
    veto: Check,
    points: np.ndarray,
    cfg: AlignmentConfig,
    budget: int,
    strict: Callable[[Scored, list[Scored], float], list[Scored]] | None = None,
    top: Callable[[list[Scored]], list[Scored]] | None = None,
) -> tuple[list[Scored], list[tuple[Scored, str]], int]:
    """While the best candidate has a distinct rival within ``close_ratio`` of its net score and
    the free space seen prefers the rival (``Check.outshone``), the best (and the candidates at its
    place) is set aside and the next best looked at, at most ``budget`` places. A close call
    between a place and its mirror image is not one a repeated search can settle (the same maps
    give the same verdict); the walls each puts where the other side saw free space can. Returns
    the candidates left (never none: a rival stays), those set aside with why, and how many
    distinct places were set aside."""
    aside: list[tuple[Scored, str]] = []
    close, places = veto.cfg.close_ratio, 0
    for _ in range(max(budget, 0)):
        if top is not None:
            cands = top(cands)
        best = max(cands, key=lambda s: s.net)
        if strict is not None:
            cands = strict(best, cands, close)
        r = cand.best_rival(best, cands, points, cfg.distinct_m)
        if r is None or best.net >= close * r.net:
            break
        why = veto.outshone(best.pose, r.pose)
        if why is None:
            break
        cands, gone = cand.without_place(cands, best.pose, points, cfg.distinct_m)
        aside += [(c, why) for c in gone]
        places += 1
    return cands, aside, places


def _accept_best(
    cands: list[Scored], robot_seg, index, robot, total, cfg, veto=None, coarse=None
) -> Alignment:
    def strict(best: Scored, cands: list[Scored], ratio: float) -> list[Scored]:
        return cands if coarse is None else _rivals_refined(best, cands, index, robot, coarse, cfg, ratio)

    def top(cands: list[Scored]) -> list[Scored]:
        return (
            cands
            if coarse is None or not cfg.refine_best
            else _best_refined(cands, index, robot, coarse, cfg)
        )

    set_aside = []
    if veto is not None:
        cands, set_aside, distinct = _set_aside(cands, veto, robot.points, cfg.distinct_m, top)
        if set_aside and (not cands or distinct == MAX_VETOED):  # every place checked contradicted
            s, why = set_aside[0]
            reason = f"rejected: the best {distinct} distinct places contradicted (best: {why})"
            return _verdict("unaligned", s, total, 1.0, reason)
    outshone = []
    if isinstance(veto, Check):  # a close call is decided by the free space seen
        cands, outshone, places = _outshone_aside(
            cands, veto, robot.points, cfg, MAX_VETOED - distinct, strict, top
        )
        distinct += places
    cands = top(cands)
    best = max(cands, key=lambda s: s.net)
    rivals_aside = []
    if veto is not None:  # a rival too close to call is checked too: a contradicted one is no rival
        cands, rivals_aside = _rivals_aside(
            best, cands, veto, robot.points, cfg, MAX_VETOED - distinct, strict
        )
    cands = strict(best, cands, cfg.min_rival_ratio)
    rival = cand.best_rival(best, cands, robot.points, cfg.distinct_m)
    ratio = best.net / max(0.0 if rival is None else rival.net, 1e-9)
    problems = _problems(best, total, index, robot, robot_seg, cfg)
    if ratio < cfg.min_rival_ratio:
        problems.append(f"rival ratio {ratio:.3f} < {cfg.min_rival_ratio:g}")
    aside = f"; {len(set_aside)} better-scored place(s) contradicted ({set_aside[0][1]})" if set_aside else ""
    if outshone:
        aside += f"; {len(outshone)} better-scored place(s) outshone ({outshone[0][1]})"
    if rivals_aside:
        aside += f"; {len(rivals_aside)} rival place(s) contradicted ({rivals_aside[0][1]})"
    rival_at = None if rival is None else np.array(rival.pose, float)
    others = _most_matched(best, cands, robot.points, cfg.distinct_m)
    if problems:
        a = _verdict("unaligned", best, total, ratio, "rejected: " + "; ".join(problems) + aside)
        return dataclasses.replace(a, rival=rival_at, others=others)
    why = (
        f"overlap {best.matched_m:.1f} m ({best.matched_m / total:.0%}), {ratio:.2f}x the best rival" + aside
    )
    a = _verdict("aligned", best, total, ratio, "matched: " + why)
    a = dataclasses.replace(a, rival=rival_at, others=others)
    if isinstance(veto, Check):  # what the free space seen says of the place (policy.quiet)
        a = dataclasses.replace(
            a, contradicted_m=veto.contradicted_m(best.pose), seen_m2=veto.seen_m2(best.pose)
        )
    return a


MOST_MATCHED = 4  # places a search's verdict keeps in Alignment.others


def _most_matched(best: Scored, cands: list[Scored], points: np.ndarray, distinct_m: float) -> np.ndarray:
    """The candidates' places other than ``best``'s, most matched length first, each distinct
    (``distinct_m``) from ``best`` and from those before it, at most MOST_MATCHED: rows x, y, theta,
    matched m."""
    out: list[Scored] = []
    for c in sorted(cands, key=lambda c: -c.matched_m):
        if len(out) == MOST_MATCHED:
            break
        if all(cand.mean_displacement(c.pose, o.pose, points) > distinct_m for o in (best, *out)):
            out.append(c)
    return np.array([[*c.pose, c.matched_m] for c in out], float).reshape(-1, 4)


def _revise(
    current: Alignment, cur: Scored, cands, robot_seg, index, robot, total, cfg, veto=None
) -> Alignment:
    """Keep the current alignment (refined while it stays verified) unless a distinct place passes
    every check and the current one lost support: it fails a check now, or the new place beats
    it by ``revise_ratio`` (symmetric buildings: the truth overtakes a mirror image slowly) — and
    the free space seen does not prefer the current one (``Check.outshone``, whatever the ratio:
    the overlap measures where the others have been, and the simulated warehouse's robots held at
    their truth were moved 34 m to the half-turn image at 3.1-3.9x the score, its walls 2.6-2.9 m
    in the free space seen, the truth's none; bench_merge seeds 10-19).
    ``veto``: a current place contradicted by the free space seen (a wrong merge the maps have
    grown to disprove) is undone — the robot is unplaced unless a distinct place passes."""
    contradicted = veto(cur.pose, cur.matched_m) if veto is not None else None
    held = ""
    cands = [cur, *[c for c in cands if veto is None or c is cur or veto(c.pose, c.matched_m) is None]]
    best = max(cands, key=lambda s: s.net)
    cur_problems = _problems(cur, total, index, robot, robot_seg, cfg)
    if contradicted is not None:
        cur_problems.insert(0, f"contradicted: {contradicted}")
    ratio = cur.net / max(cand.rival(cur, cands, robot.points, cfg.distinct_m), 1e-9)
    if cand.mean_displacement(best.pose, cur.pose, robot.points) > cfg.distinct_m:
        new_ratio = best.net / max(cand.rival(best, cands, robot.points, cfg.distinct_m), 1e-9)
        new_problems = _problems(best, total, index, robot, robot_seg, cfg)
        if new_ratio < cfg.min_rival_ratio:
            new_problems.append(f"rival ratio {new_ratio:.3f} < {cfg.min_rival_ratio:g}")
        times = best.net / max(cur.net, 1e-9)
        beaten = best.net >= cfg.revise_ratio * cur.net
        if beaten and not cur_problems and isinstance(veto, Check):
            # a held place whose walls stand in the free space seen far less densely than the new
            # place's keeps it, whatever the overlap: that measures where the others have been
            outshone = veto.outshone(best.pose, cur.pose)
            if outshone is not None:
                beaten = False
                held = f"; a distinct place {times:.2f}x the score outshone ({outshone})"
        if (cur_problems or beaten) and not new_problems:
            lost = "; ".join(cur_problems) or f"beaten {times:.2f}x"
            why = f"current place lost support ({lost}); new overlap {best.matched_m:.1f} m"
            return _verdict("aligned", best, total, new_ratio, "revised: " + why)
    if contradicted is not None:
        return _verdict("unaligned", cur, total, ratio, f"undone: the place is contradicted ({contradicted})")
    if cur_problems:
        return Alignment(
            "aligned", current.transform, current.sigma, current.score_m, current.inlier_share,
            current.rival_ratio, "kept (not re-verified: " + "; ".join(cur_problems) + ")",
        )  # fmt: skip
    return _verdict("aligned", cur, total, ratio, f"kept and refined: overlap {cur.matched_m:.1f} m{held}")


def query_reach(cfg: AlignmentConfig) -> float:
    """How far from a robot sample an attempt looks into the placed map, at most (registration's
    gates, plus the along-line slack of the coarsest samples)."""
    gates = [g for g, _ in cfg.refine_stages]
    perps = (cfg.prescore_perp_m, cfg.score_perp_m, cfg.conflict_m, cfg.opposed_perp_m)
    return max(*gates, *perps) + cfg.coarse_step_m


def floored_prior_sigma(prior_sigma: np.ndarray, cfg: AlignmentConfig) -> np.ndarray:
    """A prior's sigma ``(..., 3)`` with the configured floors (a zero sigma would pin the pose)."""
    floor = [cfg.prior_min_sigma_m, cfg.prior_min_sigma_m, cfg.prior_min_sigma_rad]
    return np.maximum(np.asarray(prior_sigma, float), floor)


def _refined_at(
    robot_seg, index: MapIndex, robot: Samples, coarse: Samples, start, sigma, cfg
) -> tuple[Scored, float, list[str]]:
    """``start`` refined by matching within ``sigma`` (floored; a Gaussian term), scored and
    verified: the candidate, how far it moved (Mahalanobis) and what keeps it from acceptance."""
    info = np.diag(1.0 / sigma**2)
    gate = max(cfg.prior_gate_sigmas * max(sigma[0], sigma[1]), cfg.refine_stages[-1][0])
    stages = tuple((min(g, gate), a) for g, a in cfg.refine_stages)
    r = refine(index, coarse, start, stages, cfg.point_sigma_m, cfg.correlation_m, start, info)
    s = cand.score(index, robot, r.pose, cfg, r)
    d = s.pose - start
    d[2] = wrap_angle(d[2])
    maha = float(np.sqrt(d @ info @ d))
    problems = _problems(s, float(robot.length.sum()), index, robot, robot_seg, cfg)
    if maha > cfg.prior_gate_sigmas:
        problems.append(f"refinement moved {maha:.1f} sigma")
    return s, maha, problems


def _from_prior(
    robot_seg, index: MapIndex, robot: Samples, coarse: Samples, prior, prior_sigma, cfg
) -> Alignment:
    """Refine the prior by matching within its sigma; keep it when the evidence is thin."""
    sigma = floored_prior_sigma(prior_sigma, cfg)
    total = float(robot.length.sum())

    def kept(why: str) -> Alignment:
        return Alignment("prior", prior, sigma, 0.0, 0.0, 0.0, "prior kept: " + why)

    if len(index.samples) == 0 or total < cfg.min_overlap_m:
        return kept("nothing placed to refine against" if len(index.samples) == 0 else "robot map too short")
    s, maha, problems = _refined_at(robot_seg, index, robot, coarse, prior, sigma, cfg)
    if problems:
        return kept("; ".join(problems))
    why = f"prior refined: overlap {s.matched_m:.1f} m, moved {maha:.1f} sigma"
    return _verdict("prior", s, total, 0.0, why)


JOIN_REFUTED = "join refuted: "  # verify_join's reason when the free space seen contradicts the claim


def verify_join(
    robot_seg: np.ndarray,
    placed_seg: np.ndarray,
    cfg: AlignmentConfig,
    claim: np.ndarray,
    claim_sigma: np.ndarray,
    index: MapIndex | None = None,
    robot_samples: tuple[Samples, Samples] | None = None,
    veto: Callable[[np.ndarray, float], str | None] | None = None,
) -> Alignment:
    """A robot's own claim ``claim (3,)`` of where its map frame is in the global frame — it found
    itself in the fused map (``fleet-slam agent --join``: robot_agent/join.py) — checked against
    the placed map: refined within ``claim_sigma`` and verified as a search's best would be, but
    for the overlap floors (``join_min_overlap_m``, ``join_min_share``: a join comes seconds
    after the robot's start, its map is small, and the claim is evidence of its own) and without
    rivals (the robot ruled them out against the whole fused map); ``veto`` as in
    :func:`estimate_alignment`. ``aligned`` there, or ``unaligned`` saying why (the robot is then
    matched as any robot); the reason starts with :data:`JOIN_REFUTED` when ``veto`` refused it
    (the claim is not checked again: Placer.round)."""
    robot_seg = np.asarray(robot_seg, float).reshape(-1, 2, 2)
    if robot_samples is None:
        robot_samples = Samples.of(robot_seg, cfg.sample_step_m), Samples.of(robot_seg, cfg.coarse_step_m)
    robot, coarse = robot_samples
    index = MapIndex(np.asarray(placed_seg, float).reshape(-1, 2, 2), cfg.sample_step_m,
                     compiled=cfg.compiled) if index is None else index  # fmt: skip
    claim = np.asarray(claim, float)
    sigma = floored_prior_sigma(claim_sigma, cfg)
    total = float(robot.length.sum())
    if len(index.samples) == 0 or total == 0.0:
        why = "nothing placed" if len(index.samples) == 0 else "empty robot map"
        return Alignment("unaligned", claim, sigma, reason="join not verified: " + why)
    jc = dataclasses.replace(cfg, min_overlap_m=cfg.join_min_overlap_m, min_share=cfg.join_min_share)
    s, maha, problems = _refined_at(robot_seg, index, robot, coarse, claim, sigma, jc)
    share = s.matched_m / total
    if not problems and veto is not None and (why := veto(s.pose, s.matched_m)) is not None:
        # the free space seen contradicts the claim: refuted
        return Alignment("unaligned", s.pose, sigma, s.matched_m, share, 0.0, JOIN_REFUTED + why)
    if problems:
        return Alignment("unaligned", s.pose, sigma, s.matched_m, share, 0.0,
                         "join not verified: " + "; ".join(problems))  # fmt: skip
    why = f"joined: its place in the fused map verified (overlap {s.matched_m:.1f} m, moved {maha:.1f} sigma)"
    return _verdict("aligned", s, total, RATIO_CAP, why)


def prior_gauge(
    transforms: np.ndarray, priors: np.ndarray, sigmas: np.ndarray, iterations: int = 4
) -> np.ndarray:
    """The rigid motion ``g (3,)`` of the whole placed set that best agrees with the priors:
    argmin_g Σ_k |compose(g, transforms[k]) − priors[k]|² weighted by ``1 / sigmas[k]²`` (all
    ``(K,3)``; Gauss-Newton from identity).

    Matching between robots is blind to a motion of all of them together, so in a prior frame
    only the priors fix it; refining one robot at a time against the others leaves that common
    motion wherever the first robot refined put it (office, three robots: all turned 0.4° by one
    map's own frame error). Applying ``g`` to every placed frame restores the gauge the joint
    estimate would have: the priors' weighted residuals balance."""
    t = np.asarray(transforms, float).reshape(-1, 3)
    p = np.asarray(priors, float).reshape(-1, 3)
    w = 1.0 / np.asarray(sigmas, float).reshape(-1, 3) ** 2
    g = np.zeros(3)
    for _ in range(iterations):
        moved = compose(g, t)
        r = moved - p
        r[:, 2] = wrap_angle(r[:, 2])
        jac = np.zeros((len(t), 3, 3))
        jac[:, 0, 0] = jac[:, 1, 1] = jac[:, 2, 2] = 1.0
        jac[:, 0, 2] = -(moved[:, 1] - g[1])  # d(R t)/dθ = R(θ + π/2) t, relative to g's origin
        jac[:, 1, 2] = moved[:, 0] - g[0]
        jw = jac * w[:, :, None]  # Jᵀ W has W on J's rows
        h = np.einsum("kri,krj->ij", jw, jac)
        b = np.einsum("kri,kr->i", jw, r)
        step = np.linalg.solve(h, -b)
        g = g + step
        if np.all(np.abs(step) < 1e-12):
            break
    g[2] = wrap_angle(g[2])
    return g
