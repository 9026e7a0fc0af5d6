"""Property tests: whatever a CARMEN log holds, :func:`read_log` returns its valid records or raises
:class:`LogFormatError` naming a bad line and its field — never another exception.

Logs are generated line by line: valid FLASER / ROBOTLASER1 / RAWLASER1 / ODOM / PARAM lines (the
beam count and geometry the same on every laser line of a log, or drawn per line), comments,
other message types, then some lines corrupted (a token replaced by NaN, inf, a huge or negative
count, text, binary junk; a token dropped or added; the line cut; two lines joined; raw bytes),
written plain or gzip (optionally with the compressed stream damaged). The oracle knows which
lines are intact: an error must point at a corrupted line (a RAWLASER1 log may also be refused
for having no intact ODOM line), and a log that reads must contain every intact record, with its
own beam angles, exactly. Budget: ~4,000 inputs, ~10 s; derandomized (the same inputs every run).
"""

from __future__ import annotations

import gzip
import math
from dataclasses import dataclass

import numpy as np
import pytest
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st

from robot_agent.sources import LaserLog, LogFormatError, read_log
from robot_agent.sources.carmen import DEFAULT_RANGE_MAX_M, RANGE_MAX_PARAMS, flaser_angles, infer_range_max_m
from robot_agent.sources.carmen_conventions import interpolate_odometry
from shared.geometry import relative

pytestmark = pytest.mark.timeout(300)

FUZZ = dict(deadline=None, suppress_health_check=[HealthCheck.too_slow], derandomize=True)

HOSTILE_TOKENS = [
    "nan", "NaN", "-nan", "inf", "-inf", "Infinity", "1e999", "-1e999", "1e308", "-1e308", "1e-320",
    "abc", "0x1F", "1,5", "1.2.3", "--1", "+", "-", ".", "e5", "１２", "٣", "1_000", "9" * 5000,
    "-1", "-0", "0", "3.5", "2147483648", "100001", "99999999999999999999", "\x00", "\ufffd",
    "FLASER", "ROBOTLASER1", "ODOM", "PARAM", "#", "",
]  # fmt: skip
OFFSET_PARAMS = ("robot_frontlaser_offset", "robot_frontlaser_side_offset", "robot_frontlaser_angular_offset")


@dataclass
class Line:
    text: str | bytes  # without the newline; bytes only for raw junk
    intact: bool = True
    laser: tuple | None = None  # (stamp, ranges, odometry (3,) | None, laser pose (3,) | None, angles)
    odom: tuple | None = None  # (stamp, x, y, theta) of an intact ODOM line
    skipped: str | None = None  # message type the reader counts as skipped


def numbers(rng: np.random.Generator, k: int, lo: float = -1e4, hi: float = 1e4) -> list[str]:
    """``k`` numbers in [lo, hi] as a log writes them: repr, fixed point or integer (valid parts of a
    line come from a seeded generator, cheap; hypothesis draws the structure and the damage)."""
    values = rng.uniform(lo, hi, k)
    style = rng.integers(0, 3, k)
    return [
        repr(float(v)) if s == 0 else f"{v:.6f}" if s == 1 else str(int(v))
        for v, s in zip(values, style, strict=True)
    ]


def ranges_text(rng: np.random.Generator, n: int) -> list[str]:
    """Ranges: numbers, sometimes a "no return" code or a non-finite reading (both allowed)."""
    out = numbers(rng, n, 0.0, 80.0)
    for i in np.flatnonzero(rng.random(n) < 0.1):
        out[i] = str(rng.choice(["nan", "inf", "81.83", "0"]))
    return out


hostile_token = st.one_of(
    st.sampled_from(HOSTILE_TOKENS), st.text(max_size=12).map(lambda t: t.replace("\n", " "))
)
seeds = st.integers(0, 2**32 - 1).map(np.random.default_rng)


def draw_geometry(rng: np.random.Generator) -> tuple[str, str, str]:
    """ROBOTLASER1 / RAWLASER1 start angle, resolution and range limit, as a log writes them."""
    return f"{rng.uniform(-3.2, 0.0):.6f}", f"{rng.uniform(0.001, 0.1):.6f}", f"{rng.uniform(1.0, 80.0):.2f}"


