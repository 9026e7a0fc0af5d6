"""Geometric FastSLAM: the report's loop (§4.2, §5, §6), step by step, on particle arrays.

``FastSLAM.step(odometry, scan)`` per scan:

1. extract line segments from the scan (clusters → split-and-merge → TLS fits), robot frame;
2. propagate every particle through the slip-aware odometry model;
3. improved proposal: align the scan to each particle's own map, sample around the result;
4. ML association of every observed segment with its particle's map elements;
5. weight each particle by the association quality, minus contradictions (seen-through walls);
6. update matched elements (refit from moments), add the rest as new elements;
7. now and then: clean the maps (bad and redundant elements);
8. resample when the effective sample size drops;
9. now and then: build the cross-particle global map and refresh the particles' maps (§5);
10. at loop closure: inject particles at geometric pose hypotheses (§6).
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field

import numpy as np

from robot_agent.slam import consensus as consensus_mod
from robot_agent.slam import kernels
from robot_agent.slam import kidnap as kidnap_mod
from robot_agent.slam import relocalize as reloc_mod
from robot_agent.slam.association import AssociationConfig, associate, match_log_likelihood, observe
from robot_agent.slam.backend import BackendConfig
from robot_agent.slam.coarse import CoarseConfig, heading_offset
from robot_agent.slam.extraction import ExtractionConfig, ScanSegments, extract_segments, scan_points
from robot_agent.slam.lines import transform_lines, transform_moments
from robot_agent.slam.motion import (
    MotionConfig,
    odometry_increment,
    predict,
    sample_gaussian,
    slip_jacobian,
    update_slip,
    walk_slip,
)
from robot_agent.slam.particles import ParticleSet, SegmentMaps
from robot_agent.slam.proposal import MeasuredOdometry, ProposalConfig, align, align_points, draw_covariance
from robot_agent.slam.resampling import effective_sample_size, systematic_resample
from robot_agent.slam.trajectory import Trajectory, keyframe_of
from robot_agent.slam.update import (
    CleaningConfig,
    TrustConfig,
    UpdateConfig,
    add_new,
    apply_misses,
    clean,
    merge_matches,
    trusted_mask,
    visibility,
)
from shared.geometry import (
    apply_points,
    compose,
    inverse,
    point_segment_distance,
    relative,
    relative_one,
    wrap_angle,
)


@dataclass(frozen=True)
class WeightConfig:
    gain: float = 0.5  # likelihood temperature: < 1 smooths the weights (scan points correlate)
    log_p_new: float = -4.0  # log-likelihood of an observation that matches nothing (new element)
    through_penalty: float = 0.5  # per trusted element the scan sees through
    max_through_penalty: float = 10.0


# odometry that changes by less than this from one scan to the next has not changed (encoder
# ticks, not noise); after this many such scans in a row a bridged scan may drive a step
ODOMETRY_STANDS_M = 1e-4
ODOMETRY_STANDS_RAD = np.radians(0.01)
STOOD_SCANS = 2
STUCK_STEPS = 10  # the scans followed this many steps' worth (1 m, 50°) while odometry stood:
# a step is taken there (odometry that stalls and catches up, as real logs' does, stalls for less)
STUCK_FIT_M = 0.05  # and the scan fits the map within this much ...
STUCK_FIT_SHARE = 0.3  # ... with this share of its points at the aligned pose ...
STUCK_FIT_GAIN = 0.1  # ... and this much more than where odometry puts the robot


@dataclass(frozen=True)
class FilterConfig:
    ess_threshold: float = 0.5  # resample when ESS < this × P
    min_travel_m: float = 0.1  # process a scan only after this much motion ...
    min_turn_rad: float = np.radians(5.0)  # ... or this much turning (between, odometry bridges)
    local_margin_m: float = 3.0  # elements farther than the scan's reach plus this are not touched
    compiled: bool = True  # the local columns by the compiled kernel (kernels.py) when it is built
    clean_every: int = 5  # steps between map cleanings
    refine_bridged: bool = True  # align a bridged scan to the best particle's map (pose only):
    # its pose then comes from the scan, not from odometry whose timing may lag the laser's
    bridge_sigma_xy_m: float = 0.05  # extra prior std of a bridged scan's pose: odometry and
    bridge_sigma_theta_rad: float = np.radians(2.0)  # laser clocks disagree while turning fast
    max_open_steps: int = 4000  # every particle's own history kept this many steps back at most
    # (beyond, when the particles have not coalesced there, the best one's: trajectory.py)
    history_scans: int = 0  # the path kept for the newest this many scans (0: the whole run's);
    # a source without end sets it (robot_agent/service.py)
    # an odometry increment beyond this (between two scans) is checked against the scan: when the
    # scan fits the map where the robot was and not where odometry puts it, odometry jumped (a
    # glitch, an edited or broken log) and that increment is not used (0: never checked)
    odometry_jump_m: float = 2.0
    odometry_jump_rad: float = np.radians(120.0)
    # odometry unchanged from scan to scan while the bridged scans followed the robot STUCK_STEPS
    # steps' worth beyond it: odometry stood while the robot moved (a stuck wheel), and steps are
    # taken with the scans' motion until it moves again (:meth:`FastSLAM._stuck`)
    scan_driven_steps: bool = True


@dataclass(frozen=True)
class SlamConfig:
    particles: int = 30
    extraction: ExtractionConfig = field(default_factory=ExtractionConfig)
    motion: MotionConfig = field(default_factory=MotionConfig)
    association: AssociationConfig = field(default_factory=AssociationConfig)
    coarse: CoarseConfig = field(default_factory=CoarseConfig)  # heading search before the proposal
    proposal: ProposalConfig = field(default_factory=ProposalConfig)
    update: UpdateConfig = field(default_factory=UpdateConfig)
    weights: WeightConfig = field(default_factory=WeightConfig)
    trust: TrustConfig = field(default_factory=TrustConfig)
    cleaning: CleaningConfig = field(default_factory=CleaningConfig)
    filter: FilterConfig = field(default_factory=FilterConfig)
    consensus: consensus_mod.ConsensusConfig = field(default_factory=consensus_mod.ConsensusConfig)
    relocalization: reloc_mod.RelocalizationConfig = field(default_factory=reloc_mod.RelocalizationConfig)
    kidnap: kidnap_mod.KidnapConfig = field(default_factory=kidnap_mod.KidnapConfig)  # moved unseen
    backend: BackendConfig = field(default_factory=BackendConfig)  # pose graph over the output path


@dataclass(frozen=True)
class Estimate:
    stamp_s: float
    pose: np.ndarray  # (3,) best particle's pose in the map frame
    processed: bool  # False when the scan was bridged by odometry (too little motion)
    ess: float
    n_segments: int


class FastSLAM:
    """The filter. ``rng`` is the only source of randomness; time comes with the scans."""

    def __init__(self, cfg: SlamConfig, rng: np.random.Generator, start: np.ndarray | None = None):
        self.cfg = cfg
        self.rng = rng
        m = cfg.motion
        self.particles = ParticleSet.create(
            cfg.particles, start, (m.slip_scale_prior_sigma, m.slip_drift_prior_sigma_rad_per_m)
        )
        self.trajectory = Trajectory(max_scans=cfg.filter.history_scans)
        self.step_index = 0
        self._last_odo: np.ndarray | None = None
        self.global_map: consensus_mod.GlobalMap | None = None
        self.stats = {
            "coarse_turns": 0,
            "resamples": 0,
            "injections": 0,
            "relocalizations": 0,
            "relocalization_candidates": 0,
            "history_closed": 0,  # steps closed along the best particle's history (max_open_steps)
            "odometry_jumps": 0,  # odometry increments the scans contradicted (not used)
            "odometry_jumps_unverified": 0,  # large ones the scans could not judge (used)
            "odometry_stuck": 0,  # steps the scans moved while odometry stood (stuck wheel)
            "odometry_caught_up": 0,  # ... after which odometry reported the motion after all
            "kidnap_doubts": 0,  # scans disagreed with odometry: the map held while in doubt ...
            "kidnappings": 0,  # ... the robot was found elsewhere in the map and moved there
            "kidnap_cleared": 0,  # ... the estimate fitted the map all along (odometry erred)
            "lost": 0,  # ... found nowhere, the estimate fitting nothing: the filter gave up
        }
        # (scan index, what, the move (3,) or None): the newest doubts and how they ended ("doubt",
        # "moved", "cleared", "lost")
        self.kidnap_events: deque[tuple[int, str, np.ndarray | None]] = deque(maxlen=100)
        self.doubt: kidnap_mod.Doubt | None = None  # scans disagree with odometry: the map is held
        self.lost = False  # the filter gave up: the robot is where its map does not reach
        self._ref: tuple[np.ndarray, np.ndarray] | None = None  # the last agreeing scan (points, odometry)
        self._disagree = 0  # scans since, in a row, that disagree with it ...
        self._disagree_step = 0  # ... from the step this one is
        # (scan index, increment (3,), fit where odometry put it, fit where the robot was): the
        # newest odometry jumps the scans contradicted
        self.odometry_jumps: deque[tuple[int, np.ndarray, float, float]] = deque(maxlen=100)
        # (scan index, odometry's increment (3,), the scan's): the newest steps the scans moved
        # while odometry stood
        self.odometry_stuck: deque[tuple[int, np.ndarray, np.ndarray]] = deque(maxlen=100)
        self._reloc_pending: reloc_mod.Pending | None = None
        self._prev_odo: np.ndarray | None = None  # the previous scan's odometry ...
        self._odometry_stood = 0  # ... and for how many scans in a row it has not changed
        self._bridged: np.ndarray | None = None  # the last bridged scan's motion since the step
        self._owed: np.ndarray | None = None  # the motion the scans drove while odometry stood,
        # which odometry may still report when it moves again (a stall that catches up)
        self._odometer_m = 0.0  # distance driven (odometry), and at the last relocalization
        self._anchor_m = 0.0
        # (scan index, pose (3,)): where each confirmed relocalization put the robot, for the
        # back end — its loop search window is too small for the drift a relocalization bridges
        self.loop_hints: list[tuple[int, np.ndarray]] = []
        self.hints_forgotten = 0  # the oldest hints, dropped with the path they refer to
        # the odometry's translation noise as the scans measure it (ProposalConfig.draw_measured_odometry)
        self.odometry_noise = MeasuredOdometry()

    # -- the loop ---------------------------------------------------------------------------

    def step(
        self,
        stamp_s: float,
        odometry: np.ndarray,
        ranges_m: np.ndarray,
        angles_rad: np.ndarray,
        laser_offset: np.ndarray,
        range_max_m: float = np.inf,
        pose: np.ndarray | None = None,
    ) -> Estimate:
        """One scan. ``pose (3,)``, when given, is the robot's known pose in the map frame
        (mapping with known poses, e.g. a trajectory the back end corrected): the particles are
        put there instead of being moved and sampled; no proposal, no slip update."""
        cfg = self.cfg
        ps = self.particles
        odometry = np.asarray(odometry, dtype=float)
        scan_driven = False  # the step's motion is the scan's, not odometry's (a stuck wheel)
        scan_xy = None  # the scan's points in the robot frame, once made
        if cfg.kidnap.enabled and pose is None:
            scan_xy = self._scan_xy(ranges_m, angles_rad, laser_offset, range_max_m)
            self._watch(odometry, scan_xy)
        if self._prev_odo is not None:  # odometry that does not change at all from scan to scan
            d = odometry_increment(self._prev_odo, odometry)
            stood = np.hypot(d[0], d[1]) < ODOMETRY_STANDS_M and abs(d[2]) < ODOMETRY_STANDS_RAD
            self._odometry_stood = self._odometry_stood + 1 if stood else 0
        self._prev_odo = odometry
        if self._last_odo is not None:
            u = odometry_increment(self._last_odo, odometry)
            if (
                pose is None
                and self._implausible(u)
                and self._jumped(u, ranges_m, angles_rad, laser_offset, range_max_m)
            ):
                self._last_odo = odometry  # the jump absorbed: increments count from here on
                u = np.zeros(3)
            if self._owed is not None and self._odometry_stood == 0:  # odometry moves again
                u = self._settle(u, ranges_m, angles_rad, laser_offset, range_max_m)
            if not self._moved(u):  # bridge: no map update, the pose from the scan (or odometry) only
                best = ps.best()
                still = u
                # odometry stands: the scans are followed from where the last bridged one was
                start = self._bridged if self._odometry_stood and self._bridged is not None else u
                if pose is not None:  # the pose is known (a rebuilt map): no scan to align
                    u = relative_one(ps.poses[best], pose)
                elif cfg.filter.refine_bridged and cfg.proposal.enabled:
                    u = self._refine_bridged(
                        best, start, ranges_m, angles_rad, laser_offset, range_max_m, scan_xy
                    )
                    self._bridged = u
                scan = (ranges_m, angles_rad, laser_offset, range_max_m)
                if not (pose is None and self._stuck(still, u, scan)):
                    self.trajectory.bridge(stamp_s, u)
                    return Estimate(
                        stamp_s, compose(ps.poses[best], u), False, effective_sample_size(ps.log_weights), 0
                    )
                # odometry stood while the scans followed the robot on (a stuck or spinning wheel, a
                # pushed robot): the step is processed, moved by what the scan says
                self.stats["odometry_stuck"] += 1
                self.odometry_stuck.append((len(self.trajectory), still.copy(), u.copy()))
                self._owed = compose(np.zeros(3) if self._owed is None else self._owed, relative(still, u))
                scan_driven = True
        else:
            u = np.zeros(3)
        self.step_index += 1
        self._bridged = None
        k = self.step_index
        self._odometer_m += float(np.hypot(u[0], u[1]))

        # 1. segments, in the robot frame
        segs = extract_segments(ranges_m, angles_rad, cfg.extraction, range_max_m).transformed(laser_offset)
        facing = wrap_angle(segs.alpha + np.pi)  # normal pointing back to the sensor

        # 2. motion (slip-aware), 3. proposal — or the known pose
        if pose is None:
            mean, cov = predict(ps.poses, ps.slip, u, cfg.motion)
            jac = slip_jacobian(ps.poses, u)
            cov = cov + np.einsum("pij,pjk,plk->pil", jac, ps.slip_cov, jac)  # the slip's own uncertainty
        else:
            mean = np.repeat(np.asarray(pose, dtype=float).reshape(1, 3), ps.n, axis=0)
        pts = segs.points  # the readings the point alignment uses (scan order, robot frame)
        reach = float(np.max(np.hypot(pts[:, 0], pts[:, 1]), initial=0.0))
        cols = self._local_columns(mean, reach + cfg.filter.local_margin_m)
        local = ps.maps.columns(cols)
        prior_term = np.zeros(ps.n)
        path = None  # what the path records when not the drawn poses (ProposalConfig.record_mean)
        if pose is not None:
            ps.poses = mean
        elif cfg.proposal.enabled and len(cols) and len(segs):
            init = self._coarse_start(mean, pts, local, float(u[2]))
            prop = align(
                mean,
                cov,
                segs.moments,
                segs.endpoints,
                facing,
                segs.cov,
                local,
                cfg.association,
                cfg.proposal,
                pts,
                init,
                segs.point_alpha,
            )
            d = prop.mean - mean  # (the scan match against odometry's prediction)
            d[:, 2] = wrap_angle(d[:, 2])
            info = prop.prior_info  # (Σ⁻¹, as the proposal solved with it)
            draw = prop.cov
            if cfg.proposal.draw_measured_odometry:
                if not scan_driven:  # (a stuck wheel's step predicts by the scans, not odometry)
                    self.odometry_noise.add(d, cov, prop.cov, cfg.proposal)
                draw = draw_covariance(prop, info, self.odometry_noise.ratio(cfg.proposal))
            ps.poses = sample_gaussian(self.rng, prop.mean, draw * cfg.proposal.sample_scale)
            path = prop.mean if cfg.proposal.record_mean else None
            prior_term = -0.5 * np.einsum("pi,pij,pj->p", d, info, d)
            if not scan_driven:  # odometry's systematic error is learned from odometry's motion
                ps.slip, ps.slip_cov = update_slip(ps.slip, ps.slip_cov, jac, info, prop.cov, d, cfg.motion)
        else:
            ps.poses = sample_gaussian(self.rng, mean, cov)
        if self._last_odo is None:  # the first scan defines the map frame: the start pose, exactly
            ps.poses, path = mean.copy(), None  # (drawn above all the same: the random stream is unchanged)
        if pose is None:
            ps.slip_cov = walk_slip(ps.slip_cov, float(np.hypot(u[0], u[1])), cfg.motion)

        # 4. association at the sampled poses, 5. weights
        obs = observe(
            ps.poses, segs.moments, segs.endpoints, facing, segs.cov, cfg.association.point_sigma_m,
            cfg.association.compiled,
        )  # fmt: skip
        assoc = associate(obs, local, cfg.association)
        ll = match_log_likelihood(assoc, obs, cfg.association, cfg.weights.log_p_new).sum(axis=1)
        laser_poses = compose(ps.poses, laser_offset)
        usable = min(cfg.extraction.max_usable_range_m, range_max_m)
        through, in_view = visibility(local, laser_poses, ranges_m, angles_rad, usable, cfg.update)
        trusted = trusted_mask(local, k, cfg.trust)
        contradictions = np.sum((through >= 2) & trusted, axis=1)
        penalty = np.minimum(cfg.weights.through_penalty * contradictions, cfg.weights.max_through_penalty)
        ps.log_weights = ps.log_weights + cfg.weights.gain * (ll + prior_term) - penalty
        ps.normalize()

        if self.doubt is None:
            # 6. update / add, misses
            matched_cols = np.zeros(local.valid.shape, bool)
            p_idx, o_idx = np.nonzero(assoc.matched)
            matched_cols[p_idx, assoc.index[p_idx, o_idx]] = True
            merge_matches(local, obs, assoc, k, cfg.update)
            apply_misses(local, through, in_view, matched_cols, cfg.update)
            # 7. cleaning
            if k % cfg.filter.clean_every == 0:
                recent = np.flatnonzero(
                    np.any(local.valid & (local.last_seen > k - cfg.filter.clean_every), axis=0)
                )
                clean(local, k, cfg.cleaning, recent)
            ps.maps.put_columns(cols, local)
            add_new(ps.maps, obs, assoc, k, cfg.update)
        else:  # in doubt the map stays as it was: is the robot where the filter thinks?
            usable = min(cfg.extraction.max_usable_range_m, range_max_m)
            rays = reloc_mod.ScanRays(ranges_m, angles_rad, laser_offset, usable, cfg.update)
            self._resolve(segs, facing, k, rays, (ranges_m, angles_rad, laser_offset, range_max_m))

        self.trajectory.record(stamp_s, ps.poses if path is None else path)
        if self.trajectory.open_steps > cfg.filter.max_open_steps:  # particles that do not coalesce
            self.stats["history_closed"] += self.trajectory.close(ps.best(), cfg.filter.max_open_steps // 2)
        if self.trajectory.over:  # a run without end: its oldest path goes
            self._forget_history()
        # 8. resampling
        ess = effective_sample_size(ps.log_weights)
        if ess < cfg.filter.ess_threshold * ps.n:
            idx = systematic_resample(self.rng, ps.log_weights)
            self.particles = ps = ps.take(idx)
            ps.log_weights = np.full(ps.n, -np.log(ps.n))
            self.trajectory.reparent(idx)
            self.stats["resamples"] += 1
        # 9. cross-particle global map (report §5), 10. relocalization (report §6)
        if cfg.consensus.enabled and k % cfg.consensus.every == 0:
            self.global_map = consensus_mod.build_global_map(ps, k, cfg.trust, cfg.consensus)
            consensus_mod.refresh_particles(ps, self.global_map, k, cfg.consensus)
        if (
            cfg.relocalization.enabled
            and k % cfg.relocalization.every == 0
            and len(segs)
            and self.doubt is None
        ):
            usable = min(cfg.extraction.max_usable_range_m, range_max_m)
            rays = reloc_mod.ScanRays(ranges_m, angles_rad, laser_offset, usable, cfg.update)
            self._maybe_relocalize(segs, facing, k, rays)
        self._last_odo = odometry
        best = ps.best()
        return Estimate(stamp_s, ps.poses[best].copy(), True, ess, len(segs))

    # -- helpers ------------------------------------------------------------------------------

    def _coarse_start(
        self, mean: np.ndarray, pts: np.ndarray, local: SegmentMaps, turn_rad: float
    ) -> np.ndarray | None:
        """Where the proposal's alignment starts: the predicted poses ``mean (P,3)`` turned by
        the heading offset at which the scan fits the best particle's local map (coarse.py), or
        None (start at the prediction)."""
        if not self.cfg.coarse.enabled:
            return None
        best = self.particles.best()
        offset = heading_offset(
            mean[best], pts, local.seg[best][local.valid[best]], turn_rad, self.cfg.coarse
        )
        if offset == 0.0:
            return None
        self.stats["coarse_turns"] += 1
        start = mean.copy()
        start[:, 2] = wrap_angle(start[:, 2] + offset)
        return start

    def _local_columns(
        self, poses: np.ndarray, radius_m: float, rows: np.ndarray | None = None
    ) -> np.ndarray:
        """Columns with an element within ``radius_m`` of the particles (cheap bound: distance to
        the segment's midpoint minus its half length); of the particles ``rows`` only when given
        (their maps alone are used: columns valid in none of them would be carried for nothing)."""
        maps = self.particles.maps
        centre = poses[:, :2].mean(axis=0)
        spread = np.max(np.hypot(*(poses[:, :2] - centre).T))
        if self.cfg.filter.compiled and kernels.AVAILABLE:  # the same test, over the whole map, compiled
            every = np.arange(maps.n_particles) if rows is None else rows
            return kernels.local_columns(maps.valid, maps.seg, every, centre, radius_m + spread)
        of = slice(None) if rows is None else rows
        valid = maps.valid[of]
        used = np.flatnonzero(valid.any(axis=0))
        if len(used) == 0:
            return used
        seg = maps.seg[of][:, used]
        mid = 0.5 * (seg[:, :, 0] + seg[:, :, 1])
        half = 0.5 * np.hypot(*(seg[:, :, 1] - seg[:, :, 0]).transpose(2, 0, 1))
        d = np.hypot(*(mid - centre).transpose(2, 0, 1)) - half
        near = np.any(valid[:, used] & (d < radius_m + spread), axis=0)
        return used[near]

    def _refine_bridged(
        self,
        best: int,
        u: np.ndarray,
        ranges_m: np.ndarray,
        angles_rad: np.ndarray,
        laser_offset: np.ndarray,
        range_max_m: float,
        scan_xy: np.ndarray | None = None,
    ) -> np.ndarray:
        """The motion ``u`` since the last processed scan, refined by aligning this scan's points
        (``scan_xy``, robot frame, when already made) to the best particle's local map (one
        particle, no sampling, no map change)."""
        cfg = self.cfg
        ps = self.particles
        pts = self._scan_xy(ranges_m, angles_rad, laser_offset, range_max_m) if scan_xy is None else scan_xy
        if len(pts) == 0:
            return u
        one = np.array([best])
        mean, cov = predict(ps.poses[one], ps.slip[one], u, cfg.motion)
        f = cfg.filter
        cov = cov + np.diag([f.bridge_sigma_xy_m**2, f.bridge_sigma_xy_m**2, f.bridge_sigma_theta_rad**2])
        reach = float(np.max(np.hypot(pts[:, 0], pts[:, 1])))
        cols = self._local_columns(mean, reach + cfg.filter.local_margin_m, one)
        if len(cols) == 0:
            return u
        local = ps.maps.row_columns(best, cols)
        prop = align_points(mean, cov, pts, local, cfg.proposal)
        return relative_one(ps.poses[best], prop.mean[0])

    def _maybe_relocalize(
        self, segs: ScanSegments, facing: np.ndarray, k: int, rays: reloc_mod.ScanRays
    ) -> None:
        ps = self.particles
        gm = self.global_map
        if gm is None or k - gm.step >= self.cfg.consensus.every:  # relocalization needs no consensus step
            gm = self.global_map = consensus_mod.build_global_map(ps, k, self.cfg.trust, self.cfg.consensus)
        traveled = self._odometer_m - self._anchor_m
        result = reloc_mod.relocalize(ps, gm, segs, facing, k, self.cfg.relocalization, rays, traveled)
        if result is None:
            return
        self.stats["relocalization_candidates"] += 1
        estimate = ps.poses[ps.best()]
        ok, self._reloc_pending = reloc_mod.confirm(
            self._reloc_pending, result, estimate, k, self.cfg.relocalization
        )
        if not ok:
            return
        self.stats["relocalizations"] += 1
        self._anchor_m = self._odometer_m
        self.loop_hints.append((len(self.trajectory) - 1, result.poses[0].copy()))
        # after a large correction the recent part of the map was drawn with the drift: it moves
        # with the injected particles (a small one is within what the proposal absorbs)
        large = reloc_mod.is_large(result, estimate, self.cfg.relocalization)
        young_since = k - self.cfg.relocalization.old_age_steps + 1 if large else None
        targets, sources = reloc_mod.inject(ps, result, young_since)
        self.stats["injections"] += len(targets)
        self.trajectory.inherit(targets, sources)

    def _scan_xy(self, ranges_m, angles_rad, laser_offset, range_max_m) -> np.ndarray:
        """The scan's usable readings as points ``(K,2)`` in the robot frame."""
        return apply_points(laser_offset, scan_points(ranges_m, angles_rad, self.cfg.extraction, range_max_m))

    def _watch(self, odometry: np.ndarray, scan_xy: np.ndarray) -> None:
        """Does the scan lie on the last agreeing one, moved by odometry's increment? Two in a row
        that do not: doubt (:mod:`robot_agent.slam.kidnap`)."""
        if self.doubt is not None:
            self.doubt.scans += 1
            return
        kc = self.cfg.kidnap
        pts = kidnap_mod.thin(scan_xy, kc.points)
        if self._ref is None or kidnap_mod.overlap(*self._ref, pts, odometry, kc) >= kc.min_overlap:
            self._ref, self._disagree = (pts, odometry), 0
            return
        self._disagree += 1
        if self._disagree == 1:
            self._disagree_step = self.step_index + 1  # the first step it may make
        if self._disagree >= kc.suspect_scans:
            first = len(self.trajectory) - self._disagree + 1  # the first scan that disagreed
            self.doubt = kidnap_mod.Doubt(first, self._odometer_m)
            self.stats["kidnap_doubts"] += 1
            self.kidnap_events.append((first, "doubt", None))
            maps = self.particles.maps  # what the scans since mapped goes: it may be elsewhere
            maps.valid &= ~(maps.born >= self._disagree_step)
            self.global_map = None  # built again without it

    def _resolve(
        self, segs: ScanSegments, facing: np.ndarray, k: int, rays: reloc_mod.ScanRays, scan: tuple
    ) -> None:
        """A step in doubt (the map held): look for the scan in the whole map; found twice,
        consistently, far from the estimate, every particle moves there. After ``doubt_m`` of
        driving without: the estimate fitted the map where the doubt began (odometry erred: go
        on; the robot may have driven out of the map since) or it did not (lost)."""
        d, kc, ps = self.doubt, self.cfg.kidnap, self.particles
        best = ps.best()
        pose = ps.poses[best].copy()
        fit = self._scan_fit(pose[None], *scan, kc.fit_m)
        d.fits.append(0.0 if fit is None else float(fit[0]))
        gm = self.global_map
        if gm is None or k - gm.step >= self.cfg.consensus.every:
            gm = self.global_map = consensus_mod.build_global_map(ps, k, self.cfg.trust, self.cfg.consensus)
        rc = self.cfg.relocalization
        result = reloc_mod.relocalize_global(
            pose, gm, segs, facing, rc, rays, kc.far_m, kc.far_rad, kc.pair_gap_m, kc.explain_share
        )
        if result is not None:
            ok, d.pending = reloc_mod.confirm(d.pending, result, pose, k, rc)
            if ok:
                move = compose(result.poses[0], inverse(pose))
                ps.poses[:] = compose(move, ps.poses)
                # the path since the doubt began was tracked in the held map from where the robot
                # was not: it moves too (the back end and a map rebuilt along it take it there)
                self.trajectory.move(np.array([d.scan - 1, d.scan]), np.array([np.zeros(3), move]))
                self.stats["kidnappings"] += 1
                self.kidnap_events.append((len(self.trajectory), "moved", move))
                self.loop_hints.append((len(self.trajectory), ps.poses[best].copy()))
                self._end_doubt()
                return
        if self._odometer_m - d.odometer_m >= kc.doubt_m or (d.scans >= kc.doubt_scans and len(d.fits) >= 3):
            if max(d.fits[: kc.first_steps]) < kc.lost_fit:  # not where the doubt began either
                self.lost = True
                self.stats["lost"] += 1
                self.kidnap_events.append((len(self.trajectory), "lost", None))
            else:
                self.stats["kidnap_cleared"] += 1
                self.kidnap_events.append((len(self.trajectory), "cleared", None))
            self._end_doubt()

    def _end_doubt(self) -> None:
        self.doubt, self._ref, self._disagree = None, None, 0

    def _moved(self, u: np.ndarray, steps: int = 1) -> bool:
        """``u`` is ``steps`` whole steps (min_travel_m / min_turn_rad) or more."""
        f = self.cfg.filter
        return bool(np.hypot(u[0], u[1]) >= steps * f.min_travel_m or abs(u[2]) >= steps * f.min_turn_rad)

    def _stuck(self, odometry_u: np.ndarray, scan_u: np.ndarray, scan: tuple) -> bool:
        """Odometry has not changed at all for STOOD_SCANS scans, and a bridged scan's alignment
        ``scan_u`` moved STUCK_STEPS steps' worth from the last step and from where odometry
        ``odometry_u`` puts it (one step's worth once a step was driven so since odometry last
        moved): odometry stood while the robot moved
        (a stuck or spinning wheel, a pushed robot). (Odometry that lags the laser while turning
        fast still changes from scan to scan: Intel's does, by up to 5° more than the scans.) And
        the scan (``scan``: ranges, angles, laser offset, range limit) must say so itself: its
        points fit the map within STUCK_FIT_M at the aligned pose (a share of STUCK_FIT_SHARE at
        least) better by STUCK_FIT_GAIN than where odometry puts the robot — an alignment that
        slid along a corridor or caught people walking by does not."""
        if not self.cfg.filter.scan_driven_steps or self._odometry_stood < STOOD_SCANS:
            return False
        steps = STUCK_STEPS if self._owed is None else 1
        if not (self._moved(scan_u, steps) and self._moved(relative(odometry_u, scan_u), steps)):
            return False
        here = self.particles.poses[self.particles.best()]
        fits = self._scan_fit(
            np.array([compose(here, odometry_u), compose(here, scan_u)]), *scan, STUCK_FIT_M
        )
        return fits is not None and fits[1] >= STUCK_FIT_SHARE and fits[1] >= fits[0] + STUCK_FIT_GAIN

    def _settle(self, u: np.ndarray, ranges_m, angles_rad, laser_offset, range_max_m) -> np.ndarray:
        """Odometry moves again, by ``u``, after the scans drove steps while it stood (their
        motion beyond odometry's: ``_owed``). A stalled reading that catches up reports that motion
        now, on top of the new one; a wheel that lost it does not. The scan says which: aligned
        from each of the two increments (with and without the owed motion), the one whose
        alignment fits the map better (ties: moved less to get there) is used."""
        owed, self._owed = self._owed, None
        if self.doubt is None:  # the scans' and odometry's motions are reconciled here: the watch
            self._ref, self._disagree = None, 0  # for a move unseen starts again from this scan
        if not (self.cfg.filter.refine_bridged and self.cfg.proposal.enabled):
            return u
        paid = relative(owed, u)  # odometry reports the owed motion now: the rest is new
        lost = u if self._bridged is None else compose(self._bridged, u)  # it does not: the scans
        # followed the robot since the last step, odometry's increment comes on top
        cands = np.array([lost, paid])
        best = self.particles.best()
        here = self.particles.poses[best]
        scan = (ranges_m, angles_rad, laser_offset, range_max_m)
        aligned = np.array([self._refine_bridged(best, c, *scan) for c in cands])
        fits = self._scan_fit(compose(here, aligned), *scan, STUCK_FIT_M)
        if fits is None:
            return u
        d = relative(cands, aligned)
        moved = np.hypot(d[:, 0], d[:, 1]) + np.abs(d[:, 2])
        pick = int(np.lexsort((moved, -np.round(fits, 2)))[0])
        if pick == 1:
            self.stats["odometry_caught_up"] += 1
        return cands[pick]

    def _implausible(self, u: np.ndarray) -> bool:
        f = self.cfg.filter
        return f.odometry_jump_m > 0 and (
            np.hypot(u[0], u[1]) > f.odometry_jump_m or abs(u[2]) > f.odometry_jump_rad
        )

    def _jumped(self, u, ranges_m, angles_rad, laser_offset, range_max_m) -> bool:
        """Odometry moved the robot implausibly far since the last step: the scan decides. Its
        points' fit to the best particle's map (share within 0.15 m of an element) where odometry
        puts the robot and where it was: fitting where it was (0.3 at least, and by 0.2 more),
        odometry jumped (True), and the increment is not used — the scan is aligned from the last
        pose. Otherwise (a gap in the log while the robot drove, an unmapped place) it is used."""
        here = self.particles.poses[self.particles.best()]
        fits = self._scan_fit(
            np.array([compose(here, u), here]), ranges_m, angles_rad, laser_offset, range_max_m, 0.15
        )
        if fits is not None and fits[1] >= 0.3 and fits[1] >= fits[0] + 0.2:
            self.stats["odometry_jumps"] += 1
            self.odometry_jumps.append((len(self.trajectory), u.copy(), fits[0], fits[1]))
            return True
        self.stats["odometry_jumps_unverified"] += 1
        return False

    def _scan_fit(
        self, poses: np.ndarray, ranges_m, angles_rad, laser_offset, range_max_m, within_m: float
    ) -> np.ndarray | None:
        """Share ``(N,)`` of the scan's points (100 at most, spread over the scan) within
        ``within_m`` of an element of the best particle's map, with the robot at each of
        ``poses (N,3)``; None when the scan or the map is empty."""
        ps = self.particles
        best = ps.best()
        pts = apply_points(laser_offset, scan_points(ranges_m, angles_rad, self.cfg.extraction, range_max_m))
        if len(pts) > 100:
            pts = pts[np.linspace(0, len(pts) - 1, 100).astype(int)]
        segs = ps.maps.seg[best][ps.maps.valid[best]]
        if len(pts) == 0 or len(segs) == 0:
            return None
        world = apply_points(poses, pts)  # (N,K,2)
        d = point_segment_distance(world[:, :, None, :], segs[None, None, :, :, :]).min(axis=2)
        return np.mean(d < within_m, axis=1)

    def move_frame(self, kf_scan: np.ndarray, moves: np.ndarray) -> None:
        """The map frame bent by a back end's correction, so that the filter continues from the
        corrected estimate: every step of the kept history, every particle's map element (with
        the step that saw it last: what the robot sees now moves with it; measured against the
        step that made it, on the three development logs online at the end: Intel 0.0237 m
        against 0.0259, ACES 0.0397 against 0.0397, MIT-CSAIL 0.0319 against 0.0310), the
        particles' poses (with the last step) and the
        relocalizations move by the transform ``moves (K,3)`` of the last keyframe of
        ``kf_scan (K,)`` at or before their scan (before the first, the first's); a scan not
        processed moves with the step it hangs from (:meth:`Trajectory.anchor_scans`)."""
        if len(kf_scan) == 0 or len(self.trajectory) == 0:
            return
        kf_scan, moves = np.asarray(kf_scan), np.asarray(moves, dtype=float)

        def at(scans) -> np.ndarray:
            return moves[keyframe_of(kf_scan, scans)]

        self.trajectory.move(kf_scan, moves)
        ps = self.particles
        ps.poses[:] = compose(at(self.trajectory.scan_of_step(self.step_index)), ps.poses)  # the last step's
        maps = ps.maps
        if maps.capacity:
            c = at(self.trajectory.scan_of_step(np.maximum(maps.last_seen, 1)))  # (P,M,3)
            maps.seg[:] = apply_points(c, maps.seg)  # each element's two endpoints by its own move
            maps.moments[:] = transform_moments(c, maps.moments)
            maps.alpha[:], maps.rho[:], _ = transform_lines(c, maps.alpha, maps.rho)
            maps.facing[:] = wrap_angle(maps.facing + c[..., 2])
        self.loop_hints = [(i, compose(at(i), pose)) for i, pose in self.loop_hints]
        self.global_map = None  # rebuilt from the moved maps at the next step
        self._reloc_pending = None  # found in the old frame

    def referenced_steps(self) -> np.ndarray:
        """The steps (sorted, unique) at which the elements of the particles' maps and of the
        global map were made (:attr:`SegmentMaps.born`), and last seen (:meth:`move_frame`)."""
        maps = self.particles.maps
        parts = [maps.born[maps.valid], maps.last_seen[maps.valid]]
        if self.global_map is not None:
            parts.append(self.global_map.born)
        return np.unique(np.concatenate(parts).astype(np.int64))

    def _forget_history(self) -> None:
        n = self.trajectory.forget(self.referenced_steps())
        self.stats["scans_forgotten"] = self.stats.get("scans_forgotten", 0) + n
        first = self.trajectory.first_scan
        old = 0
        while old < len(self.loop_hints) and self.loop_hints[old][0] < first:
            old += 1
        del self.loop_hints[:old]
        self.hints_forgotten += old

    def hints_since(self, count: int) -> tuple[list[tuple[int, np.ndarray]], int]:
        """The relocalizations after the first ``count`` of the run (those forgotten left out)
        and the count of the run's so far."""
        return self.loop_hints[max(count - self.hints_forgotten, 0) :], self.hints_forgotten + len(
            self.loop_hints
        )

    # -- outputs ------------------------------------------------------------------------------

    def best_trajectory(self) -> tuple[np.ndarray, np.ndarray]:
        """``stamps (S,)`` and poses ``(S,3)`` of the best particle's whole history, one per scan
        (from ``trajectory.first_scan`` on)."""
        return self.trajectory.backtrack(self.particles.best())

    def best_jumps(self) -> np.ndarray:
        """Mask ``(S,)``: the scans of :meth:`best_trajectory` reached by a relocalization's
        jump, not by motion (the back end bridges them by odometry)."""
        return self.trajectory.jumps(self.particles.best())

    def published_map(self) -> tuple[consensus_mod.GlobalMap, np.ndarray]:
        """The cross-particle global map as of now and the mask ``(G,)`` of its trusted
        elements — what the agent publishes (report §5)."""
        gm = consensus_mod.build_global_map(
            self.particles, self.step_index, self.cfg.trust, self.cfg.consensus
        )
        c = self.cfg.consensus
        return gm, gm.trusted(c.publish_min_trust, c.publish_min_hits)

    def best_map(self) -> SegmentMaps:
        return self.particles.maps.take(np.array([self.particles.best()]))
