"""A simulated agent's scan source keeps its scans for the back end at the end of the run."""

import argparse

import numpy as np

import robot_agent.service as service


def _source(duration_s: float) -> service.SimSource:
    args = argparse.Namespace(world="office", route=0, start=None, duration=duration_s, explore=False, seed=0)
    return service.SimSource(args, slam=None)


def test_the_kept_scans_are_the_scans_as_a_log():
    src = _source(3.0)
    assert src.recorded_log() is None  # nothing yet
    scans = list(src.scans())
    log = src.recorded_log()
    assert len(log) == len(scans) == len(src.truth) > 10
    np.testing.assert_array_equal(log.stamps_s, [s.stamp_s for s in scans])
    np.testing.assert_allclose(log.ranges_m, [s.ranges_m for s in scans], rtol=1e-6)  # float32
    np.testing.assert_array_equal(log.odometry, [s.odometry for s in scans])
    assert log.angle_table_rad.shape == (1, scans[0].angles_rad.size)  # one geometry: the sim's
    np.testing.assert_array_equal(log.scan(-1).angles_rad, scans[-1].angles_rad)
    np.testing.assert_array_equal(log.laser_offset, scans[0].laser_offset)
    assert log.range_max_m == scans[0].range_max_m


def test_past_the_cap_it_keeps_no_more_and_has_no_log(monkeypatch):
    monkeypatch.setattr(service, "MAX_KEPT_SCANS", 5)
    src = _source(3.0)
    assert len(list(src.scans())) > 5
    assert len(src._ranges) == 5 and src.recorded_log() is None
