"""A 2D pose graph, optimized by sparse Gauss-Newton (scipy.sparse): how a loop closure's
correction is shared along the path.

Nodes are the poses of the processed steps; a chain edge joins consecutive steps with the motion
the filter estimated between them, uncertain in proportion to the distance and the turn; a loop
edge joins an old step with a recent one with the motion the loop check measured. The
optimized path honours every loop found so far, not only the latest — which a linear spread of
the latest correction cannot.

The solver itself is shared with the server (shared/posegraph.py).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from shared.geometry import relative
from shared.posegraph import full_information, mahalanobis2, optimize

__all__ = ["ChainNoise", "chain_edges", "chain_information", "full_information", "mahalanobis2", "optimize"]


@dataclass(frozen=True)
class ChainNoise:
    """Standard deviations of a chain edge: a floor plus shares of the motion."""

    xy_m: float = 0.01
    xy_per_m: float = 0.02
    theta_rad: float = np.radians(0.2)
    theta_per_rad: float = 0.02
    theta_per_m: float = np.radians(0.3)


def chain_information(motion: np.ndarray, noise: ChainNoise) -> np.ndarray:
    """Diagonal information ``(E,3)`` of chain edges with measured motions ``(E,3)``."""
    d = np.hypot(motion[:, 0], motion[:, 1])
    turn = np.abs(motion[:, 2])
    s_xy = noise.xy_m + noise.xy_per_m * d
    s_th = noise.theta_rad + noise.theta_per_rad * turn + noise.theta_per_m * d
    return np.column_stack([1.0 / s_xy**2, 1.0 / s_xy**2, 1.0 / s_th**2])


def chain_edges(path: np.ndarray, noise: ChainNoise) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Chain edges ``a, b, z, info`` of consecutive poses ``path (N,3)``."""
    z = relative(path[:-1], path[1:])
    a = np.arange(len(path) - 1)
    return a, a + 1, z, chain_information(z, noise)
