"""A differential-drive robot: unicycle kinematics with velocity and acceleration limits, and a
route follower (pure pursuit that stops and turns in place at sharp corners)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from shared.geometry import wrap_angle


@dataclass(frozen=True)
class RobotConfig:
    """Kinematic limits and route-following gains.

    max_v_mps / max_w_radps: speed limits (forward speed is never negative).
    max_acc_mps2 / max_ang_acc_radps2: acceleration limits, applied every control step.
    control_rate_hz: rate of command updates and pose integration.
    lookahead_m: pure-pursuit look-ahead along the route (never past the next sharp corner).
    sharp_turn_rad: a route corner turning more than this is driven by stopping at the corner
        and turning in place (keeps the path on the route through doors).
    corner_tol_m: distance from a sharp corner at which the robot counts it as reached.
    turn_in_place_rad: heading error above which the robot stops and turns in place.
    turn_gain_per_s: turn rate per radian of heading error when turning in place.
    radius_m: robot footprint radius (used for bump checks when driven externally).
    """

    max_v_mps: float = 0.6
    max_w_radps: float = 1.0
    max_acc_mps2: float = 0.5
    max_ang_acc_radps2: float = 2.0
    control_rate_hz: float = 20.0
    lookahead_m: float = 0.6
    sharp_turn_rad: float = 0.5
    corner_tol_m: float = 0.1
    turn_in_place_rad: float = 0.35
    turn_gain_per_s: float = 2.0
    radius_m: float = 0.2

    @property
    def dt_s(self) -> float:
        """Control period."""
        return 1.0 / self.control_rate_hz


def integrate_pose(pose: np.ndarray, v_mps, w_radps, dt_s: float) -> np.ndarray:
    """Exact unicycle motion over ``dt_s`` at constant ``(v, w)``; ``pose (..., 3)`` broadcasts.

    The robot moves along a circular arc: chord ``v dt sinc(w dt / 2)`` at heading
    ``theta + w dt / 2``.
    """
    pose = np.asarray(pose, dtype=float)
    dtheta = np.asarray(w_radps) * dt_s
    chord = np.asarray(v_mps) * dt_s * np.sinc(dtheta / (2 * np.pi))  # np.sinc(x) = sin(pi x)/(pi x)
    mid = pose[..., 2] + dtheta / 2
    return np.stack(
        np.broadcast_arrays(
            pose[..., 0] + chord * np.cos(mid),
            pose[..., 1] + chord * np.sin(mid),
            wrap_angle(pose[..., 2] + dtheta),
        ),
        axis=-1,
    )


def limit_velocity(v_cmd: float, w_cmd: float, v: float, w: float, cfg: RobotConfig) -> tuple[float, float]:
    """The velocity reached after one control step from ``(v, w)`` towards a command."""
    dv, dw = cfg.max_acc_mps2 * cfg.dt_s, cfg.max_ang_acc_radps2 * cfg.dt_s
    v_new = _clip(_clip(float(v_cmd), v - dv, v + dv), 0.0, cfg.max_v_mps)
    w_new = _clip(_clip(float(w_cmd), w - dw, w + dw), -cfg.max_w_radps, cfg.max_w_radps)
    return v_new, w_new


def _clip(x: float, lo: float, hi: float) -> float:
    return lo if x < lo else hi if x > hi else x


def _wrap(angle_rad: float) -> float:
    return (angle_rad + math.pi) % (2 * math.pi) - math.pi


def _step_pose(pose: np.ndarray, v: float, w: float, dt_s: float) -> np.ndarray:
    """Scalar :func:`integrate_pose` for the control loop (numpy call overhead dominates there)."""
    dtheta = w * dt_s
    half = dtheta / 2
    chord = v * dt_s * (math.sin(half) / half if half != 0.0 else 1.0)
    x, y, th = float(pose[0]), float(pose[1]), float(pose[2])
    return np.array([x + chord * math.cos(th + half), y + chord * math.sin(th + half), _wrap(th + dtheta)])


class RouteFollower:
    """Follows a closed route ``(K, 2)`` cyclically; :meth:`command` maps a pose to ``(v, w)``.

    Progress along the route (arc length, growing over laps) only moves forward and is found by
    projecting the robot onto the route near the current progress, so crossings and legs that
    retrace themselves (into a room and back out) are followed in order.
    """

    def __init__(self, route: np.ndarray, start_xy: np.ndarray, cfg: RobotConfig):
        pts = np.asarray(route, dtype=float)
        self._a = pts
        self._d = np.roll(pts, -1, axis=0) - pts  # leg k: route[k] -> route[k+1 mod K]
        self._len = np.hypot(self._d[:, 0], self._d[:, 1])
        if np.any(self._len == 0):
            raise ValueError("route has two equal consecutive waypoints")
        self._cum = np.concatenate([[0.0], np.cumsum(self._len)])
        self.length_m = float(self._cum[-1])
        heading = np.arctan2(self._d[:, 1], self._d[:, 0])
        turn = np.abs(wrap_angle(heading - np.roll(heading, 1)))  # at waypoint k
        self._sharp_s = self._cum[:-1][turn > cfg.sharp_turn_rad]  # arc positions of sharp corners
        self._sharp_2laps = np.concatenate([self._sharp_s, self._sharp_s + self.length_m])
        self._inv_len2 = 1.0 / self._len**2
        self.cfg = cfg
        self.progress_m = self._project(np.asarray(start_xy, float), window=None)

    def resume_at(self, xy: np.ndarray) -> None:
        """Set the progress to the route point nearest ``xy`` (after the robot left the route)."""
        self.progress_m = self._project(np.asarray(xy, float), window=None)

    def point_at(self, s_m: float) -> np.ndarray:
        """Route point at arc length ``s_m`` (taken modulo the route length)."""
        s = s_m % self.length_m
        k = min(int(np.searchsorted(self._cum, s, side="right")) - 1, len(self._len) - 1)
        return self._a[k] + self._d[k] * ((s - self._cum[k]) / self._len[k])

    def _project(self, xy: np.ndarray, window: tuple[float, float] | None) -> float:
        """Arc length of the nearest route point, among those within ``window`` (behind, ahead)
        of the current progress when given."""
        rel = xy - self._a
        t = (rel[:, 0] * self._d[:, 0] + rel[:, 1] * self._d[:, 1]) * self._inv_len2
        t = np.minimum(np.maximum(t, 0.0), 1.0)
        ex, ey = rel[:, 0] - t * self._d[:, 0], rel[:, 1] - t * self._d[:, 1]
        dist = ex * ex + ey * ey  # squared: only compared
        s = self._cum[:-1] + t * self._len
        if window is None:
            return float(s[np.argmin(dist)])
        base = self.progress_m % self.length_m
        delta = (s - base + self.length_m / 2) % self.length_m - self.length_m / 2
        ok = (delta >= -window[0]) & (delta <= window[1])
        if not np.any(ok):
            return self.progress_m
        best = np.argmin(np.where(ok, dist, np.inf))
        return max(self.progress_m, self.progress_m + float(delta[best]))

    def _next_sharp_corner(self) -> float:
        """Arc length (unwrapped, ahead of progress) of the next sharp corner not yet reached."""
        if len(self._sharp_s) == 0:
            return math.inf
        lap = math.floor(self.progress_m / self.length_m) * self.length_m
        passed = self.progress_m + self.cfg.corner_tol_m - lap  # corners this close count as reached
        k = int(np.searchsorted(self._sharp_2laps, passed, side="right"))
        if k < len(self._sharp_2laps):
            return float(self._sharp_2laps[k]) + lap
        return float(self._sharp_s[0]) + 2 * self.length_m + lap

    def command(self, pose: np.ndarray) -> tuple[float, float]:
        """Velocity command ``(v, w)`` for the robot at ``pose (3,)``."""
        cfg = self.cfg
        self.progress_m = self._project(pose[:2], window=(cfg.corner_tol_m, cfg.lookahead_m + 1.0))
        corner = self._next_sharp_corner()
        target = self.point_at(min(self.progress_m + cfg.lookahead_m, corner))
        to_target = target - pose[:2]
        dist = math.hypot(to_target[0], to_target[1])
        alpha = _wrap(math.atan2(to_target[1], to_target[0]) - float(pose[2]))
        if abs(alpha) > cfg.turn_in_place_rad:
            return 0.0, _clip(cfg.turn_gain_per_s * alpha, -cfg.max_w_radps, cfg.max_w_radps)
        # brake to stop at a sharp corner: v <= sqrt(2 a d)
        to_corner = max(corner - self.progress_m, 0.0)
        v = min(cfg.max_v_mps, math.sqrt(2.0 * cfg.max_acc_mps2 * to_corner) + cfg.max_acc_mps2 * cfg.dt_s)
        curvature = 2.0 * math.sin(alpha) / max(dist, 1e-6)  # pure pursuit
        if abs(curvature) * v > cfg.max_w_radps:
            v = cfg.max_w_radps / abs(curvature)
        return float(v), float(curvature * v)


def drive_route(
    route: np.ndarray, start: np.ndarray, cfg: RobotConfig, duration_s: float
) -> tuple[np.ndarray, np.ndarray]:
    """Drive a route from ``start (3,)`` for ``duration_s``.

    Returns poses (T, 3) and velocities (T, 2) ``(v, w)`` at the control rate, ``T =
    floor(duration_s * control_rate_hz) + 1``; row ``k`` is time ``k / control_rate_hz``.
    """
    n = int(np.floor(duration_s * cfg.control_rate_hz + 1e-9)) + 1
    follower = RouteFollower(route, np.asarray(start)[:2], cfg)
    poses = np.empty((n, 3))
    vel = np.zeros((n, 2))
    poses[0] = start
    v = w = 0.0
    for k in range(1, n):
        v_cmd, w_cmd = follower.command(poses[k - 1])
        v, w = limit_velocity(v_cmd, w_cmd, v, w, cfg)
        poses[k] = _step_pose(poses[k - 1], v, w, cfg.dt_s)
        vel[k] = v, w
    return poses, vel
