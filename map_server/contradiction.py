"""Negative evidence for a placement: walls where another robot's laser saw free space.

A matcher scores what agrees (overlap of walls); a building symmetric under a half turn, or with
identical aisles, offers a mirror image that agrees about as well as the truth — the simulated
warehouse's routes are half-turn images of each other, and only pallets a metre apart tell them
apart. What a wrong place cannot hide is the disagreement: under it, some of the robot's walls
land in space the placed robots' lasers saw through, or the placed walls in space the robot saw
through (the acceptance index of occupancy-grid merging, Birk and Carpin 2006, on segments and
free-space polygons).

Pure: the robots' free space comes in as shapely geometry in each map frame
(``freespace.FreeSpaces.area``, placed with ``freespace.place_area``); nothing here does I/O.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import shapely

from shared.geometry import apply_segments, inverse, sample_segments


@dataclass(frozen=True)
class ContradictionConfig:
    # Off by default: measured (bench_merge.py, bench_demo.py --logs, 2026-11-28) it turns the
    # simulated warehouse's 15 half-turned merges in 10 seeds into unplaced robots, but the real
    # logs' pieces (Intel, ACES, MIT-CSAIL cut in 3) see their true places contradicted by 28-89 m
    # of wall and stay unplaced (1/3 placed each, against 3/3, 3/3, 1/3 without it). Not counting
    # free space within 0.6 m of the map's own walls kept Intel's pieces contradicted (28-56 m) and
    # let 10 of the warehouse's mirror images through (their pallets stand a metre off): removed.
    enabled: bool = False
    margin_m: float = 0.3  # free space is shrunk by this much first (its edges are walls seen,
    # ranges and the maps' drift move them by centimetres to a decimetre)
    step_m: float = 0.1  # walls are sampled this densely
    # a placement is refused when this much wall (both ways) contradicts and this share of the
    # overlap matched (bench_merge.py, office and warehouse, 10 seeds: true places 0.0-2.1 m at
    # 48-251 m matched, the warehouse's half-turned ones 3.4-10 m at 100-230 m)
    max_m: float = 2.0
    max_share: float = 0.02


def shrink(area, margin_m: float):
    """``area`` shrunk by ``margin_m``, prepared for point queries; None (or nothing left): None."""
    if area is None or area.is_empty:
        return None
    out = area.buffer(-margin_m, join_style="mitre")
    if out.is_empty:
        return None
    shapely.prepare(out)
    return out


def inside_m(area, seg: np.ndarray, step_m: float) -> float:
    """Length of ``seg (N,2,2)`` inside (prepared) ``area``, sampled every ``step_m``."""
    if area is None or not len(seg):
        return 0.0
    pts, _, w = sample_segments(seg, step_m)
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
    frame) — each as :func:`shrink` gives it. Either may be None (not known: no evidence)."""
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


def veto(
    robot_seg: np.ndarray, robot_free, placed_seg: np.ndarray, placed_free, cfg: ContradictionConfig
) -> Callable[[np.ndarray, float], str | None]:
    """What ``alignment.estimate_alignment`` takes as ``veto``: ``(pose, matched_m)`` -> why the
    place is contradicted (:func:`refused`), or None. Free spaces as :func:`shrink` gives them."""

    def why(pose: np.ndarray, matched_m: float) -> str | None:
        m = contradiction_m(pose, robot_seg, robot_free, placed_seg, placed_free, cfg)
        return f"{m:.1f} m of walls where free space was seen" if refused(m, matched_m, cfg) else None

    return why
