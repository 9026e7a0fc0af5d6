"""CARMEN laser logs (``.clf``, ``.clf.gz``) as arrays: :func:`read_log` and :class:`LaserLog`.

Lines read (fields split on whitespace; ``#`` comments, blank lines and ``SYNC`` skipped)::

    PARAM name value [host ts]
    ODOM x y theta tv rv accel ipc_ts host logger_ts
    FLASER n r1..rn x y theta odom_x odom_y odom_theta ipc_ts host logger_ts
    ROBOTLASER1 type start_angle fov angular_res max_range accuracy remission_mode
                n r1..rn n_rem rem1..rem_nrem laser_x laser_y laser_theta
                robot_x robot_y robot_theta tv rv forward_safety side_safety turn_axis
                ipc_ts host logger_ts

Other message types (RLASER, the rear laser; TRUEPOS, NMEA-*, RAWLASER1..4, ...) are counted
in ``LaserLog.skipped`` and ignored, as are laser lines of the other kind once the first laser
line has fixed ``kind``. Scans keep file order: Intel's ipc timestamps step back 631 times.

Rules:

- FLASER beam angles span a field of view of pi: odd ``n`` -> ``linspace(-pi/2, pi/2, n)``
  (SICK LMS, ends included); even ``n`` -> ``-pi/2 + i*pi/n`` (GMapping: 180 beams -90°..89°).
  ROBOTLASER1: ``start_angle + i*angular_res``.
- Laser offset (laser pose in the robot frame): ROBOTLASER1 ``relative(robot, laser)``; FLASER
  ``relative(odom, laser)`` of the first line, unless the two poses are identical there; then
  ``PARAM robot_frontlaser_offset`` (forward, m), ``robot_frontlaser_side_offset`` (left, m) and
  ``robot_frontlaser_angular_offset`` (rad) apply, each zero when absent.
- ``range_max_m``: ROBOTLASER1's ``max_range``. FLASER: a PARAM of :data:`RANGE_MAX_PARAMS`
  if present; else, when the largest reading recurs (at least :data:`SENTINEL_MIN_COUNT` times
  and :data:`SENTINEL_MIN_FRACTION` of all readings) it is a "no return" code, like Intel's
  81.83 m in 2.8% of its beams, and ``min(code, DEFAULT_RANGE_MAX_M)`` is used; else
  ``DEFAULT_RANGE_MAX_M`` = 81 m (all a SICK LMS measures, up to 80 m, is a return).
  Intel gives 81.0 m.

Hostile input: every malformed line raises :class:`LogFormatError` naming the line (1-based,
counted by ``\n`` only, as ``grep -n`` does) and the field, never an error from deep inside; what
a number derives (laser offset, beam angles, range limit) must be finite too. Quoted tokens in
messages are cut to :data:`_QUOTE_CHARS`. ``tests/sources/test_carmen_fuzz.py`` holds the reader to it.

Speed: the full Intel log (40,557 lines, 13,631 FLASER, 16 MB) loads in about 0.5 s (measured
in ``tests/sources/test_carmen.py::test_full_intel_log``): one ``split`` and one ``np.array``
per line; the bad field is searched for only after a conversion has failed.
"""

from __future__ import annotations

import gzip
import io
import os
import sys
import zlib
from collections import Counter
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from robot_agent.sources.base import Scan
from shared.geometry import relative

