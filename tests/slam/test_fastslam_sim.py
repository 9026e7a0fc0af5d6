"""Seeded end-to-end run of the whole filter on a simulated log, scored against the truth."""

import numpy as np
import pytest

from robot_agent.replay import replay
from robot_agent.sim import OdometryNoise, SimConfig, builtin_world, simulate_robot
from robot_agent.sim.evaluate import score_run
from robot_agent.slam.fastslam import SlamConfig
from robot_agent.slam.proposal import ProposalConfig

DURATION_S = 200.0  # office: the route comes back over its start after about 130 s


@pytest.fixture(scope="module")
def office_run():
    world = builtin_world("office")
    sim = simulate_robot(world, 0, DURATION_S, 0, SimConfig())
    log = sim.to_log()
    res = replay(log, SlamConfig(), seed=0, progress=False)
    gm, keep = res.slam.published_map()
    return sim, score_run(sim, world, res.stamps_s, res.poses, gm.seg[keep], map_poses=res.filter_poses)


def test_office_accuracy_map_and_loop(office_run):
    _, score = office_run
    assert score.revisit_pairs > 0  # the run does come back
    assert score.loop_closed, score
    assert score.ate_rmse_m <= 0.035, score  # measured 0.022
    assert score.precision >= 0.99, score  # measured 0.999
    assert score.completeness >= 0.89, score  # measured 0.904


def test_odometry_alone_is_much_worse(office_run):
    """The test can fail: the raw odometry of the same run misses every bound."""
    sim, score = office_run
    world = builtin_world("office")
    odo = score_run(sim, world, sim.stamps_s, sim.odometry, np.zeros((0, 2, 2)))
    assert odo.ate_rmse_m > 3 * score.ate_rmse_m
    assert not odo.loop_closed


def test_the_filter_learns_a_strong_odometry_bias():
    """Odometry reading 6 % long and turning 0.031 rad/m (drawn, seeded): after 100 s the
    particles' slip belief has both. (Before the slip was Rao-Blackwellized the filter ended at
    -0.052 and -0.0003 here: the drift not learned at all.)"""
    world = builtin_world("office")
    noise = OdometryNoise(scale_error_sigma=0.03, heading_drift_sigma_rad_per_m=0.012)
    sim = simulate_robot(world, 0, 100.0, 3, SimConfig(odometry=noise))
    assert sim.bias.scale_error > 0.05 and sim.bias.heading_drift_rad_per_m < -0.025  # strong, as meant
    res = replay(sim.to_log(), SlamConfig(), seed=0, progress=False)
    ps = res.slam.particles
    learned = np.exp(ps.log_weights) @ ps.slip
    # the slip corrects the reading: distance × (1 + slip) is the truth, heading + slip × distance
    want = [1.0 / (1.0 + sim.bias.scale_error) - 1.0, -sim.bias.heading_drift_rad_per_m]
    assert abs(learned[0] - want[0]) < 0.01, (learned, want)  # measured 0.002
    assert abs(learned[1] - want[1]) < 0.005, (learned, want)  # measured 0.0015
    spread = np.sqrt(np.einsum("p,pii->i", np.exp(ps.log_weights), ps.slip_cov))
    m = SlamConfig().motion
    prior = np.array([m.slip_scale_prior_sigma, m.slip_drift_prior_sigma_rad_per_m])
    assert np.all(spread < 0.4 * prior), spread  # and knows it (measured 0.009, 0.006)


