"""CARMEN log reading and writing: round trips, malformed lines, the shipped Intel excerpt."""

from __future__ import annotations

import gzip
import pickle
from pathlib import Path

import numpy as np
import pytest

from robot_agent.sources import LaserLog, LogFormatError, Scan, read_log, write_log
from robot_agent.sources.carmen import flaser_angles, infer_range_max_m
from shared.geometry import compose

DATA = Path(__file__).resolve().parents[1] / "data"
INTEL_HEAD = DATA / "intel_head.clf.gz"
INTEL_FULL = Path(__file__).resolve().parents[2] / ".." / "shared" / "datasets" / "intel" / "intel.clf"
LAST_INTEL_RANGES = (1.0, 1.12)  # first and last reading of intel.clf's last FLASER line


def _random_log(angles_rad, laser_offset, seed=0, scans=25, odoms=40, range_max_m=30.0):
    rng = np.random.default_rng(seed)
    stamps = 1000.0 + np.cumsum(rng.uniform(0.05, 0.2, scans))
    odometry = np.column_stack([rng.uniform(-20, 20, (scans, 2)), rng.uniform(-3, 3, scans)])
    ranges = rng.uniform(0.1, range_max_m, (scans, angles_rad.size))
    ranges[:, ::7] = range_max_m  # "no return" beams
    odom_stamps = np.sort(rng.uniform(stamps[0] - 1, stamps[-1] + 1, odoms))
    odom_poses = np.column_stack([rng.uniform(-20, 20, (odoms, 2)), rng.uniform(-3, 3, odoms)])
    return LaserLog.from_arrays(
        stamps,
        ranges,
        angles_rad,
        odometry,
        laser_offset,
        range_max_m,
        odom_stamps,
        odom_poses,
        params={"note": "two words"},
    )


GEOMETRIES = {
    "flaser181": (flaser_angles(181), (0.0, 0.0, 0.0), "FLASER"),
    "flaser180_offset": (flaser_angles(180), (0.25, 0.0, 0.0), "FLASER"),
    "robotlaser360_offset": (-np.pi + np.arange(360) * (2 * np.pi / 360), (0.12, -0.05, 0.3), "ROBOTLASER1"),
}


@pytest.mark.parametrize("suffix", [".clf", ".clf.gz"])
@pytest.mark.parametrize("geometry", GEOMETRIES)
def test_write_read_round_trip(tmp_path, geometry, suffix):
    angles, offset, kind = GEOMETRIES[geometry]
    log = _random_log(angles, offset)
    path = tmp_path / f"log{suffix}"
    write_log(path, log)
    back = read_log(path, progress=False)

    assert (path.read_bytes()[:2] == b"\x1f\x8b") == suffix.endswith(".gz")
    assert log.kind == back.kind == kind
    assert len(back) == len(log) == 25
    np.testing.assert_allclose(back.stamps_s, log.stamps_s, rtol=0, atol=1e-6)
    np.testing.assert_allclose(back.ranges_m, log.ranges_m, rtol=0, atol=1e-6)
    assert back.angle_table_rad.shape == (1, angles.size)
    # FLASER: the convention's own angles; ROBOTLASER1: start + i*res, found bit for bit
    np.testing.assert_allclose(back.scan(3).angles_rad, angles, rtol=0, atol=1e-12 if kind == "FLASER" else 0)
    np.testing.assert_allclose(back.odometry, log.odometry, rtol=0, atol=1e-6)
    # Derived from two poses rounded to 1e-6 each, a lever arm of 0.3 m: a few 1e-6.
    np.testing.assert_allclose(back.laser_offset, offset, rtol=0, atol=5e-6)
    np.testing.assert_allclose(back.odom_stamps_s, log.odom_stamps_s, rtol=0, atol=1e-6)
    np.testing.assert_allclose(back.odom_poses, log.odom_poses, rtol=0, atol=1e-6)
    assert back.range_max_m == 30.0
    assert back.params["note"] == "two words"


def test_written_lines_are_time_ordered_and_kind_matches(tmp_path):
    log = _random_log(*GEOMETRIES["robotlaser360_offset"][:2])
    path = tmp_path / "rl.clf"
    write_log(path, log)
    body = [line.split() for line in path.read_text().splitlines() if line[:1] not in "#P"]
    assert {parts[0] for parts in body} == {"ODOM", "ROBOTLASER1"}
    assert len(body) == 25 + 40
    stamps = [float(parts[-3]) for parts in body]
    assert stamps == sorted(stamps)