MAX_BEAMS = 100_000
"""A declared beam count above this is a corrupt line, not a laser."""
DEFAULT_RANGE_MAX_M = 81.0
"""FLASER range limit when the log names none (see module docstring)."""
SENTINEL_MIN_FRACTION = 1e-3
"""Share of all readings the largest value must reach to count as a "no return" code."""
SENTINEL_MIN_COUNT = 10
"""... and the fewest readings, so that a short log's single farthest hit is no code."""
RANGE_MAX_PARAMS = ("robot_front_laser_max", "laser_front_laser_max_range")
"""PARAM names giving the front laser's range limit in metres; the first found wins."""
FLASER_ANGLE_TOL_RAD = 1e-9
"""Beam angles this close to :func:`flaser_angles` are FLASER geometry (for the writer)."""
_GZIP_MAGIC = b"\x1f\x8b"
_QUOTE_CHARS = 40  # a token quoted in an error message is cut to this many characters
_PROGRESS_EVERY_LINES = 2000
_FLASER_TAIL = ("x", "y", "theta", "odom_x", "odom_y", "odom_theta", "ipc_timestamp")
_ODOM_NAMES = ("x", "y", "theta", "tv", "rv", "accel", "ipc_timestamp")
_RL1_HEAD = ("start_angle", "fov", "angular_res", "max_range", "accuracy")
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


def flaser_angles(n: int) -> np.ndarray:
    """FLASER beam angles ``(n,)`` in the laser frame (field of view pi, see module docs)."""
    if n % 2:
        return np.linspace(-np.pi / 2, np.pi / 2, n)
    return -np.pi / 2 + np.arange(n) * (np.pi / max(n, 1))


def is_flaser_geometry(angles_rad: np.ndarray) -> bool:
    """True when ``angles_rad`` are :func:`flaser_angles` of their count."""
    angles_rad = np.asarray(angles_rad, dtype=float)
    expected = flaser_angles(angles_rad.size)
    return bool(np.all(np.abs(angles_rad - expected) <= FLASER_ANGLE_TOL_RAD))


def infer_range_max_m(ranges_m: np.ndarray) -> float:
    """Range limit of a FLASER log naming none: a recurring "no return" code, else 81 m."""
    finite = ranges_m[np.isfinite(ranges_m)]
    if finite.size == 0:
        return DEFAULT_RANGE_MAX_M
    top = float(finite.max())
    if np.count_nonzero(finite == top) >= max(SENTINEL_MIN_COUNT, SENTINEL_MIN_FRACTION * finite.size):
        return min(top, DEFAULT_RANGE_MAX_M)
    return DEFAULT_RANGE_MAX_M


