"""SE(2) on plain arrays, with any leading batch shape.

A pose is an array ``(..., 3)`` holding ``(x, y, theta)``: the transform that maps
points from the pose's local frame into its parent frame, ``p_parent = R(theta) p_local + t``.
Points are ``(..., 2)``; segments are ``(..., 2, 2)`` (two endpoints, each ``(x, y)``).
All functions broadcast their batch axes with numpy rules and never loop in Python.
"""

from __future__ import annotations

import math

import numpy as np

TWO_PI = 2.0 * np.pi


def wrap_angle(angle_rad: np.ndarray | float) -> np.ndarray:
    """Wrap angles to ``[-pi, pi)``."""
    return (np.asarray(angle_rad) + np.pi) % TWO_PI - np.pi


def identity(batch_shape: tuple[int, ...] = ()) -> np.ndarray:
    """Identity poses of shape ``batch_shape + (3,)``."""
    return np.zeros((*batch_shape, 3))


def compose(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a ∘ b``: first ``b`` expressed in ``a``'s frame. Shapes ``(..., 3)`` broadcast."""
    a = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float)
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    x = a[..., 0] + c * b[..., 0] - s * b[..., 1]
    y = a[..., 1] + s * b[..., 0] + c * b[..., 1]
    th = wrap_angle(a[..., 2] + b[..., 2])
    return np.stack(np.broadcast_arrays(x, y, th), axis=-1)


def inverse(p: np.ndarray) -> np.ndarray:
    """Inverse transform: ``compose(p, inverse(p)) == identity``."""
    p = np.asarray(p, dtype=float)
    c, s = np.cos(p[..., 2]), np.sin(p[..., 2])
    x = -(c * p[..., 0] + s * p[..., 1])
    y = -(-s * p[..., 0] + c * p[..., 1])
    return np.stack([x, y, wrap_angle(-p[..., 2])], axis=-1)


