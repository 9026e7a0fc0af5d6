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
