"""`fleet-slam demo` end to end (short): every output of docs/design.md, sane metrics, no process left."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

pytestmark = pytest.mark.integration


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    out = tmp_path_factory.mktemp("demo")
    run = subprocess.run(
        [sys.executable, "-m", "fleet_slam.cli", "demo", "--robots", "2", "--duration", "45",
         "--particles", "15", "--out", str(out)],
        capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-3000:]
    return out, run.stdout, json.loads((out / "metrics.json").read_text())


def test_outputs_of_the_design(demo):
    out, _, _ = demo
    for name in ("metrics.json", "map.geojson", "map.svg", "map.png", "world.geojson"):
        assert (out / name).stat().st_size > 100, name
    for robot in ("robot1", "robot2"):
        for suffix in (".poses.txt", ".tum"):
            assert (out / f"{robot}{suffix}").stat().st_size > 100
        assert (out / "agents" / f"{robot}.truth.txt").exists()
    features = json.loads((out / "map.geojson").read_text())["features"]
    assert features and all({"support", "robots"} <= set(f["properties"]) for f in features)


def test_known_starts_merge_accurately(demo):
    _, stdout, m = demo
    assert "fused map" in stdout and "robot1" in stdout
    assert m["all_merged"] and not m["wrong_merges"]
    for r in m["robots"].values():
        assert r["status"] in ("prior", "reference")
        assert r["transform_error_m"] <= 0.10 and r["transform_error_deg"] <= 1.0
        # the server's error alone: each map frame placed by its trajectory fitted to the truth
        assert r["transform_error_fit_m"] <= 0.10 and r["transform_error_fit_deg"] <= 1.0
        assert r["ate_m"] < 0.15
        assert r["bytes_per_s"]["total"] > 0
    assert m["fused_precision"] >= 0.9  # 45 s, 15 particles: looser than the 3-minute demo
    assert m["fused_completeness"] >= 0.5
    assert m["fused_precision_fit"] >= 0.9 and m["fused_completeness_fit"] >= 0.5


def test_each_agent_ends_with_its_back_end_and_publishes_the_rebuilt_map(demo):
    """At the end of its run an agent's online back end makes its last update (the first pose
    stays the filter's: the map frame is the start frame), the agent publishes the map its
    correction moves, then the map rebuilt along the corrected path, last."""
    import numpy as np

    from shared.metrics import read_poses

    out, _, _ = demo
    for robot in ("robot1", "robot2"):
        summary = json.loads((out / "agents" / f"{robot}.agent.json").read_text())
        assert summary["backend"] is not None and summary["backend"]["keyframes"] > 10
        text = (out / "logs" / f"{robot}.log").read_text()
        assert "published the corrected map" in text and summary["backend"]["final_update_in_time"]
        assert text.index("published the corrected map") < text.index(
            "published the map rebuilt along the corrected path"
        )
        _, poses = read_poses(out / "agents" / f"{robot}.poses.txt")
        _, filt = read_poses(out / "agents" / f"{robot}.filter.poses.txt")
        assert poses.shape == filt.shape and summary["scans"] == len(poses)
        np.testing.assert_allclose(poses[0], filt[0], atol=1e-6)


def test_no_process_left_behind(demo):
    out, _, _ = demo
    left = subprocess.run(["pgrep", "-f", str(out)], capture_output=True, text=True)  # server, agents
    assert left.returncode == 1 and left.stdout.strip() == ""  # 1: nothing matched
