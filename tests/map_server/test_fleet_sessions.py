"""A robot that restarts (a new session, a new map frame) loses nothing the fused map held: its
old session's map is kept as a retired piece where it was placed, persisted and restored, bounded
per robot; the new session is placed by its prior or matched against the fused map, its own old
piece included."""

import dataclasses
import json
import logging

import numpy as np

from map_server.config import FleetConfig
from map_server.fleet import Fleet
from shared.geometry import relative
from shared.metrics import map_quality, transform_error
from tests.map_server.robots import robot_map_from_segments, scan_map

SIGMA = np.array([0.05, 0.05, np.radians(1.0)])


def covered(before: np.ndarray, after: np.ndarray) -> float:
    """Share of the length of ``before`` that ``after`` covers (within 0.10 m and 5°)."""
    return map_quality(after, before).completeness


def robot(name, index, duration_s, session="s1", seq=1, prior=True):
    seg, start = scan_map("office", index, duration_s)
    kw = dict(prior=start, prior_sigma=SIGMA) if prior else {}
    return robot_map_from_segments(seg, name, session=session, seq=seq, **kw)


def two_robots_with_priors() -> Fleet:
    fleet = Fleet(FleetConfig(), "srv")
    fleet.put_map(robot("r0", 0, 90.0), 0.0)
    fleet.put_map(robot("r1", 1, 90.0), 0.0)
    fleet.fuse(0.0)
    return fleet


def row(fm, name):
    return [s.robot for s in fm.robots].index(name)


def test_a_restarted_robot_keeps_its_old_map_in_the_fused_map():
    fleet = two_robots_with_priors()
    before = fleet.latest()
    assert [s.status for s in before.robots] == ["prior", "prior"]
    # robot r1 restarts: a new session whose map is tiny so far (placed by its prior)
    fleet.put_map(robot("r1", 1, 5.0, session="s2"), 100.0)
    after = fleet.fuse(100.0)
    assert after.version == before.version + 1
    assert covered(before.seg, after.seg) >= 0.99  # nothing the fused map held is lost
    s = after.robot("r1")
    assert (s.session, s.status, s.n_elements) == ("s2", "prior", len(fleet.robots["r1"].layer))
    assert after.extra["retired_pieces"] == 1.0 and after.extra["robots_merged"] == 2.0
    # the old piece's walls are credited to r1: as many segments name r1 as before
    r1_before = sum(row(before, "r1") in before.prov_robot[a:b] for a, b in _spans(before))
    r1_after = sum(row(after, "r1") in after.prov_robot[a:b] for a, b in _spans(after))
    assert r1_after >= r1_before
    # a late map of the replaced session is ignored (the agent that sent it is gone)
    fleet.put_map(robot("r1", 1, 90.0, session="s1", seq=99), 101.0)
    assert fleet.robots["r1"].map.session == "s2" and fleet.fuse(101.0) is None


def _spans(fm):
    return zip(fm.prov_offsets[:-1], fm.prov_offsets[1:], strict=True)


def test_the_new_session_re_mapping_the_same_place_merges_into_the_old_piece():
    fleet = two_robots_with_priors()
    before = fleet.latest()
    fleet.put_map(robot("r1", 1, 90.0, session="s2"), 100.0)  # the same walls again
    after = fleet.fuse(100.0)
    assert covered(before.seg, after.seg) >= 0.99 and covered(after.seg, before.seg) >= 0.99
    assert len(after.seg) <= 1.05 * len(before.seg)  # merged, not doubled
    assert after.support.sum() == before.support.sum() + len(fleet.robots["r1"].layer)


