"""Seeded end-to-end runs of the whole filter on real data (the Intel excerpt in tests/data)."""

from pathlib import Path

import numpy as np
import pytest

from robot_agent.replay import replay
from robot_agent.slam.config import apply_overrides
from robot_agent.slam.fastslam import SlamConfig
from robot_agent.sources import read_log
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
    assert s["trans_mean_m"] <= 0.03  # measured 0.018 (seed 0)
    assert s["rot_mean_deg"] <= 0.5  # measured 0.27; raw odometry 1.33
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
    from robot_agent.replay import correct_trajectory

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
    import robot_agent.replay as replay_mod
    from shared.geometry import compose

    log, _ = intel_head
    res, _ = default_run
    moved = np.array([3.0, -2.0, 0.7])
    monkeypatch.setattr(
        replay_mod,
        "run_backend",
        lambda s, p, o, pts, c, h=None: (compose(np.broadcast_to(moved, p.shape), p), {}),
    )
    out, _ = replay_mod.correct_trajectory(log, 0, res.stamps_s, res.filter_poses, SlamConfig())
    np.testing.assert_allclose(out[:, :2], res.filter_poses[:, :2], atol=1e-6)
