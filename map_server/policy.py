"""The merge policy: when a robot's alignment verdict is acted on. Conservative, since a wrong
merge ruins the fused map while "unaligned" only delays it (fleet.py's module docstring): a robot
without a prior is matched only once the maps involved are mature (or, before, when nothing the
robots saw contradicts the place found: ``quiet``), and a new place (or a
revision of one) counts only once ``confirmations`` attempts in a row put the robot there. The
rounds (placing.py) decide *which* robots get an attempt and in what order (the most decisive
first); this module decides what an attempt's verdict means."""

from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING

from map_server.alignment import Alignment
from map_server.candidates import mean_displacement

if TYPE_CHECKING:
    from map_server.config import FleetConfig
    from map_server.state import RobotState


def contradicts_self(noise_m: float | None, limit_m: float) -> bool:
    """Whether a map's own contradiction (its walls in its own free space, m) is known and beyond
    ``limit_m`` (``graph.consistent_self_m``: a real log's piece, its path bent)."""
    return noise_m is not None and noise_m > limit_m


def agrees(noise_m: float | None, limit_m: float) -> bool:
    """Whether a map's own contradiction (None: not known) is within ``limit_m``."""
    return noise_m is not None and noise_m <= limit_m


def waiting(cfg: FleetConfig) -> str:
    """The reason an unplaced robot without a prior shows while the maps are not mature."""
    return f"waiting for mature maps (grown by at most {cfg.mature_growth:.0%} in {cfg.mature_window_s:g} s)"


def mature(robots: list[RobotState], now_s: float, cfg: FleetConfig) -> bool:
    """Whether every one of ``robots``' maps grew by at most ``mature_growth`` over the last
    ``mature_window_s`` (a young map's match is not evidence yet)."""
    return all(r.mature(now_s, cfg.mature_window_s, cfg.mature_growth) for r in robots)


def quiet(a: Alignment, cfg: FleetConfig) -> bool:
    """Whether a verdict found on young maps counts all the same: its place is checked against
    the free space seen, where both sides saw enough of it, and nothing contradicts it. A mirror
    image of a young map matches as well as the truth but puts some wall where a laser saw through
    (contradiction.py); a real map contradicts itself anyway (a door open once, people), so its
    verdicts wait for maturity."""
    return (
        cfg.young_max_contradicted_m >= 0.0
        and a.contradicted_m is not None
        and a.contradicted_m <= cfg.young_max_contradicted_m
        and a.seen_m2 >= cfg.young_min_seen_m2
    )


def young(a: Alignment, cfg: FleetConfig) -> Alignment:
    """What a verdict found on young maps means: itself when it is not a place or is ``quiet``,
    else "unaligned" saying why it waits (the place found, and what contradicts it)."""
    if a.status != "aligned" or quiet(a, cfg):
        return a
    found = f"the place found ({a.reason.removeprefix('matched: ')})"
    if a.contradicted_m is None:
        found += " not checked against the free space seen"
    else:
        found += f": {a.contradicted_m:.1f} m of wall contradicted over {a.seen_m2:.0f} m2 seen by both"
    return dataclasses.replace(a, status="unaligned", reason=f"{waiting(cfg)}; {found}")


def moved(r: RobotState, a: Alignment, b: Alignment, cfg: FleetConfig) -> bool:
    """Whether ``a`` and ``b`` put the robot's map at different places (its segments' midpoints
    moved more than ``same_place_m`` on average)."""
    pts = 0.5 * (r.layer.seg[:, 0] + r.layer.seg[:, 1])
    return mean_displacement(a.transform, b.transform, pts) > cfg.same_place_m


def confirm(
    r: RobotState,
    a: Alignment,
    current: Alignment | None,
    cfg: FleetConfig,
    now_s: float,
    young: bool = False,
) -> Alignment:
    """A new alignment (or a revision) counts once ``confirmations`` attempts in a row put the
    robot at the same place over at least ``confirm_s`` (a young map's mirror image holds for a
    few seconds of growth, then the matcher refuses it; the truth stays); until then the robot
    stays unaligned (or where it was, ``current``). A ``young`` verdict (one that is ``quiet``)
    over at least ``young_once_seen_m2`` of free space seen by both needs ``young_confirmations``:
    the free-space check is the second test the repetition stands for. Keeps the count on ``r``
    (``pending``, ``pending_count``, ``pending_s``)."""
    once = young and a.seen_m2 >= cfg.young_once_seen_m2
    needed = cfg.young_confirmations if once else cfg.confirmations
    same = r.pending is not None and not moved(r, r.pending, a, cfg)
    r.pending_count = r.pending_count + 1 if same else 1
    if not same:
        r.pending_s = now_s
    r.pending = a
    held = now_s - r.pending_s
    if r.pending_count >= needed and held >= cfg.confirm_s:
        r.pending, r.pending_count = None, 0
        return a
    count = f"{r.pending_count}/{needed}, {held:.0f}/{cfg.confirm_s:g} s"
    why = f"awaiting confirmation ({count}) of {a.reason}"
    if current is not None:
        c = current
        return Alignment("aligned", c.transform, c.sigma, c.score_m, c.inlier_share, c.rival_ratio, why)
    return Alignment("unaligned", a.transform, a.sigma, a.score_m, a.inlier_share, a.rival_ratio, why)
