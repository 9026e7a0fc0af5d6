"""Relocalization at loop closure (report §6): inject particles where the geometry says the
robot may be.

When the robot is back among old, reliable elements of the global map, the drift accumulated
in between can put the true pose outside what the particles cover. Pose hypotheses are computed
from the latest scan's segments against the reliable elements near the estimate (pairs of
non-parallel segments: corners and near-corners, shared/matching.py), scored by how much of the
scan they explain, and the best few that explain clearly more than the current estimate are
injected as particles (report: "in practice, one each"), replacing the weakest ones. They carry
the best particle's map and get an even chance: later scans keep them or kill them. After a
large correction (one that had to be found twice) the young elements of that map — mapped from
the drifted estimate — move with the pose in the injected copies; left where they were, they
fitted the drifted particles better than the old map fitted the right ones, and every injection
died while the drift stayed.

A hypothesis must also not contradict the map: the scan's beams, cast from it, may pass through
no more of those old reliable elements than from the current estimate. In a repetitive building
(a corridor of alike doors) a shifted pose explains the nearby segments as well as the true one,
but its beams run through the end wall or the far rooms' walls.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

from robot_agent.slam.consensus import GlobalMap
from robot_agent.slam.extraction import ScanSegments
from robot_agent.slam.lines import transform_lines, transform_moments
from robot_agent.slam.particles import ParticleSet, SegmentMaps
from robot_agent.slam.update import UpdateConfig, visibility
from shared.geometry import (
    apply_segments,
    compose,
    inverse,
    point_segment_distance,
    relative,
    segment_lengths,
    wrap_angle,
)
from shared.matching import MatchingConfig, cluster_poses, overlap_scores, pose_hypotheses


@dataclass(frozen=True)
class RelocalizationConfig:
    enabled: bool = True
    every: int = 5  # steps between attempts while among old elements
    old_age_steps: int = 200  # an element this old (in steps) marks a revisited place
    min_hits: int = 5  # reliability of the elements used (report: age and update count)
    min_trust: float = 0.4
    search_radius_m: float = 10.0  # elements within this distance of the estimate take part
    min_old_elements: int = 3  # this many old reliable elements nearby make a loop closure
    min_jump_m: float = 0.15  # closer hypotheses are already covered by the proposal
    min_jump_rad: float = np.radians(2.0)
    max_jump_m: float = 6.0  # drift between loop closures stays below this ...
    jump_base_m: float = 1.0  # ... and below this plus ...
    jump_per_m: float = 0.03  # ... this share of the distance driven since the last relocalization
    # when the estimate itself explains at least anchored_m of the scan with old elements: a
    # corridor of alike doors offers its whole period as a jump to a robot that is not lost
    anchored_m: float = 2.0
    max_jump_rad: float = np.radians(30.0)
    min_score_m: float = 4.0  # a hypothesis must explain at least this much scan length ...
    score_gain_m: float = 1.5  # ... and this much more than the current estimate
    unique_ratio: float = 1.3  # the best must beat every distinct alternative (current estimate
    # included) by this factor: in repetitive places (aisles, rows of doors) aliases score alike
    distinct_radius_m: float = 1.0  # hypotheses farther apart than this are distinct places
    inject: int = 2  # particles replaced per relocalization
    confirm_steps: int = 15  # a large correction is injected only when found again within this
    # many steps (0: at once): a lone large jump is more often an alias than a loop closure ...
    confirm_beyond_m: float = 1.0  # ... large: farther than this or turning more than
    confirm_beyond_rad: float = np.radians(10.0)
    confirm_m: float = 0.25  # ... the second finding within this distance and angle of the first
    confirm_rad: float = np.radians(3.0)
    max_extra_through: int = 1  # old elements a hypothesis's beams may pass through beyond the
    # current estimate's count
    matching: MatchingConfig = field(default_factory=MatchingConfig)


@dataclass(frozen=True)
class ScanRays:
    """The raw scan, for the negative evidence: ranges ``(B,)`` at ``angles_rad (B,)`` from the
    laser at ``laser_offset (3,)`` in the robot frame; readings at or beyond ``usable_range_m``
    are no return."""

    ranges_m: np.ndarray
    angles_rad: np.ndarray
    laser_offset: np.ndarray
    usable_range_m: float
    update: UpdateConfig = field(default_factory=UpdateConfig)


def through_counts(
    poses: np.ndarray, seg: np.ndarray, alpha: np.ndarray, facing: np.ndarray, rays: ScanRays
) -> np.ndarray:
    """``(H,)``: how many of the elements ``seg (G,2,2)`` the scan's beams pass through (at two
    or more sample points) when cast from each robot pose of ``poses (H,3)``."""
    h, g = len(poses), len(seg)
    if g == 0:
        return np.zeros(h, int)
    maps = _Elements(
        np.broadcast_to(seg, (h, g, 2, 2)),
        np.broadcast_to(alpha, (h, g)),
        np.broadcast_to(facing, (h, g)),
        np.ones((h, g), bool),
    )
    laser = compose(poses, rays.laser_offset)
    through, _ = visibility(maps, laser, rays.ranges_m, rays.angles_rad, rays.usable_range_m, rays.update)
    return np.sum(through >= 2, axis=1)


@dataclass(frozen=True)
class _Elements:  # the fields of SegmentMaps that visibility() reads
    seg: np.ndarray
    alpha: np.ndarray
    facing: np.ndarray
    valid: np.ndarray


@dataclass(frozen=True)
class Relocalization:
    poses: np.ndarray  # (H,3) hypotheses to inject, best first
    scores: np.ndarray  # (H,) explained length [m]
    current_score: float


def relocalize(
    ps: ParticleSet,
    gm: GlobalMap,
    segs: ScanSegments,
    facing: np.ndarray,
    step: int,
    cfg: RelocalizationConfig,
    rays: ScanRays | None = None,
    traveled_m: float = np.inf,
) -> Relocalization | None:
    """Hypotheses clearly better than the current estimate (and, given the raw scan ``rays``,
    contradicting the map no more than it), within the drift possible over ``traveled_m`` driven
    since the last relocalization; or None."""
    if step % cfg.every or len(gm) == 0:
        return None
    pose = ps.poses[ps.best()]
    near = _reliable(gm, cfg) & (point_segment_distance(pose[:2], gm.seg) <= cfg.search_radius_m)
    old = near & (step - gm.born >= cfg.old_age_steps)
    if old.sum() < cfg.min_old_elements:
        return None
    mc = cfg.matching
    # the loop closes against the OLD part of the map: recent elements were mapped with the
    # drifted pose and would let the current estimate explain the scan as well as the truth
    # every hypothesis is scored: implausible ones still count as rivals (aliases)
    scored = _scored(pose, segs, facing, gm.seg[old], gm.facing[old], mc)
    if scored is None:
        return None
    hyp, scores, current = scored
    d = relative(pose, hyp)
    dist, dang = np.hypot(d[:, 0], d[:, 1]), np.abs(d[:, 2])
    far_enough = (dist >= cfg.min_jump_m) | (dang >= cfg.min_jump_rad)
    max_jump = cfg.max_jump_m
    if current >= cfg.anchored_m:  # the estimate fits the old map: only drift-sized jumps
        max_jump = min(max_jump, cfg.jump_base_m + cfg.jump_per_m * traveled_m)
    plausible = (dist <= max_jump) & (dang <= cfg.max_jump_rad)
    good = far_enough & plausible & (scores >= cfg.min_score_m) & (scores >= current + cfg.score_gain_m)
    if not np.any(good):
        return None
    # all reliable elements for the beams: an alias runs through the young ones the estimate is
    # consistent with; after real drift the estimate's beams run through old ones as much
    return _pick(pose, hyp, scores, current, good, cfg, rays, gm, near)


def _unique(
    hyp: np.ndarray,
    scores: np.ndarray,
    best: int,
    pose: np.ndarray,
    current: float,
    cfg: RelocalizationConfig,
) -> bool:
    """The best hypothesis beats every distinct alternative (and the current pose) clearly."""
    others = np.vstack([hyp, pose])
    other_scores = np.append(scores, current)
    far = np.hypot(*(others[:, :2] - hyp[best, :2]).T) > cfg.distinct_radius_m
    rival = float(other_scores[far].max(initial=0.0))
    return scores[best] >= cfg.unique_ratio * rival


def _move_young(maps: SegmentMaps, rows: np.ndarray, corrections: np.ndarray, young_since: int) -> None:
    """In particles ``rows (T,)``, the elements born at or after ``young_since`` mapped by the
    particle's ``corrections (T,3)``."""
    young = maps.valid[rows] & (maps.born[rows] >= young_since)  # (T,M)
    c = corrections[:, None, :]
    alpha, rho, _ = transform_lines(c, maps.alpha[rows], maps.rho[rows])
    moved = {
        "seg": apply_segments(corrections, maps.seg[rows]),
        "moments": transform_moments(c, maps.moments[rows]),
        "alpha": alpha,
        "rho": rho,
        "facing": wrap_angle(maps.facing[rows] + c[..., 2]),
    }
    for name, value in moved.items():
        old = getattr(maps, name)
        mask = young.reshape(young.shape + (1,) * (value.ndim - 2))
        old[rows] = np.where(mask, value, old[rows])


