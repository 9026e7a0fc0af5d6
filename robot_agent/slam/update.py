"""Map update (report §4.2 "update element f with the information of e, else add e"), negative
evidence (elements the laser sees through), element weights (report §5) and map cleaning.

All functions work on a local copy of the map columns near the robot (``SegmentMaps`` of shape
``(P,C)``) and modify it in place.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from robot_agent.slam import kernels
from robot_agent.slam.association import Association, Observations
from robot_agent.slam.lines import interval_overlap, project_to_line
from robot_agent.slam.particles import SegmentMaps
from shared.geometry import wrap_angle


@dataclass(frozen=True)
class UpdateConfig:
    max_points: float = 2000.0  # moments are scaled down past this many points: old evidence fades
    quality_rate: float = 0.2  # EMA rate of an element's match quality
    initial_quality: float = 0.5
    miss_decay_on_hit: float = 0.5  # misses are multiplied by this on each match
    through_margin_m: float = 0.25  # a beam longer than the element by this much saw through it
    through_margin_rel: float = 0.05  # ... plus this share of the range
    min_incidence_rad: float = np.radians(25.0)  # grazing beams are not evidence
    through_miss: float = 1.0  # misses added when seen through
    unmatched_miss: float = 0.25  # misses added when fully in view and unmatched
    min_view_beams: int = 8  # "in view" only if the element spans this many beams (and not grazing)
    compiled: bool = True  # visibility() by the compiled kernel (kernels.py) when it is built


def merge_matches(
    maps: SegmentMaps, obs: Observations, assoc: Association, step: int, cfg: UpdateConfig
) -> None:
    """Merge every matched observation into its element: add moments, refit the line, extend."""
    p_idx, o_idx = np.nonzero(assoc.matched)
    if len(p_idx) == 0:
        return
    c_idx = assoc.index[p_idx, o_idx]
    np.add.at(maps.moments, (p_idx, c_idx), obs.moments[p_idx, o_idx])
    # fade old evidence: keep at most max_points (same centroid and scatter shape)
    n = maps.moments[p_idx, c_idx, 0]
    scale = np.minimum(1.0, cfg.max_points / np.maximum(n, 1.0))
    maps.moments[p_idx, c_idx] *= scale[:, None]
    # refit, and extend to the union of the old extent and every merged observation
    maps.refit_extend(p_idx, c_idx, obs.ends[p_idx, o_idx])
    q = np.exp(-0.5 * assoc.cost[p_idx, o_idx]).astype(np.float32)
    maps.quality[p_idx, c_idx] += cfg.quality_rate * (q - maps.quality[p_idx, c_idx])
    np.add.at(maps.hits, (p_idx, c_idx), 1)
    maps.last_seen[p_idx, c_idx] = step
    maps.misses[p_idx, c_idx] *= cfg.miss_decay_on_hit


def add_new(
    maps: SegmentMaps, obs: Observations, assoc: Association, step: int, cfg: UpdateConfig
) -> np.ndarray:
    """Add every observation left unmatched in some particle as a new element.

    One fresh column per such observation, shared by all particles that did not match it
    (column alignment, see particles.py). Returns the columns used ``(O_new,)``.
    """
    unmatched = ~assoc.matched  # (P,O)
    new_obs = np.flatnonzero(unmatched.any(axis=0))
    if len(new_obs) == 0:
        return new_obs
    cols = maps.free_columns(len(new_obs))
    rows = unmatched[:, new_obs]  # (P,K)
    p_idx, k_idx = np.nonzero(rows)
    c_idx, o_idx = cols[k_idx], new_obs[k_idx]
    maps.valid[p_idx, c_idx] = True
    maps.moments[p_idx, c_idx] = obs.moments[p_idx, o_idx]
    maps.alpha[p_idx, c_idx] = obs.alpha[p_idx, o_idx]
    maps.rho[p_idx, c_idx] = obs.rho[p_idx, o_idx]
    maps.facing[p_idx, c_idx] = obs.facing[p_idx, o_idx]
    maps.seg[p_idx, c_idx] = obs.ends[p_idx, o_idx]
    maps.hits[p_idx, c_idx] = 1
    maps.born[p_idx, c_idx] = step
    maps.last_seen[p_idx, c_idx] = step
    maps.misses[p_idx, c_idx] = 0.0
    maps.quality[p_idx, c_idx] = cfg.initial_quality
    return cols


# --- negative evidence ------------------------------------------------------------------------

# Points sampled along each element for the visibility test, as fractions of its extent.
VISIBILITY_SAMPLES = np.array([0.15, 0.5, 0.85])


def visibility(
    maps: SegmentMaps,
    laser_poses: np.ndarray,
    ranges_m: np.ndarray,
    angles_rad: np.ndarray,
    usable_range_m: float,
    cfg: UpdateConfig,
) -> tuple[np.ndarray, np.ndarray]:
    """What the scan says about each element from each particle's laser pose ``(P,3)``.

    Returns ``through (P,C)`` — number of sample points the beams passed through (the element
    should have stopped them) — and ``in_view (P,C)`` — all sample points inside the field of
    view and range, seen from the element's free side and not at a grazing angle, with the beam
    ending at the element (it was visible and unoccluded), the element spanning at least
    ``cfg.min_view_beams`` beams: a scan that could not have made a segment of it is no miss.
    """
    a0, da = angles_rad[0], (angles_rad[-1] - angles_rad[0]) / max(len(angles_rad) - 1, 1)
    if cfg.compiled and kernels.AVAILABLE:  # the same tests, compiled
        return kernels.visibility(
            maps.seg,
            maps.alpha,
            maps.facing,
            maps.valid,
            laser_poses,
            ranges_m,
            VISIBILITY_SAMPLES,
            a0,
            da,
            usable_range_m,
            np.sin(cfg.min_incidence_rad),
            cfg.through_margin_m,
            cfg.through_margin_rel,
            cfg.min_view_beams * abs(da),
        )
    t = VISIBILITY_SAMPLES[None, None, :, None]
    pts = maps.seg[:, :, None, 0, :] * (1 - t) + maps.seg[:, :, None, 1, :] * t  # (P,C,3,2)
    rel = pts - laser_poses[:, None, None, :2]
    dist = np.hypot(rel[..., 0], rel[..., 1])
    bearing = wrap_angle(np.arctan2(rel[..., 1], rel[..., 0]) - laser_poses[:, None, None, 2])
    beam = np.rint((bearing - a0) / da).astype(int)
    inside = (beam >= 0) & (beam < len(angles_rad)) & (dist < usable_range_m) & (dist > 0.1)
    measured = ranges_m[np.clip(beam, 0, len(angles_rad) - 1)]
    has_return = np.isfinite(measured) & (measured < usable_range_m)
    # incidence: angle between the beam and the element's normal
    normal = np.stack([np.cos(maps.alpha), np.sin(maps.alpha)], axis=-1)[:, :, None, :]
    cos_inc = np.abs(np.sum(normal * rel, axis=-1)) / np.maximum(dist, 1e-9)
    steep = cos_inc > np.sin(cfg.min_incidence_rad)
    margin = cfg.through_margin_m + cfg.through_margin_rel * dist
    seen_through = inside & steep & ((measured > dist + margin) | ~has_return) & maps.valid[..., None]
    # the sensor must be on the element's free side: the far face of a thin wall (0.15 m behind
    # the near face, inside the margin) is not "in view and missed" from the near side
    front = np.cos(maps.facing)[..., None] * rel[..., 0] + np.sin(maps.facing)[..., None] * rel[..., 1] < 0
    ends_here = inside & front & steep & has_return & (np.abs(measured - dist) <= margin)
    # ... and wide enough in the scan that the extraction would have made a segment of it
    span = np.abs(wrap_angle(bearing[..., 2] - bearing[..., 0])) / (
        VISIBILITY_SAMPLES[2] - VISIBILITY_SAMPLES[0]
    )
    wide = span >= cfg.min_view_beams * abs(da)
    return seen_through.sum(axis=-1), np.all(ends_here, axis=-1) & wide & maps.valid


def apply_misses(
    maps: SegmentMaps, through: np.ndarray, in_view: np.ndarray, matched_cols: np.ndarray, cfg: UpdateConfig
) -> None:
    """Count misses: seen through (strong), or fully in view yet not matched this scan (weak)."""
    maps.misses += (cfg.through_miss * (through >= 2)).astype(np.float32)
    maps.misses += (cfg.unmatched_miss * (in_view & ~matched_cols)).astype(np.float32)


# --- element weights and cleaning ---------------------------------------------------------------


@dataclass(frozen=True)
class TrustConfig:
    hits_scale: float = 5.0  # hits for trust to reach 63 %
    age_scale_steps: float = 50.0  # age (scans) for trust to reach 63 %: older elements preferred
    miss_scale: float = 2.0  # misses that divide trust by e
    trusted_min: float = 0.3  # trust at or above which an element is "trusted" (published)
    trusted_min_hits: int = 3


def element_trust(maps: SegmentMaps, step: int, cfg: TrustConfig) -> np.ndarray:
    """Element weights ``(P,M)`` in [0, 1] (report §5): match quality, preference for older and
    more often confirmed elements, penalty for misses. 0 where invalid."""
    age = np.maximum(step - maps.born, 0).astype(float)
    w = (
        maps.quality
        * (1.0 - np.exp(-maps.hits / cfg.hits_scale))
        * (1.0 - np.exp(-(age + 1.0) / cfg.age_scale_steps))
        * np.exp(-maps.misses / cfg.miss_scale)
    )
    return np.where(maps.valid, w, 0.0)


def trusted_mask(maps: SegmentMaps, step: int, cfg: TrustConfig) -> np.ndarray:
    return (element_trust(maps, step, cfg) >= cfg.trusted_min) & (maps.hits >= cfg.trusted_min_hits)


@dataclass(frozen=True)
class CleaningConfig:
    max_misses: float = 3.0  # remove an element seen through / missed this often
    young_steps: int = 60  # an element still this young with ...
    young_min_hits: int = 2  # ... fewer hits, and out of view, was a one-off: remove it
    min_length_m: float = 0.2
    redundant_angle_rad: float = np.radians(4.0)
    redundant_perp_m: float = 0.08
    redundant_overlap_m: float = 0.05  # must overlap (or touch within this) to be merged
    compiled: bool = True  # the redundant pairs by the compiled kernel (kernels.py) when it is built


def clean(maps: SegmentMaps, step: int, cfg: CleaningConfig, recent: np.ndarray | None = None) -> None:
    """Remove bad elements and merge redundant ones (collinear, overlapping) — in place.

    ``recent (R,)`` limits the redundancy test to pairs with a recently touched column (only a
    new or extended element can have become redundant): ``(P,R,C)`` instead of ``(P,C,C)``.
    """
    length = np.hypot(*(maps.seg[..., 1, :] - maps.seg[..., 0, :]).transpose(2, 0, 1))
    age = step - maps.born
    bad = (maps.misses >= cfg.max_misses) | (length < cfg.min_length_m)
    bad |= (age > cfg.young_steps) & (maps.hits < cfg.young_min_hits)
    maps.valid &= ~bad
    _merge_redundant(maps, cfg, np.arange(maps.capacity) if recent is None else recent)


def _redundant_pairs(maps: SegmentMaps, cfg: CleaningConfig, recent: np.ndarray) -> np.ndarray:
    """``(P,C,R)``: column ``x`` and recent column ``r`` are both valid, distinct, face the same
    way, lie on one line and overlap (or touch)."""
    if cfg.compiled and kernels.AVAILABLE:  # the same tests, compiled
        return kernels.redundant_pairs(
            maps.valid, maps.seg, maps.alpha, maps.rho, maps.facing, recent,
            cfg.redundant_angle_rad, cfg.redundant_perp_m, -cfg.redundant_overlap_m,
        )  # fmt: skip
    fr, sr = maps.facing[:, recent], maps.seg[:, recent]
    da = np.abs(wrap_angle(maps.facing[:, :, None] - fr[:, None, :]))
    mid = 0.5 * (sr[..., 0, :] + sr[..., 1, :])
    a_x, r_x = maps.alpha[:, :, None], maps.rho[:, :, None]
    _, perp = project_to_line(mid[:, None, :, :], a_x, r_x)  # r's midpoint on x's line
    t_x, _ = project_to_line(maps.seg[:, :, None, :, :], a_x[..., None], r_x[..., None])
    t_r, _ = project_to_line(sr[:, None, :, :, :], a_x[..., None], r_x[..., None])
    overlap = interval_overlap(t_x, t_r)
    distinct = np.arange(maps.capacity)[:, None] != recent[None, :]
    return (
        maps.valid[:, :, None]
        & maps.valid[:, recent][:, None, :]
        & distinct
        & (da < cfg.redundant_angle_rad)
        & (np.abs(perp) < cfg.redundant_perp_m)
        & (overlap > -cfg.redundant_overlap_m)
    )


def _merge_redundant(maps: SegmentMaps, cfg: CleaningConfig, recent: np.ndarray) -> None:
    """Merge element j into i (i older) when they face the same way, lie on one line and
    overlap: one refitted element instead of two (report §4.2 "redundant elements").
    Pairs with at least one column in ``recent``, whichever of the two is the older."""
    c = maps.capacity
    if c < 2 or len(recent) == 0:
        return
    near = _redundant_pairs(maps, cfg, recent)  # (P,C,R): column x and recent column r alike
    born_x, born_r = maps.born[:, :, None], maps.born[:, recent][:, None, :]
    col_x, col_r = np.arange(c)[:, None], recent[None, :]
    x_older = (born_x < born_r) | ((born_x == born_r) & (col_x < col_r))
    # pair[p, i, j]: j is absorbed by the older i; built from both roles of the recent column
    pair = np.zeros((maps.n_particles, c, c), bool)
    pair[:, :, recent] |= near & x_older
    pair[:, recent, :] |= np.transpose(near & ~x_older, (0, 2, 1))
    # a column absorbed this round absorbs nothing itself
    absorbed = pair.any(axis=1)
    pair &= ~absorbed[:, :, None]
    p_idx, j_idx = np.nonzero(pair.any(axis=1))
    if len(p_idx) == 0:
        return
    i_idx = np.argmax(pair[p_idx, :, j_idx], axis=1)
    np.add.at(maps.moments, (p_idx, i_idx), maps.moments[p_idx, j_idx])
    np.add.at(maps.hits, (p_idx, i_idx), maps.hits[p_idx, j_idx])
    maps.valid[p_idx, j_idx] = False
    maps.refit_extend(p_idx, i_idx, maps.seg[p_idx, j_idx])
    maps.last_seen[p_idx, i_idx] = np.maximum(maps.last_seen[p_idx, i_idx], maps.last_seen[p_idx, j_idx])
