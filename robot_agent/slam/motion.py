"""Odometry motion model with noise that includes biased slip (report §2: real slip is biased).

Each particle carries a slip state ``(scale_error, heading_drift_rad_per_m)``: a Gaussian belief
(mean ``slip``, covariance ``slip_cov``) of the robot's systematic odometry error, so the filter
learns the bias instead of treating it as white noise. It is Rao-Blackwellized: the pose prior
of a step includes the slip's uncertainty (``J Σ_slip Jᵀ``), and after the scan alignment the
slip is conditioned on what the scan said about the pose (``update_slip``) — only in the
directions the scan constrains (an aisle's length teaches nothing about the distance scale, its
end does). Between steps the belief's covariance grows as a slow random walk. The odometry increment
``u = relative(odo_prev, odo_now)`` is corrected by the particle's slip, then perturbed with
Gaussian noise proportional to the motion (Thrun et al., Probabilistic Robotics §5.4, in the
increment form that handles backward and pure-rotation motion alike).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from shared.geometry import compose, relative_one


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
    slip_scale_prior_sigma: float = 0.03  # initial std of the distance scale error
    slip_drift_prior_sigma_rad_per_m: float = 0.02  # initial std of the heading drift [rad/m]
    slip_scale_walk_per_sqrt_m: float = 0.003  # random walk of the scale error, per √m driven
    slip_drift_walk_per_sqrt_m: float = 0.001  # random walk of heading drift [rad/m], per √m
    slip_scale_max: float = 0.15  # |scale error| bound
    slip_drift_max_rad_per_m: float = 0.05  # |heading drift| bound


def odometry_increment(odo_prev: np.ndarray, odo_now: np.ndarray) -> np.ndarray:
    """The motion ``(3,)`` measured by odometry between two readings, in the robot frame."""
    return relative_one(odo_prev, odo_now)


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


def slip_jacobian(poses: np.ndarray, u: np.ndarray) -> np.ndarray:
    """``J (P,3,2)``: how the predicted pose moves with the slip state (scale error, heading
    drift) for the odometry increment ``u`` from ``poses (P,3)``."""
    dist = float(np.hypot(u[0], u[1]))
    c, s = np.cos(poses[:, 2]), np.sin(poses[:, 2])
    jac = np.zeros((len(poses), 3, 2))
    jac[:, 0, 0] = c * u[0] - s * u[1]  # the increment's translation, in the map frame
    jac[:, 1, 0] = s * u[0] + c * u[1]
    jac[:, 2, 1] = dist
    return jac


def update_slip(
    slip: np.ndarray,
    slip_cov: np.ndarray,
    jac: np.ndarray,
    prior_info: np.ndarray,
    post_cov: np.ndarray,
    shift: np.ndarray,
    cfg: MotionConfig,
) -> tuple[np.ndarray, np.ndarray]:
    """Condition each particle's slip belief on the scan alignment of this step.

    The predicted pose is ``x = mean + J (s - slip) + w`` with ``w ~ N(0, Q)``, so its prior
    covariance is ``prior_cov = Q + J slip_cov Jᵀ``, given as its inverse ``prior_info`` (the
    caller has it for the weight's prior term). The scan adds information ``H`` about ``x``;
    the alignment returned the posterior pose ``mean + shift`` with covariance
    ``post_cov = (prior_cov⁻¹ + H)⁻¹``. The slip's posterior given the scan (the pose
    marginalized) is then, without forming ``H`` (exact for Gaussians)::

        slip     += slip_cov Jᵀ prior_cov⁻¹ shift
        slip_cov -= slip_cov Jᵀ (prior_cov⁻¹ - prior_cov⁻¹ post_cov prior_cov⁻¹) J slip_cov

    A direction the scan does not constrain has no shift and removes no variance.
    """
    info = prior_info
    gain = np.einsum("pij,pkj,pkl->pil", slip_cov, jac, info)  # slip_cov Jᵀ Σ⁻¹  (P,2,3)
    out = slip + np.einsum("pik,pk->pi", gain, shift)
    m = info - np.einsum("pij,pjk,pkl->pil", info, post_cov, info)
    jp = np.einsum("pij,pjk->pik", jac, slip_cov)  # (P,3,2)
    cov = slip_cov - np.einsum("pji,pjk,pkl->pil", jp, m, jp)
    cov = 0.5 * (cov + np.transpose(cov, (0, 2, 1)))
    out[:, 0] = np.clip(out[:, 0], -cfg.slip_scale_max, cfg.slip_scale_max)
    out[:, 1] = np.clip(out[:, 1], -cfg.slip_drift_max_rad_per_m, cfg.slip_drift_max_rad_per_m)
    return out, cov


def walk_slip(slip_cov: np.ndarray, dist_m: float, cfg: MotionConfig) -> np.ndarray:
    """The slip beliefs' covariance after driving ``dist_m``: a random walk, its variance
    proportional to the distance."""
    d = max(dist_m, 0.0)
    grow = np.diag([cfg.slip_scale_walk_per_sqrt_m**2 * d, cfg.slip_drift_walk_per_sqrt_m**2 * d])
    return slip_cov + grow