@st.composite
def laser_line(draw, kind: str, n: int | None, geometry: tuple[str, str, str] | None) -> Line:
    """One laser line; ``n`` / ``geometry`` None: drawn for this line alone."""
    rng = draw(seeds)
    n = int(rng.integers(0, 7)) if n is None else n
    start, res, max_range = draw_geometry(rng) if geometry is None else geometry
    ranges, laser, odom = ranges_text(rng, n), numbers(rng, 3), numbers(rng, 3)
    if rng.random() < 0.2:
        laser = odom  # identical poses: the FLASER offset comes from the PARAMs
    stamp, logger_stamp = numbers(rng, 2, 0.0, 2e9)
    tail = [stamp, "nohost", logger_stamp]
    rem = numbers(rng, int(rng.integers(0, 3)), 0.0, 1.0)
    config = ["0", start, "3.14", res, max_range, "0.01", "0", str(n), *ranges, str(len(rem)), *rem]
    if kind == "FLASER":
        tokens = ["FLASER", str(n), *ranges, *laser, *odom, *tail]
        angles = flaser_angles(n)
    elif kind == "ROBOTLASER1":
        tokens = ["ROBOTLASER1", *config, *laser, *odom, "0", "0", "0.5", "0.2", "0", *tail]
        angles = float(start) + np.arange(n) * float(res)
    else:  # RAWLASER1: no poses
        tokens, laser, odom = ["RAWLASER1", *config, *tail], None, None
        angles = float(start) + np.arange(n) * float(res)
    poses = [None if p is None else [float(v) for v in p] for p in (odom, laser)]
    record = (float(stamp), [float(r) for r in ranges], *poses, angles)
    return Line(" ".join(tokens), laser=record)


@st.composite
def odom_line(draw) -> Line:
    rng = draw(seeds)
    pose, (stamp,) = numbers(rng, 3), numbers(rng, 1, 0.0, 2e9)
    text = " ".join(["ODOM", *pose, "0.1", "0", "0", stamp, "nohost", "0.5"])
    return Line(text, odom=(float(stamp), *map(float, pose)))


@st.composite
def param_line(draw) -> Line:
    name = draw(st.sampled_from([*OFFSET_PARAMS, *RANGE_MAX_PARAMS, "note", "robot_name"]))
    rng = draw(seeds)
    if name in OFFSET_PARAMS:
        (value,) = numbers(rng, 1, -1.0, 1.0)
    elif name in RANGE_MAX_PARAMS:
        value = f"{rng.uniform(1.0, 100.0):.3f}"
    else:
        value = draw(st.text(st.characters(exclude_categories=["Z", "C"]), min_size=1, max_size=8))
    tail = draw(st.sampled_from([[], ["nohost"], ["nohost", "0.0"]]))
    return Line(" ".join(["PARAM", name, value, *tail]))


other_line = st.one_of(
    st.just(Line("")),
    st.text(max_size=20).map(lambda t: Line("#" + t.replace("\n", " "))),
    st.just(Line("SYNC tag")),
    st.sampled_from(["RLASER", "TRUEPOS", "NMEA-GGA", "RAWLASER3", "ROBOTLASER2"]).map(
        lambda k: Line(f"{k} 2 1 1 0 0 0 0 0 0 100.0 nohost 0.1", skipped=k)
    ),
)


@st.composite
def corrupt(draw, line: Line) -> Line:
    """``line`` damaged one way; it may still happen to be valid (the oracle allows both)."""
    tokens = line.text.split(" ")
    op = draw(st.sampled_from(["replace", "replace", "count", "drop", "insert", "cut", "bytes"]))
    event(f"corruption: {op}")
    i = draw(st.integers(0, len(tokens) - 1))
    if op == "replace":
        tokens[i] = draw(hostile_token)
    elif op == "count":  # the beam or remission count
        j = 1 if tokens[0] == "FLASER" else min(8, len(tokens) - 1)
        tokens[j] = str(draw(st.one_of(st.integers(-5, 12), st.sampled_from([100_000, 100_001, 10**30]))))
    elif op == "drop":
        del tokens[i]
    elif op == "insert":
        tokens.insert(i, draw(hostile_token))
    elif op == "cut":
        text = line.text[: draw(st.integers(0, max(0, len(line.text) - 1)))]
        return Line(text, intact=False)
    else:
        return Line(draw(st.binary(max_size=60)).replace(b"\n", b" "), intact=False)
    return Line(" ".join(tokens), intact=False)


