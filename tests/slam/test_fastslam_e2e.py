"""Seeded end-to-end runs of the whole filter on real data (the Intel excerpt in tests/data)."""

from pathlib import Path

import numpy as np
import pytest

from robot_agent.replay import replay
from robot_agent.slam.config import apply_overrides
from robot_agent.slam.fastslam import SlamConfig
from robot_agent.sources import read_log
from shared.geometry import compose, inverse
from shared.metrics import read_relations, relations_error

DATA = Path(__file__).resolve().parents[1] / "data"


@pytest.fixture(scope="module")
def intel_head():
    return read_log(DATA / "intel_head.clf.gz"), read_relations(DATA / "intel_head.relations")


def score(log, rel, cfg, seed=0):
    res = replay(log, cfg, seed=seed, progress=False)
    return res, relations_error(res.stamps_s, res.poses, rel, log.odom_stamps_s, log.odom_poses)


@pytest.fixture(scope="module")
def default_run(intel_head):
    log, rel = intel_head
    return score(log, rel, SlamConfig())


def test_one_pose_per_scan_with_the_scans_own_stamp(intel_head, default_run):
    log, _ = intel_head
    res, _ = default_run
    assert len(res.poses) == len(log) == 1500
    np.testing.assert_array_equal(res.stamps_s, log.stamps_s)
    assert np.all(np.isfinite(res.poses))


def test_accuracy_on_real_excerpt(intel_head, default_run):
    log, rel = intel_head
    _, err = default_run
    odo = relations_error(log.stamps_s, log.odometry, rel, log.odom_stamps_s, log.odom_poses)
    s = err.summary()
    assert s["trans_mean_m"] <= 0.024  # measured 0.019 (seed 0; 0.019, 0.019 for seeds 1, 2)
    assert s["rot_mean_deg"] <= 0.4  # measured 0.32; raw odometry 1.33
    assert s["rot_mean_deg"] < 0.6 * odo.summary()["rot_mean_deg"]


def test_proposal_improves_rotation(intel_head, default_run):
    log, rel = intel_head
    _, with_prop = default_run
    _, without = score(log, rel, apply_overrides(SlamConfig(), ["proposal.enabled=false"]))
    assert with_prop.summary()["rot_mean_deg"] < 0.75 * without.summary()["rot_mean_deg"]


def test_seeded_runs_are_reproducible(intel_head):
    log, _ = intel_head
    cfg = SlamConfig()
    a = replay(log, cfg, seed=5, progress=False, limit=300)  # 300 scans are enough to tell
    b = replay(log, cfg, seed=5, progress=False, limit=300)
    np.testing.assert_array_equal(a.poses, b.poses)


def test_the_back_end_keeps_the_trajectory_in_the_maps_frame(intel_head, default_run):
    """The corrected trajectory is put where the filter's fits best (the frame of the map the
    server aligns), and a piece of the log is corrected with its own scans and odometry."""
    from robot_agent.backend import correct_trajectory

    log, _ = intel_head
    res, _ = default_run
    gap = np.hypot(*(res.poses[:, :2] - res.filter_poses[:, :2]).T)
    assert gap.mean() < 0.05, gap.mean()  # the excerpt's filter is good: the frames coincide
    first = 600
    piece, _ = correct_trajectory(log, first, res.stamps_s[first:], res.filter_poses[first:], SlamConfig())
    assert piece.shape == (len(log) - first, 3) and np.all(np.isfinite(piece))
    assert np.hypot(*(piece[:, :2] - res.filter_poses[first:, :2]).T).mean() < 0.05