def test_write_from_mapping_and_gzip_detected_by_magic_bytes(tmp_path):
    gz_path = tmp_path / "log.gz"
    arrays = {
        "stamps_s": [1.0, 2.0],
        "ranges_m": [[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]],
        "angles_rad": flaser_angles(3),
        "odometry": [[0, 0, 0], [1, 0, 0.5]],
        "range_max_m": 10.0,
    }
    write_log(gz_path, arrays)
    plain_name = tmp_path / "log.clf"  # gzip bytes under a plain name
    plain_name.write_bytes(gz_path.read_bytes())
    back = read_log(plain_name)
    np.testing.assert_array_equal(back.ranges_m, arrays["ranges_m"])
    assert back.odom_poses.shape == (0, 3) and back.odom_stamps_s.shape == (0,)


def test_uneven_angles_cannot_be_written(tmp_path):
    angles = np.array([-0.5, 0.0, 0.1, 0.6])
    log = LaserLog.from_arrays([1.0], [[1.0] * 4], angles, [[0, 0, 0]], range_max_m=5.0)
    with pytest.raises(ValueError, match="evenly spaced"):
        write_log(tmp_path / "x.clf", log)


def test_from_arrays_names_bad_argument_and_shapes():
    with pytest.raises(ValueError, match=r"odometry has shape \(2, 2\).*S=2"):
        LaserLog.from_arrays([1.0, 2.0], np.ones((2, 3)), flaser_angles(3), np.zeros((2, 2)))
    with pytest.raises(ValueError, match=r"angles_rad has shape \(4,\).*B=3"):
        LaserLog.from_arrays([1.0, 2.0], np.ones((2, 3)), np.zeros(4), np.zeros((2, 3)))
    with pytest.raises(ValueError, match=r"beam_counts has shape \(2,\).*values in \[0, 3\]"):
        LaserLog.from_arrays([1.0, 2.0], np.ones((2, 3)), np.zeros(3), np.zeros((2, 3)), beam_counts=[3, 4])
    with pytest.raises(ValueError, match=r"odom_poses has shape \(5, 3\).*M=4"):
        LaserLog.from_arrays(
            [1.0],
            np.ones((1, 3)),
            flaser_angles(3),
            np.zeros((1, 3)),
            odom_stamps_s=np.zeros(4),
            odom_poses=np.zeros((5, 3)),
        )


def test_scans_and_read_only_arrays():
    log = LaserLog.from_arrays(
        [5.0, 6.0],
        [[1.0, 2.0], [3.0, 4.0]],
        flaser_angles(2),
        [[0, 0, 0], [1, 2, 3]],
        (0.1, 0, 0),
        range_max_m=8.0,
    )
    scans = list(log.scans())
    assert len(log) == 2 and log.duration_s == 1.0
    assert isinstance(scans[1], Scan) and scans[1].stamp_s == 6.0
    np.testing.assert_array_equal(scans[1].ranges_m, [3.0, 4.0])
    np.testing.assert_array_equal(scans[1].odometry, [1, 2, 3])
    np.testing.assert_array_equal(scans[0].laser_offset, [0.1, 0, 0])
    np.testing.assert_allclose(np.degrees(scans[0].angles_rad), [-90.0, 0.0])
    assert scans[0].range_max_m == 8.0
    with pytest.raises(ValueError, match="read-only"):
        log.ranges_m[0, 0] = 9.0


# --- malformed input ---------------------------------------------------------------------------

POSES = "0 0 0 0 0 0"


def _flaser(ranges="1.0 2.0 3.0", n=None, poses=POSES, stamp="100.5"):
    n = len(ranges.split()) if n is None else n
    return f"FLASER {n} {ranges} {poses} {stamp} nohost 0.1"


def _rl1(n=3, n_rem="0"):
    ranges = " ".join(["1.5"] * 3)
    return (
        f"ROBOTLASER1 0 -1.0 2.0 1.0 20.0 0.01 0 {n} {ranges} {n_rem} 0 0 0 0 0 0 0 0 0 0 0 100.0 nohost 0.1"
    )