@dataclass(frozen=True)
class Pending:
    """A correction found once, awaiting confirmation: the map-frame transform ``correction (3,)``
    that takes the estimate then onto the best hypothesis, found at ``step``."""

    correction: np.ndarray
    step: int


def is_large(result: Relocalization, pose: np.ndarray, cfg: RelocalizationConfig) -> bool:
    """The best hypothesis is a large correction of ``pose (3,)`` (beyond confirm_beyond_m / _rad)."""
    jump = relative(pose, result.poses[0])
    return bool(np.hypot(jump[0], jump[1]) > cfg.confirm_beyond_m or abs(jump[2]) > cfg.confirm_beyond_rad)


def confirm(
    pending: Pending | None, result: Relocalization, pose: np.ndarray, step: int, cfg: RelocalizationConfig
) -> tuple[bool, Pending]:
    """Whether ``result`` (found with the estimate at ``pose (3,)``) may be injected: a small
    correction at once, a large one only if it repeats the ``pending``
    correction — a hypothesis of it within ``confirm_m``/``confirm_rad`` of where that correction
    puts the estimate now — and the new pending correction (this result's best)."""
    new = Pending(compose(result.poses[0], inverse(pose)), step)
    if cfg.confirm_steps <= 0 or not is_large(result, pose, cfg):
        return True, new
    if pending is None or step - pending.step > cfg.confirm_steps:
        return False, new
    d = relative(compose(pending.correction, pose), result.poses)
    agree = (np.hypot(d[:, 0], d[:, 1]) <= cfg.confirm_m) & (np.abs(d[:, 2]) <= cfg.confirm_rad)
    return bool(np.any(agree)), new


