"""Hand-made map elements and the exact scans of them, shared by the filter's tests."""

import numpy as np

from robot_agent.slam.lines import fit_lines, line_covariance, moments_of, project_to_line
from shared.geometry import apply_points, inverse, wrap_angle


def wall_points(a, b, per_m: float = 20.0, min_points: int = 5) -> np.ndarray:
    """Evenly spaced points ``(K,2)`` from ``a`` to ``b``, both included."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    return np.linspace(a, b, max(round(np.hypot(*(b - a)) * per_m) + 1, min_points))


def put_element(maps, col, points, facing, rows=slice(None), ends=None, **fields):
    """Column ``col`` of particles ``rows`` becomes the element fitted to ``points (K,2)``: its
    exact TLS line, extent ``ends`` (default: the points' projection on the line); ``fields``
    sets any other per-element array (``hits=5``, ``born=0``, ...)."""
    points = np.asarray(points, float)
    m = moments_of(points)
    alpha, rho, _ = fit_lines(m)
    if ends is None:
        t, _ = project_to_line(points, alpha, rho)
        ends = [points[np.argmin(t)], points[np.argmax(t)]]
    maps.valid[rows, col] = True
    maps.moments[rows, col] = m
    maps.alpha[rows, col], maps.rho[rows, col] = alpha, rho
    maps.seg[rows, col] = np.array(ends, float)
    maps.facing[rows, col] = facing
    for name, value in fields.items():
        getattr(maps, name)[rows, col] = value


def seen_from(segments_map, pose, point_sigma_m: float, per_m: float = 20.0):
    """Robot-frame ``moments (O,6), ends (O,2,2), facing (O,), cov (O,2,2)`` of walls ``(a, b)``
    given in the map frame, seen from ``pose``: exact points, facing = the normal back to the
    sensor, line covariance with at least ``point_sigma_m`` of point noise."""
    to_robot = inverse(pose)
    points = [apply_points(to_robot, wall_points(a, b, per_m)) for a, b in segments_map]
    moments = np.array([moments_of(p) for p in points])
    ends = np.array([apply_points(to_robot, np.array([a, b], float)) for a, b in segments_map])
    alpha, _, s2 = fit_lines(moments)
    cov = line_covariance(moments, alpha, np.maximum(s2, point_sigma_m**2))
    return moments, ends, wrap_angle(alpha + np.pi), cov
