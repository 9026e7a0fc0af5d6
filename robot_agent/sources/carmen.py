"""CARMEN laser logs (``.clf``, ``.clf.gz``) as arrays: :func:`read_log` returns a :class:`LaserLog`.

Line formats, as CARMEN's logger writes them (``src/logger/writelog.c``) and reads them back
(``readlog.c``; read in the public copy ``pblop/missionlab-carmen``); fields split on whitespace,
``#`` comments, blank lines and ``SYNC`` skipped::

    PARAM name value [ipc_ts] host logger_ts
    ODOM x y theta tv rv accel ipc_ts host logger_ts
    FLASER n r1..rn x y theta odom_x odom_y odom_theta ipc_ts host logger_ts
    ROBOTLASER1 type start_angle fov angular_res max_range accuracy remission_mode
                n r1..rn n_rem rem1..rem_nrem laser_x laser_y laser_theta
                robot_x robot_y robot_theta tv rv forward_safety side_safety turn_axis
                ipc_ts host logger_ts
    RAWLASER1   type start_angle fov angular_res max_range accuracy remission_mode
                n r1..rn n_rem rem1..rem_nrem ipc_ts host logger_ts

The rear laser and lasers 3, 4 use the same shapes: ``RLASER`` as FLASER, ``ROBOTLASER2`` as
ROBOTLASER1, ``RAWLASER2..4`` as RAWLASER1. ``PARAM``: ``writelog.c`` writes ``name value ipc_ts
host logger_ts``; older logs (Intel, ACES) ``name value host logger_ts``. The value is text
(``on``, ``off``, a list of numbers): everything between the name and that tail, which is three
fields when the third last parses as a number and the line has at least six, else two (a value
is one field when the line has fewer than five). So an old-shape value of several fields ending
in a number loses that number to the tail; the PARAMs this reader uses are one field each.

One laser per log, the front one: the first message type of ROBOTLASER1, FLASER, RAWLASER1 that
the log holds. ROBOTLASER1 comes first as it states its geometry, range limit and both poses; a
log with ROBOTLASER1 and FLASER lines for the same laser (a converted log) reads ROBOTLASER1.
FLASER has the poses but no geometry; RAWLASER1 has neither pose. Lines of every other type (the
front laser's other formats, rear lasers, TRUEPOS, NMEA, ...) are counted in ``LaserLog.skipped``,
not parsed: a first pass over the file counts the message types (a few % of the read time).
Scans keep file order: Intel's ipc timestamps step back 631 times.

Rules (CARMEN's conventions and their sources: :mod:`robot_agent.sources.carmen_conventions`):

- Beam geometry is per line. ROBOTLASER1, RAWLASER1: ``start_angle + i*angular_res``, ``n``
  beams (``fov`` is not used). FLASER: :func:`flaser_angles` of its ``n`` with the field of view
  and resolution the PARAMs ``laser_front_laser_{fov,resolution}`` (or ``laser_laser<id>_...``)
  give in degrees, pi and none when absent (then 180 beams span -90°..89°, 181 -90°..90°, 360
  -90°..89.5°, 361 -90°..90°, CARMEN's own reading). With a resolution, every FLASER count must
  fill the field of view as CARMEN's driver does (``fov/res`` or one more beam); a count that does
  not is read with the default angles, and a warning names its first line and the PARAMs
  (``LaserLog.warnings``: a PARAM may describe a laser setup other than the one logged).
  ``laser_front_laser_flipped`` changes nothing (the driver reverses a flipped scan before
  publishing it). Any PARAM the reader uses whose value it cannot use (text where a number is
  due, a field of view in radians) is likewise replaced by its default, with a warning.
- Odometry: ROBOTLASER1's robot pose, FLASER's ``odom_*``; RAWLASER1 has none, so the ODOM lines
  are interpolated at its ipc timestamp (:func:`interpolate_odometry`; a RAWLASER1 log without
  ODOM lines is refused).
- Laser offset (laser pose in the robot frame): ROBOTLASER1 ``relative(robot, laser)`` of its
  first line; FLASER ``relative(odom, laser)`` of its first line unless the two poses are
  identical there; then, and for RAWLASER1, ``PARAM robot_frontlaser_offset`` (forward, m),
  ``robot_frontlaser_side_offset`` (left, m), ``robot_frontlaser_angular_offset`` (rad), each 0
  when absent.
- ``range_max_m``: ROBOTLASER1's and RAWLASER1's ``max_range`` of the first line. FLASER: a PARAM
  of :data:`RANGE_MAX_PARAMS` if present; else, when the largest reading recurs (at least
  :data:`SENTINEL_MIN_COUNT` times and :data:`SENTINEL_MIN_FRACTION` of all readings) it is a
  "no return" code, like Intel's 81.83 m in 2.8% of its beams, and ``min(code,
  DEFAULT_RANGE_MAX_M)`` is used; else ``DEFAULT_RANGE_MAX_M`` = 81 m (all a SICK LMS measures, up
  to 80 m, is a return). Intel gives 81.0 m.

Hostile input: every malformed line of a type the log is read from (PARAM, ODOM, the chosen laser)
raises :class:`LogFormatError` naming the line (1-based, counted by ``\n`` only, as ``grep -n``
does) and the field, never an error from deep inside; what a number derives (laser offset, beam
angles, range limit) must be finite too. Quoted tokens in messages are cut to :data:`_QUOTE_CHARS`.
``tests/sources/test_carmen_fuzz.py`` holds the reader to it.

Speed: one ``split`` and one ``np.array`` per line; the bad field is searched for only after a
conversion has failed. ``benchmarks/bench_read_log.py`` times the development logs.
"""

