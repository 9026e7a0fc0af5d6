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


def test_a_simulated_robot_runs_without_end_and_keeps_its_newest_truth():
    """An agent on a simulated world keeps its path (and the truth beside it) for the newest
    SIM_HISTORY_SCANS scans unless told otherwise; the truth goes with that bound."""
    import dataclasses

    from robot_agent.slam.config import command_line_config

    cfg = service.endless_config(command_line_config([], 10))
    assert cfg.filter.history_scans == service.SIM_HISTORY_SCANS
    chosen = service.endless_config(command_line_config(["filter.history_scans=500"], 10))
    assert chosen.filter.history_scans == 500
    small = dataclasses.replace(cfg, filter=dataclasses.replace(cfg.filter, history_scans=10))
    slam = type("Slam", (), {"cfg": small})()
    args = argparse.Namespace(world="office", route=0, start=None, duration=20.0, explore=False, seed=0)
    src = service.SimSource(args, slam=slam)
    scans = list(src.scans())
    assert len(scans) > 40 and 10 <= len(src.truth) <= 12 and len(src.stamps) == len(src.truth)
    np.testing.assert_array_equal(src.stamps.view(), [s.stamp_s for s in scans][-len(src.stamps) :])


class _Corrector:
    def __init__(self):
        self.stats = {"loops": 3, "keyframes": 40, "update_s_max": 0.5, "retired_thinned": 7}
        self.updates = 9
        self.failures, self.last_failure = 0, ""


def test_the_back_end_report_says_what_the_bounds_dropped(capsys):
    slam = type("Slam", (), {"stats": {"scans_forgotten": 1234}})()
    core = type("Core", (), {"slam": slam, "corrector": _Corrector()})()
    service.BackendReport("robot1")(core)
    out = capsys.readouterr().out
    assert "3 loops, 40 keyframes, 9 updates" in out
    assert "path of the oldest 1234 scans forgotten, 7 keyframes thinned from the graph" in out


def test_the_back_end_report_warns_of_every_failed_update(capsys):
    corrector = _Corrector()
    core = type("Core", (), {"slam": type("Slam", (), {"stats": {}})(), "corrector": corrector})()
    report = service.BackendReport("robot1")
    report(core)
    assert "warning" not in capsys.readouterr().out
    corrector.failures, corrector.last_failure = 1, "ValueError: track: starts after the last keyframe"
    report(core)
    out = capsys.readouterr().out
    assert "warning: the online back end could not update (1 so far): ValueError: track" in out
    report(core)  # said once
    assert "warning" not in capsys.readouterr().out
