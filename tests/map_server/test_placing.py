"""The alignment rounds' searches (map_server/placing.py): what an unplaced robot is searched against."""

from __future__ import annotations

import numpy as np

from map_server.config import FleetConfig
from map_server.fleet import Fleet
from shared.geometry import compose, inverse
from shared.metrics import transform_error
from tests.map_server.robots import robot_map_from_segments, scan_map


def _fleet_of_two() -> tuple[Fleet, np.ndarray]:
    """The office's robots 0 (the reference) and 1, exact maps of 175 s; robot 1's true place."""
    f = Fleet(FleetConfig(), "server")
    (seg0, start0), (seg1, start1) = scan_map("office", 0, 175.0), scan_map("office", 1, 175.0)
    f.put_map(robot_map_from_segments(seg0, "robot0"), 0.0)
    f.put_map(robot_map_from_segments(seg1, "robot1"), 1.0)
    f.fuse(1.0)
    assert f.robots["robot0"].alignment.status == "reference"
    return f, compose(inverse(start0), start1)


def test_a_robot_not_placed_against_the_rigid_maps_is_searched_against_the_bent_ones(monkeypatch):
    """A search that finds no place against the placed maps as their alignments put them is made
    again against them as the fleet's graph bent them (MIT-CSAIL in 3 pieces: the rigid placed
    piece was off where the newcomer met it); only when a placed map is bent at all."""
    f, truth = _fleet_of_two()
    whole, asked = f.global_segments, []

    def rigid_is_empty(exclude, lo=None, hi=None, rigid=False):
        asked.append(rigid)
        seg = whole(exclude, lo, hi)
        return seg[:0] if rigid else seg  # the rigid placed map shows nothing of the overlap

    monkeypatch.setattr(f, "global_segments", rigid_is_empty)
    r = f.robots["robot1"]
    a = f.placer.estimate(r, None, None, None, search=True)
    assert asked == [True] and a.status == "unaligned"  # no placed map is bent: one search

    ref = f.robots["robot0"]
    ref.bent = ref.layer  # the graph bent it (here: where it was)
    asked.clear()
    a = f.placer.estimate(r, None, None, None, search=True)
    assert asked == [True, False]
    assert a.status == "aligned" and "as the graph bent them" in a.reason
    err_m, err_rad = transform_error(a.transform, truth)
    assert err_m < 0.05 and err_rad < np.radians(0.5)
