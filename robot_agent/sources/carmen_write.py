"""Write a :class:`LaserLog` as a CARMEN log that :func:`read_log` reads back.

FLASER when the beam angles are the FLASER convention for their count (field of view pi),
ROBOTLASER1 otherwise, so any simulated laser round-trips. Poses and timestamps are written
with ``%.6f`` (within 5e-7 of the array), ranges with ``%.6f`` stripped of trailing zeros
(Intel's ``1.07`` stays ``1.07``), ROBOTLASER1 angles and ``range_max_m`` exactly (``%.17g``).
ODOM and laser lines are merged by timestamp; each stream keeps its own order, so a log whose
stamps step back (Intel) is written back line for line.
"""

from __future__ import annotations

import gzip
import heapq
import os
import re
from collections.abc import Iterator, Mapping
from typing import Any

import numpy as np

from robot_agent.sources.carmen import RANGE_MAX_PARAMS, LaserLog, is_flaser_geometry
from shared.geometry import compose

ANGLE_SPACING_TOL_RAD = 1e-9
"""ROBOTLASER1 stores ``start + i*res``: angles further than this from that line are refused."""
_TRAILING_ZEROS = re.compile(r"\.?0+(?= |$)")
_HEADER = """\
# CARMEN log written by robot_agent.sources.carmen_write
# message_name [message contents] ipc_timestamp ipc_hostname logger_timestamp
# PARAM param_name param_value
# ODOM x y theta tv rv accel
# FLASER num_readings [range_readings] x y theta odom_x odom_y odom_theta
# ROBOTLASER1 laser_type start_angle field_of_view angular_resolution maximum_range accuracy \
remission_mode num_readings [range_readings] num_remissions [remissions] laser_pose_x \
laser_pose_y laser_pose_theta robot_pose_x robot_pose_y robot_pose_theta laser_tv laser_rv \
forward_safety_dist side_safty_dist turn_axis
"""


def write_log(
    path: str | os.PathLike[str], log_or_arrays: LaserLog | Mapping[str, Any], host: str = "nohost"
) -> None:
    """Write ``log_or_arrays`` (a LaserLog, or the keyword arguments of
    :meth:`LaserLog.from_arrays`) to ``path``, gzip-compressed when it ends with ``.gz``.

    Raises ValueError when ROBOTLASER1 is needed but the angles are not evenly spaced.
    """
    log = log_or_arrays if isinstance(log_or_arrays, LaserLog) else LaserLog.from_arrays(**log_or_arrays)
    flaser = is_flaser_geometry(log.angles_rad)
    laser_lines = _flaser_lines(log) if flaser else _robotlaser_lines(log)
    t0 = float(min(log.stamps_s.min(initial=np.inf), log.odom_stamps_s.min(initial=np.inf)))
    t0 = 0.0 if not np.isfinite(t0) else t0
    opener = gzip.open if str(path).endswith(".gz") else open
    with opener(path, "wt", encoding="utf-8") as out:
        out.write(_HEADER)
        for name, value in _params(log, flaser).items():
            out.write(f"PARAM {name} {value} {host} 0.000000\n")
        # Stable merge on time: ODOM first on ties, each stream in its own (file) order.
        for stamp, body in heapq.merge(_odom_lines(log), laser_lines, key=lambda e: e[0]):
            out.write(f"{body} {stamp:.6f} {host} {stamp - t0:.6f}\n")


def _params(log: LaserLog, flaser: bool) -> dict[str, str]:
    params = {k: v for k, v in log.params.items() if k not in RANGE_MAX_PARAMS}
    if flaser:
        # The reader takes these only when laser and odometry poses coincide in the lines.
        for key, value in zip(("offset", "side_offset", "angular_offset"), log.laser_offset, strict=True):
            params[f"robot_frontlaser_{key}"] = f"{value:.17g}"
        params[RANGE_MAX_PARAMS[0]] = f"{log.range_max_m:.17g}"
    return params


def _ranges_text(ranges_m: np.ndarray) -> Iterator[str]:
    fmt = " ".join(["%.6f"] * ranges_m.shape[1])
    for row in ranges_m.tolist():
        yield _TRAILING_ZEROS.sub("", fmt % tuple(row))


def _poses_text(poses: np.ndarray) -> list[str]:
    return [f"{x:.6f} {y:.6f} {theta:.6f}" for x, y, theta in poses.tolist()]


def _flaser_lines(log: LaserLog) -> Iterator[tuple[float, str]]:
    n = log.ranges_m.shape[1]
    lasers = _poses_text(compose(log.odometry, log.laser_offset))
    robots = _poses_text(log.odometry)
    for i, ranges in enumerate(_ranges_text(log.ranges_m)):
        yield float(log.stamps_s[i]), f"FLASER {n} {ranges} {lasers[i]} {robots[i]}"


def _robotlaser_lines(log: LaserLog) -> Iterator[tuple[float, str]]:
    angles = log.angles_rad
    n = angles.size
    res = float(angles[-1] - angles[0]) / (n - 1) if n > 1 else 0.0
    deviation = np.abs(angles - (angles[0] + np.arange(n) * res)) if n else np.zeros(0)
    if np.any(deviation > ANGLE_SPACING_TOL_RAD):
        raise ValueError(
            f"angles_rad are not evenly spaced (off by up to "
            f"{deviation.max():.3g} rad); ROBOTLASER1 cannot store them"
        )
    start = float(angles[0]) if n else 0.0
    head = (
        f"ROBOTLASER1 0 {start:.17g} {res * max(n - 1, 0):.17g} {res:.17g} {log.range_max_m:.17g} 0.0 0 {n}"
    )
    lasers = _poses_text(compose(log.odometry, log.laser_offset))
    robots = _poses_text(log.odometry)
    for i, ranges in enumerate(_ranges_text(log.ranges_m)):
        yield (float(log.stamps_s[i]), f"{head} {ranges} 0 {lasers[i]} {robots[i]} 0.0 0.0 0.0 0.0 0.0")


def _odom_lines(log: LaserLog) -> Iterator[tuple[float, str]]:
    for stamp, pose in zip(log.odom_stamps_s.tolist(), _poses_text(log.odom_poses), strict=True):
        yield stamp, f"ODOM {pose} 0.000000 0.000000 0.000000"
