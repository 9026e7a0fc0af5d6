"""Hand-made test scenes shared by several test modules."""

import numpy as np

# An L-shaped room (lower arm x in [-1, 7], y in [-3, 1]; upper arm x in [-1, 3], y in [1, 4]) with a
# 1 m box in the lower arm, in the map frame. Facing: the normal toward the free side.
L_ROOM = np.array(
    [
        [(-1, -3), (7, -3)],
        [(7, -3), (7, 1)],
        [(7, 1), (3, 1)],
        [(3, 1), (3, 4)],
        [(3, 4), (-1, 4)],
        [(-1, 4), (-1, -3)],
        [(4.5, -2.5), (5.5, -2.5)],
        [(5.5, -2.5), (5.5, -1.5)],
        [(5.5, -1.5), (4.5, -1.5)],
        [(4.5, -1.5), (4.5, -2.5)],
    ],
    float,
)
L_FACING = np.array([np.pi / 2, np.pi, -np.pi / 2, np.pi, -np.pi / 2, 0.0, -np.pi / 2, 0.0, np.pi / 2, np.pi])
TRUE_POSE = np.array([2.0, -1.0, 0.4])
ANGLES = np.linspace(-np.pi, np.pi, 721)[:-1]  # a 360° scanner, 0.5° apart


def drifted_office(duration_s: float):
    """Robot 0's office patrol for ``duration_s`` (one round is ~100 m), and its true path drifted
    0.2°/m and stretched 2 %: ``(sim, log, drifted (S,3), points)`` — ``points(i)`` scan ``i``'s
    points in the robot frame. Where the round comes back the path is 1.5 m and 20° off."""
    from robot_agent.backend import scan_points_robot
    from robot_agent.sim import SimConfig, builtin_world, simulate_robot
    from robot_agent.slam.fastslam import SlamConfig
    from shared.geometry import compose, relative

    sim = simulate_robot(builtin_world("office"), 0, duration_s, 0, SimConfig())
    log, truth = sim.to_log(), sim.truth
    u = relative(truth[:-1], truth[1:])
    u[:, :2] *= 1.02
    u[:, 2] += np.radians(0.2) * np.hypot(u[:, 0], u[:, 1])
    drifted = [truth[0]]
    for step in u:
        drifted.append(compose(drifted[-1], step))
    cfg = SlamConfig()
    return sim, log, np.array(drifted), lambda i: scan_points_robot(log, i, cfg)
