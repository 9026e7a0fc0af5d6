"""Replay over a log whose beam geometry changes from scan to scan (ROBOTLASER1 logs do): the
filter and the back end get each scan's own beams."""

from pathlib import Path

import numpy as np
import pytest

import robot_agent.backend.batch as batch_mod
import robot_agent.replay as replay_mod
from robot_agent.slam.config import apply_overrides
from robot_agent.slam.extraction import scan_points
from robot_agent.slam.fastslam import SlamConfig
from robot_agent.sources import LaserLog, read_log
from shared.geometry import apply_points

INTEL_HEAD = Path(__file__).resolve().parent / "data" / "intel_head.clf.gz"
N = 150


@pytest.fixture(scope="module")
def logs() -> tuple[LaserLog, LaserLog]:
    """The first N Intel scans as they are, and with every other scan's first beam (-90°) gone."""
    log = read_log(INTEL_HEAD, progress=False)
    angles = np.tile(log.scan(0).angles_rad, (N, 1))
    ranges = log.ranges_m[:N].copy()
    counts = np.full(N, 180)
    angles[1::2, :179], ranges[1::2, :179], counts[1::2] = angles[1::2, 1:], ranges[1::2, 1:], 179
    args = (log.odometry[:N], log.laser_offset, log.range_max_m, log.odom_stamps_s, log.odom_poses)
    varying = LaserLog.from_arrays(log.stamps_s[:N], ranges, angles, *args, beam_counts=counts)
    uniform = LaserLog.from_arrays(log.stamps_s[:N], log.ranges_m[:N], log.scan(0).angles_rad, *args)
    assert varying.geometry_beams.tolist() == [180, 179]
    return varying, uniform


def test_the_filter_gets_each_scans_beams(logs):
    varying, _ = logs
    seen = []

    class Recorder:
        def step(self, stamp_s, odometry, ranges_m, angles_rad, laser_offset, range_max_m, pose):
            seen.append((stamp_s, ranges_m, angles_rad))

    for i in (0, 1, 2, 3):
        batch_mod.feed(Recorder(), varying, i)
    assert [a.size for _, _, a in seen] == [180, 179, 180, 179]
    np.testing.assert_array_equal(seen[1][2][:2], np.radians([-89.0, -88.0]))
    np.testing.assert_array_equal(seen[1][1], varying.ranges_m[1, :179])
    assert [s for s, _, _ in seen] == varying.stamps_s[:4].tolist()


def test_the_back_end_gets_each_scans_points(logs, monkeypatch):
    varying, _ = logs
    got = {}

    def backend(stamps, poses, odometry, points, cfg, hints, jumps=None):
        got.update({i: points(i) for i in (0, 1)})
        return poses, {}

    monkeypatch.setattr(batch_mod, "run_backend", backend)
    cfg = SlamConfig()
    poses = np.zeros((4, 3))
    batch_mod.correct_trajectory(varying, 2, np.arange(4.0), poses, cfg)
    for i in (0, 1):  # scans 2 (180 beams) and 3 (179 beams)
        scan = varying.scan(2 + i)
        want = apply_points(
            scan.laser_offset, scan_points(scan.ranges_m, scan.angles_rad, cfg.extraction, 81.0)
        )
        np.testing.assert_array_equal(got[i], want)


def test_replay_over_varying_geometry_follows_the_same_path(logs):
    varying, uniform = logs
    cfg = apply_overrides(SlamConfig(), ["particles=5"])
    a = replay_mod.replay(varying, cfg, seed=0, progress=False)
    b = replay_mod.replay(uniform, cfg, seed=0, progress=False)
    assert a.poses.shape == b.poses.shape == (N, 3) and np.isfinite(a.poses).all()
    # the same walls seen through one beam fewer on every other scan: the same path, within centimetres
    assert np.abs(a.poses[:, :2] - b.poses[:, :2]).max() < 0.05, np.abs(a.poses - b.poses).max(axis=0)