def test_a_restarted_reference_robot_elsewhere_without_prior_is_matched_to_its_old_piece():
    """One robot, no priors: its first session defines the global frame. It restarts somewhere
    else (route 1's start): the new session must not become the reference again at identity,
    but be matched against its own old piece (maturity window, then confirmation)."""
    fleet = Fleet(FleetConfig(), "srv")
    seg0, start0 = scan_map("office", 0, 150.0)
    fleet.put_map(robot_map_from_segments(seg0, "r0"), 0.0)
    before = fleet.fuse(0.0)
    assert before.robot("r0").status == "reference"
    seg1, start1 = scan_map("office", 1, 150.0)
    for k, t in enumerate(np.arange(100.0, 170.0, 10.0)):
        fleet.put_map(robot_map_from_segments(seg1, "r0", session="s2", seq=k + 1), t)
        fm = fleet.fuse(t) or fleet.latest()
        assert covered(before.seg, fm.seg) >= 0.99  # kept all along
        if t < 130.0:
            assert fm.robot("r0").status == "unaligned"  # a young map is not evidence yet
    s = fm.robot("r0")
    assert s.status == "aligned" and s.session == "s2", fleet.robots["r0"].alignment.reason
    err_m, err_deg = transform_error(s.transform, relative(start0, start1))
    assert err_m < 0.05 and err_deg < 0.5  # exact maps: measured ~0.001 m
    assert fleet.reference is None and fm.extra["retired_pieces"] == 1.0


def test_retired_pieces_are_persisted_and_restored():
    fleet = two_robots_with_priors()
    fleet.put_map(robot("r1", 1, 20.0, session="s2"), 100.0)
    a = fleet.fuse(100.0)
    meta, maps = fleet.snapshot()
    meta = json.loads(json.dumps(meta, allow_nan=False))  # the store writes it as JSON
    assert set(maps) == {"r0", "r1", "r1~s1"} and maps["r1~s1"].session == "s1"
    back = Fleet.restore(meta, maps, FleetConfig(), "srv")
    b = back.latest()
    assert b.version == a.version
    np.testing.assert_array_equal(b.seg, a.seg)
    np.testing.assert_array_equal(b.prov_robot, a.prov_robot)
    for t in (200.0, 220.0, 240.0):  # and it goes on exactly as the original would (priors refined)
        x, y = fleet.fuse(t), back.fuse(t)
        assert (x is None) == (y is None)
        if x is not None:
            assert x.version == y.version and np.array_equal(x.seg, y.seg)
    assert [p.session for p in back.retired["r1"]] == ["s1"]
    back.put_map(robot("r1", 1, 90.0, session="s1", seq=5), 201.0)  # the old session, late
    assert back.robots["r1"].map.session == "s2"


def test_retired_pieces_are_bounded_per_robot(caplog):
    cfg = FleetConfig(max_retired=2)
    fleet = Fleet(cfg, "srv")
    fleet.put_map(robot("r0", 0, 90.0), 0.0)
    fleet.fuse(0.0)
    with caplog.at_level(logging.INFO, logger="fleet_slam.fleet"):
        for k in range(2, 6):  # four restarts, each placed by its prior
            fleet.put_map(robot("r0", 0, 90.0, session=f"s{k}"), 10.0 * k)
            fleet.fuse(10.0 * k)
    assert [p.session for p in fleet.retired["r0"]] == ["s3", "s4"]
    assert sum("oldest (s1" in m or "oldest (s2" in m for m in caplog.messages) == 2
    assert set(fleet.snapshot()[1]) == {"r0", "r0~s3", "r0~s4"}


def test_an_unplaced_session_that_is_replaced_is_dropped(caplog):
    fleet = two_robots_with_priors()
    fleet.put_map(robot("r2", 2, 30.0, prior=False), 1.0)  # matched later: unaligned now
    fleet.fuse(1.0)
    assert fleet.latest().robot("r2").status == "unaligned"
    with caplog.at_level(logging.INFO, logger="fleet_slam.fleet"):
        fleet.put_map(robot("r2", 2, 30.0, session="s2", prior=False), 2.0)
    assert "r2" not in fleet.retired and any("replaced unplaced" in m for m in caplog.messages)


def test_an_older_seq_of_the_current_session_is_still_ignored():
    fleet = two_robots_with_priors()
    m = fleet.robots["r0"].map
    fleet.put_map(dataclasses.replace(m, seq=0), 5.0)
    assert fleet.robots["r0"].map is m and fleet.fuse(5.0) is None