@dataclass(frozen=True, eq=False)
class LaserLog:
    """One laser's scans with odometry; arrays are read-only, SI units.

    ``stamps_s (S,)`` ipc time of each laser line in file order, ``ranges_m (S,B)``,
    ``angles_rad (B,)`` in the laser frame, ``odometry (S,3)`` robot odometry pose at each
    scan, ``laser_offset (3,)`` laser pose in the robot frame, ``odom_stamps_s (M,)`` and
    ``odom_poses (M,3)`` from ODOM lines, ``skipped`` counts of ignored message types.
    """

    stamps_s: np.ndarray
    ranges_m: np.ndarray
    angles_rad: np.ndarray
    odometry: np.ndarray
    laser_offset: np.ndarray
    range_max_m: float
    odom_stamps_s: np.ndarray
    odom_poses: np.ndarray
    params: dict[str, str] = field(default_factory=dict)
    path: str = ""
    kind: str = "FLASER"
    skipped: dict[str, int] = field(default_factory=dict)

    def __post_init__(self) -> None:
        dims: dict[str, int] = {}
        for name, layout in (
            ("stamps_s", "S"),
            ("ranges_m", "SB"),
            ("angles_rad", "B"),
            ("odometry", "S3"),
            ("laser_offset", "3"),
            ("odom_stamps_s", "M"),
            ("odom_poses", "M3"),
        ):
            array = np.array(getattr(self, name), dtype=float)
            expected = tuple(
                int(d) if d.isdigit() else dims.setdefault(d, n)
                for d, n in zip(layout, array.shape, strict=False)
            )
            if array.ndim != len(layout) or array.shape != expected:
                known = ", ".join(f"{k}={v}" for k, v in dims.items())
                raise ValueError(
                    f"{name} has shape {array.shape}, expected "
                    f"({', '.join(layout)}) with {known or 'no sizes yet'}"
                )
            array.flags.writeable = False
            object.__setattr__(self, name, array)
        range_max_m = float(self.range_max_m)
        if not range_max_m > 0:
            raise ValueError(f"range_max_m must be positive, got {self.range_max_m!r}")
        object.__setattr__(self, "range_max_m", range_max_m)

    @classmethod
    def from_arrays(
        cls,
        stamps_s,
        ranges_m,
        angles_rad,
        odometry,
        laser_offset=(0.0, 0.0, 0.0),
        range_max_m: float | None = None,
        odom_stamps_s=None,
        odom_poses=None,
        params: dict[str, str] | None = None,
    ) -> LaserLog:
        """Build a log from arrays (shapes as in the class docstring; ValueError if not).

        ``range_max_m=None`` applies the FLASER rule of :func:`infer_range_max_m`; ``kind``
        is FLASER when ``angles_rad`` follow :func:`flaser_angles`, else ROBOTLASER1.
        """
        ranges_m = np.asarray(ranges_m, dtype=float)
        return cls(
            stamps_s=stamps_s,
            ranges_m=ranges_m,
            angles_rad=angles_rad,
            odometry=odometry,
            laser_offset=laser_offset,
            range_max_m=infer_range_max_m(ranges_m) if range_max_m is None else range_max_m,
            odom_stamps_s=np.zeros(0) if odom_stamps_s is None else odom_stamps_s,
            odom_poses=np.zeros((0, 3)) if odom_poses is None else odom_poses,
            params=dict(params or {}),
            kind="FLASER" if is_flaser_geometry(angles_rad) else "ROBOTLASER1",
        )

    def __len__(self) -> int:
        return self.stamps_s.shape[0]

    @property
    def duration_s(self) -> float:
        """Time spanned by the laser stamps (max - min: file order is not time order)."""
        return float(np.ptp(self.stamps_s)) if len(self) else 0.0

    def odometry_track(self) -> tuple[np.ndarray, np.ndarray]:
        """The densest odometry the log holds: its ODOM lines, or the laser lines' odometry when
        it has none — ``stamps_s (M,)``, ``poses (M,3)`` (for the relations metric's shift)."""
        if len(self.odom_stamps_s) > 1:
            return self.odom_stamps_s, self.odom_poses
        return self.stamps_s, self.odometry

    def scans(self) -> Iterator[Scan]:
        """The scans in file order, each sharing this log's read-only arrays."""
        for i in range(len(self)):
            yield Scan(
                stamp_s=float(self.stamps_s[i]),
                ranges_m=self.ranges_m[i],
                angles_rad=self.angles_rad,
                odometry=self.odometry[i],
                laser_offset=self.laser_offset,
                range_max_m=self.range_max_m,
            )


def read_log(path: str | os.PathLike[str], progress: bool | None = None) -> LaserLog:
    """Read a CARMEN log (plain or gzip, told by its magic bytes) into a :class:`LaserLog`.

    ``progress``: a bar over bytes read on stderr; ``None`` shows it when stderr is a TTY.
    Raises :class:`LogFormatError` naming file, line and field for any malformed line.
    """
    path = str(path)
    reader = _Reader(path)
    with open(path, "rb") as raw:
        compressed = raw.read(2) == _GZIP_MAGIC
        raw.seek(0)
        stream = gzip.GzipFile(fileobj=raw, mode="rb") if compressed else raw
        # newline="\n": a stray "\r" is whitespace inside a line, so line numbers are grep's
        text = io.TextIOWrapper(stream, encoding="utf-8", errors="replace", newline="\n")
        show = sys.stderr.isatty() if progress is None else progress
        with _progress_bar(show, os.fstat(raw.fileno()).st_size, Path(path).name) as advance:
            try:
                for line_no, line in enumerate(text, 1):
                    reader.feed(line_no, line)
                    if line_no % _PROGRESS_EVERY_LINES == 0:
                        advance(raw.tell())
            except (gzip.BadGzipFile, EOFError, zlib.error) as err:
                raise LogFormatError(
                    path, reader.line_no + 1, "gzip", "stream", f"unreadable compressed data ({err})"
                ) from err
            advance(raw.tell())
    return reader.finish()


