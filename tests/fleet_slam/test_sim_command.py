"""`fleet-slam sim` end to end: files written, logs replay, odometry drifts, truth scores zero."""

import json

import numpy as np
import pytest

from fleet_slam.cli import main
from robot_agent.sources import read_log
from shared.metrics import read_poses, read_relations, relations_error


@pytest.fixture(scope="module")
def sim_dir(tmp_path_factory):
    out = tmp_path_factory.mktemp("sim")
    assert (
        main(
            [
                "sim",
                "--world",
                "office",
                "--robots",
                "2",
                "--duration",
                "120",
                "--seed",
                "0",
                "--out",
                str(out),
            ]
        )
        == 0
    )
    return out


def test_writes_every_file(sim_dir):
    for name in ("robot1", "robot2"):
        for ext in (".clf", ".truth.txt", ".relations"):
            assert (sim_dir / f"{name}{ext}").stat().st_size > 0
    for f in ("world.geojson", "world.svg", "world.png"):
        assert (sim_dir / f).stat().st_size > 1000
    world = json.loads((sim_dir / "world.geojson").read_text())
    assert sum(f["properties"].get("kind") == "wall" for f in world["features"]) > 50
    svg = (sim_dir / "world.svg").read_text()
    assert svg.count("<polyline") == 2  # both true paths drawn


def test_logs_replay_and_match_truth(sim_dir):
    log = read_log(sim_dir / "robot1.clf")
    t, _truth = read_poses(sim_dir / "robot1.truth.txt")
    assert len(log) == len(t) == 601  # 120 s at 5 Hz, both ends
    np.testing.assert_allclose(log.stamps_s, t, atol=1e-6)
    assert log.ranges_m.shape == (601, 181)
    assert np.all(np.diff(log.stamps_s) > 0)
    np.testing.assert_allclose(log.odometry[0], 0.0, atol=1e-9)  # odometry frame starts at identity


def test_truth_scores_zero_and_odometry_drift_grows_with_span(sim_dir):
    log = read_log(sim_dir / "robot1.clf")
    rel = read_relations(sim_dir / "robot1.relations")
    t, truth = read_poses(sim_dir / "robot1.truth.txt")
    assert relations_error(t, truth, rel).trans_m.max() < 1e-5
    odo = relations_error(log.stamps_s, log.odometry, rel)
    span = rel.t2_s - rel.t1_s
    short, long_ = odo.trans_m[span < 5.0], odo.trans_m[span > 60.0]
    assert len(short) > 50 and len(long_) > 20
    assert long_.mean() > 5 * short.mean()  # biased slip: error grows with the span
    assert long_.mean() > 0.2


def test_bad_arguments_are_named(capsys, tmp_path):
    assert main(["sim", "--world", "nowhere", "--out", str(tmp_path)]) == 2
    assert "nowhere" in capsys.readouterr().err
    assert main(["sim", "--robots", "9", "--out", str(tmp_path)]) == 2
    assert "--robots" in capsys.readouterr().err