from __future__ import annotations

import gzip
import io
import os
import sys
import zlib
from collections import Counter
from collections.abc import Callable, Iterator
from contextlib import closing, contextmanager
from pathlib import Path

import numpy as np

from robot_agent.sources.carmen_conventions import (
    DEFAULT_RANGE_MAX_M,
    OFFSET_PARAMS,
    RANGE_MAX_PARAMS,
    SENTINEL_MIN_COUNT,
    SENTINEL_MIN_FRACTION,
    ParamError,
    beams_fit,
    flaser_angles,
    flaser_field_of_view,
    infer_range_max_m,
    interpolate_odometry,
    is_flaser_geometry,
    param_number,
)
from robot_agent.sources.laserlog import LaserLog
from shared.geometry import relative

__all__ = [
    "DEFAULT_RANGE_MAX_M",
    "FRONT_LASERS",
    "MAX_BEAMS",
    "RANGE_MAX_PARAMS",
    "SENTINEL_MIN_COUNT",
    "SENTINEL_MIN_FRACTION",
    "LaserLog",
    "LogFormatError",
    "flaser_angles",
    "infer_range_max_m",
    "is_flaser_geometry",
    "read_log",
]

MAX_BEAMS = 100_000
"""A declared beam count above this is a corrupt line, not a laser."""
FRONT_LASERS = ("ROBOTLASER1", "FLASER", "RAWLASER1")
"""The front laser's message types, in the order of preference (module docstring)."""
_GZIP_MAGIC = b"\x1f\x8b"
_QUOTE_CHARS = 40  # a token quoted in an error message is cut to this many characters
_PROGRESS_EVERY_LINES = 2000
_FLASER_TAIL = ("x", "y", "theta", "odom_x", "odom_y", "odom_theta", "ipc_timestamp")
_ODOM_NAMES = ("x", "y", "theta", "tv", "rv", "accel", "ipc_timestamp")
_CONFIG = ("start_angle", "fov", "angular_res", "max_range", "accuracy")
_RL1_TAIL = (
    "laser_x",
    "laser_y",
    "laser_theta",
    "robot_x",
    "robot_y",
    "robot_theta",
    "tv",
    "rv",
    "forward_safety",
    "side_safety",
    "turn_axis",
    "ipc_timestamp",
)


