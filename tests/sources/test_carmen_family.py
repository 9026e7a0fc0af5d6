"""The CARMEN log family, line by line as CARMEN's logger writes it (``logger/writelog.c``):
both PARAM shapes, PARAM-given laser geometry, ROBOTLASER1 geometry varying per line, FLASER of
any beam count, RAWLASER1 with odometry interpolated from ODOM lines, which laser a log is read
from, and exact round trips of all of it. Every expected number is worked out by hand."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from robot_agent.sources import LaserLog, LogFormatError, read_log, write_log

DATASETS = Path(__file__).resolve().parents[2] / ".." / "shared" / "datasets"
DEG = np.pi / 180


def flaser(n: int, stamp: float = 100.0, poses: str = "0 0 0 0 0 0", reading: float = 1.5) -> str:
    return f"FLASER {n} {' '.join([str(reading)] * n)} {poses} {stamp:.6f} host 0.1"


def robotlaser(start: str, res: str, n: int, stamp: float, robot="0 0 0", laser="0 0 0", name="ROBOTLASER1"):
    ranges = " ".join(f"{1 + i / 8:.3f}" for i in range(n))
    config = f"0 {start} 3.141593 {res} 81.9 0.01 0 {n} {ranges} 0"
    return f"{name} {config} {laser} {robot} 0.2 0.1 0.5 0.2 0 {stamp:.6f} host 0.1"


def rawlaser(stamp: float, n: int = 3, name: str = "RAWLASER1", max_range: str = "81.9") -> str:
    ranges = " ".join(f"{2 + i:.3f}" for i in range(n))
    return f"{name} 0 -1.570796 3.141593 0.017453 {max_range} 0.01 0 {n} {ranges} 0 {stamp:.6f} host 0.1"


def odom(x, y, theta, stamp: float) -> str:
    return f"ODOM {x} {y} {theta} 0.1 0.0 0.0 {stamp:.6f} host 0.1"


def read(tmp_path, lines: list[str], name: str = "log.clf") -> LaserLog:
    path = tmp_path / name
    path.write_text("\n".join(lines) + "\n")
    return read_log(path, progress=False)


def refusal(tmp_path, lines: list[str]) -> LogFormatError:
    with pytest.raises(LogFormatError) as info:
        read(tmp_path, lines)
    return info.value


# --- PARAM ------------------------------------------------------------------------------------


def test_param_both_shapes_and_text_values(tmp_path):
    log = read(
        tmp_path,
        [
            "PARAM robot_use_laser on nohost 0",  # older logs: name value host logger_ts
            "PARAM robot_front_laser_max 80.99 1071078718.462518 somehost 12.3",  # writelog.c
            "PARAM robot_use_rear_laser off 1071078718.462518 somehost 12.3",
            "PARAM robot_sonar_offsets 0.1 0.2 0.3 1071078718.462518 somehost 12.3",
            "PARAM robot_name two words nohost 0",
            "PARAM hand_written 7",
            flaser(3),
        ],
    )
    assert log.params == {
        "robot_use_laser": "on",
        "robot_front_laser_max": "80.99",
        "robot_use_rear_laser": "off",
        "robot_sonar_offsets": "0.1 0.2 0.3",
        "robot_name": "two words",
        "hand_written": "7",
    }
    assert log.range_max_m == 80.99  # was refused: "cannot parse '80.99 1071078718.462518'"


def test_param_offsets_in_the_new_shape(tmp_path):
    log = read(
        tmp_path,
        [
            "PARAM robot_frontlaser_offset 0.25 1071078718.4 somehost 12.3",
            "PARAM robot_frontlaser_side_offset -0.05 1071078718.4 somehost 12.3",
            "PARAM robot_frontlaser_angular_offset 0.1 1071078718.4 somehost 12.3",
            flaser(3, poses="1 2 0.5 1 2 0.5"),  # identical poses: the PARAMs give the mount
        ],
    )
    np.testing.assert_array_equal(log.laser_offset, [0.25, -0.05, 0.1])


def test_range_limit_params_in_order(tmp_path):
    lines = [flaser(3, reading=81.83)] * 20  # without PARAMs, 81.83 recurring: "no return", 81 m
    assert read(tmp_path, lines).range_max_m == 81.0
    sim = "PARAM simulator_frontlaser_maxrange 50 1.0 h 0"
    assert read(tmp_path, [sim, *lines]).range_max_m == 50.0
    robot = "PARAM robot_front_laser_max 30.5 1.0 h 0"
    assert read(tmp_path, [sim, robot, *lines]).range_max_m == 30.5  # the robot module's comes first


def test_param_field_of_view_and_resolution_in_degrees(tmp_path):
    fov = "PARAM laser_front_laser_fov 100 1.0 h 0"
    res = "PARAM laser_front_laser_resolution 0.25 1.0 h 0"
    # 401 beams at 0.25° over 100°: -50° .. 50°, ends included; 400: the last one dropped
    log = read(tmp_path, [fov, res, flaser(401), flaser(400, 101.0)])
    a, b = log.scan(0).angles_rad / DEG, log.scan(1).angles_rad / DEG
    np.testing.assert_allclose(a[[0, 1, 200, 400]], [-50.0, -49.75, 0.0, 50.0], atol=1e-12)
    np.testing.assert_allclose(b[[0, 1, 399]], [-50.0, -49.75, 49.75], atol=1e-12)
    # a field of view alone spreads any count over it, as pi does by default: 5 beams, 25° apart
    log = read(tmp_path, [fov, flaser(5)])
    np.testing.assert_allclose(log.scan(0).angles_rad / DEG, [-50, -25, 0, 25, 50], atol=1e-12)
    # newer CARMEN: laser_laser<id>_*, <id> the front laser's robot_frontlaser_id
    newer = ["PARAM robot_frontlaser_id 2 1.0 h 0", "PARAM laser_laser2_fov 90 1.0 h 0", flaser(3)]
    np.testing.assert_allclose(read(tmp_path, newer).scan(0).angles_rad / DEG, [-45, 0, 45], atol=1e-12)
    # flipped changes nothing: CARMEN's driver reversed the scan before it was logged
    flipped = read(tmp_path, ["PARAM laser_front_laser_flipped 1 1.0 h 0", flaser(181)])
    np.testing.assert_allclose(flipped.scan(0).angles_rad[[0, -1]] / DEG, [-90, 90], atol=1e-12)


@pytest.mark.parametrize(
    ("lines", "line_no", "detail"),
    [
        (["PARAM laser_front_laser_resolution 0.5 1.0 h 0", flaser(181)], 2, "360 or 361"),
        (["PARAM laser_front_laser_fov 3.1416 1.0 h 0", flaser(181)], 1, "radians"),
        (["PARAM laser_front_laser_fov 400 1.0 h 0", flaser(181)], 1, "above 360"),
        (["PARAM laser_front_laser_resolution on 1.0 h 0", flaser(181)], 1, "'on'"),
    ],
)
def test_unusable_geometry_params_are_warned_and_the_scan_read_by_its_count(tmp_path, lines, line_no, detail):
    """A PARAM may describe a laser setup other than the one logged: the log is read, with the
    default angles (181 beams over 180°), and a warning names the line and what was done."""
    log = read(tmp_path, lines)
    assert len(log) == 1 and len(log.warnings) == 1, log.warnings
    assert f"log.clf:{line_no}:" in log.warnings[0] and detail in log.warnings[0], log.warnings
    assert "180°" in log.warnings[0]
    np.testing.assert_allclose(log.scan(0).angles_rad[[0, 90, 180]] / DEG, [-90, 0, 90], atol=1e-12)


def test_an_unusable_range_param_is_warned_and_the_range_read_from_the_data(tmp_path):
    log = read(tmp_path, ["PARAM robot_front_laser_max off 1.0 h 0", flaser(3)])
    assert len(log.warnings) == 1 and "log.clf:1:" in log.warnings[0] and "'off'" in log.warnings[0]
    assert log.range_max_m == 81.0  # the rule for a log naming none (module docstring)
    offset = read(tmp_path, ["PARAM robot_frontlaser_offset front 1.0 h 0", flaser(3, 1.0, "1 2 0 1 2 0")])
    assert offset.laser_offset[0] == 0.0 and "used 0 instead" in offset.warnings[0]


# --- beam geometry per scan ---------------------------------------------------------------------


def test_robotlaser_geometry_varying_slightly_and_fully(tmp_path):
    log = read(
        tmp_path,
        [
            robotlaser("-1.570796", "0.017453", 3, 100.0),
            robotlaser("-1.566433", "0.017453", 3, 100.1),  # was refused: "beam geometry changed"
            robotlaser("-2.0", "0.5", 5, 100.2),  # another start, resolution and count
            robotlaser("0.1", "0.25", 2, 100.3),
            robotlaser("-1.570796", "0.017453", 3, 100.4),  # the first geometry again
        ],
    )
    assert log.kind == "ROBOTLASER1" and len(log) == 5
    np.testing.assert_array_equal(log.beam_counts, [3, 3, 5, 2, 3])
    np.testing.assert_array_equal(log.scan_geometry, [0, 1, 2, 3, 0])  # each geometry stored once
    assert log.angle_table_rad.shape == (4, 5) and log.ranges_m.shape == (5, 5)
    by_hand = [
        [-1.570796, -1.553343, -1.535890],
        [-1.566433, -1.548980, -1.531527],
        [-2.0, -1.5, -1.0, -0.5, 0.0],
        [0.1, 0.35],
        [-1.570796, -1.553343, -1.535890],
    ]
    for i, angles in enumerate(by_hand):
        scan = log.scan(i)
        np.testing.assert_allclose(scan.angles_rad, angles, rtol=0, atol=1e-12)
        np.testing.assert_array_equal(scan.ranges_m, 1 + np.arange(len(angles)) / 8)
    assert np.isnan(log.ranges_m[3, 2:]).all() and np.isnan(log.angle_table_rad[0, 3:]).all()  # padding
    assert log.range_max_m == 81.9


@pytest.mark.parametrize(
    ("n", "picks", "degrees"),
    [
        (180, [0, 1, 90, 179], [-90, -89, 0, 89]),  # the last beam dropped (CARMEN readlog.c)
        (181, [0, 1, 90, 180], [-90, -89, 0, 90]),
        (360, [0, 1, 180, 359], [-90, -89.5, 0, 89.5]),
        (361, [0, 1, 180, 360], [-90, -89.5, 0, 90]),
    ],
)
def test_flaser_beam_counts(tmp_path, n, picks, degrees):
    scan = read(tmp_path, [flaser(n)] * 2).scan(1)
    assert scan.ranges_m.size == scan.angles_rad.size == n
    np.testing.assert_allclose(scan.angles_rad[picks] / DEG, degrees, rtol=0, atol=1e-12)


def test_flaser_beam_count_changing_from_line_to_line(tmp_path):
    log = read(tmp_path, [flaser(180, 1.0), flaser(361, 2.0), flaser(181, 3.0), flaser(180, 4.0)])
    np.testing.assert_array_equal(log.beam_counts, [180, 361, 181, 180])
    assert log.ranges_m.shape == (4, 361) and log.angle_table_rad.shape == (3, 361)
    np.testing.assert_allclose(log.scan(1).angles_rad[[1, -1]] / DEG, [-89.5, 90], atol=1e-12)
    np.testing.assert_allclose(log.scan(3).angles_rad[[1, -1]] / DEG, [-89, 89], atol=1e-12)


# --- odometry ---------------------------------------------------------------------------------


def test_odometry_only_on_laser_lines(tmp_path):
    log = read(tmp_path, [flaser(3, 1.0, "0 0 0 1 2 0.3"), flaser(3, 2.0, "0 0 0 1.5 2 0.4")])
    assert log.odom_stamps_s.shape == (0,) and log.odom_poses.shape == (0, 3)
    np.testing.assert_array_equal(log.odometry, [[1, 2, 0.3], [1.5, 2, 0.4]])
    stamps, poses = log.odometry_track()  # the relations metric falls back to the laser lines
    np.testing.assert_array_equal(stamps, [1.0, 2.0])
    np.testing.assert_array_equal(poses, log.odometry)


def test_rawlaser_odometry_interpolated_from_odom_lines(tmp_path):
    log = read(
        tmp_path,
        [
            "PARAM robot_frontlaser_offset 0.25 1071078718.4 somehost 12.3",
            rawlaser(9.0),
            odom(0, 0, 0.1, 10.0),
            rawlaser(11.0),
            odom(2, 3, 3.0, 14.0),
            odom(2, 1, 0.5, 12.0),  # out of file order: the track is sorted by time
            rawlaser(13.5),
            odom(4, 3, -3.1, 16.0),
            rawlaser(15.0),
            rawlaser(17.0),
        ],
    )
    assert log.kind == "RAWLASER1" and log.skipped == {}
    by_hand = [
        [0, 0, 0.1],  # before the first ODOM line: held
        [1, 0.5, 0.3],  # halfway from (0, 0, 0.1) at 10 s to (2, 1, 0.5) at 12 s
        [2, 2.5, 2.375],  # 3/4 of the way from 12 s to 14 s: 0.5 + 0.75 * 2.5
        [3, 3, np.pi - 0.05],  # 3.0 -> -3.1 the short way (through pi, 2 pi - 6.1 rad): halfway
        [4, 3, -3.1],  # after the last: held
    ]
    np.testing.assert_allclose(log.odometry, by_hand, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(log.laser_offset, [0.25, 0.0, 0.0])  # no poses: the PARAMs
    assert log.range_max_m == 81.9
    np.testing.assert_allclose(log.scan(0).angles_rad, -1.570796 + np.arange(3) * 0.017453, atol=1e-15)


def test_rawlaser_without_odom_lines_is_refused(tmp_path):
    e = refusal(tmp_path, ["# no ODOM", rawlaser(1.0), rawlaser(2.0)])
    assert (e.line_no, e.message_type, e.field) == (2, "RAWLASER1", "odometry") and "no ODOM" in e.problem


# --- which laser --------------------------------------------------------------------------------


def test_one_front_laser_by_priority_the_rest_counted(tmp_path):
    rear = [
        "RLASER 2 1 1 0 0 0 0 0 0 100.0 nohost 0.1",
        robotlaser("-1.5", "0.5", 7, 100.0, name="ROBOTLASER2"),
        rawlaser(100.0, name="RAWLASER2"),
        rawlaser(100.0, name="RAWLASER3"),
    ]
    front = [flaser(3, 100.5), robotlaser("-1.0", "1.0", 3, 100.7), rawlaser(100.9), odom(0, 0, 0, 100.0)]
    log = read(tmp_path, [*rear, *front])
    assert log.kind == "ROBOTLASER1" and log.stamps_s.tolist() == [100.7]
    assert log.skipped == {
        "RLASER": 1,
        "ROBOTLASER2": 1,
        "RAWLASER2": 1,
        "RAWLASER3": 1,
        "FLASER": 1,
        "RAWLASER1": 1,
    }
    log = read(tmp_path, [*rear, *front[::2], front[3]])  # no ROBOTLASER1: FLASER before RAWLASER1
    assert log.kind == "FLASER" and log.stamps_s.tolist() == [100.5] and log.skipped["RAWLASER1"] == 1
    log = read(tmp_path, [*rear, *front[2:]])
    assert log.kind == "RAWLASER1" and log.stamps_s.tolist() == [100.9]


def test_lines_of_skipped_types_are_not_parsed_but_the_chosen_ones_are(tmp_path):
    junk = ["RLASER two words", "FLASER 99 1 2", "ROBOTLASER2"]
    assert len(read(tmp_path, [*junk, robotlaser("-1.0", "1.0", 3, 1.0)])) == 1
    bad = robotlaser("-1.0", "1.0", 3, 2.0).replace(" 3.141593 ", " x ")
    e = refusal(tmp_path, [flaser(3), robotlaser("-1.0", "1.0", 3, 1.0), bad])
    assert (e.line_no, e.message_type, e.field) == (3, "ROBOTLASER1", "fov")


def test_rear_lasers_only_is_refused_naming_them(tmp_path):
    e = refusal(tmp_path, ["RLASER 2 1 1 0 0 0 0 0 0 100.0 h 0.1"] * 2 + [odom(0, 0, 0, 1.0)])
    assert e.field == "ROBOTLASER1|FLASER|RAWLASER1" and e.line_no == 3
    assert e.problem == "no front laser lines in the log; not read: RLASER (2 lines)"


# --- malformed lines of the newly read types -----------------------------------------------------

RAW_MALFORMED = {
    "too_few": (rawlaser(1.0).rsplit(" ", 2)[0], "num_remissions", "too few"),
    "zero_range": (rawlaser(1.0, max_range="0"), "max_range", "positive"),
    "nan_stamp": (rawlaser(1.0).replace("1.000000", "nan"), "ipc_timestamp", "not finite"),
    "bad_reading": (rawlaser(1.0).replace(" 3.000 ", " 3,0 "), "range[1]", "'3,0'"),
}


@pytest.mark.parametrize("case", RAW_MALFORMED)
def test_malformed_rawlaser_names_line_and_field(tmp_path, case):
    line, field, detail = RAW_MALFORMED[case]
    e = refusal(tmp_path, [odom(0, 0, 0, 1.0), rawlaser(0.5), line, rawlaser(1.5)])  # not the last line
    assert (e.line_no, e.message_type, e.field) == (3, "RAWLASER1", field) and detail in e.problem, str(e)


# --- round trips -------------------------------------------------------------------------------


def same_log(a: LaserLog, b: LaserLog) -> None:
    """Bit for bit: every array (NaN padding included) and what is derived."""
    for name in (
        "stamps_s", "ranges_m", "angle_table_rad", "geometry_beams", "scan_geometry", "odometry",
        "laser_offset", "odom_stamps_s", "odom_poses",
    ):  # fmt: skip
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name, strict=True)
    assert (a.range_max_m, a.kind, len(a)) == (b.range_max_m, b.kind, len(b))


@pytest.mark.parametrize("suffix", [".clf", ".clf.gz"])
def test_varying_geometry_read_write_read_is_exact(tmp_path, suffix):
    robot = ["1.5 -2.25 0.3", "1.6 -2.2 0.31", "1.7 -2.1 0.33", "1.8 -2.0 0.35"]
    laser = ["1.69107 -2.190827 0.4", "1.79107 -2.140827 0.41", "1.89107 -2.040827 0.43", "1.99 -1.94 0.45"]
    lines = [
        robotlaser("-1.570796", "0.017453", 3, 100.0, robot[0], laser[0]),
        robotlaser("-1.566433", "0.017453", 3, 100.1, robot[1], laser[1]),
        odom(1.55, -2.2, 0.305, 100.05),
        robotlaser("-2.356194", "0.004363", 7, 100.2, robot[2], laser[2]),
        robotlaser("-1.570796", "0.017453", 3, 100.3, robot[3], laser[3]),
    ]
    first = read(tmp_path, lines)
    write_log(tmp_path / f"again{suffix}", first)
    again = read_log(tmp_path / f"again{suffix}", progress=False)
    same_log(first, again)
    assert len(first.geometry_beams) == 3


def test_rawlaser_and_flaser_read_write_read_are_exact(tmp_path):
    raw = read(tmp_path, [odom(0, 0, 0.1, 10.0), rawlaser(11.0), odom(2, 1, 0.5, 12.0), rawlaser(11.5, 5)])
    write_log(tmp_path / "raw_again.clf", raw)
    same_log(raw, read_log(tmp_path / "raw_again.clf"))
    params = [
        "PARAM robot_frontlaser_offset 0.123 1.0 h 0",
        "PARAM laser_front_laser_fov 100 1.0 h 0",
        "PARAM laser_front_laser_resolution 0.5 1.0 h 0",
    ]
    fl = read(
        tmp_path, [*params, flaser(201, 1.0, "1 2 0.5 1 2 0.5"), flaser(200, 2.0, "1 2.1 0.5 1 2.1 0.5")]
    )
    assert fl.kind == "FLASER" and fl.laser_offset[0] == 0.123  # PARAM offset: identical poses
    write_log(tmp_path / "fl_again.clf", fl)
    same_log(fl, read_log(tmp_path / "fl_again.clf"))


def test_varying_geometry_from_arrays_writes_robotlaser_lines(tmp_path):
    starts, steps = np.array([-1.2, -1.19, 0.3]), np.array([0.01, 0.01, 0.2])
    counts = np.array([4, 4, 2])
    angles = np.full((3, 4), np.nan)
    for i, (a, d, n) in enumerate(zip(starts, steps, counts, strict=True)):
        angles[i, :n] = a + np.arange(n) * d
    ranges = np.array([[1.0, 2.0, 3.0, 4.0], [1.5, 2.5, 3.5, 4.5], [7.25, 8.0, -1.0, -1.0]])
    log = LaserLog.from_arrays(
        [1.0, 2.0, 3.0], ranges, angles, np.zeros((3, 3)), (0.1, 0.0, 0.0), 9.0, beam_counts=counts
    )
    assert log.kind == "ROBOTLASER1" and len(log.geometry_beams) == 3
    path = tmp_path / "varying.clf"
    write_log(path, log)
    heads = [line.split()[:9] for line in path.read_text().splitlines() if line.startswith("ROBOTLASER1")]
    assert [(float(h[2]), float(h[4]), int(h[8])) for h in heads] == list(
        zip(starts, steps, counts, strict=True)
    )
    back = read_log(path)
    for i, n in enumerate(counts):
        np.testing.assert_array_equal(back.scan(i).angles_rad, angles[i, :n])  # bit for bit
        np.testing.assert_array_equal(back.scan(i).ranges_m, ranges[i, :n])
    assert np.isnan(back.ranges_m[2, 2:]).all()  # the -1.0 beyond 2 beams was padding, never written


# --- the development logs ----------------------------------------------------------------------


@pytest.mark.parametrize(
    ("name", "scans", "beams", "last_deg", "odom_lines", "range_max_m"),
    [
        ("intel", 13631, 180, 89.0, 26915, 81.0),
        ("aces", 7374, 180, 89.0, 7375, 50.0),
        ("mit-csail", 1988, 361, 90.0, 0, 81.0),
    ],
)
def test_development_logs(name, scans, beams, last_deg, odom_lines, range_max_m):
    path = DATASETS / name / f"{name}.clf"
    if not path.exists():
        pytest.skip(f"{path} is absent")
    log = read_log(path, progress=False)
    assert (len(log), log.kind, log.odom_stamps_s.size, log.range_max_m) == (
        scans,
        "FLASER",
        odom_lines,
        range_max_m,
    )
    assert log.angle_table_rad.shape == (1, beams) and np.all(log.beam_counts == beams)
    np.testing.assert_array_equal(log.laser_offset, [0.0, 0.0, 0.0])
    np.testing.assert_allclose(log.scan(-1).angles_rad[[0, -1]] / DEG, [-90, last_deg], rtol=0, atol=1e-12)
    if odom_lines == 0:  # MIT-CSAIL: odometry only on the laser lines
        np.testing.assert_array_equal(log.odometry_track()[1], log.odometry)