@st.composite
def carmen_log(draw) -> tuple[list[Line], str]:
    kind = draw(st.sampled_from(["FLASER", "ROBOTLASER1", "RAWLASER1"]))
    fixed = draw(st.booleans())  # one beam count and geometry for the log, or drawn per line
    n = draw(st.integers(0, 6)) if fixed else None
    geometry = draw_geometry(draw(seeds)) if fixed else None
    laser = laser_line(kind, n, geometry)
    make = st.one_of(laser, laser, laser, odom_line(), param_line(), other_line)
    lines = draw(st.lists(make, max_size=9))
    lines.insert(draw(st.integers(0, len(lines))), draw(laser))  # at least one laser line
    if kind == "RAWLASER1" and draw(st.integers(0, 9)):  # mostly with an ODOM line to interpolate
        lines.insert(draw(st.integers(0, len(lines))), draw(odom_line()))
    for i in draw(st.lists(st.integers(0, len(lines) - 1), max_size=3, unique=True)):
        lines[i] = draw(corrupt(lines[i]))
    if len(lines) > 1 and draw(st.integers(0, 9)) == 0:  # two lines joined: the newline lost
        i = draw(st.integers(0, len(lines) - 2))
        a, b = (
            line.text if isinstance(line.text, str) else line.text.decode("utf-8", "replace")
            for line in lines[i : i + 2]
        )
        lines[i : i + 2] = [Line(a + " " + b, intact=False)]
    return lines, kind


def file_bytes(lines: list[Line], crlf: bool, final_newline: bool) -> bytes:
    body = [line.text if isinstance(line.text, bytes) else line.text.encode() for line in lines]
    data = (b"\r\n" if crlf else b"\n").join(body)
    return data + (b"\n" if final_newline else b"")


def read(path, data: bytes) -> LaserLog | LogFormatError:
    """The property every input must satisfy: a LaserLog or a LogFormatError, nothing else."""
    path.write_bytes(data)
    try:
        return read_log(path, progress=False)
    except LogFormatError as e:
        message = str(e)
        assert message == f"{path}:{e.line_no}: {e.message_type} field '{e.field}': {e.problem}"
        assert e.problem and e.field and len(message) < 300 + len(str(path)), message
        event(f"refused: {e.message_type} {e.field}".split("[")[0])
        return e


def check_error(e: LogFormatError, lines: list[Line]) -> None:
    """A refusal points at a corrupted line."""
    corrupted = {i + 1 for i, line in enumerate(lines) if not line.intact}
    if e.message_type == "log":  # no laser lines: there must have been none intact
        assert not any(line.laser for line in lines), str(e)
        return
    if e.problem.startswith(f"no {e.message_type} line left"):  # those left out had no beams
        assert not any(line.laser and len(line.laser[1]) for line in lines), str(e)
        return
    if (e.message_type, e.field) == ("RAWLASER1", "odometry"):  # nothing to interpolate from
        assert not any(line.odom for line in lines), str(e)
        return
    assert e.line_no in corrupted, (str(e), sorted(corrupted))


def same(a, b) -> bool:
    return np.array_equal(np.asarray(a, float), np.asarray(b, float), equal_nan=True)


def check_log(log: LaserLog, lines: list[Line], kind: str) -> None:
    """Every intact record is in the log, in order, with its own beam angles, exactly; what the
    reader derives is finite."""
    scans = list(log.scans())
    assert (
        log.ranges_m.shape == (len(log), log.angle_table_rad.shape[1]) == (len(scans), log.beam_counts.max())
    )
    assert all(s.ranges_m.size == s.angles_rad.size == n for s, n in zip(scans, log.beam_counts, strict=True))
    for name in ("stamps_s", "odometry", "laser_offset", "odom_poses", "odom_stamps_s"):
        assert np.all(np.isfinite(getattr(log, name))), name
    assert all(np.all(np.isfinite(s.angles_rad)) for s in scans)
    assert math.isfinite(log.range_max_m) and log.range_max_m > 0
    if log.kind == "RAWLASER1":  # odometry interpolated from the ODOM lines (checked below)
        np.testing.assert_array_equal(
            log.odometry, interpolate_odometry(log.odom_stamps_s, log.odom_poses, log.stamps_s)
        )
    lasers = [line.laser for line in lines if line.laser] if log.kind == kind else []
    if any(len(laser[1]) == 0 for laser in lasers):  # lines without beams: left out, and said
        assert any("no beams left out" in w for w in log.warnings), log.warnings
    lasers = [laser for laser in lasers if len(laser[1])]
    rows = iter(scans)
    for stamp, ranges, odometry, _, angles in lasers:  # a subsequence: accepted corrupted lines between
        assert any(
            s.stamp_s == stamp
            and same(s.ranges_m, ranges)
            and (odometry is None or same(s.odometry, odometry))
            and same(s.angles_rad, angles)
            for s in rows
        ), stamp
    odoms = [line.odom for line in lines if line.odom]
    rows = iter(np.column_stack([log.odom_stamps_s, log.odom_poses]))
    for record in odoms:
        assert any(same(row, record) for row in rows), record
    if all(line.intact for line in lines):  # nothing corrupted: exactly these records
        assert log.kind == kind and len(log) == len(lasers) and len(log.odom_stamps_s) == len(odoms)
        skipped = [line.skipped for line in lines if line.skipped]
        assert log.skipped == {k: skipped.count(k) for k in set(skipped)}
        check_derived(log, lines, kind)