class LogFormatError(ValueError):
    """A malformed log: the message names file, 1-based line, message type and field."""

    def __init__(self, path: str, line_no: int, message_type: str, field: str, problem: str):
        super().__init__(f"{path}:{line_no}: {message_type} field '{field}': {problem}")
        self.path, self.line_no, self.message_type = path, line_no, message_type
        self.field, self.problem = field, problem

    def __reduce__(self):
        return type(self), (self.path, self.line_no, self.message_type, self.field, self.problem)


def read_log(path: str | os.PathLike[str], progress: bool | None = None, strict: bool = False) -> LaserLog:
    """Read a CARMEN log (plain or gzip, told by its magic bytes) into a :class:`LaserLog`.

    ``progress``: a bar over bytes read on stderr; ``None`` shows it when stderr is a TTY.
    Raises :class:`LogFormatError` naming file, line and field for any malformed line — but, as
    logs come off robots, a last line cut short (power lost while recording) and laser lines
    without beams are left out with a warning (``LaserLog.warnings``) unless ``strict``.
    """
    path = str(path)
    types: Counter[str] = Counter()
    with closing(_lines(path, False)) as lines:  # pass 1: which laser the log is read from
        for _, line in lines:
            head = line.split(None, 1)
            if head and not head[0].startswith("#"):
                types[head[0]] += 1
    kind = next((k for k in FRONT_LASERS if types[k]), None)
    reader = _Reader(path, kind, types, strict)
    show = sys.stderr.isatty() if progress is None else progress
    cut: LogFormatError | None = None  # a line with too few fields: the last one, cut short?
    with closing(_lines(path, show)) as lines:
        for line_no, line in lines:
            if cut is not None and line.strip():
                raise cut  # more came after it: malformed, not cut short
            try:
                reader.feed(line_no, line)
            except LogFormatError as err:
                if strict or not err.problem.startswith("too few fields"):
                    raise
                cut = err
    if cut is not None:
        reader.warnings.append(
            f"{path}:{cut.line_no}: the last line is cut short ({cut.message_type} {cut.problem}); "
            "the log is read without it"
        )
    log = reader.finish()
    reader.handlers.clear()  # its bound methods hold the reader: what it read goes now, not at a gc
    return log


def _lines(path: str, show: bool) -> Iterator[tuple[int, str]]:
    """``(line_no, line)`` of the file, gunzipped when it starts with gzip's magic bytes; damaged
    compressed data raises LogFormatError at the line after the last one read."""
    with open(path, "rb") as raw:
        compressed = raw.read(2) == _GZIP_MAGIC
        raw.seek(0)
        stream = gzip.GzipFile(fileobj=raw, mode="rb") if compressed else raw
        # newline="\n": a stray "\r" is whitespace inside a line, so line numbers are grep's
        text = io.TextIOWrapper(stream, encoding="utf-8", errors="replace", newline="\n")
        with _progress_bar(show, os.fstat(raw.fileno()).st_size, Path(path).name) as advance:
            line_no = 0
            try:
                for line_no, line in enumerate(text, 1):
                    yield line_no, line
                    if line_no % _PROGRESS_EVERY_LINES == 0:
                        advance(raw.tell())
            except (gzip.BadGzipFile, EOFError, zlib.error) as err:
                raise LogFormatError(
                    path, line_no + 1, "gzip", "stream", f"unreadable compressed data ({err})"
                ) from err
            advance(raw.tell())


