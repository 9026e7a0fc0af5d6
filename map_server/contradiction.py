"""Negative evidence for a placement: walls where another robot's laser saw free space.

A matcher scores what agrees (overlap of walls); a building symmetric under a half turn, or with
identical aisles, offers a mirror image that agrees about as well as the truth — the simulated
warehouse's routes are half-turn images of each other, and only pallets a metre apart tell them
apart. What a wrong place cannot hide is the disagreement: under it, some of the robot's walls
land in space the placed robots' lasers saw through, or the placed walls in space the robot saw
through (the acceptance index of occupancy-grid merging, Birk and Carpin 2006, on segments and
free-space polygons).

Pure: the robots' free space comes in as shapely geometry in each map frame
(``freespace.FreeSpaces.area``); nothing here does I/O.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import shapely
from shapely import affinity

from shared.geometry import apply_segments, inverse


@dataclass(frozen=True)
class ContradictionConfig:
    # Off by default: measured (bench_merge.py, bench_demo.py --logs, 2026-11-28) it turns the
    # simulated warehouse's 15 half-turned merges in 10 seeds into unplaced robots, but the real
    # logs' pieces (Intel, ACES, MIT-CSAIL cut in 3) see their true places contradicted by 28-89 m
    # of wall and stay unplaced (1/3 placed each, against 3/3, 3/3, 1/3 without it).
    enabled: bool = False
    margin_m: float = 0.3  # free space is shrunk by this much first (its edges are walls seen,
    # ranges and the maps' drift move them by centimetres to a decimetre)
    step_m: float = 0.1  # walls are sampled this densely
    near_wall_m: float = 0.0  # free space this close to the map's own walls is no evidence (two
    # maps bent apart put a wall beside the other's, not across its free space); 0.6 m kept the
    # real logs' pieces contradicted (Intel: 28-56 m) and let 10 of the warehouse's mirror images
    # through (their pallets stand a metre off)
    # a placement is refused when this much wall (both ways) contradicts and this share of the
    # overlap matched (bench_merge.py, office and warehouse, 10 seeds: true places 0.0-2.1 m at
    # 48-251 m matched, the warehouse's half-turned ones 3.4-10 m at 100-230 m)
    max_m: float = 2.0
    max_share: float = 0.02


def shrink(area, margin_m: float, walls: np.ndarray | None = None, near_m: float = 0.0):
    """``area`` shrunk by ``margin_m``, less what lies within ``near_m`` of ``walls (N,2,2)``
    (same frame), prepared for point queries; None stays None."""
    if area is None or area.is_empty:
        return None
    out = area.buffer(-margin_m, join_style="mitre")
    if walls is not None and len(walls) and near_m > 0 and not out.is_empty:
        lines = shapely.multilinestrings(np.asarray(walls, float).reshape(-1, 2, 2))
        out = out.difference(lines.buffer(near_m, cap_style="flat", quad_segs=2))
    if out.is_empty:
        return None
    shapely.prepare(out)
    return out


def moved(area, pose: np.ndarray):
    """``area`` with its frame placed at ``pose (3,)``."""
    c, s = np.cos(pose[2]), np.sin(pose[2])
    return affinity.affine_transform(area, [c, -s, s, c, pose[0], pose[1]])


def samples(seg: np.ndarray, step_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Points along ``seg (N,2,2)`` every ``step_m`` at most, and the length each stands for."""
    seg = np.asarray(seg, float).reshape(-1, 2, 2)
    if not len(seg):
        return np.zeros((0, 2)), np.zeros(0)
    length = np.linalg.norm(seg[:, 1] - seg[:, 0], axis=1)
    n = np.maximum(1, np.ceil(length / step_m).astype(int))
    owner = np.repeat(np.arange(len(seg)), n)
    first = np.repeat(np.cumsum(n) - n, n)
    u = (np.arange(len(owner)) - first + 0.5) / n[owner]
    pts = seg[owner, 0] + u[:, None] * (seg[owner, 1] - seg[owner, 0])
    return pts, (length / n)[owner]


def inside_m(area, seg: np.ndarray, step_m: float) -> float:
    """Length of ``seg`` inside (prepared) ``area``."""
    if area is None or not len(seg):
        return 0.0
    pts, w = samples(seg, step_m)
    return float(w[shapely.contains_xy(area, pts[:, 0], pts[:, 1])].sum())


def contradiction_m(
    pose: np.ndarray,
    robot_seg: np.ndarray,
    robot_free,
    placed_seg: np.ndarray,
    placed_free,
    cfg: ContradictionConfig,
) -> float:
    """Metres of wall that contradict the robot's map frame at ``pose``: the robot's walls
    ``robot_seg`` (its frame) inside the placed robots' free space ``placed_free`` (global), plus
    the placed walls ``placed_seg`` (global) inside the robot's free space ``robot_free`` (its
    frame) — each as :func:`shrink` gives it, away from its own map's walls. Either may be None
    (not known: no evidence)."""
    pose = np.asarray(pose, float)
    out = inside_m(placed_free, apply_segments(pose, robot_seg), cfg.step_m)
    if robot_free is not None and len(placed_seg):
        local = apply_segments(inverse(pose), placed_seg)
        lo, hi = np.array(robot_free.bounds[:2]), np.array(robot_free.bounds[2:])
        near = ((local.max(axis=1) >= lo) & (local.min(axis=1) <= hi)).all(axis=1)
        out += inside_m(robot_free, local[near], cfg.step_m)
    return out


def refused(contradicted_m: float, matched_m: float, cfg: ContradictionConfig) -> bool:
    """Whether that much contradiction refuses a placement that matched ``matched_m``."""
    return contradicted_m > max(cfg.max_m, cfg.max_share * matched_m)