class _Reader:
    """Collects one log's lines into lists; :meth:`finish` stacks them into a LaserLog."""

    def __init__(self, path: str) -> None:
        self.path, self.line_no = path, 0
        self.kind: str | None = None
        self.first: tuple[int, np.ndarray, np.ndarray, bool] | None = None
        self.geometry: tuple[float, float] | None = None  # ROBOTLASER1 (start_angle, angular_res)
        self.range_max_m: float | None = None
        self.stamps: list[float] = []
        self.rows: list[np.ndarray] = []
        self.odometry: list[np.ndarray] = []
        self.odom_rows: list[np.ndarray] = []
        self.params: dict[str, str] = {}
        self.param_lines: dict[str, int] = {}
        self.skipped: Counter[str] = Counter()
        self.handlers = {
            "FLASER": self._flaser,
            "ROBOTLASER1": self._robotlaser,
            "ODOM": self._odom,
            "PARAM": self._param,
            "SYNC": lambda parts: None,
        }

    def error(self, message_type: str, field: str, problem: str) -> LogFormatError:
        return LogFormatError(self.path, self.line_no, message_type, field, problem)

    def feed(self, line_no: int, line: str) -> None:
        self.line_no = line_no
        parts = line.split()
        if not parts or parts[0].startswith("#"):
            return
        handler = self.handlers.get(parts[0])
        if handler is None or (parts[0] in _LASERS and self.kind not in (None, parts[0])):
            self.skipped[parts[0]] += 1
        else:
            handler(parts)

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

    def _flaser(self, parts: list[str]) -> None:
        n = self.count(parts, 1, "num_readings")
        self.expect_fields(parts, n + 11, "num_readings", f"it declares {n} beams")
        values = self.floats(parts, 2, n + 9, _Names(n, _FLASER_TAIL), finite_from=n)
        self._add_scan(
            parts[0],
            values[:n],
            values[n + 3 : n + 6],
            values[n : n + 3],
            values[n + 6],
            lambda: flaser_angles(n),
        )

    def _robotlaser(self, parts: list[str]) -> None:
        n = self.count(parts, 8, "num_readings")
        n_rem = self.count(parts, 9 + n, "num_remissions")
        self.expect_fields(
            parts, n + n_rem + 24, "num_remissions", f"it declares {n} beams and {n_rem} remissions"
        )
        start, _, res, max_range_m, _ = self.floats(parts, 2, 7, _Names(0, _RL1_HEAD))
        if not max_range_m > 0:
            raise self.error(parts[0], "max_range", f"{_quote(parts[5])} is not a positive range")
        geometry = (float(start), float(res))
        if self.geometry is None:
            self.geometry = geometry
        elif geometry != self.geometry:  # the angles of the first line are used for every scan
            i = 0 if geometry[0] != self.geometry[0] else 1
            raise self.error(
                parts[0], ("start_angle", "angular_res")[i],
                f"beam geometry changed from {self.geometry[i]!r} (line {self.first[0]}) to {geometry[i]!r}",
            )  # fmt: skip
        ranges = self.floats(parts, 9, 9 + n, _Names(n, ()), finite_from=n)
        tail = self.floats(parts, n + n_rem + 10, n + n_rem + 22, _Names(0, _RL1_TAIL))
        if self.range_max_m is None:
            self.range_max_m = float(max_range_m)
        self._add_scan(parts[0], ranges, tail[3:6], tail[0:3], tail[11], lambda: start + np.arange(n) * res)

    def _add_scan(
        self,
        kind: str,
        ranges: np.ndarray,
        odom: np.ndarray,
        laser: np.ndarray,
        stamp: float,
        angles: Callable[[], np.ndarray],
    ) -> None:
        if self.first is None:
            with np.errstate(over="ignore", invalid="ignore"):  # huge values: checked just below
                offset, beam_angles = relative(odom, laser), angles()
            if not np.all(np.isfinite(offset)):
                field = "x" if kind == "FLASER" else "laser_x"
                raise self.error(kind, field, "laser and robot poses too far apart: their offset overflows")
            if not np.all(np.isfinite(beam_angles)):
                raise self.error(kind, "angular_res", "beam angles overflow")
            self.kind = kind
            self.first = (self.line_no, offset, beam_angles, bool(np.array_equal(odom, laser)))
        elif ranges.size != self.rows[0].size:
            raise self.error(
                kind,
                "num_readings",
                f"beam count changed from {self.rows[0].size} (line {self.first[0]}) to {ranges.size}",
            )
        self.rows.append(ranges)
        self.odometry.append(odom)
        self.stamps.append(float(stamp))

    def _odom(self, parts: list[str]) -> None:
        self.expect_fields(parts, 10, "ipc_hostname", "ODOM carries 9 values")
        self.odom_rows.append(self.floats(parts, 1, 8, _Names(0, _ODOM_NAMES))[[6, 0, 1, 2]])

    def _param(self, parts: list[str]) -> None:
        if len(parts) < 3:
            raise self.error("PARAM", "param_value", f"too few fields: found {len(parts)}")
        self.params[parts[1]] = " ".join(parts[2:-2] if len(parts) >= 5 else parts[2:3])
        self.param_lines[parts[1]] = self.line_no

    def param_float(self, name: str, default: float, positive: bool = False) -> float:
        """The PARAM ``name`` as a finite number (``positive``: > 0), ``default`` when absent;
        a bad value raises naming the PARAM's line."""
        if name not in self.params:
            return default
        text = self.params[name]
        try:
            value = float(text)
        except ValueError:
            value = None
        problem = (
            f"cannot parse {_quote(text)} as a number" if value is None
            else f"value {_quote(text)} is not finite" if not np.isfinite(value)
            else f"{_quote(text)} is not a positive range" if positive and not value > 0
            else None
        )  # fmt: skip
        if problem is not None:
            self.line_no = self.param_lines[name]
            raise self.error("PARAM", name, problem)
        return value

    def laser_offset(self) -> np.ndarray:
        _, offset, _, identical = self.first
        if self.kind == "ROBOTLASER1" or not identical:
            return offset
        return np.array(
            [
                self.param_float(f"robot_frontlaser_{key}", 0.0)
                for key in ("offset", "side_offset", "angular_offset")
            ]
        )

    def finish(self) -> LaserLog:
        if self.first is None:
            raise self.error("log", "FLASER|ROBOTLASER1", "no laser lines in the log")
        ranges = np.stack(self.rows)
        named = [name for name in RANGE_MAX_PARAMS if name in self.params]
        if self.range_max_m is None:
            self.range_max_m = (
                self.param_float(named[0], 0.0, positive=True) if named else infer_range_max_m(ranges)
            )
        odom = np.array(self.odom_rows).reshape(-1, 4)
        return LaserLog(
            stamps_s=np.array(self.stamps),
            ranges_m=ranges,
            angles_rad=self.first[2],
            odometry=np.stack(self.odometry),
            laser_offset=self.laser_offset(),
            range_max_m=self.range_max_m,
            odom_stamps_s=odom[:, 0],
            odom_poses=odom[:, 1:],
            params=dict(self.params),
            path=self.path,
            kind=self.kind,
            skipped=dict(self.skipped),
        )


_LASERS = ("FLASER", "ROBOTLASER1")


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