def inject(
    ps: ParticleSet, reloc: Relocalization, young_since: int | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Replace the weakest particles by the hypotheses, with the best particle's map and an
    even weight. Elements born at or after step ``young_since`` were mapped from the drifted
    estimate: in each injected map they move with the pose (the correction that takes the best
    particle's pose onto the hypothesis), as a loop closure moves the recent part of a map.
    Returns ``(targets, sources)`` particle indices."""
    best = ps.best()
    order = np.argsort(ps.log_weights)
    targets = order[order != best][: len(reloc.poses)]
    sources = np.full(len(targets), best)
    src = ps.take(sources)
    ps.poses[targets] = reloc.poses[: len(targets)]
    ps.slip[targets] = src.slip
    ps.slip_cov[targets] = src.slip_cov
    for k, v in ps.maps.arrays().items():
        v[targets] = getattr(src.maps, k)
    if young_since is not None:
        _move_young(ps.maps, targets, compose(ps.poses[targets], inverse(ps.poses[best])), young_since)
    ps.log_weights[targets] = ps.log_weights[best]
    ps.normalize()
    return targets, sources


def relocalize_global(
    pose: np.ndarray,
    gm: GlobalMap,
    segs: ScanSegments,
    facing: np.ndarray,
    cfg: RelocalizationConfig,
    rays: ScanRays | None,
    far_m: float,
    far_rad: float,
    pair_gap_m: float,
    min_share: float,
) -> Relocalization | None:
    """Where in the whole map the scan is, when the robot may have been moved without odometry
    seeing it (kidnapping): hypotheses against every reliable element (no search radius, no jump
    bound, no age: the map is the one from before the doubt, kept unchanged since), the best one
    farther than ``far_m`` / ``far_rad`` from the estimate ``pose (3,)`` (closer ones are tracking,
    the proposal's job), explaining ``min_score_m`` of the scan and ``score_gain_m`` more than the
    estimate, unique by ``unique_ratio`` against every distinct rival (the estimate included) and,
    given ``rays``, its beams through no more reliable elements than the estimate's; or None.
    Map pairs of segments up to ``pair_gap_m`` apart fix hypotheses; the best must explain
    ``min_share`` of the scan's segment length (the place it is in, not an alike corridor of it)."""
    reliable = _reliable(gm, cfg)
    if reliable.sum() < cfg.min_old_elements or len(segs) == 0:
        return None
    # the whole map: its long walls' corners too, where one ends on another's middle, and walls
    # across a door from each other (``pair_gap_m``)
    mc = dataclasses.replace(cfg.matching, gap_to_segment=True, max_pair_gap_m=pair_gap_m)
    scored = _scored(pose, segs, facing, gm.seg[reliable], gm.facing[reliable], mc)
    if scored is None:
        return None
    hyp, scores, current = scored
    d = relative(pose, hyp)
    far = (np.hypot(d[:, 0], d[:, 1]) > far_m) | (np.abs(d[:, 2]) > far_rad)
    length = float(segment_lengths(segs.endpoints).sum())
    good = far & (scores >= max(cfg.min_score_m, min_share * length)) & (scores >= current + cfg.score_gain_m)
    if not np.any(good):
        return None
    return _pick(pose, hyp, scores, current, good, cfg, rays, gm, reliable)


def _reliable(gm: GlobalMap, cfg: RelocalizationConfig) -> np.ndarray:
    """The map's elements seen often enough and trusted enough to relocalize against."""
    return (gm.hits >= cfg.min_hits) & (gm.trust >= cfg.min_trust)


def _scored(
    pose: np.ndarray, segs: ScanSegments, facing: np.ndarray, map_ends: np.ndarray,
    map_facing: np.ndarray, mc: MatchingConfig,
) -> tuple[np.ndarray, np.ndarray, float] | None:  # fmt: skip
    """The scan's pose hypotheses against the map elements ``map_ends``, their overlap scores and
    the estimate ``pose``'s; None without a hypothesis."""
    hyp = pose_hypotheses(segs.endpoints, facing, map_ends, map_facing, mc)
    if len(hyp) == 0:
        return None
    scores = overlap_scores(np.vstack([pose, hyp]), segs.endpoints, facing, map_ends, map_facing, mc)
    return hyp, scores[1:], float(scores[0])


def _pick(
    pose: np.ndarray,
    hyp: np.ndarray,
    scores: np.ndarray,
    current: float,
    good: np.ndarray,
    cfg: RelocalizationConfig,
    rays: ScanRays | None,
    gm: GlobalMap,
    elements: np.ndarray,
) -> Relocalization | None:
    """The ``good`` hypotheses to inject, best first, when the best of them is unique and (given
    ``rays``) its beams pass through no more of the map's ``elements`` (mask) than the
    estimate's; else None (the place is ambiguous: wait)."""
    best = int(np.argmax(np.where(good, scores, -np.inf)))
    if not _unique(hyp, scores, best, pose, current, cfg):
        return None
    hyp, scores = hyp[good], scores[good]
    if rays is not None:
        seg, alpha, facing = gm.seg[elements], gm.alpha[elements], gm.facing[elements]
        through = through_counts(np.vstack([pose, hyp]), seg, alpha, facing, rays)
        ok = through[1:] <= through[0] + cfg.max_extra_through
        if not ok[np.argmax(scores)]:  # the best is refuted
            return None
        hyp, scores = hyp[ok], scores[ok]
    keep = cluster_poses(hyp, scores, 0.2, np.radians(3.0))[: cfg.inject]
    return Relocalization(hyp[keep], scores[keep], current)