def test_the_back_ends_gauge_is_the_filters(intel_head, default_run, monkeypatch):
    """Whatever pose the graph holds fixed, the output is put in the frame that fits the filter's
    trajectory: a back end that returned the trajectory moved rigidly changes nothing."""
    import robot_agent.backend.batch as replay_mod
    from shared.geometry import compose

    log, _ = intel_head
    res, _ = default_run
    moved = np.array([3.0, -2.0, 0.7])
    monkeypatch.setattr(
        replay_mod,
        "run_backend",
        lambda s, p, o, pts, c, h=None, j=None: (compose(np.broadcast_to(moved, p.shape), p), {}),
    )
    out, _ = replay_mod.correct_trajectory(log, 0, res.stamps_s, res.filter_poses, SlamConfig())
    np.testing.assert_allclose(out[:, :2], res.filter_poses[:, :2], atol=1e-6)
    # the start gauge (an agent's: its map frame stays its start frame) keeps the first pose
    # where the filter had it, and the corrected motion with it
    start, _ = replay_mod.correct_trajectory(
        log, 0, res.stamps_s, res.filter_poses, SlamConfig(), gauge="start"
    )
    np.testing.assert_allclose(start, res.filter_poses, atol=1e-9)
    with pytest.raises(ValueError, match="gauge"):
        replay_mod.correct_trajectory(log, 0, res.stamps_s, res.filter_poses, SlamConfig(), gauge="end")


def test_the_start_gauge_keeps_the_first_pose_and_the_corrected_motion(intel_head, default_run):
    from robot_agent.backend import correct_trajectory
    from shared.geometry import relative

    log, _ = intel_head
    res, _ = default_run
    first = 600
    stamps, poses = res.stamps_s[first:], res.filter_poses[first:]
    fit, _ = correct_trajectory(log, first, stamps, poses, SlamConfig())
    start, _ = correct_trajectory(log, first, stamps, poses, SlamConfig(), gauge="start")
    np.testing.assert_allclose(start[0], poses[0], atol=1e-9)
    step_fit, step_start = relative(fit[:-1], fit[1:]), relative(start[:-1], start[1:])
    np.testing.assert_allclose(step_start, step_fit, atol=1e-9)


def test_remap_builds_the_map_along_the_given_poses(intel_head, default_run):
    """Mapping with known poses (the back end's path, published by a log piece's agent): the
    particles sit exactly on the given poses, the map moves with them, and the scans drawn at
    those poses lie on it."""
    from robot_agent.backend import remap
    from shared.geometry import apply_points, apply_segments, compose

    log, _ = intel_head
    res, _ = default_run
    cfg = SlamConfig()
    first, n = 300, 400
    poses = res.poses[first : first + n]
    a = remap(log, first, poses, cfg)
    assert a.particles.n == 1 and a.stats["relocalizations"] == 0
    stamps, traj = a.best_trajectory()
    np.testing.assert_array_equal(stamps, log.stamps_s[first : first + n])
    assert 0 < a.step_index < n  # some scans bridged ...
    d = traj - poses
    d[:, 2] = (d[:, 2] + np.pi) % (2 * np.pi) - np.pi
    assert np.abs(d).max() < 1e-9  # ... and every scan at its given pose, the bridged ones too
    # the map is drawn along the poses: moved rigidly, they give the same map moved rigidly
    moved = np.array([2.0, -1.0, 0.5])
    b = remap(log, first, compose(np.broadcast_to(moved, poses.shape), poses), cfg)
    ma, mb = a.best_map(), b.best_map()
    np.testing.assert_array_equal(ma.valid, mb.valid)
    gap = np.abs(mb.seg[mb.valid] - apply_segments(moved, ma.seg[ma.valid])).max(axis=(1, 2))
    # (rounding can tip a gate: 1 of 38 elements took a different extension when measured)
    assert np.mean(gap < 1e-6) >= 0.9, np.sort(gap)[-5:]
    # and the scans at those poses lie on it
    from robot_agent.slam.extraction import scan_points
    from shared.metrics import nearest_segment

    def world_points(i):
        scan = log.scan(first + i)
        xy = scan_points(scan.ranges_m, scan.angles_rad, cfg.extraction, scan.range_max_m)
        return apply_points(poses[i], apply_points(scan.laser_offset, xy))

    pts = np.vstack([world_points(i) for i in range(0, n, 20)])
    d, _ = nearest_segment(pts, ma.seg[ma.valid])
    assert np.median(d) < 0.022, np.median(d)  # measured 0.0203 (0.0192 with the drawn poses recorded)


# --- the other development logs' excerpts (tests/data/README.md): 361 beams without ODOM lines,
# odometry that turns by up to 15° more or less than the robot in one step (MIT-CSAIL), and a
# 1° laser with in-place turns then a long corridor (ACES)


