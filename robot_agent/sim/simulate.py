"""Simulated robot runs: drive a patrol route, read odometry, cast laser scans.

:func:`simulate_robot` produces a whole run as arrays (for logs and benchmarks); :class:`LiveSim`
steps one robot on demand and yields :class:`~robot_agent.sources.base.Scan` records, with a
velocity hook for an external controller.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field

import numpy as np

from robot_agent.sim.lidar import LidarConfig, beam_angles, simulate_scans
from robot_agent.sim.odometry import (
    OdometryBias,
    OdometryNoise,
    draw_bias,
    integrate_odometry,
    noisy_increments,
)
from robot_agent.sim.robot import RobotConfig, RouteFollower, _step_pose, drive_route, limit_velocity
from robot_agent.sim.world import World
from robot_agent.sources.base import Scan
from robot_agent.sources.laserlog import LaserLog
from shared.geometry import compose, point_segment_distance, relative


@dataclass(frozen=True)
class SimConfig:
    """Everything a simulated robot run needs.

    lidar / robot / odometry: the parts' configurations.
    duration_s: default run length for :func:`simulate_robot`.
    laser_offset: laser pose ``(x, y, theta)`` in the robot frame.
    epoch_s: time stamp of the first control step (and first scan); all robots share the clock.
    """

    lidar: LidarConfig = field(default_factory=LidarConfig)
    robot: RobotConfig = field(default_factory=RobotConfig)
    odometry: OdometryNoise = field(default_factory=OdometryNoise)
    duration_s: float = 120.0
    laser_offset: tuple[float, float, float] = (0.0, 0.0, 0.0)
    epoch_s: float = 1_000_000.0

    def __post_init__(self) -> None:
        ratio = self.robot.control_rate_hz / self.lidar.rate_hz
        if abs(ratio - round(ratio)) > 1e-9 or round(ratio) < 1:
            raise ValueError(
                f"robot.control_rate_hz ({self.robot.control_rate_hz}) must be a whole multiple of "
                f"lidar.rate_hz ({self.lidar.rate_hz})"
            )

    @property
    def steps_per_scan(self) -> int:
        """Control steps between two scans."""
        return round(self.robot.control_rate_hz / self.lidar.rate_hz)


@dataclass(frozen=True, eq=False)
class SimRun:
    """One robot's simulated run.

    At scan times: ``stamps_s`` (S,), ``truth`` (S, 3) world-frame poses, ``odometry`` (S, 3) in
    the robot's odometry frame (starts at the identity), ``ranges_m`` (S, B). ``angles_rad`` (B,)
    beam angles in the laser frame, ``laser_offset`` (3,) laser pose in the robot frame. Dense, at
    the control rate: ``odom_stamps_s`` (T,), ``odom_poses`` (T, 3), ``truth_dense`` (T, 3).
    ``bias`` is the odometry bias this robot drew.
    """

    stamps_s: np.ndarray
    truth: np.ndarray
    odometry: np.ndarray
    ranges_m: np.ndarray
    angles_rad: np.ndarray
    range_max_m: float
    laser_offset: np.ndarray
    odom_stamps_s: np.ndarray
    odom_poses: np.ndarray
    truth_dense: np.ndarray
    bias: OdometryBias

    def to_log(self, params: dict[str, str] | None = None) -> LaserLog:
        """The run as a :class:`~robot_agent.sources.LaserLog` (scans, odometry at scan times and
        the dense odometry track), as it would be recorded."""
        return LaserLog.from_arrays(
            stamps_s=self.stamps_s,
            ranges_m=self.ranges_m,
            angles_rad=self.angles_rad,
            odometry=self.odometry,
            laser_offset=self.laser_offset,
            range_max_m=self.range_max_m,
            odom_stamps_s=self.odom_stamps_s,
            odom_poses=self.odom_poses,
            params=params,
        )

    def scans(self) -> Iterator[Scan]:
        """The run as a scan source."""
        for k in range(len(self.stamps_s)):
            yield Scan(
                float(self.stamps_s[k]),
                self.ranges_m[k],
                self.angles_rad,
                self.odometry[k],
                self.laser_offset,
                self.range_max_m,
            )


def _check_robot(world: World, robot_index: int) -> None:
    if not 0 <= robot_index < world.num_robots:
        raise ValueError(
            f"robot_index {robot_index} out of range: world {world.name!r} has {world.num_robots} routes"
        )


def simulate_robot(
    world: World,
    robot_index: int,
    duration_s: float | None = None,
    seed: int = 0,
    cfg: SimConfig = SimConfig(),  # frozen, so a shared default is safe
) -> SimRun:
    """Simulate robot ``robot_index`` on its route for ``duration_s`` (default ``cfg.duration_s``).

    Reproducible: the randomness comes from ``np.random.default_rng([seed, robot_index])``, so
    robots of one seed differ from each other.
    """
    _check_robot(world, robot_index)
    duration_s = cfg.duration_s if duration_s is None else float(duration_s)
    if not duration_s >= 0.0:
        raise ValueError(f"duration_s must be >= 0, got {duration_s}")
    rng = np.random.default_rng([seed, robot_index])
    truth_dense, _ = drive_route(world.routes[robot_index], world.starts[robot_index], cfg.robot, duration_s)
    bias = draw_bias(rng, cfg.odometry)
    odom_dense = integrate_odometry(rng, truth_dense, cfg.odometry, bias)
    odom_stamps = cfg.epoch_s + np.arange(len(truth_dense)) * cfg.robot.dt_s
    at_scan = np.arange(0, len(truth_dense), cfg.steps_per_scan)
    offset = np.asarray(cfg.laser_offset, dtype=float)
    ranges = simulate_scans(rng, truth_dense[at_scan], world.walls, cfg.lidar, offset)
    return SimRun(
        stamps_s=odom_stamps[at_scan],
        truth=truth_dense[at_scan],
        odometry=odom_dense[at_scan],
        ranges_m=ranges,
        angles_rad=beam_angles(cfg.lidar),
        range_max_m=cfg.lidar.range_max_m,
        laser_offset=offset,
        odom_stamps_s=odom_stamps,
        odom_poses=odom_dense,
        truth_dense=truth_dense,
        bias=bias,
    )


class LiveSim:
    """One simulated robot stepped on demand.

    By default it patrols its route; after :meth:`set_velocity` it obeys the given ``(v, w)``
    (within the robot's limits) until :meth:`follow_route`. A move that would bring the robot
    closer than ``cfg.robot.radius_m`` to a wall is refused (a bumper): the robot stops in place
    and :attr:`bumped` is set until the next accepted move.
    """

    def __init__(
        self,
        world: World,
        robot_index: int = 0,
        seed: int = 0,
        cfg: SimConfig = SimConfig(),
        start: np.ndarray | None = None,
    ):
        _check_robot(world, robot_index)
        self.world, self.cfg = world, cfg
        self._rng = np.random.default_rng([seed, robot_index])
        self._bias = draw_bias(self._rng, cfg.odometry)
        self._pose = np.array(world.starts[robot_index] if start is None else start, dtype=float)
        self._odom = np.zeros(3)
        self._v = self._w = 0.0
        self._step = 0
        self._command: tuple[float, float] | None = None
        self._follower = RouteFollower(world.routes[robot_index], self._pose[:2], cfg.robot)
        self._angles = beam_angles(cfg.lidar)
        self._offset = np.asarray(cfg.laser_offset, dtype=float)
        self.bumped = False

    @property
    def stamp_s(self) -> float:
        """Current simulated time."""
        return self.cfg.epoch_s + self._step * self.cfg.robot.dt_s

    @property
    def truth(self) -> np.ndarray:
        """Current true pose (3,) in the world frame."""
        return self._pose.copy()

    @property
    def odometry(self) -> np.ndarray:
        """Current odometry reading (3,)."""
        return self._odom.copy()

    def set_velocity(self, v_mps: float, w_radps: float) -> None:
        """Drive with this command from now on (external controller)."""
        self._command = (float(v_mps), float(w_radps))

    def follow_route(self) -> None:
        """Go back to patrolling the route (resumes at the route point nearest the robot)."""
        self._command = None
        self._follower.resume_at(self._pose[:2])

    def step(self) -> None:
        """Advance one control step."""
        cmd = self._follower.command(self._pose) if self._command is None else self._command
        self._v, self._w = limit_velocity(*cmd, self._v, self._w, self.cfg.robot)
        new = _step_pose(self._pose, self._v, self._w, self.cfg.robot.dt_s)
        if len(self.world.walls):
            xy = np.stack([new[:2], self._pose[:2]])[:, None, :]
            new_clear, old_clear = point_segment_distance(xy, self.world.walls[None]).min(axis=1)
            self.bumped = bool(new_clear < self.cfg.robot.radius_m and new_clear < old_clear)
            if self.bumped:
                new[:2] = self._pose[:2]
                self._v = 0.0
        true_increment = relative(self._pose, new)[None]
        increment = noisy_increments(self._rng, true_increment, self.cfg.odometry, self._bias)[0]
        self._odom = compose(self._odom, increment)
        self._pose = new
        self._step += 1

    def scan(self) -> Scan:
        """A scan taken now (without advancing time)."""
        ranges = simulate_scans(self._rng, self._pose[None], self.world.walls, self.cfg.lidar, self._offset)
        return Scan(
            self.stamp_s, ranges[0], self._angles, self._odom.copy(), self._offset, self.cfg.lidar.range_max_m
        )

    def scans(self, duration_s: float | None = None) -> Iterator[Scan]:
        """A scan now, then one every scan period, for ``duration_s`` (forever when ``None``)."""
        end = np.inf if duration_s is None else self.stamp_s + duration_s + 1e-9
        while self.stamp_s <= end:
            yield self.scan()
            for _ in range(self.cfg.steps_per_scan):
                self.step()
