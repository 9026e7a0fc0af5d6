"""Joining a fleet whose fused map exists (``fleet-slam agent … --join``; issue 21, item 3).

A robot that starts where the fleet has mapped need not map from scratch and wait until its own
map is big enough for the server to match: it takes the fused map by query, finds where it is in
it with the report's geometric relocalization (§6: pose hypotheses from pairs of non-parallel
segments — corners and near-corners — scored by how much of the observation lies on the map), and
from then on its map frame is tied to the fused map's global frame by the transform found. It
sends that transform with its map (``RobotMap.prior`` with ``joined``): the server places it there
at once after checking it against the fused map (map_server/fleet.py), and its new walls join the
fused map from its first published map on.

The observation is the robot's own map so far, seen from its current pose (the filter's map is a
scan of a few seconds, with more walls than one scan: fewer look-alike places). A transform is
taken only when

- the best place explains ``min_score_m`` of the robot's map and ``min_share`` of its length;
- it beats every distinct place (farther than ``distinct_m`` / ``distinct_rad``) by
  ``unique_ratio``: a symmetric building offers its mirror image, which scores alike until the
  robot has seen what tells the halves apart;
- a later attempt (``every_s`` on) finds the same transform again (within ``confirm_m`` /
  ``confirm_rad``): the map grew in between, and a look-alike rarely survives that.

If no transform is taken within ``window_s`` of the robot's start, the robot maps on its own and
the server merges it as any robot (by matching, once its map is mature).

Pure numpy: the agent (robot_agent/service.py) fetches the fused map and feeds this its filter's
map and pose.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from robot_agent.sim.lidar import cast_rays
from robot_agent.slam.relocalize import ScanRays
from shared.geometry import apply_segments, compose, inverse, relative, segment_lengths
from shared.matching import MatchingConfig, cluster_poses, overlap_scores, pose_hypotheses


def _matching() -> MatchingConfig:
    # the fused map as a whole: a wall ending on another's middle (a T) is a pair too, and so are
    # walls across a door from each other
    return MatchingConfig(gap_to_segment=True, max_pair_gap_m=1.5, obs_max_pair_gap_m=1.5)


@dataclass(frozen=True)
class JoinConfig:
    window_s: float = 60.0  # source seconds from the robot's start spent trying to join
    every_s: float = 1.0  # between attempts
    min_hits: int = 2  # the robot's own map elements seen this often take part
    min_score_m: float = 5.0  # the best place explains at least this much of the robot's map ...
    min_share: float = 0.9  # ... and this share of its length (the robot is where the fleet mapped)
    unique_ratio: float = 1.3  # ... beating every distinct place by this factor
    distinct_m: float = 1.0  # places farther apart than this (or turned more) are distinct
    distinct_rad: float = np.radians(10.0)
    confirm_m: float = 0.25  # the next attempt must find the transform again within this ...
    confirm_rad: float = np.radians(3.0)  # ... and this
    max_through: float = 0.05  # a place where more of the scan's beams than this share pass
    # through fused walls (by through_m or more) is contradicted: set aside, as the best and as a rival
    through_m: float = 0.3
    places: int = 8  # distinct places (clusters of hypotheses) checked against the scan's beams
    max_hypotheses: int = 400  # the most voted-for hypotheses scored (bins of vote_m, vote_rad)
    vote_m: float = 0.2
    vote_rad: float = np.radians(2.0)
    sigma: tuple[float, float, float] = (0.25, 0.25, float(np.radians(3.0)))  # sent with the transform
    matching: MatchingConfig = field(default_factory=_matching)


@dataclass(frozen=True)
class Attempt:
    """One localization: ``transform (3,)`` (the robot's map frame in the fused map's frame) of
    the best place, ``score_m`` the robot map's length it explains, ``share`` of the whole,
    ``rival_m`` the best distinct place's score, ``ok`` whether it passes, ``reason`` why (not)."""

    transform: np.ndarray
    score_m: float
    share: float
    rival_m: float
    ok: bool
    reason: str


def facing_of(seg: np.ndarray) -> np.ndarray:
    """The facing angles ``(N,)`` of directed segments ``(N,2,2)`` (the left normal of p0 → p1:
    the side the sensor saw the wall from, shared/messages.py)."""
    d = seg[:, 1] - seg[:, 0]
    return np.arctan2(d[:, 1], d[:, 0]) + np.pi / 2


def through_share(poses: np.ndarray, fused_seg: np.ndarray, rays: ScanRays, through_m: float) -> np.ndarray:
    """``(H,)``: the share of the scan's beams that pass through a fused wall by ``through_m`` or
    more when cast from each robot pose of ``poses (H,3)`` (a reading at or beyond the usable
    range passes through every wall before it)."""
    laser = compose(np.asarray(poses, float).reshape(-1, 3), rays.laser_offset)
    measured = np.minimum(np.asarray(rays.ranges_m, float), rays.usable_range_m)
    ok = np.isfinite(measured) & (measured > 0)
    if not ok.any():
        return np.zeros(len(laser))
    angles = laser[:, 2:3] + np.asarray(rays.angles_rad, float)[None, ok]
    expected = cast_rays(laser[:, :2], angles, fused_seg, rays.usable_range_m)
    return np.mean(measured[None, ok] > expected + through_m, axis=1)


