"""The agent's bus-free core: what it publishes from a real filter run (no zenoh here)."""

import numpy as np
import pytest

from robot_agent.agent import AgentConfig, AgentCore, paced
from robot_agent.publish import PublishConfig, directed, top_particle_maps
from robot_agent.sim import LiveSim, builtin_world
from robot_agent.slam.fastslam import FastSLAM, SlamConfig
from shared import codec
from shared.messages import PoseUpdate, RobotMap


@pytest.fixture(scope="module")
def run():
    """30 s of robot 0 in the office, 10 particles; the core steps with the default periods."""
    sim = LiveSim(builtin_world("office"), 0, seed=0)
    core = AgentCore("robot1", FastSLAM(SlamConfig(particles=10), np.random.default_rng(0)), AgentConfig())
    maps, poses = [], []
    for s in sim.scans(30.0):
        core.step(s)
        if (p := core.pose_message()) is not None:
            poses.append(p)
        if (m := core.map_messages()) is not None:
            maps.append(m)
    return core, maps, poses


def test_directed_puts_the_facing_on_the_left():
    seg = np.array([[[0.0, 0.0], [1.0, 0.0]], [[0.0, 0.0], [1.0, 0.0]]])
    out = directed(seg, np.array([np.pi / 2, -np.pi / 2]))  # seen from above / from below
    assert np.array_equal(out[0], seg[0])
    assert np.array_equal(out[1], seg[1][::-1])


def test_pose_updates_at_the_pose_period_with_increasing_seq(run):
    _, _, poses = run
    stamps = np.array([p.stamp_s for p in poses])
    assert all(isinstance(p, PoseUpdate) for p in poses)
    assert [p.seq for p in poses] == list(range(len(poses)))
    assert np.all(np.diff(stamps) >= 0.2 - 1e-9)  # 5 Hz at most
    assert 30.0 / 0.2 * 0.6 < len(poses) <= 30.0 / 0.2 + 1


def test_maps_are_published_when_changed_and_round_trip_the_wire(run):
    core, maps, _ = run
    assert 5 <= len(maps) <= 31  # at most one per second of source time
    last = maps[-1]
    assert all(isinstance(c, RobotMap) and c.robot == "robot1" and c.session == core.session for c in last)
    assert [m[0].seq for m in maps] == list(range(len(maps)))
    whole = codec.Assembler().add(codec.decode(codec.encode(last[0])))
    assert whole is not None and len(whole.seg) > 20
    # elements are directed (facing = left normal) and lie on the office's walls
    assert np.all(whole.members >= 1) and np.all(whole.members < 2**whole.n_particles)
    assert whole.particle_weights.sum() <= 1.0 + 1e-9


def test_an_unchanged_map_is_not_sent_again_but_can_be_forced(run):
    core, _, _ = run
    core._next_map_s = -np.inf  # due now; the filter has not moved since the last map
    assert core.map_messages() is None
    forced = core.map_messages(force=True)
    assert forced is not None and forced[0].seq == core.map_seq - 1


def test_top_particles_share_elements_through_the_membership_mask(run):
    core, _, _ = run
    arrays = top_particle_maps(core.slam, PublishConfig(top_particles=5))
    shared_by = np.array([bin(int(m)).count("1") for m in arrays.members])
    assert len(arrays.particle_weights) == 5
    assert shared_by.max() >= 2  # resampled particles hold identical versions: sent once
    pairs = set(zip(arrays.element.tolist(), map(tuple, arrays.seg.reshape(-1, 4).tolist()), strict=True))
    assert len(pairs) == len(arrays.element)  # no (element, version) twice
    single = top_particle_maps(core.slam, PublishConfig(top_particles=1))
    assert np.all(single.members == 1)
    assert len(single.seg) <= len(arrays.seg)


def test_prior_travels_with_every_chunk():
    slam = FastSLAM(SlamConfig(particles=3), np.random.default_rng(0))
    core = AgentCore("r2", slam, prior=np.array([1.0, 2.0, 0.5]))
    sim = LiveSim(builtin_world("office"), 1, seed=1)
    for s in sim.scans(3.0):
        core.step(s)
    chunks = core.map_messages(force=True)
    assert np.allclose(chunks[0].prior, [1.0, 2.0, 0.5]) and chunks[0].prior_sigma is not None


def test_paced_follows_the_source_clock_and_stops():
    import threading
    import time

    from robot_agent.sources.base import Scan

    scans = [
        Scan(100.0 + 0.1 * i, np.zeros(3), np.zeros(3), np.zeros(3), np.zeros(3), 10.0) for i in range(6)
    ]
    t = time.monotonic()
    assert len(list(paced(iter(scans), 2.0, threading.Event()))) == 6
    assert time.monotonic() - t >= 0.5 * 0.5 / 2.0  # 0.5 s of source time at 2x takes ~0.25 s
    stop = threading.Event()
    stop.set()
    assert list(paced(iter(scans), 0.0, stop)) == []


def test_a_rebuilt_map_and_the_corrected_pose_are_published_next():
    """At the end of a run the back end's rebuilt map (a one-particle filter) and corrected pose
    replace the filter's; both go out on the next publication, whatever the periods."""
    scans = list(LiveSim(builtin_world("office"), 1, seed=0).scans(8.0))
    core = AgentCore("robot2", FastSLAM(SlamConfig(particles=5), np.random.default_rng(0)), AgentConfig())
    for s in scans:
        core.step(s)
        core.pose_message(), core.map_messages()
    assert core.pose_message() is None and core.map_messages() is None  # nothing due
    other = FastSLAM(SlamConfig(particles=1), np.random.default_rng(1))
    for s in scans:
        other.step(s.stamp_s, s.odometry, s.ranges_m, s.angles_rad, s.laser_offset, s.range_max_m)
    corrected = np.array([1.0, -2.0, 0.25])
    core.rebuilt(other, corrected)
    pose = core.pose_message()
    assert pose is not None and np.array_equal(pose.pose, corrected)
    chunks = core.map_messages()
    assert chunks is not None and len(chunks[0].particle_weights) == 1  # the rebuilt map's
    whole = codec.Assembler().add(codec.decode(codec.encode(chunks[0])))
    assert whole is not None and len(whole.seg) > 5
