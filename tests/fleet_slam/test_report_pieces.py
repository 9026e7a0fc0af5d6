"""A real log's pieces scored on the reference relations: all merged relations, those across
pieces, and a pair of pieces placed apart from each other flagged as a wrong merge."""

from __future__ import annotations

from dataclasses import dataclass
from types import SimpleNamespace

import numpy as np

from fleet_slam.report import WRONG_MERGE_M, _log_scores
from shared.geometry import compose, relative
from shared.metrics import Relations, write_relations


@dataclass
class _Log:
    stamps: np.ndarray
    poses: np.ndarray

    def odometry_track(self):
        return self.stamps, self.poses


def _setup(tmp_path, offset_m: float):
    """A loop driven in 3 pieces of 100 poses; relations between poses 1 and 5 steps apart and
    across the whole run; the third piece moved by ``offset_m`` (placed apart)."""
    t = np.arange(300) * 0.5
    theta = t / t[-1] * 2 * np.pi
    truth = np.column_stack([5 * np.cos(theta), 5 * np.sin(theta), theta + np.pi / 2])
    i = np.concatenate([np.arange(299), np.arange(295), [10, 150]])
    j = np.concatenate([np.arange(1, 300), np.arange(5, 300), [250, 290]])
    write_relations(tmp_path / "r.relations", Relations(t[i], t[j], relative(truth[i], truth[j])))
    pieces = [(0, 100), (100, 200), (200, 300)]
    stamps = [t[a:b] for a, b in pieces]
    poses = [truth[a:b].copy() for a, b in pieces]
    poses[2] = compose(np.array([offset_m, 0.0, 0.0]), poses[2])
    cfg = SimpleNamespace(relations=str(tmp_path / "r.relations"))
    split = SimpleNamespace(pieces=pieces, log=_Log(t, truth))
    return _log_scores(cfg, tmp_path, stamps, poses, split, ["robot1", "robot2", "robot3"])


def test_pieces_placed_right_score_zero_across(tmp_path):
    res = _setup(tmp_path, 0.0)
    assert res["relations"]["trans_mean_m"] < 1e-5  # (the relations file holds 6 decimals)
    assert res["relations_across_scored"] == 2 * (1 + 5) + 2  # at each cut: 1 + 5 relations; 2 long ones
    assert res["relations_across"]["trans_mean_m"] < 1e-5
    assert res["wrong_piece_pairs"] == []


def test_a_piece_placed_apart_is_a_wrong_merge_with_each_neighbour(tmp_path):
    res = _setup(tmp_path, 2.0 * WRONG_MERGE_M)
    assert res["relations_across"]["trans_max_m"] > WRONG_MERGE_M
    assert res["wrong_piece_pairs"] == [["robot1", "robot3"], ["robot2", "robot3"]]
    # within the pieces nothing changed: only relations across the moved piece carry the offset
    small = _setup(tmp_path, 0.5 * WRONG_MERGE_M)
    assert small["wrong_piece_pairs"] == []