def check_derived(log: LaserLog, lines: list[Line], kind: str) -> None:
    """Laser offset and range limit by the documented rules (module docstring of carmen.py)."""
    params = {}
    for line in lines:
        parts = line.text.split()
        if parts and parts[0] == "PARAM":
            params[parts[1]] = parts[2]
    _, _, odometry, laser, _ = next(line.laser for line in lines if line.laser and len(line.laser[1]))
    if kind == "RAWLASER1" or (kind == "FLASER" and odometry == laser):
        offset = [float(params.get(name, 0.0)) for name in OFFSET_PARAMS]
    else:
        offset = relative(np.array(odometry), np.array(laser))
    np.testing.assert_allclose(log.laser_offset, offset, rtol=0, atol=1e-9)
    if kind == "FLASER":
        named = [params[name] for name in RANGE_MAX_PARAMS if name in params]
        expected = float(named[0]) if named else infer_range_max_m(log.ranges_m)
        assert log.range_max_m == expected
        assert named or log.range_max_m <= DEFAULT_RANGE_MAX_M
    else:  # the first laser line's max_range
        first = next(line.text.split() for line in lines if line.laser)
        assert log.range_max_m == float(first[5])


@pytest.fixture(scope="module")
def scratch(tmp_path_factory):
    return tmp_path_factory.mktemp("carmen_fuzz") / "log.clf"


@settings(max_examples=2000, **FUZZ)
@given(carmen_log(), st.booleans(), st.booleans())
def test_generated_logs(scratch, generated, crlf, final_newline):
    lines, kind = generated
    out = read(scratch, file_bytes(lines, crlf, final_newline))
    if isinstance(out, LogFormatError):
        check_error(out, lines)
    else:
        event(f"read {out.kind}, {'one geometry' if len(out.geometry_beams) == 1 else 'geometries vary'}")
        check_log(out, lines, kind)


@settings(max_examples=600, **FUZZ)
@given(carmen_log(), st.data())
def test_generated_logs_gzip_and_damaged_streams(scratch, generated, data):
    lines, kind = generated
    packed = bytearray(gzip.compress(file_bytes(lines, False, True), mtime=0))
    damaged = data.draw(st.booleans())
    if damaged:
        for _ in range(data.draw(st.integers(0, 3))):
            packed[data.draw(st.integers(0, len(packed) - 1))] ^= data.draw(st.integers(1, 255))
        packed = packed[: data.draw(st.integers(2, len(packed)))]
    out = read(scratch, bytes(packed))
    if damaged:  # a damaged stream may still read (damage in the header's spare bytes), or refuse anywhere
        event("damaged: " + ("read" if isinstance(out, LaserLog) else out.message_type))
    elif isinstance(out, LogFormatError):
        assert out.message_type != "gzip", str(out)
        check_error(out, lines)
    else:
        check_log(out, lines, kind)


@settings(max_examples=1000, **FUZZ)
@given(st.binary(max_size=400), st.sampled_from([b"", b"\x1f\x8b", b"FLASER 3 ", b"ROBOTLASER1 0 0 0 0 "]))
def test_random_bytes(scratch, data, head):
    read(scratch, head + data)