class _Reader:
    """Collects one log's lines of the chosen ``kind`` (and ODOM, PARAM) into lists;
    :meth:`finish` stacks them into a LaserLog."""

    def __init__(self, path: str, kind: str | None, types: Counter[str], strict: bool = False) -> None:
        self.path, self.kind, self.line_no, self.strict = path, kind, 0, strict
        self.blind: list[int] = []  # laser lines without beams (left out): their line numbers
        read = {"PARAM", "ODOM", "SYNC", kind}
        self.skipped = {name: n for name, n in types.items() if name not in read}
        self.warnings: list[str] = []
        self.first: tuple[int, np.ndarray | None, np.ndarray | None] | None = None  # line, odom, laser
        self.range_max_m: float | None = None
        self.geometry_of: dict[object, int] = {}  # key -> row of the geometry table
        self.geometries: list[tuple[int, int, np.ndarray | None]] = []  # first line, beams, angles
        self.stamps: list[float] = []
        self.rows = _Rows(types[kind] if kind else 0)  # every scan's ranges
        self.scan_geometry: list[int] = []
        self.odometry = _Rows(types[kind] if kind else 0)  # the laser lines' own odometry
        self.odom_rows = _Rows(types["ODOM"])  # ODOM lines: stamp, x, y, theta
        self.params: dict[str, str] = {}
        self.param_lines: dict[str, int] = {}
        self.handlers: dict[str | None, Callable[[list[str]], None]] = {
            "ODOM": self._odom,
            "PARAM": self._param,
            "FLASER": self._flaser,
            "ROBOTLASER1": self._robotlaser,
            "RAWLASER1": self._rawlaser,
        }
        self.handlers = {k: v for k, v in self.handlers.items() if k in read}

    def error(
        self, message_type: str, field: str, problem: str, line_no: int | None = None
    ) -> LogFormatError:
        return LogFormatError(
            self.path, self.line_no if line_no is None else line_no, message_type, field, problem
        )

    def feed(self, line_no: int, line: str) -> None:
        self.line_no = line_no
        parts = line.split()
        handler = self.handlers.get(parts[0]) if parts else None
        if handler is not None:
            handler(parts)

    # --- fields ---------------------------------------------------------------------------------

    def floats(self, parts: list[str], a: int, b: int, names: _Names, finite_from: int = 0) -> np.ndarray:
        """``parts[a:b]`` as floats, finite from index ``finite_from``; names[i] is parts[a+i]."""
        try:
            values = np.array(parts[a:b], dtype=float)
        except ValueError:
            for i, text in enumerate(parts[a:b]):
                try:
                    float(text)
                except ValueError:
                    raise self.error(parts[0], names[i], f"cannot parse {_quote(text)} as a number") from None
            values = np.array([float(text) for text in parts[a:b]])  # numpy stricter than float
        finite = np.isfinite(values[finite_from:])
        if not finite.all():
            i = finite_from + int(np.argmin(finite))
            raise self.error(parts[0], names[i], f"value {_quote(parts[a + i])} is not finite")
        return values

    def count(self, parts: list[str], index: int, field: str) -> int:
        """The beam count at ``parts[index]``: an integer in ``[0, MAX_BEAMS]``."""
        if index >= len(parts):
            raise self.error(parts[0], field, f"too few fields: line ends after {len(parts)}")
        try:
            n = int(parts[index])
        except ValueError:
            raise self.error(parts[0], field, f"cannot parse {_quote(parts[index])} as an integer") from None
        if not 0 <= n <= MAX_BEAMS:
            raise self.error(parts[0], field, f"beam count {n} outside [0, {MAX_BEAMS}]")
        return n

    def expect_fields(self, parts: list[str], expected: int, field: str, why: str) -> None:
        if len(parts) != expected:
            few_or_many = "few" if len(parts) < expected else "many"
            raise self.error(
                parts[0],
                field,
                f"too {few_or_many} fields: {why}, so the line needs {expected} fields; found {len(parts)}",
            )

    # --- lines ----------------------------------------------------------------------------------

    def _flaser(self, parts: list[str]) -> None:
        n = self.count(parts, 1, "num_readings")
        self.expect_fields(parts, n + 11, "num_readings", f"it declares {n} beams")
        values = self.floats(parts, 2, n + 9, _Names(n, _FLASER_TAIL), finite_from=n)
        # the angles wait for finish(): PARAMs anywhere in the file may set them
        self._add_scan(values[:n], values[n + 3 : n + 6], values[n : n + 3], values[n + 6], n, None)

    def _config(self, parts: list[str], tail: int) -> tuple[int, int, float, float]:
        """ROBOTLASER1 / RAWLASER1: beams, remissions, start angle and resolution of the line,
        which must have ``tail`` fields after its remissions; sets the range limit once."""
        n = self.count(parts, 8, "num_readings")
        n_rem = self.count(parts, 9 + n, "num_remissions")
        self.expect_fields(
            parts, n + n_rem + 10 + tail, "num_remissions", f"it declares {n} beams and {n_rem} remissions"
        )
        start, _, res, max_range_m, _ = self.floats(parts, 2, 7, _Names(0, _CONFIG))
        if not max_range_m > 0:
            raise self.error(parts[0], "max_range", f"{_quote(parts[5])} is not a positive range")
        if self.range_max_m is None:
            self.range_max_m = float(max_range_m)
        return n, n_rem, float(start), float(res)

    def _robotlaser(self, parts: list[str]) -> None:
        n, n_rem, start, res = self._config(parts, len(_RL1_TAIL) + 2)
        ranges = self.floats(parts, 9, 9 + n, _Names(n, ()), finite_from=n)
        tail = self.floats(parts, n + n_rem + 10, n + n_rem + 22, _Names(0, _RL1_TAIL))
        self._add_scan(ranges, tail[3:6], tail[0:3], tail[11], (start, res, n), _even_angles)

    def _rawlaser(self, parts: list[str]) -> None:
        n, n_rem, start, res = self._config(parts, 3)
        ranges = self.floats(parts, 9, 9 + n, _Names(n, ()), finite_from=n)
        (stamp,) = self.floats(parts, n + n_rem + 10, n + n_rem + 11, _Names(0, ("ipc_timestamp",)))
        self._add_scan(ranges, None, None, stamp, (start, res, n), _even_angles)

    def _add_scan(
        self,
        ranges: np.ndarray,
        odom: np.ndarray | None,
        laser: np.ndarray | None,
        stamp: float,
        key: object,
        angles: Callable[[float, float, int], np.ndarray] | None,
    ) -> None:
        """Append one scan; ``key`` names its geometry, ``angles(*key)`` computes it (None: later).
        A line without beams is left out (``strict``: refused)."""
        if ranges.size == 0:
            if self.strict:
                raise self.error(self.kind, "num_readings", "a laser line with no beams")
            self.blind.append(self.line_no)
            return
        if self.first is None:
            if odom is not None:
                with np.errstate(over="ignore", invalid="ignore"):  # huge values: checked just below
                    offset = relative(odom, laser)
                if not np.all(np.isfinite(offset)):
                    field = "x" if self.kind == "FLASER" else "laser_x"
                    raise self.error(
                        self.kind, field, "laser and robot poses too far apart: their offset overflows"
                    )
            self.first = (self.line_no, odom, laser)
        g = self.geometry_of.get(key)
        if g is None:
            beam_angles = None
            if angles is not None:
                with np.errstate(over="ignore", invalid="ignore"):
                    beam_angles = angles(*key)
                if not np.all(np.isfinite(beam_angles)):
                    raise self.error(self.kind, "angular_res", "beam angles overflow")
            g = self.geometry_of[key] = len(self.geometries)
            self.geometries.append((self.line_no, ranges.size, beam_angles))
        self.rows.append(ranges)
        self.scan_geometry.append(g)
        if odom is not None:
            self.odometry.append(odom)
        self.stamps.append(float(stamp))

    def _odom(self, parts: list[str]) -> None:
        self.expect_fields(parts, 10, "ipc_hostname", "ODOM carries 9 values")
        self.odom_rows.append(self.floats(parts, 1, 8, _Names(0, _ODOM_NAMES))[[6, 0, 1, 2]])

    def _param(self, parts: list[str]) -> None:
        if len(parts) < 3:
            raise self.error("PARAM", "param_value", f"too few fields: found {len(parts)}")
        if len(parts) < 5:  # no (full) tail: hand-written
            value = parts[2:3]
        elif len(parts) >= 6 and _is_number(parts[-3]):  # value ipc_ts host logger_ts
            value = parts[2:-3]
        else:  # value host logger_ts
            value = parts[2:-2]
        self.params[parts[1]] = " ".join(value)
        self.param_lines[parts[1]] = self.line_no

    # --- PARAMs ---------------------------------------------------------------------------------

    def param_float(self, name: str, default: float, positive: bool = False) -> float:
        """The PARAM ``name`` as a finite number (``positive``: > 0), ``default`` when absent or
        unusable (then a warning names the PARAM's line and what was used instead)."""
        try:
            return param_number(self.params, name, default, positive)
        except ParamError as err:
            self.warn_param(err, f"used {default:g} instead" if np.isfinite(default) else "not used")
            return default

    def warn_param(self, err: ParamError, instead: str) -> None:
        """A PARAM that cannot be used: the log is read all the same (a PARAM may describe a setup
        other than the one logged), and the user is told which line and what was done."""
        self.warnings.append(f"{self.path}:{self.param_lines[err.name]}: {err}; {instead}")

    def laser_offset(self) -> np.ndarray:
        _, odom, laser = self.first
        if odom is not None and (self.kind == "ROBOTLASER1" or not np.array_equal(odom, laser)):
            return relative(odom, laser)
        return np.array([self.param_float(name, 0.0) for name in OFFSET_PARAMS])

    # --- the log --------------------------------------------------------------------------------

    def table(self) -> np.ndarray:
        """The geometry table ``(G,B)``, NaN-padded; FLASER angles from the PARAMs."""
        width = max(beams for _, beams, _ in self.geometries)
        table = np.full((len(self.geometries), width), np.nan)
        if self.kind == "FLASER":
            try:
                fov_rad, res_rad, names = flaser_field_of_view(self.params)
            except ParamError as err:
                self.warn_param(err, "beams spread over 180° by their count instead")
                fov_rad, res_rad, names = np.pi, None, []
        for g, (line_no, beams, angles) in enumerate(self.geometries):
            if angles is None:  # FLASER
                geometry = (fov_rad, res_rad)
                if res_rad is not None and not beams_fit(beams, fov_rad, res_rad):
                    said = [f"{name} {self.params[name]} (line {self.param_lines[name]})" for name in names]
                    if len(said) == 1:
                        said.insert(0, "a field of view of 180° (none named)")
                    k = round(fov_rad / res_rad)
                    self.warnings.append(
                        f"{self.path}:{line_no}: {self.kind} {beams} beams do not fit {' and '.join(said)} "
                        f"(CARMEN's driver gives {k} or {k + 1}); these beams spread over 180° by their "
                        "count instead"
                    )
                    geometry = (np.pi, None)
                angles = flaser_angles(beams, *geometry)
            table[g, :beams] = angles
        return table

    def finish(self) -> LaserLog:
        if self.blind:
            n = len(self.blind)
            self.warnings.append(
                f"{self.path}:{self.blind[0]}: {self.kind} laser lines with no beams left out "
                f"({n} line{'s' if n > 1 else ''}, the first here)"
            )
        if self.kind is None:
            rear = ", ".join(f"{k} ({n} lines)" for k, n in sorted(self.skipped.items()) if "LASER" in k)
            raise self.error("log", "|".join(FRONT_LASERS), "no front laser lines in the log"
                             + (f"; not read: {rear}" if rear else ""))  # fmt: skip
        if not self.rows:
            why = [f"{len(self.blind)} without beams"] if self.blind else []
            why += ["the last cut short"] if any("cut short" in w for w in self.warnings) else []
            left = f"no {self.kind} line left to read ({', '.join(why)})"
            raise self.error(self.kind, "num_readings", left)
        ranges = self.rows.stack()
        odom = self.odom_rows.stack().reshape(-1, 4)
        stamps = np.array(self.stamps)
        if self.kind == "RAWLASER1":
            if not len(odom):
                raise self.error("RAWLASER1", "odometry", "RAWLASER1 lines carry no pose and the log has "
                                 "no ODOM lines to interpolate one from", self.first[0])  # fmt: skip
            odometry = interpolate_odometry(odom[:, 0], odom[:, 1:], stamps)
        else:
            odometry = self.odometry.stack()
        table = self.table()
        if self.range_max_m is None:
            named = [name for name in RANGE_MAX_PARAMS if name in self.params]
            said = self.param_float(named[0], np.nan, positive=True) if named else np.nan
            self.range_max_m = said if np.isfinite(said) else infer_range_max_m(ranges)
        return LaserLog(
            stamps_s=stamps,
            ranges_m=ranges,
            angle_table_rad=table,
            geometry_beams=[beams for _, beams, _ in self.geometries],
            scan_geometry=self.scan_geometry,
            odometry=odometry,
            laser_offset=self.laser_offset(),
            range_max_m=self.range_max_m,
            odom_stamps_s=odom[:, 0],
            odom_poses=odom[:, 1:],
            params=dict(self.params),
            path=self.path,
            kind=self.kind,
            skipped=dict(self.skipped),
            warnings=tuple(self.warnings),
        )


