"""Write a :class:`LaserLog` as a CARMEN log that :func:`read_log` reads back.

The laser lines: FLASER when the log is a FLASER log whose every geometry is what FLASER lines
read back as (:func:`flaser_compatible`: the field of view pi, or what its PARAMs name);
RAWLASER1 for a RAWLASER1 log (its ODOM lines give the odometry back); ROBOTLASER1 otherwise, one
line per scan with that scan's own start angle, resolution and beam count, so any simulated
laser and any log whose geometry varies round-trips. Poses and timestamps are written with
``%.6f`` (within 5e-7 of the array), ranges with ``%.6f`` stripped of trailing zeros (Intel's
``1.07`` stays ``1.07``), ROBOTLASER1 angles and ``range_max_m`` exactly (``%.17g``; the
resolution is searched so that ``start + i*res`` gives the angles back bit for bit).
A log read from a file written with at most 6 decimals (as CARMEN writes) thus reads back
identical, laser offset included: FLASER and RAWLASER1 carry it in PARAMs (FLASER laser poses
equal the odometry when the log's PARAMs state its offset exactly, else they are the laser's
pose), ROBOTLASER1 in poses that print as they were read. ODOM and laser lines are merged by
timestamp; each stream keeps its own order, so a log whose stamps step back (Intel) is written
back line for line. PARAM lines take CARMEN's ``name value ipc_ts host logger_ts`` shape,
unambiguous whatever the value.
"""

from __future__ import annotations

import gzip
import heapq
import os
import re
from collections.abc import Iterator, Mapping
from typing import Any

import numpy as np

from robot_agent.sources.carmen_conventions import (
    OFFSET_PARAMS,
    RANGE_MAX_PARAMS,
    ParamError,
    flaser_compatible,
    param_number,
)
from robot_agent.sources.laserlog import LaserLog
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

    Raises ValueError when ROBOTLASER1 is needed but a scan's angles are not evenly spaced, or a
    PARAM cannot be written as one line (a name with whitespace, an empty value).
    """
    log = log_or_arrays if isinstance(log_or_arrays, LaserLog) else LaserLog.from_arrays(**log_or_arrays)
    kind = _kind(log)
    laser_lines = {"FLASER": _flaser_lines, "RAWLASER1": _rawlaser_lines}.get(kind, _robotlaser_lines)(log)
    t0 = float(min(log.stamps_s.min(initial=np.inf), log.odom_stamps_s.min(initial=np.inf)))
    t0 = 0.0 if not np.isfinite(t0) else t0
    params = _params(log, kind)
    opener = gzip.open if str(path).endswith(".gz") else open
    with opener(path, "wt", encoding="utf-8") as out:
        out.write(_HEADER)
        for name, value in params.items():
            out.write(f"PARAM {name} {value} 0.000000 {host} 0.000000\n")
        # Stable merge on time: ODOM first on ties, each stream in its own (file) order.
        for stamp, body in heapq.merge(_odom_lines(log), laser_lines, key=lambda e: e[0]):
            out.write(f"{body} {stamp:.6f} {host} {stamp - t0:.6f}\n")


def _kind(log: LaserLog) -> str:
    """The laser message to write: the log's own when it can hold the log, else ROBOTLASER1."""
    if log.kind == "FLASER" and flaser_compatible(log.angle_table_rad, log.geometry_beams, log.params):
        return "FLASER"
    if log.kind == "RAWLASER1" and len(log.odom_stamps_s):  # its odometry: interpolated ODOM
        return "RAWLASER1"
    return "ROBOTLASER1"


def _offset_in_params(log: LaserLog) -> bool:
    """Whether the log's PARAMs state its laser offset exactly (Intel's, ACES's, a RAWLASER1 log's):
    then FLASER lines get identical laser and odometry poses, so the reader takes the PARAMs."""
    try:
        stated = [param_number(log.params, name, 0.0) for name in OFFSET_PARAMS]
    except ParamError:
        return False
    return bool(np.array_equal(stated, log.laser_offset))


def _params(log: LaserLog, kind: str) -> dict[str, str]:
    params = {k: v for k, v in log.params.items() if k not in RANGE_MAX_PARAMS}
    if kind != "ROBOTLASER1":
        # FLASER: the reader takes these only when laser and odometry poses coincide in the lines
        for name, value in zip(OFFSET_PARAMS, log.laser_offset, strict=True):
            params[name] = f"{value:.17g}"
    if kind == "FLASER":
        params[RANGE_MAX_PARAMS[0]] = f"{log.range_max_m:.17g}"
    for name, value in params.items():
        if not name or len(name.split()) != 1 or not value.split() or "\n" in value or "\r" in value:
            raise ValueError(f"PARAM {name!r} = {value!r} cannot be written as one CARMEN line")
    return params


def _ranges_text(log: LaserLog) -> Iterator[str]:
    """Each scan's own readings, ``%.6f`` without trailing zeros."""
    formats: dict[int, str] = {}
    for row, n in zip(log.ranges_m.tolist(), log.beam_counts.tolist(), strict=True):
        fmt = formats.get(n) or formats.setdefault(n, " ".join(["%.6f"] * n))
        yield _TRAILING_ZEROS.sub("", fmt % tuple(row[:n]))


def _poses_text(poses: np.ndarray) -> list[str]:
    return [f"{x:.6f} {y:.6f} {theta:.6f}" for x, y, theta in poses.tolist()]


