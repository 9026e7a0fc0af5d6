"""What a CARMEN log means beyond its syntax: beam angles, range limits, odometry between lines.

Sources, CARMEN's ``src/`` (read in the public copy ``pblop/missionlab-carmen``):

- ``laser/laser_main.c``, ``set_laser_config_structure``: the SICK driver's geometry per beam
  count — 181 / 361 beams span the field of view ends included (start ``-fov/2``); 180 / 360 are
  an older driver's scans with the last beam dropped (start ``-pi/2``, same step). Its PARAMs
  ``laser_front_laser_fov`` and ``laser_front_laser_resolution`` are in **degrees** (the driver
  refuses a field of view near pi or 100° in radians); newer CARMEN modules (the simulator's
  ``read_parameters``) read them as ``laser_laser<id>_fov`` / ``laser_laser<id>_resolution``, in
  degrees too, with ``<id>`` = ``robot_frontlaser_id``.
- ``laser/laser_ipc.c``: a flipped laser's ranges are reversed *before* they are published, so
  logged scans are always counter-clockwise and ``laser_front_laser_flipped`` needs no action.
- ``logger/readlog.c``, ``carmen_laser_guess_fov`` / ``..._angle_increment``: how CARMEN itself
  reads FLASER (no geometry on the line) — the same angles :func:`flaser_angles` gives for 180,
  181, 360 and 361 beams.
- ``robot/robot_main.c``: the robot module interpolates odometry at a laser's timestamp
  (``carmen_robot_get_fraction``, heading along the shorter arc); :func:`interpolate_odometry`
  does the same for RAWLASER lines, clamped at the ends instead of extrapolated.
- Robot PARAMs (``robot`` module): ``robot_frontlaser_{offset,side_offset,angular_offset}`` (m, m,
  rad), ``robot_front_laser_max`` (m); the simulator's ``simulator_frontlaser_maxrange`` (m).
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from shared.geometry import wrap_angle

DEFAULT_RANGE_MAX_M = 81.0
"""FLASER range limit when the log names none (see ``carmen.py``'s module docstring)."""
SENTINEL_MIN_FRACTION = 1e-3
"""Share of all readings the largest value must reach to count as a "no return" code."""
SENTINEL_MIN_COUNT = 10
"""... and the fewest readings, so that a short log's single farthest hit is no code."""
RANGE_MAX_PARAMS = ("robot_front_laser_max", "simulator_frontlaser_maxrange", "laser_front_laser_max_range")
"""PARAM names giving the front laser's range limit in metres; the first found wins. The last is
no CARMEN name (not in its sources); this reader accepted it before, so it still does."""
OFFSET_PARAMS = ("robot_frontlaser_offset", "robot_frontlaser_side_offset", "robot_frontlaser_angular_offset")
"""PARAM names of the front laser's mount: forward (m), left (m), yaw (rad); each 0 when absent."""
LASER_ID_PARAM = "robot_frontlaser_id"
"""Which ``laser_laser<id>_*`` PARAMs describe the front laser (CARMEN's default: 1)."""
FLASER_ANGLE_TOL_RAD = 1e-9
"""Beam angles this close to :func:`flaser_angles` are FLASER geometry (for the writer)."""
BEAMS_PER_STEP_TOL = 1e-6
"""``fov / resolution`` this close to an integer ``k`` allows ``k`` or ``k + 1`` beams."""
RADIAN_LIKE_FOV_RAD = (np.pi, np.radians(100.0))
"""A field-of-view PARAM within 0.1 of these is in radians: CARMEN's driver refuses it too."""


class ParamError(ValueError):
    """A PARAM whose value cannot be used; the reader adds the line it came from."""

    def __init__(self, name: str, problem: str):
        super().__init__(f"PARAM {name}: {problem}")
        self.name, self.problem = name, problem


def param_number(
    params: Mapping[str, str], name: str, default: float, positive: bool = False, upper: float = np.inf
) -> float:
    """PARAM ``name`` as a finite number (``positive``: > 0; at most ``upper``), ``default`` when
    absent; :class:`ParamError` naming the value otherwise."""
    if name not in params:
        return default
    text = params[name]
    try:
        value = float(text)
    except ValueError:
        value = None
    shown = repr(text) if len(text) <= 40 else f"{text[:40]!r}... ({len(text)} characters)"
    problem = (
        f"cannot parse {shown} as a number" if value is None
        else f"value {shown} is not finite" if not np.isfinite(value)
        else f"{shown} is not positive" if positive and not value > 0
        else f"{shown} is above {upper:g}" if value > upper
        else None
    )  # fmt: skip
    if problem is not None:
        raise ParamError(name, problem)
    return value


def flaser_field_of_view(params: Mapping[str, str]) -> tuple[float, float | None, list[str]]:
    """The front laser's field of view and resolution in radians (``pi`` and ``None`` when the log
    names neither) from its PARAMs in degrees, and the names found; :class:`ParamError` if bad."""
    laser_id = 1.0
    if any(name.startswith("laser_laser") for name in params):  # the newer names carry the id
        laser_id = param_number(params, LASER_ID_PARAM, 1.0)
        if laser_id != int(laser_id):
            raise ParamError(LASER_ID_PARAM, f"{params[LASER_ID_PARAM]!r} is not an integer")
    names = geometry_param_names(int(laser_id))
    fov_name = next((n for n in names["fov"] if n in params), None)
    res_name = next((n for n in names["resolution"] if n in params), None)
    fov_rad, res_rad = np.pi, None  # exactly the default angles when no field of view is named
    if fov_name is not None:
        fov_deg = param_number(params, fov_name, 180.0, positive=True, upper=360.0)
        if min(abs(fov_deg - r) for r in RADIAN_LIKE_FOV_RAD) < 0.1:
            raise ParamError(fov_name, f"{fov_deg:g} looks like radians; CARMEN gives it in degrees")
        fov_rad = float(np.radians(fov_deg))
    if res_name is not None:
        res_rad = float(np.radians(param_number(params, res_name, 1.0, positive=True, upper=360.0)))
    return fov_rad, res_rad, [name for name in (fov_name, res_name) if name]


def geometry_param_names(laser_id: int) -> dict[str, tuple[str, ...]]:
    """The PARAM names of the front laser's field of view and resolution (degrees), old name first."""
    return {
        key: (f"laser_front_laser_{key}", f"laser_laser{laser_id}_{key}") for key in ("fov", "resolution")
    }


def flaser_angles(n: int, fov_rad: float = np.pi, res_rad: float | None = None) -> np.ndarray:
    """FLASER beam angles ``(n,)`` in the laser frame, centred on the field of view ``fov_rad``.

    With ``res_rad`` (the log names the resolution): ``-fov/2 + i*res``, CARMEN's driver geometry.
    Without: odd ``n`` -> ``linspace(-fov/2, fov/2, n)`` (ends included: 181 and 361 beams of a
    SICK LMS); even ``n`` -> ``-fov/2 + i*fov/n`` (the last beam dropped: 180 beams -90°..89°).
    """
    if res_rad is not None:
        return -fov_rad / 2 + np.arange(n) * res_rad
    if n % 2:
        return np.linspace(-fov_rad / 2, fov_rad / 2, n)
    return -fov_rad / 2 + np.arange(n) * (fov_rad / max(n, 1))


def is_flaser_geometry(angles_rad: np.ndarray, fov_rad: float = np.pi, res_rad: float | None = None) -> bool:
    """True when ``angles_rad`` are :func:`flaser_angles` of their count (same ``fov``/``res``)."""
    angles_rad = np.asarray(angles_rad, dtype=float)
    expected = flaser_angles(angles_rad.size, fov_rad, res_rad)
    return bool(np.all(np.abs(angles_rad - expected) <= FLASER_ANGLE_TOL_RAD))


def flaser_compatible(
    angle_table_rad: np.ndarray, geometry_beams: np.ndarray, params: Mapping[str, str]
) -> bool:
    """Whether every geometry (rows of ``angle_table_rad (G,B)``, ``geometry_beams (G,)`` long) is
    what FLASER lines read back as, given ``params``: False too when those PARAMs are unusable."""
    try:
        fov_rad, res_rad, _ = flaser_field_of_view(params)
    except ParamError:
        return False
    return all(
        (res_rad is None or beams_fit(int(n), fov_rad, res_rad))
        and is_flaser_geometry(row[:n], fov_rad, res_rad)
        for row, n in zip(angle_table_rad, geometry_beams, strict=True)
    )


def beams_fit(n: int, fov_rad: float, res_rad: float) -> bool:
    """Whether ``n`` beams at ``res_rad`` fill ``fov_rad`` as CARMEN's driver does: ``k + 1`` beams
    (ends included) or ``k`` (the last dropped), ``k = fov / res`` an integer."""
    k = fov_rad / res_rad
    return abs(k - round(k)) <= BEAMS_PER_STEP_TOL * max(1.0, k) and n in (round(k), round(k) + 1)


def infer_range_max_m(ranges_m: np.ndarray) -> float:
    """Range limit of a FLASER log naming none: a recurring "no return" code, else 81 m."""
    finite = np.isfinite(ranges_m)  # masks, not a copy of the log's ranges
    n_finite = int(np.count_nonzero(finite))
    if n_finite == 0:
        return DEFAULT_RANGE_MAX_M
    top = float(np.max(ranges_m, where=finite, initial=-np.inf))
    at_top = int(np.count_nonzero(ranges_m == top))
    if at_top >= max(SENTINEL_MIN_COUNT, SENTINEL_MIN_FRACTION * n_finite):
        return min(top, DEFAULT_RANGE_MAX_M)
    return DEFAULT_RANGE_MAX_M


def interpolate_odometry(
    odom_stamps_s: np.ndarray, odom_poses: np.ndarray, stamps_s: np.ndarray
) -> np.ndarray:
    """Odometry poses ``(S,3)`` at ``stamps_s (S,)`` from the track ``odom_stamps_s (M,)``,
    ``odom_poses (M,3)``, ``M >= 1``: linear in x, y and in heading along the shorter arc between
    the two neighbouring ODOM lines (CARMEN's robot module), held at the first / last pose outside
    the track. The track is sorted by time first (stable: ties keep file order)."""
    order = np.argsort(odom_stamps_s, kind="stable")
    t, poses = odom_stamps_s[order], odom_poses[order]
    heading = np.unwrap(poses[:, 2])  # consecutive steps along the shorter arc
    return np.column_stack(
        [
            np.interp(stamps_s, t, poses[:, 0]),
            np.interp(stamps_s, t, poses[:, 1]),
            wrap_angle(np.interp(stamps_s, t, heading)),
        ]
    )