@settings(max_examples=400, **FUZZ)
@given(st.lists(st.lists(hostile_token, min_size=1, max_size=30), min_size=1, max_size=6), st.booleans())
def test_random_tokens_after_a_message_type(scratch, rows, gz):
    names = ["FLASER", "ROBOTLASER1", "ODOM", "PARAM"]
    text = "\n".join(" ".join([names[i % 4], *row]) for i, row in enumerate(rows)) + "\n"
    read(scratch, gzip.compress(text.encode(), mtime=0) if gz else text.encode())


# -- what the fuzz found (each was a crash or an unclear error before) --------------------------

F = "FLASER 3 1 2 3 0 0 0 0 0 0 100.5 nohost 0.1"
RL1 = "ROBOTLASER1 0 -1.0 2.0 {res} 20.0 0.01 0 3 1 1 1 0 0 0 0 0 0 0 0 0 0 0 0 {stamp} nohost 0.1"
MAX_PARAM, OFFSET_PARAM = "laser_front_laser_max_range", "robot_frontlaser_offset"
FOUND = {  # lines, the line and field the error names, a detail of its text
    # were accepted with an infinite laser offset / infinite beam angles (overflow warnings only)
    "offset_overflow": (["FLASER 3 1 2 3 1e308 0 0 -1e308 0 0 100.5 nohost 0.1"], 1, "x", "overflows"),
    "angles_overflow": ([RL1.format(res="1e308", stamp=100)], 1, "angular_res", "overflow"),
    # a later line's geometry overflowing (each geometry is computed on its first line)
    "later_angles_overflow": (
        [RL1.format(res="1.0", stamp=100), RL1.format(res="1e308", stamp=101)],
        2,
        "angular_res",
        "overflow",
    ),
    # was a 5,000-character message
    "huge_token": (["FLASER " + "9" * 5000 + " 1"], 1, "num_readings", "(5000 characters)"),
}


# PARAMs the fuzz found unusable (they were a ValueError naming no line, or accepted as an
# infinite range limit / a NaN laser offset): now warned, naming the line, and their defaults used
WARNED = {
    "range_max_param_nan": (f"PARAM {MAX_PARAM} nan nohost 0", "not finite"),
    "range_max_param_negative": (f"PARAM {MAX_PARAM} -5 nohost 0", "positive"),
    "range_max_param_inf": (f"PARAM {MAX_PARAM} inf nohost 0", "not finite"),
    "offset_param_nan": (f"PARAM {OFFSET_PARAM} nan nohost 0", "not finite"),
}


@pytest.mark.parametrize("case", WARNED)
def test_unusable_params_found_by_the_fuzz_are_warned(tmp_path, case):
    param, detail = WARNED[case]
    path = tmp_path / "log.clf"
    path.write_text(f"{param}\n{F}\n")
    log = read_log(path)
    assert len(log.warnings) == 1 and f"{path}:1: PARAM" in log.warnings[0] and detail in log.warnings[0]
    assert np.isfinite(log.range_max_m) and log.range_max_m > 0 and np.all(np.isfinite(log.laser_offset))


@pytest.mark.parametrize("case", FOUND)
def test_found_by_the_fuzz(tmp_path, case):
    lines, line_no, field, detail = FOUND[case]
    path = tmp_path / "log.clf"
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(LogFormatError) as info:
        read_log(path)
    assert info.value.line_no == line_no and info.value.field == field, str(info.value)
    assert detail in str(info.value) and len(str(info.value)) < 200 + len(str(path))


def test_a_changed_geometry_is_read_per_scan(tmp_path):
    # was read with the first line's angles for every scan, then refused ("geometry changed")
    path = tmp_path / "log.clf"
    path.write_text(f"{RL1.format(res='1.0', stamp=100)}\n{RL1.format(res='0.5', stamp=101)}\n")
    log = read_log(path)
    np.testing.assert_array_equal(log.scan(0).angles_rad, [-1.0, 0.0, 1.0])
    np.testing.assert_array_equal(log.scan(1).angles_rad, [-1.0, -0.5, 0.0])


def test_a_stray_carriage_return_is_whitespace_and_line_numbers_are_greps(tmp_path):
    path = tmp_path / "cr.clf"
    split = F.replace(" 2 ", " 2\r")
    path.write_bytes(f"# a\rb\n{split}\nFLASER 3 1 x 3 0 0 0 0 0 0 1 h 0\n".encode())
    with pytest.raises(LogFormatError, match=r"cr\.clf:3: FLASER field 'range\[1\]'"):
        read_log(path)