def relative(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``inverse(a) ∘ b``: the motion from pose ``a`` to pose ``b`` in ``a``'s frame."""
    return compose(inverse(a), b)


def relative_one(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """:func:`relative` of two single poses ``(3,)``, in Python floats: the same operations in the
    same order (the same result), without numpy's cost per call on three numbers."""
    a0, a1, a2 = (float(v) for v in a)
    b0, b1, b2 = (float(v) for v in b)
    c, s = math.cos(a2), math.sin(a2)
    ix, iy = -(c * a0 + s * a1), -(-s * a0 + c * a1)  # inverse(a)
    ith = _wrap_float(-a2)
    c, s = math.cos(ith), math.sin(ith)
    return np.array([ix + c * b0 - s * b1, iy + s * b0 + c * b1, _wrap_float(ith + b2)])


def _wrap_float(angle_rad: float) -> float:
    """:func:`wrap_angle` of one Python float (the same floor modulo)."""
    return (angle_rad + math.pi) % TWO_PI - math.pi


def transform_points(pose: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Map points ``(..., 2)`` by ``pose (..., 3)``; the batch axes broadcast element-wise.

    To apply one pose per batch entry to ``N`` points each, pass ``pose[..., None, :]``
    (or use :func:`apply_points`).
    """
    pose = np.asarray(pose, dtype=float)
    points = np.asarray(points, dtype=float)
    c, s = np.cos(pose[..., 2]), np.sin(pose[..., 2])
    x = c * points[..., 0] - s * points[..., 1] + pose[..., 0]
    y = s * points[..., 0] + c * points[..., 1] + pose[..., 1]
    return np.stack([x, y], axis=-1)


def apply_points(pose: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Map a point set ``(..., N, 2)`` by ``pose (..., 3)`` (one pose per point set)."""
    return transform_points(np.asarray(pose)[..., None, :], points)


def apply_segments(pose: np.ndarray, segments: np.ndarray) -> np.ndarray:
    """Map a segment set ``(..., N, 2, 2)`` by ``pose (..., 3)`` (one pose per set)."""
    return transform_points(np.asarray(pose)[..., None, None, :], segments)


def to_matrix(p: np.ndarray) -> np.ndarray:
    """Homogeneous matrices ``(..., 3, 3)``."""
    p = np.asarray(p, dtype=float)
    c, s = np.cos(p[..., 2]), np.sin(p[..., 2])
    m = np.zeros((*p.shape[:-1], 3, 3))
    m[..., 0, 0], m[..., 0, 1], m[..., 0, 2] = c, -s, p[..., 0]
    m[..., 1, 0], m[..., 1, 1], m[..., 1, 2] = s, c, p[..., 1]
    m[..., 2, 2] = 1.0
    return m


def from_matrix(m: np.ndarray) -> np.ndarray:
    """Poses ``(..., 3)`` from homogeneous matrices ``(..., 3, 3)``."""
    m = np.asarray(m, dtype=float)
    th = np.arctan2(m[..., 1, 0], m[..., 0, 0])
    return np.stack([m[..., 0, 2], m[..., 1, 2], th], axis=-1)


# --- segments -------------------------------------------------------------------------------


def segment_lengths(segments: np.ndarray) -> np.ndarray:
    """Lengths ``(...,)`` of segments ``(..., 2, 2)``."""
    d = segments[..., 1, :] - segments[..., 0, :]
    return np.hypot(d[..., 0], d[..., 1])


def segment_directions(segments: np.ndarray) -> np.ndarray:
    """Direction angles ``(...,)`` in ``[-pi, pi)`` from the first endpoint to the second."""
    d = segments[..., 1, :] - segments[..., 0, :]
    return np.arctan2(d[..., 1], d[..., 0])


def sample_segments(
    segments: np.ndarray, step_m: float, ends: bool = False
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Points every ``step_m`` along segments ``(N,2,2)`` → ``points (K,2)``, owner ``(K,)``,
    the length each piece stands for ``(K,)``: each segment cut into equal pieces no longer than
    ``step_m`` (at least one), a point at the middle of each piece — or, with ``ends``, at the
    ends of the pieces (both endpoints included: one point more a segment)."""
    seg = np.asarray(segments, dtype=float).reshape(-1, 2, 2)
    d = seg[:, 1] - seg[:, 0]
    length = np.hypot(d[:, 0], d[:, 1])
    counts = np.maximum(np.ceil(length / step_m).astype(int), 1)
    per = counts + 1 if ends else counts
    owner = np.repeat(np.arange(len(seg)), per)
    start = np.cumsum(per) - per
    k = np.arange(per.sum()) - start[owner]
    t = k / counts[owner] if ends else (k + 0.5) / counts[owner]
    pts = seg[owner, 0] + t[:, None] * d[owner]
    return pts, owner, (length / counts)[owner]


def line_angle_diff(a_rad: np.ndarray, b_rad: np.ndarray) -> np.ndarray:
    """Unsigned difference of undirected line angles, in ``[0, pi/2]``."""
    d = np.abs(wrap_angle(np.asarray(a_rad) - np.asarray(b_rad)))
    return np.minimum(d, np.pi - d)


def point_line_distance(points: np.ndarray, segments: np.ndarray) -> np.ndarray:
    """Signed distance of points ``(..., 2)`` to the infinite lines through segments ``(..., 2, 2)``.

    Positive on the left of the direction first→second endpoint. Degenerate segments give 0 by
    convention (their direction is undefined).
    """
    a = segments[..., 0, :]
    d = segments[..., 1, :] - a
    n = np.hypot(d[..., 0], d[..., 1])
    r = points - a
    cross = d[..., 0] * r[..., 1] - d[..., 1] * r[..., 0]
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(n > 0, cross / np.where(n > 0, n, 1.0), 0.0)


def point_segment_distance(points: np.ndarray, segments: np.ndarray) -> np.ndarray:
    """Unsigned Euclidean distance of points ``(..., 2)`` to segments ``(..., 2, 2)``."""
    a = segments[..., 0, :]
    d = segments[..., 1, :] - a
    dd = np.sum(d * d, axis=-1)
    t = np.sum((points - a) * d, axis=-1) / np.where(dd > 0, dd, 1.0)
    t = np.clip(t, 0.0, 1.0)
    proj = a + t[..., None] * d
    diff = points - proj
    return np.hypot(diff[..., 0], diff[..., 1])