MALFORMED = {
    "range_not_a_number": ([_flaser("1.0 abc 3.0")], "range[1]", "'abc'"),
    "too_few_fields": ([_flaser(n=4)], "num_readings", "too few"),
    "too_many_fields": ([_flaser(n=2)], "num_readings", "too many"),
    "negative_count": ([_flaser(n=-3)], "num_readings", "-3"),
    "absurd_count": ([_flaser(n=200000)], "num_readings", "200000"),
    "count_not_integer": ([_flaser(n="3.5")], "num_readings", "'3.5'"),
    "nan_odometry": ([_flaser(poses="0 0 0 nan 0 0")], "odom_x", "not finite"),
    "inf_timestamp": ([_flaser(stamp="inf")], "ipc_timestamp", "not finite"),
    "nan_odom_line": (["ODOM 1 2 nan 0 0 0 100.0 nohost 0.1"], "theta", "not finite"),
    "odom_too_short": (["ODOM 1 2 0.5 0 0 0 100.0"], "ipc_hostname", "too few"),
    "rl1_bad_remission_count": ([_rl1(n_rem="x")], "num_remissions", "'x'"),
    "rl1_too_many_remissions": ([_rl1(n_rem="2")], "num_remissions", "too few"),
    "rl1_zero_max_range": ([_rl1().replace(" 20.0 ", " 0 ")], "max_range", "positive"),
    "rl1_nan_start_angle": ([_rl1().replace(" -1.0 ", " nan ")], "start_angle", "not finite"),
    "no_laser_lines": (
        ["ODOM 1 2 0.5 0 0 0 100.0 nohost 0.1"],
        "ROBOTLASER1|FLASER|RAWLASER1",
        "no front laser",
    ),
}


@pytest.mark.parametrize("case", MALFORMED)
def test_malformed_line_names_file_line_and_field(tmp_path, case):
    lines, field, detail = MALFORMED[case]
    path = tmp_path / f"{case}.clf"
    after = "" if case == "no_laser_lines" else _flaser() + "\n"  # not the last line: not cut short
    path.write_text("# header\n" + "\n".join(lines) + "\n" + after)
    with pytest.raises(LogFormatError) as info:
        read_log(path)
    bad_line = 1 + (1 if case == "no_laser_lines" else len(lines))
    message = str(info.value)
    assert f"{path}:{bad_line}:" in message
    assert f"field '{field}'" in message
    assert detail in message
    assert info.value.line_no == bad_line and info.value.field == field
    assert str(pickle.loads(pickle.dumps(info.value))) == message


def test_an_unusable_offset_param_is_warned_not_refused(tmp_path):
    """A PARAM is configuration, not data: ``robot_frontlaser_offset abc`` leaves the log readable
    with the offset's default, and says so, naming the line."""
    path = tmp_path / "offset.clf"
    path.write_text("# header\nPARAM robot_frontlaser_offset abc nohost 0\n" + _flaser() + "\n")
    log = read_log(path)
    assert len(log) == 1 and log.laser_offset[0] == 0.0
    assert log.warnings == (f"{path}:2: PARAM robot_frontlaser_offset: cannot parse 'abc' as a number; "
                            "used 0 instead",)  # fmt: skip


def test_truncated_gzip_is_a_log_format_error(tmp_path):
    path = tmp_path / "cut.clf.gz"
    path.write_bytes(gzip.compress(("\n".join([_flaser()] * 200) + "\n").encode())[:60])
    with pytest.raises(LogFormatError, match=r"cut\.clf\.gz:\d+: gzip field 'stream'"):
        read_log(path)


# --- rules -------------------------------------------------------------------------------------


def test_other_message_types_are_skipped_and_counted(tmp_path):
    path = tmp_path / "mixed.clf"
    lines = [
        "SYNC tag",
        _flaser(),
        "RLASER 2 1 1 0 0 0 0 0 0 100.0 nohost 0.1",
        "TRUEPOS 0 0 0 0 0 0 100.0 nohost 0.1",
        "RLASER 2 1 1 0 0 0 0 0 0 101.0 nohost 0.1",
        "",
        _flaser(stamp="101.5"),
    ]
    path.write_text("\n".join(lines))
    log = read_log(path)
    assert len(log) == 2 and log.kind == "FLASER"
    assert log.skipped == {"RLASER": 2, "TRUEPOS": 1}
    np.testing.assert_array_equal(log.stamps_s, [100.5, 101.5])
    # a ROBOTLASER1 line anywhere makes the log a ROBOTLASER1 log: its FLASER lines are skipped
    path.write_text("\n".join([*lines, _rl1()]))
    log = read_log(path)
    assert len(log) == 1 and log.kind == "ROBOTLASER1" and log.stamps_s[0] == 100.0
    assert log.skipped == {"RLASER": 2, "TRUEPOS": 1, "FLASER": 2}


