"""A robot that joins a fleet finds itself in the fused map (robot_agent/join.py), and the server
places it there once it checked the claim (map_server alignment.verify_join, Fleet) — without
processes (the processes: tests/integration/test_agent_join.py)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from map_server.config import FleetConfig
from map_server.fleet import Fleet
from robot_agent.agent import AgentConfig, AgentCore
from robot_agent.join import JoinConfig, Joiner, facing_of, locate, through_share
from robot_agent.sim import builtin_world
from robot_agent.slam.fastslam import FastSLAM, SlamConfig
from robot_agent.slam.relocalize import ScanRays
from shared.geometry import apply_segments, compose, relative
from tests.map_server.robots import robot_map_from_segments, scan_map, simulated

FIRST_S = 120.0  # robot 0's route mapped this long: the fused map
JOIN_S = 12.0  # robot 1's scans fed to its agent


def office_fleet() -> tuple[Fleet, np.ndarray]:
    """A fleet whose fused map is robot 0's map of the office (the reference: its start frame is
    the global frame), and the true transform of robot 1's map frame in it."""
    seg, _ = scan_map("office", 0, FIRST_S)
    fleet = Fleet(FleetConfig(), "srv")
    fleet.put_map(robot_map_from_segments(seg, "robot0"), 0.0)
    fleet.fuse(0.0)
    world = builtin_world("office")
    return fleet, relative(world.starts[0], world.starts[1])


def joined_agent(fused_seg: np.ndarray) -> tuple[AgentCore, list[tuple[float, list]]]:
    """robot 1's agent with --join's Joiner, fed JOIN_S of its scans; its maps as they went out."""
    core = AgentCore("robot1", FastSLAM(SlamConfig(), np.random.default_rng(1)), AgentConfig(speed=0))
    core.joiner = Joiner(fused_seg)
    sent = []
    for scan in simulated("office", 1, JOIN_S, 1).to_log().scans():
        core.step(scan)
        msgs = core.map_messages()
        if msgs:
            sent.append((float(scan.stamp_s), msgs))
    return core, sent


def test_a_joining_robot_finds_itself_in_the_fused_map_and_is_placed_there_at_once():
    fleet, truth = office_fleet()
    fused = fleet.latest()
    core, sent = joined_agent(fused.seg)
    j = core.joiner
    assert j.transform is not None, j.last.reason
    e = relative(truth, j.transform)
    assert np.hypot(e[0], e[1]) <= 0.1 and abs(e[2]) <= np.radians(1.0)
    t0 = sent[0][0]
    first_joined = next(t for t, msgs in sent if msgs[0].joined)
    assert first_joined - t0 <= 8.0  # found twice in a row within seconds of the start
    assert np.array_equal(core.map_whole[0].prior, j.transform) and core.map_whole[0].joined
    placed_at = None
    for t, msgs in sent:
        fleet.put_map(msgs[0], t - t0)
        f = fleet.fuse(t - t0)
        s = f.robot("robot1") if f is not None else None
        if s is not None and s.status != "unaligned":
            placed_at = t - t0
            break
    assert placed_at is not None and placed_at <= first_joined - t0 + 1e-6  # the first joined map
    assert s.status == "aligned" and fleet.robots["robot1"].alignment.reason.startswith("joined:")
    e = relative(truth, s.transform)
    assert np.hypot(e[0], e[1]) <= 0.05 and abs(e[2]) <= np.radians(0.5)


def test_a_claim_the_fused_map_does_not_bear_out_is_not_taken():
    """The server checks a joined robot's claim: moved 1.5 m off the truth it is refused, the robot
    stays unplaced (to be matched as any robot, once its map is mature)."""
    fleet, truth = office_fleet()
    _, sent = joined_agent(fleet.latest().seg)
    msgs = next(m for _, m in sent if m[0].joined)
    wrong = compose(np.array([1.5, 0.0, 0.0]), msgs[0].prior)
    fleet.put_map(dataclasses.replace(msgs[0], prior=wrong), 0.0)
    fleet.fuse(0.0)
    a = fleet.robots["robot1"].alignment
    assert a.status == "unaligned" and a.reason.startswith("join not verified")
    # the same map with its own claim is placed
    fleet.put_map(dataclasses.replace(msgs[0], seq=msgs[0].seq + 1), 1.0)
    f = fleet.fuse(1.0)
    e = relative(truth, f.robot("robot1").transform)
    assert f.robot("robot1").status == "aligned" and np.hypot(e[0], e[1]) <= 0.05