def locate(
    fused_seg: np.ndarray,
    own_seg: np.ndarray,
    own_facing: np.ndarray,
    pose: np.ndarray,
    cfg: JoinConfig,
    rays: ScanRays | None = None,
) -> Attempt:
    """Where the robot's map ``own_seg (N,2,2)`` (facing ``own_facing (N,)``, in its map frame;
    the robot at ``pose (3,)`` there) lies in the fused map ``fused_seg (M,2,2)`` (directed).
    Given the current scan's ``rays``, a place where its beams pass through fused walls is set
    aside (as the best and as a rival)."""
    none = np.zeros(3)
    length = float(segment_lengths(own_seg).sum()) if len(own_seg) else 0.0
    if length < cfg.min_score_m:
        return Attempt(none, 0.0, 0.0, 0.0, False, f"own map only {length:.1f} m long")
    to_robot = inverse(np.asarray(pose, float))
    obs = apply_segments(to_robot, own_seg)
    obs_facing = own_facing - pose[2]
    fused_facing = facing_of(fused_seg)
    hyp = pose_hypotheses(obs, obs_facing, fused_seg, fused_facing, cfg.matching)
    if len(hyp) == 0:
        return Attempt(none, 0.0, 0.0, 0.0, False, "no corner correspondences")
    # every correct pair of pairs votes for the true place: score the most voted-for bins only
    bins = np.column_stack([np.round(hyp[:, :2] / cfg.vote_m), np.round(hyp[:, 2] / cfg.vote_rad)])
    _, first, votes = np.unique(bins.astype(np.int64), axis=0, return_index=True, return_counts=True)
    hyp = hyp[first[np.argsort(-votes, kind="stable")[: cfg.max_hypotheses]]]
    scores = overlap_scores(hyp, obs, obs_facing, fused_seg, fused_facing, cfg.matching)
    keep = cluster_poses(hyp, scores, cfg.distinct_m, cfg.distinct_rad, cfg.places)
    hyp, scores = hyp[keep], scores[keep]  # distinct places, best first
    aside = ""
    if rays is not None:
        through = through_share(hyp, fused_seg, rays, cfg.through_m)
        bad = through > cfg.max_through
        if bad.all():
            why = f"the best {len(hyp)} places all contradicted by the scan (min {through.min():.0%})"
            return Attempt(compose(hyp[0], to_robot), float(scores[0]), 0.0, 0.0, False, why)
        if bad.any():
            aside = f", {int(bad.sum())} better place(s) contradicted by the scan" if bad[0] else ""
        hyp, scores = hyp[~bad], scores[~bad]
    score = float(scores[0])
    rival = float(scores[1]) if len(scores) > 1 else 0.0
    transform = compose(hyp[0], to_robot)
    share = score / length
    if score < cfg.min_score_m or share < cfg.min_share:
        why = f"best place explains {score:.1f} m ({share:.0%}) of {length:.1f} m{aside}"
        return Attempt(transform, score, share, rival, False, why)
    if score < cfg.unique_ratio * rival:
        why = f"ambiguous: {score:.1f} m against {rival:.1f} m elsewhere{aside}"
        return Attempt(transform, score, share, rival, False, why)
    why = f"explains {score:.1f} m ({share:.0%}) of its map, next best place {rival:.1f} m{aside}"
    return Attempt(transform, score, share, rival, True, why)


class Joiner:
    """The attempts of one robot's start: :meth:`step` with the filter's map and pose until it
    returns the transform (found twice in a row), or :attr:`given_up` (``window_s`` passed)."""

    def __init__(self, fused_seg: np.ndarray, cfg: JoinConfig = JoinConfig()):
        self.fused = np.asarray(fused_seg, float).reshape(-1, 2, 2)
        self.cfg = cfg
        self.start_s: float | None = None
        self.next_s = -np.inf
        self.last: Attempt | None = None  # the latest attempt (its reason is the join's state)
        self.candidate: np.ndarray | None = None  # a transform found once, to be found again
        self.transform: np.ndarray | None = None  # taken: the robot's map frame in the fused frame
        self.given_up = False
        self.attempts = 0

    @property
    def done(self) -> bool:
        return self.transform is not None or self.given_up

    def due(self, stamp_s: float) -> bool:
        """Whether an attempt is due at ``stamp_s`` (the first call starts the window; past the
        window the join is given up)."""
        if self.done:
            return False
        if self.start_s is None:
            self.start_s = stamp_s
        if stamp_s - self.start_s > self.cfg.window_s:
            self.given_up = True
            return False
        return stamp_s >= self.next_s

    def step(
        self,
        stamp_s: float,
        own_seg: np.ndarray,
        own_facing: np.ndarray,
        pose: np.ndarray,
        rays: ScanRays | None = None,
    ) -> bool:
        """One attempt when due (the filter's map, its pose and the current scan); True when the
        transform is taken now."""
        if not self.due(stamp_s):
            return False
        self.next_s = stamp_s + self.cfg.every_s
        self.attempts += 1
        a = self.last = locate(self.fused, own_seg, own_facing, pose, self.cfg, rays)
        if not a.ok:
            self.candidate = None
            return False
        c = self.candidate
        if c is not None:
            d = relative(c, a.transform)
            if np.hypot(d[0], d[1]) <= self.cfg.confirm_m and abs(d[2]) <= self.cfg.confirm_rad:
                self.transform = a.transform
                return True
        self.candidate = a.transform
        return False