def _heading_drift_deg(cfg: SlamConfig, seeds: range, duration_s: float) -> np.ndarray:
    """Warehouse robot3's turn from its first pose to its last (best particle's path) against the
    truth's, per seed: down the aisle along the south wall and its pillars."""
    from robot_agent.sim import LiveSim
    from robot_agent.slam.fastslam import FastSLAM
    from shared.geometry import relative, wrap_angle

    world, out = builtin_world("warehouse"), []
    for seed in seeds:
        slam, sim = FastSLAM(cfg, np.random.default_rng(seed)), LiveSim(world, 2, seed=seed)
        stamps, truth = [], []
        for scan in sim.scans(duration_s):
            stamps.append(scan.stamp_s)
            truth.append(sim.truth.copy())
            slam.step(scan.stamp_s, scan.odometry, scan.ranges_m, scan.angles_rad, scan.laser_offset,
                      scan.range_max_m)  # fmt: skip
        st, path = slam.best_trajectory()
        true = np.asarray(truth)[np.searchsorted(stamps, st)]
        out.append(wrap_angle(relative(path[0], path[-1])[2] - relative(true[0], true[-1])[2]))
    return np.degrees(out)


def test_a_wall_with_pillars_does_not_turn_the_path():
    """The pillars' sides are faces too short to keep as segments, 0.1-0.3 m off the wall they
    jut from: their points paired with the wall's line (within the point gate) and turned the
    path one way — -0.14 deg on average over these 8 seeds in 30 s (-0.19 deg over 20 seeds),
    -0.02 without the pillars. Each point pairs only with an element along its own piece's line
    (``proposal.point_angle_gate_rad``): measured -0.03 deg on average."""
    seeds = range(8)
    gated = _heading_drift_deg(SlamConfig(), seeds, 30.0)
    assert abs(gated.mean()) <= 0.06, gated
    unchecked = SlamConfig(proposal=ProposalConfig(point_angle_gate_rad=np.pi / 2))
    assert _heading_drift_deg(unchecked, seeds, 30.0).mean() <= -0.11  # the bias it removes


def test_the_path_records_the_scan_match_not_the_draw():
    """Each particle's pose is drawn from its proposal (its map made there differs from the
    others'), but the path records the proposal's mean, the scan match's pose: the draw's spread
    is noise on the path that the back end's chain edges carried. The path's turn from one scan
    to the next against the truth's, office route 0, 30 s: measured 0.044 deg (std over the
    scans, seeds 0-1) recording the mean, 0.105 recording the draw."""
    from shared.geometry import wrap_angle

    world = builtin_world("office")

    def jitter_deg(record_mean: bool, seed: int) -> float:
        sim = simulate_robot(world, 0, 30.0, seed, SimConfig())
        cfg = SlamConfig(proposal=ProposalConfig(record_mean=record_mean))
        res = replay(sim.to_log(), cfg, seed=seed, progress=False)
        d = wrap_angle(np.diff(res.filter_poses[:, 2]) - np.diff(sim.truth[:, 2]))
        return float(np.degrees(d.std()))

    mean = [jitter_deg(True, s) for s in (0, 1)]
    drawn = [jitter_deg(False, s) for s in (0, 1)]
    assert max(mean) <= 0.06, mean
    assert min(drawn) >= 1.8 * max(mean), (mean, drawn)  # what recording the mean removes


def test_the_filter_measures_the_odometrys_noise_and_draws_with_it():
    """The simulated odometry's translation noise is a fraction of the motion model's: the scans,
    where they pin the pose, measure it (measured 0.16 of the model's variance, office route 0,
    60 s) and the particles are drawn with it along what the scans leave open. Odometry noisier
    than the model (0.3 m/m against its 0.05: measured 3.2) is held at the model's, the draws as
    they were."""
    world = builtin_world("office")

    def measured(noise: OdometryNoise) -> float:
        sim = simulate_robot(world, 0, 60.0, 0, SimConfig(odometry=noise))
        res = replay(sim.to_log(), SlamConfig(), seed=0, progress=False)
        assert res.slam.odometry_noise.steps >= 100  # (pinned steps measured)
        return res.slam.odometry_noise.ratio(SlamConfig().proposal)

    assert measured(OdometryNoise()) <= 0.3
    assert measured(OdometryNoise(trans_per_m=0.3, trans_per_rad=0.1)) == 1.0