def _flaser_lines(log: LaserLog) -> Iterator[tuple[float, str]]:
    robots = _poses_text(log.odometry)
    lasers = robots if _offset_in_params(log) else _poses_text(compose(log.odometry, log.laser_offset))
    counts = log.beam_counts.tolist()
    for i, ranges in enumerate(_ranges_text(log)):
        yield float(log.stamps_s[i]), f"FLASER {counts[i]} {ranges} {lasers[i]} {robots[i]}"


def _robotlaser_lines(log: LaserLog) -> Iterator[tuple[float, str]]:
    heads = [
        _config(log, angles[:n]) for angles, n in zip(log.angle_table_rad, log.geometry_beams, strict=True)
    ]
    lasers = _poses_text(compose(log.odometry, log.laser_offset))
    robots = _poses_text(log.odometry)
    geometry = log.scan_geometry.tolist()
    for i, ranges in enumerate(_ranges_text(log)):
        tail = f"0 {lasers[i]} {robots[i]} 0.0 0.0 0.0 0.0 0.0"
        yield float(log.stamps_s[i]), f"ROBOTLASER1 {heads[geometry[i]]} {ranges} {tail}"


def _rawlaser_lines(log: LaserLog) -> Iterator[tuple[float, str]]:
    heads = [
        _config(log, angles[:n]) for angles, n in zip(log.angle_table_rad, log.geometry_beams, strict=True)
    ]
    geometry = log.scan_geometry.tolist()
    for i, ranges in enumerate(_ranges_text(log)):
        yield float(log.stamps_s[i]), f"RAWLASER1 {heads[geometry[i]]} {ranges} 0"


def _config(log: LaserLog, angles_rad: np.ndarray) -> str:
    """``laser_type start_angle fov angular_res max_range accuracy remission_mode n`` of a geometry."""
    n = angles_rad.size
    start, res = even_spacing(angles_rad)
    return f"0 {start:.17g} {res * max(n - 1, 0):.17g} {res:.17g} {log.range_max_m:.17g} 0.0 0 {n}"


def even_spacing(angles_rad: np.ndarray) -> tuple[float, float]:
    """``(start, res)`` with ``start + arange(n) * res`` equal to ``angles_rad (n,)`` bit for bit
    when any resolution does it (angles read from ROBOTLASER1 or RAWLASER1 lines, or built that
    way), else within :data:`ANGLE_SPACING_TOL_RAD` of them (ValueError if not)."""
    n = angles_rad.size
    if n < 2:
        return (float(angles_rad[0]) if n else 0.0), 0.0
    start = float(angles_rad[0])
    steps = np.arange(n)
    mean_step = float(angles_rad[-1] - angles_rad[0]) / (n - 1)
    res = _exact_step(start, angles_rad, mean_step)
    if res is not None:
        return start, res
    deviation = np.abs(start + steps * mean_step - angles_rad)
    if np.any(deviation > ANGLE_SPACING_TOL_RAD):
        raise ValueError(
            f"angles_rad are not evenly spaced (off by up to "
            f"{deviation.max():.3g} rad); ROBOTLASER1 cannot store them"
        )
    return start, mean_step


def _exact_step(start: float, angles_rad: np.ndarray, mean_step: float) -> float | None:
    """A resolution ``r`` with ``start + k*r == angles_rad[k]`` for every ``k``, or None.

    ``start + k*r`` rounds monotonically in ``r``, so for each ``k >= 1`` the ``r`` that give
    ``angles_rad[k]`` form an interval of floats; both ends are found by bisection on the floats'
    order (all ``k`` at once, 64 halvings), and any ``r`` in every interval will do. The short
    decimals near the mean step (what a log wrote, ``0.004363``) are tried first."""
    steps = np.arange(angles_rad.size)
    decimals = [float(f"{mean_step:.{digits}g}") for digits in range(1, 18)]
    for res in decimals:  # most often one of these (what a log wrote): no search
        if np.array_equal(start + steps * res, angles_rad):
            return res
    k, target = steps[1:], angles_rad[1:]
    slack = 8 * (np.spacing(np.abs(angles_rad).max()) + np.spacing(abs(mean_step)))  # |r - mean_step| bound
    low, high = _ordered(mean_step - slack), _ordered(mean_step + slack)

    def first_at_least(at_least: bool) -> np.ndarray:  # per k: the first r whose angle >= target (> target)
        lo, hi = np.full(k.size, low), np.full(k.size, high + 1)
        for _ in range(64):
            mid = lo + (hi - lo) // 2
            angle = start + k * _float(mid)
            past = angle >= target if at_least else angle > target
            hi, lo = np.where(past, mid, hi), np.where(past, lo, mid + 1)
        return lo

    lowest, highest = first_at_least(True).max(), first_at_least(False).min() - 1
    if lowest > highest:
        return None
    res = float(_float(lowest))
    return res if np.array_equal(start + steps * res, angles_rad) else None


def _ordered(x: float) -> np.int64:
    """The float's rank among float64 values, as an integer (adjacent floats differ by one)."""
    bits = np.array(x, dtype=np.float64).view(np.int64)
    return np.int64(bits) if bits >= 0 else np.int64(np.iinfo(np.int64).min) - bits


def _float(ordered: np.ndarray) -> np.ndarray:
    """Inverse of :func:`_ordered`, element-wise."""
    ordered = np.asarray(ordered, dtype=np.int64)
    bits = np.where(ordered >= 0, ordered, np.iinfo(np.int64).min - ordered)
    return bits.view(np.float64)


def _odom_lines(log: LaserLog) -> Iterator[tuple[float, str]]:
    for stamp, pose in zip(log.odom_stamps_s.tolist(), _poses_text(log.odom_poses), strict=True):
        yield stamp, f"ODOM {pose} 0.000000 0.000000 0.000000"
