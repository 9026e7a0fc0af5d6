"""Robot maps as agents send them, built from a real FastSLAM run or from hand-made segments.

:func:`robot_map_from_slam` is what an agent publishes (robot_agent/publish.py): the top
particles' trusted elements, one row per distinct version with a membership bitmask, segments
directed (facing = left normal of ``p0 → p1``).
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from map_server.fusion import FusionConfig, merge_segments
from robot_agent.publish import PublishConfig, directed, top_particle_maps
from robot_agent.replay import replay
from robot_agent.sim import SimConfig, builtin_world, simulate_robot
from robot_agent.slam.extraction import extract_segments
from robot_agent.slam.fastslam import FastSLAM, SlamConfig
from shared.geometry import compose, relative, wrap_angle
from shared.messages import RobotMap


def robot_map_from_slam(
    slam: FastSLAM, robot: str, session: str = "s1", seq: int = 1, stamp_s: float = 1.0, **prior
) -> RobotMap:
    """What the agent publishes for a filter (robot_agent/publish.py), as one assembled RobotMap."""
    a = top_particle_maps(slam, PublishConfig())
    return RobotMap(
        robot, session, seq, stamp_s, 0, 1, a.particle_weights, a.particle_poses, a.seg, a.element,
        a.members, a.trust, a.hits, a.age, **prior,
    )  # fmt: skip


def robot_map_from_segments(
    seg: np.ndarray, robot: str, session: str = "s1", seq: int = 1, prior=None, prior_sigma=None
) -> RobotMap:
    """A one-particle map of directed segments ``(N,2,2)``, every element trusted."""
    n = len(seg)
    return RobotMap(
        robot=robot,
        session=session,
        seq=seq,
        stamp_s=1.0,
        chunk=0,
        n_chunks=1,
        particle_weights=np.ones(1),
        particle_poses=np.zeros((1, 3)),
        seg=np.asarray(seg, float),
        element=np.arange(n, dtype=np.int64),
        members=np.ones(n, np.int64),
        trust=np.full(n, 0.8),
        hits=np.full(n, 10, np.int64),
        age=np.full(n, 100, np.int64),
        prior=prior,
        prior_sigma=prior_sigma,
    )


@lru_cache(maxsize=16)
def slam_run(world_name: str, robot_index: int, duration_s: float, seed: int) -> tuple:
    """A seeded FastSLAM run of one simulated robot: ``(slam, sim)`` (cached per test session).

    The filter starts at the identity, so its map frame is the robot's true start pose
    ``world.starts[robot_index]``: that pose is the true robot-to-global transform.
    """
    world = builtin_world(world_name)
    sim = simulate_robot(world, robot_index, duration_s, seed, SimConfig())
    res = replay(sim.to_log(), SlamConfig(), seed=seed, progress=False)
    return res.slam, sim


@lru_cache(maxsize=16)
def simulated(world_name: str, robot_index: int, duration_s: float, seed: int):
    """A simulated run of one robot (scans, truth), shared by :func:`scan_map` and :func:`scan_free`."""
    return simulate_robot(builtin_world(world_name), robot_index, duration_s, seed, SimConfig())


@lru_cache(maxsize=16)
def scan_map(world_name: str, robot_index: int, duration_s: float, every: int = 5, seed: int = 0) -> tuple:
    """A map without SLAM error: the segments of every ``every``-th scan, extracted at the true pose
    and expressed in the robot's start frame, merged. Returns ``(seg (N,2,2), start (3,))``; the
    start pose is the true robot-to-world transform."""
    sim = simulated(world_name, robot_index, duration_s, seed)
    start = sim.truth[0]
    parts = []
    for k in range(0, len(sim.stamps_s), every):
        segs = extract_segments(sim.ranges_m[k], sim.angles_rad, range_max_m=sim.range_max_m)
        pose = compose(relative(start, sim.truth[k]), sim.laser_offset)
        facing = wrap_angle(segs.alpha + np.pi + pose[2])  # back to the sensor, in the start frame
        parts.append(directed(segs.transformed(pose).endpoints, facing))
    seg = np.concatenate(parts)
    merged, *_ = merge_segments(seg, np.ones(len(seg)), np.zeros(len(seg), np.int64), FusionConfig())
    return merged, start


@lru_cache(maxsize=16)
def scan_free(world_name: str, robot_index: int, duration_s: float, every: int = 5, seed: int = 0):
    """The free space the robot's laser saw (every ``every``-th scan at the true pose, as
    robot_agent/freespace.py cuts it), united, in its start frame (shapely) — :func:`scan_map`'s."""
    import shapely

    from robot_agent.freespace import scan_region

    sim = simulated(world_name, robot_index, duration_s, seed)
    start = sim.truth[0]
    parts = []
    for k in range(0, len(sim.stamps_s), every):
        pose = relative(start, sim.truth[k])
        c, s = np.cos(pose[2]), np.sin(pose[2])
        for ring, _wall in scan_region(sim.ranges_m[k], sim.angles_rad, sim.laser_offset, sim.range_max_m):
            xy = ring @ np.array([[c, s], [-s, c]]) + pose[:2]
            parts.append(shapely.Polygon(xy).buffer(0))
    return shapely.union_all(parts)
