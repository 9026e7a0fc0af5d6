"""Odometry motion model with noise that includes biased slip (report §2: real slip is biased).

Each particle carries a slip state ``(scale_error, heading_drift_rad_per_m)``, a slow random walk:
particles whose slip belief matches the robot's real bias predict better and survive, so the
filter learns the bias instead of treating it as white noise. The odometry increment
``u = relative(odo_prev, odo_now)`` is corrected by the particle's slip, then perturbed with
Gaussian noise proportional to the motion (Thrun et al., Probabilistic Robotics §5.4, in the
increment form that handles backward and pure-rotation motion alike).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from shared.geometry import compose, relative


@dataclass(frozen=True)
class MotionConfig:
    """Noise per motion: σ_xy² = (trans_per_m·d)² + (trans_per_rad·|dθ|)² + trans_min²,
    σ_θ² = (rot_per_rad·|dθ|)² + (rot_per_m·d)² + rot_min²."""

    trans_per_m: float = 0.05  # [m/m] translation noise per metre driven
    trans_per_rad: float = 0.02  # [m/rad] translation noise per radian turned
    trans_min_m: float = 0.005  # [m] floor (also lets a standing robot's particles spread a little)
    rot_per_rad: float = 0.05  # [rad/rad] rotation noise per radian turned
    rot_per_m: float = 0.02  # [rad/m] rotation noise per metre driven
    rot_min_rad: float = 0.01  # [rad] (also covers odometry and laser clocks disagreeing while turning)
    slip_scale_walk_per_sqrt_m: float = 0.003  # random walk of the scale error, per √m driven
    slip_drift_walk_per_sqrt_m: float = 0.001  # random walk of heading drift [rad/m], per √m
    slip_scale_max: float = 0.15  # |scale error| bound
    slip_drift_max_rad_per_m: float = 0.05  # |heading drift| bound


def odometry_increment(odo_prev: np.ndarray, odo_now: np.ndarray) -> np.ndarray:
    """The motion ``(3,)`` measured by odometry between two readings, in the robot frame."""
    return relative(odo_prev, odo_now)


def predict(
    poses: np.ndarray, slip: np.ndarray, u: np.ndarray, cfg: MotionConfig
) -> tuple[np.ndarray, np.ndarray]:
    """Slip-corrected mean poses ``(P,3)`` and the motion covariance ``(P,3,3)`` in the map frame.

    ``u (3,)`` is the odometry increment; ``slip (P,2)`` the particles' slip states.
    """
    dist = float(np.hypot(u[0], u[1]))
    corrected = np.empty((len(poses), 3))
    corrected[:, :2] = u[:2] * (1.0 + slip[:, :1])
    corrected[:, 2] = u[2] + slip[:, 1] * dist
    mean = compose(poses, corrected)
    s_xy2 = (cfg.trans_per_m * dist) ** 2 + (cfg.trans_per_rad * abs(u[2])) ** 2 + cfg.trans_min_m**2
    s_th2 = (cfg.rot_per_rad * abs(u[2])) ** 2 + (cfg.rot_per_m * dist) ** 2 + cfg.rot_min_rad**2
    cov = np.zeros((len(poses), 3, 3))
    cov[:, 0, 0] = cov[:, 1, 1] = s_xy2  # isotropic in xy: invariant under rotation to the map frame
    cov[:, 2, 2] = s_th2
    return mean, cov


def sample_gaussian(rng: np.random.Generator, mean: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """One draw per row from ``N(mean (P,3), cov (P,3,3))`` (Cholesky, batched)."""
    chol = np.linalg.cholesky(cov)
    z = rng.standard_normal(mean.shape)
    out = mean + np.einsum("pij,pj->pi", chol, z)
    out[:, 2] = (out[:, 2] + np.pi) % (2 * np.pi) - np.pi
    return out


def walk_slip(rng: np.random.Generator, slip: np.ndarray, dist_m: float, cfg: MotionConfig) -> np.ndarray:
    """Random walk of the slip states, proportional to √distance, kept within bounds."""
    root = np.sqrt(max(dist_m, 0.0))
    step = rng.standard_normal(slip.shape) * root
    step[:, 0] *= cfg.slip_scale_walk_per_sqrt_m
    step[:, 1] *= cfg.slip_drift_walk_per_sqrt_m
    out = slip + step
    out[:, 0] = np.clip(out[:, 0], -cfg.slip_scale_max, cfg.slip_scale_max)
    out[:, 1] = np.clip(out[:, 1], -cfg.slip_drift_max_rad_per_m, cfg.slip_drift_max_rad_per_m)
    return out
