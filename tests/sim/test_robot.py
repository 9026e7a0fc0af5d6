"""Diff-drive kinematics, limits, route following, LiveSim."""

from __future__ import annotations

import numpy as np
import pytest
from shapely.geometry import LineString, Point, box

from robot_agent.sim.robot import RobotConfig, RouteFollower, drive_route, integrate_pose, limit_velocity
from robot_agent.sim.simulate import LiveSim, SimConfig, simulate_robot
from robot_agent.sim.world import make_world, walls_geometry
from robot_agent.sim.worlds import builtin_world


def test_defaults():
    cfg = RobotConfig()
    assert cfg.max_v_mps == 0.6 and cfg.max_w_radps == 1.0
    assert cfg.dt_s == pytest.approx(0.05)


def test_integrate_pose_straight_turn_and_arc():
    np.testing.assert_allclose(integrate_pose([1.0, 2.0, 0.0], 1.0, 0.0, 2.0), [3.0, 2.0, 0.0])
    np.testing.assert_allclose(integrate_pose([1.0, 2.0, 0.0], 0.0, 0.5, 1.0), [1.0, 2.0, 0.5])
    # quarter circle of radius v / w = 2 m, turning left from heading 0
    end = integrate_pose([0.0, 0.0, 0.0], 1.0, 0.5, np.pi)
    np.testing.assert_allclose(end, [2.0, 2.0, np.pi / 2], atol=1e-12)
    # exact arcs compose: many small steps land on the same pose
    pose = np.zeros(3)
    for _ in range(100):
        pose = integrate_pose(pose, 1.0, 0.5, np.pi / 100)
    np.testing.assert_allclose(pose, end, atol=1e-12)
    # batch axes broadcast
    batch = integrate_pose(np.zeros((4, 3)), np.array([0.0, 1.0, 1.0, 2.0]), 0.0, 1.0)
    np.testing.assert_allclose(batch[:, 0], [0.0, 1.0, 1.0, 2.0])


def test_limit_velocity_respects_acceleration_and_speed():
    cfg = RobotConfig()
    v, w = limit_velocity(5.0, 5.0, 0.0, 0.0, cfg)
    assert v == pytest.approx(cfg.max_acc_mps2 * cfg.dt_s)
    assert w == pytest.approx(cfg.max_ang_acc_radps2 * cfg.dt_s)
    v, w = limit_velocity(5.0, -5.0, 0.6, -1.0, cfg)
    assert (v, w) == (cfg.max_v_mps, -cfg.max_w_radps)
    v, _ = limit_velocity(-1.0, 0.0, 0.01, 0.0, cfg)
    assert v == 0.0  # never backwards


@pytest.fixture(scope="module")
def office_run():
    w = builtin_world("office")
    cfg = RobotConfig()
    poses, vel = drive_route(w.routes[0], w.starts[0], cfg, 200.0)
    return w, cfg, poses, vel


def test_route_follower_returns_to_start_and_visits_every_waypoint(office_run):
    w, _, poses, _ = office_run
    driven = np.r_[0.0, np.cumsum(np.hypot(*np.diff(poses[:, :2], axis=0).T))]
    lap_m = LineString(np.vstack([w.routes[0], w.routes[0][:1]])).length
    near_start = np.hypot(*(poses[:, :2] - w.starts[0][:2]).T) < 0.2
    assert np.any(near_start & (driven > 0.95 * lap_m))  # a lap closes at the start
    # every waypoint (room corners included) reached within the turning tolerance
    for waypoint in w.routes[0]:
        assert np.hypot(*(poses[:, :2] - waypoint).T).min() < 0.4


def test_true_path_keeps_clearance(office_run):
    w, _, poses, _ = office_run
    assert LineString(poses[:, :2]).distance(walls_geometry(w)) > 0.2


def test_commands_within_limits(office_run):
    _, cfg, _, vel = office_run
    assert vel[:, 0].min() >= 0.0 and vel[:, 0].max() <= cfg.max_v_mps + 1e-12
    assert np.abs(vel[:, 1]).max() <= cfg.max_w_radps + 1e-12
    acc = np.abs(np.diff(vel, axis=0)) / cfg.dt_s
    assert acc[:, 0].max() <= cfg.max_acc_mps2 + 1e-9
    assert acc[:, 1].max() <= cfg.max_ang_acc_radps2 + 1e-9
    assert vel[:, 0].max() == pytest.approx(cfg.max_v_mps)  # it does reach cruise speed


def test_follower_handles_retraced_legs_and_crossings():
    # a figure eight with an out-and-back spur: progress must follow the order, not the nearest leg
    route = np.array([(0, 0), (10, 0), (10, 5), (5, 5), (5, -5), (5, 5), (0, 5)], dtype=float)
    cfg = RobotConfig()
    follower = RouteFollower(route, [-1.0, 0.0], cfg)
    assert follower.length_m == pytest.approx(10 + 5 + 5 + 10 + 10 + 5 + 5)
    start = np.array([0.0, 4.0, -np.pi / 2])
    poses, _ = drive_route(route, start, cfg, 120.0)
    assert np.hypot(*(poses[:, :2] - [5.0, -5.0]).T).min() < 0.35  # the spur's end is reached
    dev = [LineString(np.vstack([route, route[:1]])).distance(Point(p)) for p in poses[::10, :2]]
    assert max(dev) < 0.15


def test_live_sim_follows_the_same_path_as_simulate_robot():
    w = builtin_world("office")
    cfg = SimConfig()
    run = simulate_robot(w, 1, 20.0, seed=3, cfg=cfg)
    sim = LiveSim(w, 1, seed=3, cfg=cfg)
    truths, stamps = [], []
    for scan in sim.scans(20.0):
        stamps.append(scan.stamp_s)
        truths.append(sim.truth)
        assert scan.ranges_m.shape == (cfg.lidar.beams,)
    np.testing.assert_allclose(stamps, run.stamps_s)
    np.testing.assert_allclose(truths, run.truth, atol=1e-12)


def test_live_sim_external_velocity_and_bumper():
    world = make_world("room", [box(0, 0, 6, 4)], routes=[[(1, 2), (5, 2), (5, 3)]])
    sim = LiveSim(world, 0, seed=0, start=np.array([3.0, 2.0, 0.0]))
    sim.set_velocity(10.0, 0.0)  # too fast: clipped to max_v
    for _ in range(200):  # 10 s: would be 6 m
        sim.step()
        assert sim.truth[0] <= 6.0 - sim.cfg.robot.radius_m + 1e-9
    assert sim.bumped
    assert sim.truth[0] > 5.5  # drove up to the wall
    sim.set_velocity(0.0, 1.0)  # turning in place is allowed at the wall
    sim.step()
    assert not sim.bumped
    odo_before = sim.odometry
    sim.follow_route()
    for _ in range(400):
        sim.step()
    assert not np.array_equal(sim.odometry, odo_before)
