"""Wheel odometry: the true motion, step by step, corrupted by random noise proportional to the
motion and by a systematic per-robot bias (distance scale error, heading drift per metre)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from shared.geometry import relative, wrap_angle


@dataclass(frozen=True)
class OdometryNoise:
    """Odometry error model (per step; the classic alpha1..alpha4 shape plus a bias).

    trans_per_m / trans_per_rad: the translational noise std of a step (applied to its x and y
        in the robot frame) is ``trans_per_m |distance| + trans_per_rad |dtheta|`` (m).
    rot_per_rad / rot_per_m: the rotational noise std of a step is
        ``rot_per_rad |dtheta| + rot_per_m |distance|`` (rad).
    scale_error_sigma: std of the robot's distance scale error, drawn once per robot
        (wheel radius error: every distance reads ``1 + scale_error`` times the truth).
    heading_drift_sigma_rad_per_m: std of the robot's heading drift, drawn once per robot
        (wheel base / slip asymmetry: every metre driven turns the reading by this much).
    """

    trans_per_m: float = 0.02
    trans_per_rad: float = 0.002
    rot_per_rad: float = 0.02
    rot_per_m: float = 0.005
    scale_error_sigma: float = 0.02
    heading_drift_sigma_rad_per_m: float = 0.01

    @classmethod
    def none(cls) -> OdometryNoise:
        """Perfect odometry: no noise and no bias."""
        return cls(0.0, 0.0, 0.0, 0.0, 0.0, 0.0)


@dataclass(frozen=True)
class OdometryBias:
    """One robot's systematic odometry error (see :class:`OdometryNoise`)."""

    scale_error: float = 0.0
    heading_drift_rad_per_m: float = 0.0


def draw_bias(rng: np.random.Generator, noise: OdometryNoise) -> OdometryBias:
    """Draw a robot's bias once, from zero-mean Gaussians with the configured stds."""
    scale, drift = rng.normal(0.0, 1.0, 2)
    return OdometryBias(
        scale_error=float(scale * noise.scale_error_sigma),
        heading_drift_rad_per_m=float(drift * noise.heading_drift_sigma_rad_per_m),
    )


def noisy_increments(
    rng: np.random.Generator, increments: np.ndarray, noise: OdometryNoise, bias: OdometryBias
) -> np.ndarray:
    """Corrupt true relative motions ``(N, 3)`` (each in the frame of the pose before it)."""
    inc = np.asarray(increments, dtype=float).reshape(-1, 3)
    dist = np.hypot(inc[:, 0], inc[:, 1])
    dtheta = np.abs(inc[:, 2])
    sigma_trans = noise.trans_per_m * dist + noise.trans_per_rad * dtheta
    sigma_rot = noise.rot_per_rad * dtheta + noise.rot_per_m * dist
    z = rng.normal(0.0, 1.0, inc.shape)
    out = np.empty_like(inc)
    out[:, :2] = inc[:, :2] * (1.0 + bias.scale_error) + z[:, :2] * sigma_trans[:, None]
    out[:, 2] = inc[:, 2] + bias.heading_drift_rad_per_m * dist + z[:, 2] * sigma_rot
    return out


def accumulate(increments: np.ndarray) -> np.ndarray:
    """Poses ``(N+1, 3)`` from the identity through relative motions ``(N, 3)``.

    Vectorized cumulative composition: heading ``theta_k = sum_{j<=k} dtheta_j``, position
    ``p_k = sum_{j<=k} R(theta_{j-1}) [dx_j, dy_j]``.
    """
    inc = np.asarray(increments, dtype=float).reshape(-1, 3)
    theta = np.concatenate([[0.0], np.cumsum(inc[:, 2])])
    c, s = np.cos(theta[:-1]), np.sin(theta[:-1])
    step = np.stack([c * inc[:, 0] - s * inc[:, 1], s * inc[:, 0] + c * inc[:, 1]], axis=1)
    xy = np.concatenate([np.zeros((1, 2)), np.cumsum(step, axis=0)])
    return np.column_stack([xy, wrap_angle(theta)])


def integrate_odometry(
    rng: np.random.Generator,
    true_poses: np.ndarray,
    noise: OdometryNoise,
    bias: OdometryBias | None = None,
) -> np.ndarray:
    """Odometry readings ``(T, 3)`` for a true trajectory ``(T, 3)``, starting at ``(0, 0, 0)``
    (the robot's own odometry frame). ``bias`` is drawn from ``rng`` when not given."""
    true_poses = np.asarray(true_poses, dtype=float).reshape(-1, 3)
    if bias is None:
        bias = draw_bias(rng, noise)
    if len(true_poses) == 0:
        return np.zeros((0, 3))
    increments = relative(true_poses[:-1], true_poses[1:])
    return accumulate(noisy_increments(rng, increments, noise, bias))
