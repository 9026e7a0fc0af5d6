"""The log demo's half-time figure: each piece's trajectory as published at half its scans, in the
frame of the fused map the server had published by then, scored on the relations it covers."""

import json
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from fleet_slam.report import _half_time
from fleet_slam.watch import Update
from shared.geometry import compose
from shared.metrics import Relations, read_relations, relations_error, write_poses

DATA = Path(__file__).parents[1] / "data"


class Fused:
    def __init__(self, version, placed):
        self.version, self.placed = version, placed

    def robot(self, name):
        t = self.placed.get(name)
        return None if t is None else SimpleNamespace(merged=True, transform=t)


def test_half_time_scores_the_snapshots_in_the_fused_frame_of_that_moment(tmp_path):
    rel = read_relations(DATA / "intel_head.relations")
    t = np.unique(np.concatenate([rel.t1_s, rel.t2_s]))
    rng = np.random.default_rng(0)
    truth = np.cumsum(rng.normal(0, [0.05, 0.05, 0.02], (len(t), 3)), axis=0)  # any path
    split = SimpleNamespace(log=SimpleNamespace(odometry_track=lambda: (t, truth)))
    g = np.array([3.0, -1.0, 0.4])  # robot2's frame in the global frame
    own = compose(np.array([-3.0, 1.0, 0.0]), truth)  # robot2's own frame: anything rigid
    write_poses(tmp_path / "robot2.snapshot.poses.txt", t, own)
    write_poses(tmp_path / "robot1.snapshot.poses.txt", t[:5], truth[:5])
    for name, moment in (("robot1", 10.0), ("robot2", 12.0)):
        (tmp_path / f"{name}.snapshot.json").write_text(json.dumps({"monotonic_s": moment, "scans": 5}))
    fused_then = Fused(7, {"robot2": g})
    updates = [Update(11.0, fused_then, "put"), Update(13.0, Fused(8, {}), "put")]
    cfg = SimpleNamespace(relations=str(DATA / "intel_head.relations"))
    half = _half_time(cfg, tmp_path, ["robot1", "robot2"], updates, 2.0, split)
    assert half["fused_version"] == 7 and half["merged"] == ["robot2"]  # the map of that moment
    assert half["at_s"] == 10.0 and half["relations_scored"] > 0
    # robot2's snapshot put in the global frame is a rigid move of ``truth``: the same error
    keep = (rel.t1_s <= t.max() + 0.5) & (rel.t2_s <= t.max() + 0.5)
    direct = relations_error(t, truth, Relations(rel.t1_s[keep], rel.t2_s[keep], rel.delta[keep]), t, truth)
    assert half["relations"]["n"] == half["relations_scored"] == int(keep.sum())
    assert half["relations"]["trans_mean_m"] == pytest.approx(
        direct.summary()["trans_mean_m"], abs=1e-6
    )  # (files: 9 digits)
    (tmp_path / "robot1.snapshot.json").unlink()
    assert _half_time(cfg, tmp_path, ["robot1", "robot2"], updates, 2.0, split) is None