def test_a_place_found_twice_over_is_ambiguous_and_a_scan_that_sees_through_walls_refutes_one():
    fleet, truth = office_fleet()
    fused = fleet.latest().seg
    seg, _ = scan_map("office", 1, 6.0)  # robot 1's first metres, in its start frame
    own = seg
    pose = np.zeros(3)  # the robot at its start
    cfg = JoinConfig()
    a = locate(fused, own, facing_of(own), pose, cfg)
    assert a.ok, a.reason
    e = relative(truth, a.transform)
    assert np.hypot(e[0], e[1]) <= 0.1
    # the fused map twice, the copy 40 m away: two places explain the robot's map alike
    twice = np.concatenate([fused, apply_segments(np.array([40.0, 0.0, 0.0]), fused)])
    b = locate(twice, own, facing_of(own), pose, cfg)
    assert not b.ok and b.reason.startswith("ambiguous")
    # the robot's own scan refutes the copy whose surroundings it would see through
    sim = simulated("office", 1, 6.0, 1)
    rays = ScanRays(sim.ranges_m[0], sim.angles_rad, sim.laser_offset, sim.range_max_m)
    at_truth = through_share(truth[None], fused, rays, cfg.through_m)[0]
    shifted = through_share(compose(truth, np.array([0.0, 1.0, 0.0]))[None], fused, rays, cfg.through_m)[0]
    assert at_truth <= 0.02 < cfg.max_through < shifted


def test_the_join_is_given_up_after_its_window_and_the_robot_maps_alone():
    j = Joiner(np.zeros((0, 2, 2)), JoinConfig(window_s=3.0))
    for t in np.arange(0.0, 5.0, 0.2):
        assert not j.step(float(t), np.zeros((0, 2, 2)), np.zeros(0), np.zeros(3))
    assert j.given_up and j.transform is None and j.attempts == 4  # at 0, 1, 2, 3 s


def test_prior_and_join_exclude_each_other():
    import argparse

    from robot_agent.service import add_arguments, run

    p = argparse.ArgumentParser()
    add_arguments(p)
    args = p.parse_args(["--robot", "r", "--world", "office", "--prior", "1,2,0", "--join"])
    with pytest.raises(ValueError, match="--prior and --join: choose one"):
        run(args)


def test_bench_join_counts_a_true_join_and_the_placement():
    from tests.benchscripts import bench_script

    with bench_script("bench_join") as bench:
        row = bench.run_pair(("office", 0, 1, 60.0, 10.0))
    assert row["joined_s"] is not None and not row["wrong_join"], row
    assert row["join_error_m"] <= 0.1 and row["placed_status"] == "aligned" and row["placed_s"] <= 8.0
    # fed to the end of the run (with both robots' free space): still where the truth says
    assert row["final_status"] == "aligned" and row["final_error_m"] <= 0.1, row
    assert not row["wrong_placed"] and not row["wrong_at_end"] and row["undone_s"] is None


def test_a_claim_undone_is_not_verified_again():
    """Warehouse, robot 3's first 120 s the fused map: robot 0 joins the half-turned image of its
    start at 5 s; the fleet places it there, the free space seen undoes it at 56 s — and the claim
    is not checked again (it was, at every fusion, until at 95 s the overlap's share allowance let
    the same 2.5 m of contradiction through: a wrong merge at the end, 2026-12-05)."""
    from tests.benchscripts import bench_script

    with bench_script("bench_join") as bench:
        row = bench.run_pair(("warehouse", 3, 0, 120.0, 120.0))
    assert row["wrong_join"] and row["wrong_placed"], row  # the scenario: a wrong join, placed
    assert row["undone_s"] is not None and not row["wrong_at_end"], row


def test_a_refuted_claim_is_kept_with_the_robot_and_forgotten_with_its_session():
    from map_server.state import RobotState

    fleet, _ = office_fleet()
    _, sent = joined_agent(fleet.latest().seg)
    m = next(m for _, m in sent if m[0].joined)[0]
    r = RobotState("robot1", 1, map=m)
    assert not r.claim_refuted()
    r.refute_claim()
    assert r.claim_refuted()
    back = RobotState.from_dict("robot1", r.to_dict(), m)  # a restarted server keeps it
    assert back.claim_refuted()
    other = dataclasses.replace(m, prior=compose(np.array([1.0, 0.0, 0.0]), m.prior))
    assert not RobotState("robot1", 1, map=other, refuted_claim=r.refuted_claim).claim_refuted()
    d = r.to_dict()
    del d["refuted_claim"]  # a snapshot from before the field
    assert not RobotState.from_dict("robot1", d, m).claim_refuted()
    r.new_session()
    assert r.refuted_claim is None
