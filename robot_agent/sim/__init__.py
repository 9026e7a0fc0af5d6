"""Simulated worlds, lidar, differential-drive robot and odometry (see docs/design.md, ``sim/``)."""

from robot_agent.sim.lidar import (
    MAX_PAIRS_PER_CHUNK,
    LidarConfig,
    beam_angles,
    cast_rays,
    simulate_scans,
    walls_in_range,
)
from robot_agent.sim.odometry import (
    OdometryBias,
    OdometryNoise,
    accumulate,
    draw_bias,
    integrate_odometry,
    noisy_increments,
)
from robot_agent.sim.robot import RobotConfig, RouteFollower, drive_route, integrate_pose, limit_velocity
from robot_agent.sim.simulate import LiveSim, SimConfig, SimRun, simulate_robot
from robot_agent.sim.world import (
    BUILTIN_WORLDS,
    World,
    WorldError,
    free_space,
    from_geojson,
    load_geojson,
    make_world,
    route_line,
    start_on_route,
    to_geojson,
    walls_from_geometries,
    walls_geometry,
)
from robot_agent.sim.worlds import builtin_world

__all__ = [
    "BUILTIN_WORLDS",
    "MAX_PAIRS_PER_CHUNK",
    "LidarConfig",
    "LiveSim",
    "OdometryBias",
    "OdometryNoise",
    "RobotConfig",
    "RouteFollower",
    "SimConfig",
    "SimRun",
    "World",
    "WorldError",
    "accumulate",
    "beam_angles",
    "builtin_world",
    "cast_rays",
    "draw_bias",
    "drive_route",
    "free_space",
    "from_geojson",
    "integrate_odometry",
    "integrate_pose",
    "limit_velocity",
    "load_geojson",
    "make_world",
    "noisy_increments",
    "route_line",
    "simulate_robot",
    "simulate_scans",
    "start_on_route",
    "to_geojson",
    "walls_from_geometries",
    "walls_geometry",
    "walls_in_range",
]