def test_flaser_offset_from_poses_beats_param(tmp_path):
    path = tmp_path / "offset.clf"
    # odom (1, 2, pi/2), laser 0.3 m ahead of it: (1, 2.3, pi/2).
    poses = "1 2.3 1.5707963267948966 1 2 1.5707963267948966"
    path.write_text(f"PARAM robot_frontlaser_offset 0.5 nohost 0\n{_flaser(poses=poses)}\n")
    np.testing.assert_allclose(read_log(path).laser_offset, [0.3, 0.0, 0.0], atol=1e-12)
    path.write_text(
        "PARAM robot_frontlaser_offset 0.5 nohost 0\n"
        "PARAM robot_frontlaser_angular_offset 0.1 nohost 0\n"
        f"{_flaser(poses='1 2 0.7 1 2 0.7')}\n"
    )
    np.testing.assert_array_equal(read_log(path).laser_offset, [0.5, 0.0, 0.1])


def test_robotlaser_geometry_and_offset(tmp_path):
    path = tmp_path / "rl.clf"
    robot = np.array([2.0, -1.0, 0.4])
    laser = compose(robot, [0.2, 0.1, -0.3])
    line = _rl1().replace(
        "0 0 0 0 0 0 0 0 0 0 0 100.0", " ".join(f"{v:.12f}" for v in (*laser, *robot)) + " 0 0 0 0 0 100.0"
    )
    path.write_text(line + "\n")
    log = read_log(path)
    np.testing.assert_allclose(log.scan(0).angles_rad, [-1.0, 0.0, 1.0])
    np.testing.assert_allclose(log.laser_offset, [0.2, 0.1, -0.3], atol=1e-9)
    np.testing.assert_allclose(log.odometry[0], robot)
    assert log.range_max_m == 20.0 and log.kind == "ROBOTLASER1"


def test_flaser_angle_conventions():
    np.testing.assert_allclose(np.degrees(flaser_angles(181))[[0, 1, 90, 180]], [-90, -89, 0, 90])
    np.testing.assert_allclose(np.degrees(flaser_angles(180))[[0, 1, 179]], [-90, -89, 89])
    np.testing.assert_allclose(np.degrees(flaser_angles(360))[[0, 1, 359]], [-90, -89.5, 89.5])


def test_range_max_rules(tmp_path):
    sentinel = np.full((10, 100), 3.0)
    sentinel[:, ::9] = 8.183
    assert infer_range_max_m(sentinel) == 8.183  # recurring "no return" code
    assert infer_range_max_m(np.where(sentinel > 5, 81.83, sentinel)) == 81.0  # Intel's code
    assert infer_range_max_m(np.linspace(0.1, 30.0, 1000)) == 81.0  # no code: the default
    path = tmp_path / "p.clf"
    path.write_text(f"PARAM laser_front_laser_max_range 50 nohost 0\n{_flaser('81.83 1 2')}\n")
    assert read_log(path).range_max_m == 50.0


# --- the Intel log ---------------------------------------------------------------------------


def test_intel_excerpt():
    log = read_log(INTEL_HEAD, progress=False)
    assert len(log) == 1500 and log.ranges_m.shape == (1500, 180) and log.kind == "FLASER"
    assert log.angle_table_rad.shape == (1, 180) and np.all(log.beam_counts == 180)
    np.testing.assert_allclose(np.degrees(log.scan(700).angles_rad), np.arange(-90.0, 90.0), atol=1e-12)
    # ipc stamps mostly increase but step back 83 times in the first 1500 FLASER lines
    # (counted with awk), by at most 0.87 s; distinct, over about 298 s.
    steps = np.diff(log.stamps_s)
    assert np.count_nonzero(steps < 0) == 83 and steps.min() > -0.9
    assert np.unique(log.stamps_s).size == 1500 and 297 < log.duration_s < 298
    assert log.stamps_s[0] == 976052857.337530 and log.stamps_s[-1] == 976053154.272557
    assert np.isfinite(log.odometry).all() and np.isfinite(log.ranges_m).all()
    np.testing.assert_array_equal(log.odometry[-1], [7.299, -5.762, -1.944444])  # line 4483
    assert log.range_max_m == 81.0 and (log.ranges_m.max() == 81.83)
    np.testing.assert_array_equal(log.laser_offset, [0.0, 0.0, 0.0])
    assert log.odom_poses.shape == (2972, 3) and log.params["robot_frontlaser_offset"] == "0.0"
    relations = np.loadtxt(DATA / "intel_head.relations")
    assert relations.shape == (166, 8)
    assert np.isin(relations[:, :2], log.stamps_s).all()