class _Rows:
    """Rows of varying length in one array ``(capacity, longest)`` (NaN past each row's end),
    sized by the first pass's count of laser lines: the log's ranges take their own size in
    memory while read (a list of rows stacked at the end took twice that: Intel's 19 MB of ranges
    peaked at 145 MB read, 119 MB this way)."""

    def __init__(self, capacity: int) -> None:
        self.capacity, self.n = max(int(capacity), 1), 0
        self.array: np.ndarray | None = None

    def __len__(self) -> int:
        return self.n

    def append(self, row: np.ndarray) -> None:
        if self.array is None:
            self.array = np.full((self.capacity, row.size), np.nan)
        rows, width = self.array.shape
        if self.n == rows or row.size > width:  # more lines than counted (never), or a longer row
            grown = np.full((rows * 2 if self.n == rows else rows, max(width, row.size)), np.nan)
            grown[:rows, :width] = self.array
            self.array = grown
        self.array[self.n, : row.size] = row
        self.n += 1

    def stack(self) -> np.ndarray:
        """All rows ``(n, longest)``."""
        if self.array is None:
            return np.zeros((0, 0))  # (reshaped by the caller where a width is needed)
        return self.array if self.n == len(self.array) else self.array[: self.n].copy()


def _even_angles(start_rad: float, res_rad: float, n: int) -> np.ndarray:
    return start_rad + np.arange(n) * res_rad


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def _quote(text: str) -> str:
    """``repr(text)``, cut to :data:`_QUOTE_CHARS` characters (a hostile token can be megabytes)."""
    if len(text) <= _QUOTE_CHARS:
        return repr(text)
    return f"{text[:_QUOTE_CHARS]!r}... ({len(text)} characters)"


class _Names:
    """Field names of ``n`` ranges then ``tail``, formatted only when an error needs one."""

    def __init__(self, n: int, tail: tuple[str, ...]) -> None:
        self.n, self.tail = n, tail

    def __getitem__(self, i: int) -> str:
        return f"range[{i}]" if i < self.n else self.tail[i - self.n]


@contextmanager
def _progress_bar(show: bool, total_bytes: int, label: str) -> Iterator[Callable[[int], None]]:
    """Yields ``advance(bytes_done)``: a rich bar on stderr when ``show``, else a no-op."""
    if not show:
        yield lambda done: None
        return
    from rich.console import Console  # imported only when a bar is drawn
    from rich.progress import Progress

    with Progress(console=Console(stderr=True), transient=True) as bar:
        task = bar.add_task(f"reading {label}", total=total_bytes)
        yield lambda done: bar.update(task, completed=done)
