"""Candidate frames of a robot map in the placed map: corner hypotheses, votes, refined scores.

1. hypotheses: every pair of non-parallel, nearby segments of the robot map (a corner or a
   near-corner) against every such pair of the placed map whose relative angle agrees fixes a
   pose (shared/matching.py — report §6's geometry, on whole maps instead of one scan);
2. votes: the hypotheses are binned in (x, y, θ) on two grids half a cell apart; the densest
   bins, one per neighbourhood, are the candidates (a true overlap makes many corners agree);
3. each candidate is pre-scored by the robot-map length it lays on the placed map with generous
   tolerances; the best are refined (point-to-line least squares) and scored strictly: length
   on placed walls minus length that contradicts them (registration.py).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from map_server.registration import MapIndex, Refined, Samples, refine
from shared.geometry import segment_directions, transform_points, wrap_angle
from shared.matching import cluster_poses, pose_hypotheses

if TYPE_CHECKING:
    from map_server.config import AlignmentConfig


@dataclass(frozen=True, eq=False)
class Scored:
    """A candidate pose with its evidence: ``matched_m`` robot length on placed walls,
    ``conflict_m`` length near placed walls but not on them, ``net`` the score compared between
    candidates; ``refined`` is None for a candidate only pre-scored (then ``net`` is generous)."""

    pose: np.ndarray
    matched_m: float
    conflict_m: float
    net: float
    refined: Refined | None


def facing_of(seg: np.ndarray) -> np.ndarray:
    """Facing angles ``(N,)`` of directed segments: the left normal of ``p0 → p1``."""
    return wrap_angle(segment_directions(seg) + 0.5 * np.pi)


def vote_peaks(hyp: np.ndarray, cell_m: float, cell_rad: float, max_peaks: int) -> tuple:
    """Candidate poses ``(C,3)`` and their votes ``(C,)``: the densest (x, y, θ) bins of the
    hypotheses ``(H,3)`` on two grids half a cell apart, one per neighbourhood, best first."""
    poses, votes = [], []
    for shift in (0.0, 0.5):
        k = np.floor(np.column_stack([hyp[:, :2] / cell_m, (hyp[:, 2] + np.pi) / cell_rad]) + shift)
        k = (k - k.min(axis=0)).astype(np.int64)
        span = k.max(axis=0) + 1
        key = (k[:, 0] * span[1] + k[:, 1]) * span[2] + k[:, 2]
        _, inv, cnt = np.unique(key, return_inverse=True, return_counts=True)
        inv = inv.reshape(-1)

        def mean(v: np.ndarray, inv=inv, cnt=cnt) -> np.ndarray:
            return np.bincount(inv, weights=v) / cnt

        theta = np.arctan2(mean(np.sin(hyp[:, 2])), mean(np.cos(hyp[:, 2])))
        poses.append(np.column_stack([mean(hyp[:, 0]), mean(hyp[:, 1]), theta]))
        votes.append(cnt)
    poses, votes = np.vstack(poses), np.concatenate(votes).astype(float)
    keep = cluster_poses(poses, votes, cell_m, cell_rad, max_peaks)
    return poses[keep], votes[keep]


def mean_displacement(a: np.ndarray, b: np.ndarray, points: np.ndarray) -> float:
    """Mean distance [m] between ``points (K,2)`` moved by pose ``a`` and by pose ``b``."""
    if len(points) == 0:
        return 0.0
    d = transform_points(a, points) - transform_points(b, points)
    return float(np.mean(np.hypot(d[:, 0], d[:, 1])))


def score(index: MapIndex, robot: Samples, pose: np.ndarray, cfg: AlignmentConfig, refined=None) -> Scored:
    """Strict evidence for ``pose``: matched and conflicting robot-map length and their masks."""
    on, near = index.evidence(pose, robot, cfg.score_perp_m, cfg.score_angle_rad, cfg.conflict_m)
    matched, conflict = float(robot.length[on].sum()), float(robot.length[near & ~on].sum())
    net = matched - cfg.conflict_weight * conflict
    return Scored(np.asarray(pose, float), matched, conflict, net, refined)


def refine_and_score(
    index: MapIndex, robot: Samples, coarse: Samples, pose: np.ndarray, cfg: AlignmentConfig, **prior
) -> Scored:
    """Refine on the coarse samples, score strictly on the fine ones."""
    r = refine(index, coarse, pose, cfg.refine_stages, cfg.point_sigma_m, cfg.correlation_m, **prior)
    return score(index, robot, r.pose, cfg, r)


def search(
    robot_seg, placed_seg, index: MapIndex, robot: Samples, coarse: Samples, cfg: AlignmentConfig
) -> list[Scored]:
    """Candidates from the vote peaks, best first: the best ``max_refined`` by pre-score refined
    and scored strictly, the rest with their generous pre-score — they still count as rivals."""
    hyp = pose_hypotheses(robot_seg, facing_of(robot_seg), placed_seg, facing_of(placed_seg), cfg.matching)
    if len(hyp) == 0:
        return []
    peaks = vote_peaks(hyp, cfg.vote_cell_m, cfg.vote_cell_rad, cfg.max_peaks)[0]
    pre = np.array([index.overlap(p, coarse, cfg.prescore_perp_m, cfg.prescore_angle_rad) for p in peaks])
    order = np.argsort(-pre, kind="stable")
    refined = [refine_and_score(index, robot, coarse, peaks[i], cfg) for i in order[: cfg.max_refined]]
    rest = [Scored(peaks[i], float(pre[i]), 0.0, float(pre[i]), None) for i in order[cfg.max_refined :]]
    return sorted(refined, key=lambda s: -s.net) + rest


def rival(best: Scored, others: list[Scored], points: np.ndarray, distinct_m: float) -> float:
    """The best net score among candidates that are a distinct place from ``best`` (they move the
    robot map's ``points`` more than ``distinct_m`` away on average)."""
    nets = [o.net for o in others if mean_displacement(o.pose, best.pose, points) > distinct_m]
    return max(nets, default=0.0)