def test_intel_excerpt_with_progress_bar(capsys):
    log = read_log(INTEL_HEAD, progress=True)
    assert len(log) == 1500
    assert capsys.readouterr().out == ""  # the bar goes to stderr only


def test_full_intel_log():
    # what the reader did, not how fast (benchmarks/bench_read_log.py times it)
    if not INTEL_FULL.exists():
        pytest.skip(f"{INTEL_FULL} is absent")
    log = read_log(INTEL_FULL, progress=False)
    assert len(log) == 13631 and log.odom_poses.shape == (26915, 3)
    assert log.ranges_m.shape == (13631, 180) and log.angle_table_rad.shape == (1, 180)
    assert log.skipped == {} and log.params == {
        "robot_frontlaser_offset": "0.0",
        "robot_rearlaser_offset": "0.0",
    }
    # First FLASER (line 13) and last FLASER line of the file: odom_x odom_y odom_theta.
    np.testing.assert_array_equal(log.odometry[0], [0.0, 0.0, -0.002458])
    np.testing.assert_array_equal(log.odometry[-1], [-50.883999, -35.825001, 2.538102])
    assert log.stamps_s[-1] == 976055548.624744
    # the last FLASER line's first and last readings (awk '/^FLASER/{l=$0} END{print l}' | cut)
    last = log.scan(-1)
    assert last.ranges_m.size == 180 and (last.ranges_m[0], last.ranges_m[-1]) == LAST_INTEL_RANGES


# --- logs as they come off robots (issue 24 rows 6 and 7) ----------------------------------------


def _good_lines(n: int) -> list[str]:
    return [_flaser(poses=f"{0.1 * i} 0 0 {0.1 * i} 0 0", stamp=f"{100 + i}.5") for i in range(n)]


def test_row6_a_cut_last_line_is_a_warning_and_the_rest_is_read(tmp_path):
    """Power lost while recording: the last line ends mid-way. The complete scans are read, the
    warning names the line; ``strict`` refuses as before; a cut line with more after it is still
    an error (that is not a recording cut short)."""
    lines = _good_lines(5)
    path = tmp_path / "cut.clf"
    path.write_text("\n".join(lines) + "\n" + lines[0][: len(lines[0]) // 2])  # no newline: cut
    log = read_log(path)
    assert len(log) == 5
    assert any(f"{path}:6:" in w and "cut" in w for w in log.warnings), log.warnings
    with pytest.raises(LogFormatError, match="too few fields"):
        read_log(path, strict=True)
    middle = tmp_path / "middle.clf"
    middle.write_text("\n".join([*lines[:2], lines[2][:20], *lines[3:]]) + "\n")
    with pytest.raises(LogFormatError) as info:
        read_log(middle)
    assert info.value.line_no == 3


def test_row7_a_laser_line_without_beams_is_skipped_and_counted(tmp_path):
    """A blind line (0 beams) among 3-beam ones: skipped with a warning naming its line and the
    count, not a refusal of the log; ``strict`` refuses it."""
    lines = _good_lines(6)
    lines.insert(3, _flaser(ranges="", n=0, poses="0.25 0 0 0.25 0 0", stamp="102.7"))
    lines.insert(5, _flaser(ranges="", n=0, poses="0.35 0 0 0.35 0 0", stamp="103.7"))
    path = tmp_path / "zero.clf"
    path.write_text("\n".join(lines) + "\n")
    log = read_log(path)
    assert len(log) == 6 and np.all(log.beam_counts == 3)
    assert any(f"{path}:4:" in w and "no beams" in w and "2 lines" in w for w in log.warnings), log.warnings
    with pytest.raises(LogFormatError, match="no beams"):
        read_log(path, strict=True)