@pytest.fixture(scope="module")
def mit_csail_head():
    return read_log(DATA / "mit_csail_head.clf.gz"), read_relations(DATA / "mit_csail_head.relations")


@pytest.fixture(scope="module")
def aces_head():
    return read_log(DATA / "aces_head.clf.gz"), read_relations(DATA / "aces_head.relations")


def test_accuracy_on_the_mit_csail_excerpt(mit_csail_head):
    log, rel = mit_csail_head
    assert len(log) == 400 and log.beam_counts.max() == 361 and len(log.odom_stamps_s) == 0
    res, err = score(log, rel, SlamConfig())
    s = err.summary()
    assert s["trans_mean_m"] <= 0.035  # measured 0.024 (seed 0; 0.027 before point_angle_gate_rad)
    assert s["rot_mean_deg"] <= 0.8  # measured 0.49 (0.60)
    assert res.slam.stats["coarse_turns"] > 50  # the heading search did the work (below)


def test_the_heading_search_is_what_holds_mit_csail(mit_csail_head):
    """Without the coarse heading search the alignment starts where odometry's spikes put it and
    maps walls at wrong angles: measured 0.032 m, 1.43° (seed 0) against 0.024 m, 0.49° (before
    the points' own lines were checked, proposal.point_angle_gate_rad: 0.058 m, 2.50° against
    0.026 m, 0.60°)."""
    log, rel = mit_csail_head
    _, err = score(log, rel, apply_overrides(SlamConfig(), ["coarse.enabled=false"]))
    assert err.summary()["rot_mean_deg"] >= 1.2


def test_accuracy_on_the_aces_excerpt(aces_head):
    log, rel = aces_head
    _, err = score(log, rel, SlamConfig())
    s = err.summary()
    assert s["trans_mean_m"] <= 0.045  # measured 0.035 (seed 0; 0.034, 0.034 for seeds 1, 2)
    assert s["rot_mean_deg"] <= 0.45  # measured 0.31


def test_robotlaser1_with_beam_geometry_changing_every_scan(mit_csail_head, tmp_path):
    """The MIT-CSAIL excerpt written as ROBOTLASER1 lines whose beam geometry changes from scan to
    scan (each scan loses up to 6 beams at either end: its start angle and count change; the
    laser sits 0.12 m ahead of the robot, said by the lines' own poses), read back and mapped:
    as accurate as the log it came from (measured 0.027 m there)."""
    from robot_agent.sources import LaserLog, write_log

    log, rel = mit_csail_head
    rng = np.random.default_rng(7)
    n, beams = len(log), log.beam_counts.max()
    head, tail = rng.integers(0, 7, n), rng.integers(0, 7, n)
    counts = beams - head - tail
    ranges, angles = np.full((n, beams), np.nan), np.full((n, beams), np.nan)
    for i in range(n):
        scan = log.scan(i)
        ranges[i, : counts[i]] = scan.ranges_m[head[i] : beams - tail[i]]
        angles[i, : counts[i]] = scan.angles_rad[head[i] : beams - tail[i]]
    offset = np.array([0.12, 0.0, 0.0])  # the robot is 0.12 m behind the laser the scans came from
    robot = compose(log.odometry, inverse(offset))
    varying = LaserLog.from_arrays(
        log.stamps_s, ranges, angles, robot, offset, log.range_max_m, beam_counts=counts
    )
    write_log(tmp_path / "varying.clf", varying)
    back = read_log(tmp_path / "varying.clf")
    assert back.kind == "ROBOTLASER1" and len(np.unique(back.beam_counts)) > 5
    np.testing.assert_allclose(back.laser_offset, offset, atol=1e-5)  # poses written to 1 µm
    res = replay(back, SlamConfig(), seed=0, progress=False)
    # the trajectory is the robot's: relations of the laser's motion compare against its laser poses
    laser = compose(res.poses, offset)
    err = relations_error(res.stamps_s, laser, rel)
    assert err.summary()["trans_mean_m"] <= 0.035  # measured 0.025
    assert err.summary()["rot_mean_deg"] <= 0.8  # measured 0.55
