"""`fleet-slam replay` outputs: files, metrics, the map rebuilt along the corrected path."""

import json
from pathlib import Path

import numpy as np

from fleet_slam.cli import main
from fleet_slam.replayrun import replay_to_dir
from robot_agent.slam.extraction import ExtractionConfig, scan_points
from robot_agent.sources import read_log
from shared.geometry import apply_points, compose, point_segment_distance
from shared.metrics import read_poses

DATA = Path(__file__).resolve().parents[1] / "data"
LOG, REL = DATA / "intel_head.clf.gz", DATA / "intel_head.relations"


def test_replay_writes_the_corrected_path_and_the_map_along_it(tmp_path):
    m = replay_to_dir(str(LOG), tmp_path, str(REL), limit=400, progress=False)
    for name in ("intel_head.poses.txt", "intel_head.filter.poses.txt", "intel_head.tum", "map.geojson",
                 "map.svg", "map.png", "metrics.json"):  # fmt: skip
        assert (tmp_path / name).stat().st_size > 0, name
    stamps, poses = read_poses(tmp_path / "intel_head.poses.txt")
    assert len(stamps) == 400 and m["scans"] == 400
    assert m["relations"]["n"] > 0 and m["relations"]["trans_mean_m"] < 0.05
    assert m["map_rebuild_s"] > 0 and m["map_segments"] >= 10
    # the map agrees with the written poses: the scans, put where those poses say, fall on it
    segs = np.array(
        [f["geometry"]["coordinates"] for f in json.loads((tmp_path / "map.geojson").read_text())["features"]]
    )
    log = read_log(LOG)
    dist = []
    for i in range(0, 400, 40):
        scan = log.scan(i)
        xy = scan_points(scan.ranges_m, scan.angles_rad, ExtractionConfig(), scan.range_max_m)
        xy = apply_points(compose(poses[i], scan.laser_offset), xy[np.hypot(*xy.T) < 5.0])
        dist.append(np.min(point_segment_distance(xy[:, None, :], segs[None]), axis=1))
    assert np.median(np.concatenate(dist)) < 0.03


def test_a_limit_before_the_first_relation_reports_none(tmp_path, capsys):
    assert main(["replay", str(LOG), "--relations", str(REL), "--limit", "20", "--out", str(tmp_path)]) == 0
    assert "no relation lies within the scans replayed" in capsys.readouterr().out
    m = json.loads((tmp_path / "metrics.json").read_text())
    assert "relations" not in m and m["scans"] == 20


def test_replay_says_what_the_reader_could_not_use(tmp_path, capsys):
    """A PARAM the reader cannot use is a warning on stderr and in metrics.json, and the log is
    mapped all the same."""
    import gzip

    text = gzip.decompress(LOG.read_bytes()).decode()
    log = tmp_path / "odd.clf"
    log.write_text("PARAM laser_front_laser_resolution 0.5 1.0 host 0\n" + text)
    m = replay_to_dir(str(log), tmp_path / "out", limit=50, progress=False)
    err = capsys.readouterr().err
    assert "warning:" in err and "180 beams do not fit" in err and "resolution 0.5 (line 1)" in err
    assert m["scans"] == 50 and m["log_warnings"] and "360 or 361" in m["log_warnings"][0]


def test_live_snapshots_score_what_the_robot_would_publish_then(tmp_path):
    """``--live K``: at the end of each K-th part of the run, the trajectory the robot would publish
    then — the filter's path as a run stopped there has it, corrected by the online back end —
    scored on the relations before it."""
    from robot_agent.replay import replay
    from robot_agent.slam.fastslam import SlamConfig

    m = replay_to_dir(str(LOG), tmp_path, str(REL), limit=900, progress=False, live=3)
    assert [row["scans"] for row in m["live"]] == [300, 600]
    assert 0 < m["live"][0]["n"] < m["live"][1]["n"] <= m["relations"]["n"]
    assert m["live_worst_trans_m"] == max(row["trans_mean_m"] for row in m["live"])
    log = read_log(LOG)
    full = replay(log, SlamConfig(), seed=0, progress=False, limit=900, snapshots=3)
    # a run stopped there with the same online back end (the filter continues from its
    # corrections): the filter's own path (the adopted correction taken out again: to rounding)
    stopped = replay(log, SlamConfig(), seed=0, progress=False, limit=600, snapshots=3)
    np.testing.assert_allclose(full.live[1].filter_poses, stopped.filter_poses, rtol=0, atol=1e-9)
    np.testing.assert_array_equal(full.live[1].stamps_s, stopped.stamps_s)
    assert full.live[1].poses.shape == stopped.filter_poses.shape
    assert "relations_online" in m and m["online_backend"]["updates"] > 1
