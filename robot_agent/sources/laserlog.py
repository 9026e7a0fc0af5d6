"""One laser's scans with odometry, as arrays: :class:`LaserLog` (what :func:`read_log` returns).

Beam geometry may change from scan to scan (CARMEN ``ROBOTLASER1`` lines carry their own start
angle, resolution and beam count). A log holds each distinct geometry once, in a table, and each
scan's index into it; ranges are padded with NaN to the longest scan. :meth:`LaserLog.scan`
slices one scan back to its own beams; nothing else should index ``ranges_m`` by scan.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field

import numpy as np

from robot_agent.sources.base import Scan
from robot_agent.sources.carmen_conventions import flaser_compatible, infer_range_max_m

_LAYOUTS = (  # field, axes, dtype; a digit is a fixed size, a letter a size shared by fields
    ("stamps_s", "S", float),
    ("ranges_m", "SB", float),
    ("angle_table_rad", "GB", float),
    ("geometry_beams", "G", np.int64),
    ("scan_geometry", "S", np.int64),
    ("odometry", "S3", float),
    ("laser_offset", "3", float),
    ("odom_stamps_s", "M", float),
    ("odom_poses", "M3", float),
)


@dataclass(frozen=True, eq=False)
class LaserLog:
    """One laser's scans with odometry; arrays are read-only, SI units. The log takes the arrays
    it is given (no copy: :meth:`from_arrays` copies the caller's) and makes them read-only.

    ``S`` scans, ``G`` distinct beam geometries, ``B`` beams of the longest scan, ``M`` ODOM lines:

    - ``stamps_s (S,)`` ipc time of each laser line, in file order;
    - ``ranges_m (S,B)`` readings; scan ``i`` has ``beam_counts[i]`` of them, NaN after;
    - ``angle_table_rad (G,B)`` beam angles in the laser frame of each geometry, row ``g`` holding
      ``geometry_beams[g]`` angles, NaN after; ``geometry_beams (G,)`` their counts;
    - ``scan_geometry (S,)`` each scan's row in the table (``beam_counts (S,)`` follows from it);
    - ``odometry (S,3)`` robot odometry pose at each scan, ``laser_offset (3,)`` the laser pose in
      the robot frame, ``range_max_m`` the range limit (a reading at or past it: no return);
    - ``odom_stamps_s (M,)``, ``odom_poses (M,3)`` the ODOM lines;
    - ``params`` every PARAM as text, ``kind`` the laser message read, ``skipped`` counts of the
      message types not read, ``warnings`` what the reader could not use and did instead.

    A log whose scans all share one geometry has ``G = 1``; :meth:`scan` gives scan ``i`` with its
    own ``ranges_m (n,)`` and ``angles_rad (n,)``, views of these arrays.
    """

    stamps_s: np.ndarray
    ranges_m: np.ndarray
    angle_table_rad: np.ndarray
    geometry_beams: np.ndarray
    scan_geometry: np.ndarray
    odometry: np.ndarray
    laser_offset: np.ndarray
    range_max_m: float
    odom_stamps_s: np.ndarray
    odom_poses: np.ndarray
    params: dict[str, str] = field(default_factory=dict)
    path: str = ""
    kind: str = "FLASER"
    skipped: dict[str, int] = field(default_factory=dict)
    warnings: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        dims: dict[str, int] = {}
        for name, layout, dtype in _LAYOUTS:
            # taken as given when already an array of its type (a log's ranges are most of its
            # memory: a copy doubled it), and made read-only below: the log owns it from now on
            array = np.array(getattr(self, name), dtype=dtype, copy=None)
            if not array.flags.writeable:  # another log's (dataclasses.replace): its padding is set
                array = array.copy()
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
            object.__setattr__(self, name, array)
        beams, index = self.geometry_beams, self.scan_geometry
        if beams.size and not (beams.min() >= 0 and beams.max() <= self.ranges_m.shape[1]):
            raise ValueError(f"geometry_beams must lie in [0, {self.ranges_m.shape[1]}], got {beams}")
        if index.size and not (index.min() >= 0 and index.max() < beams.size):
            raise ValueError(f"scan_geometry must index the {beams.size} geometries, got {index}")
        # the padding is NaN whatever the caller passed, so no stale value can pass for a beam
        beam_axis = np.arange(self.ranges_m.shape[1])
        self.angle_table_rad[beam_axis >= beams[:, None]] = np.nan
        self.ranges_m[beam_axis >= beams[index][:, None]] = np.nan
        for name, _, _ in _LAYOUTS:
            getattr(self, name).flags.writeable = False
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
        beam_counts=None,
    ) -> LaserLog:
        """Build a log from per-scan arrays (ValueError naming the argument if a shape is wrong).

        ``ranges_m (S,B)``; ``angles_rad`` either ``(B,)``, the same for every scan, or ``(S,B)``,
        one row per scan; ``beam_counts (S,)`` how many leading beams of each row are real
        (default: all ``B``; the rest is ignored). ``range_max_m=None`` applies the FLASER rule of
        :func:`infer_range_max_m`; ``kind`` is FLASER when every geometry is what FLASER lines read
        as (:func:`flaser_compatible`, ``params`` may name the field of view), else ROBOTLASER1.
        """
        ranges_m = np.array(ranges_m, dtype=float)  # copies: the log takes what it is given
        if ranges_m.ndim != 2:
            raise ValueError(f"ranges_m has shape {ranges_m.shape}, expected (S, B)")
        s, b = ranges_m.shape
        counts = np.full(s, b, np.int64) if beam_counts is None else np.asarray(beam_counts, np.int64)
        if counts.shape != (s,) or (s and not (counts.min() >= 0 and counts.max() <= b)):
            raise ValueError(
                f"beam_counts has shape {counts.shape}, expected (S,) with S={s}, values in [0, {b}]"
            )
        table, beams, index = geometry_table(angles_rad, counts, b)
        return cls(
            stamps_s=np.array(stamps_s, dtype=float),
            ranges_m=ranges_m,
            angle_table_rad=table,
            geometry_beams=beams,
            scan_geometry=index,
            odometry=np.array(odometry, dtype=float),
            laser_offset=np.array(laser_offset, dtype=float),
            range_max_m=infer_range_max_m(_real(ranges_m, counts)) if range_max_m is None else range_max_m,
            odom_stamps_s=np.zeros(0) if odom_stamps_s is None else np.array(odom_stamps_s, dtype=float),
            odom_poses=np.zeros((0, 3)) if odom_poses is None else np.array(odom_poses, dtype=float),
            params=dict(params or {}),
            kind="FLASER" if flaser_compatible(table, beams, params or {}) else "ROBOTLASER1",
        )

    def __len__(self) -> int:
        return self.stamps_s.shape[0]

    @property
    def beam_counts(self) -> np.ndarray:
        """``(S,)`` beams of each scan."""
        return self.geometry_beams[self.scan_geometry]

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

    def scan(self, i: int) -> Scan:
        """Scan ``i`` (negative counts from the end): its ``ranges_m (n,)`` and ``angles_rad (n,)``
        are read-only views cut to its ``n`` beams."""
        i = range(len(self))[i]  # IndexError past the ends
        g = self.scan_geometry[i]
        n = self.geometry_beams[g]
        return Scan(
            stamp_s=float(self.stamps_s[i]),
            ranges_m=self.ranges_m[i, :n],
            angles_rad=self.angle_table_rad[g, :n],
            odometry=self.odometry[i],
            laser_offset=self.laser_offset,
            range_max_m=self.range_max_m,
        )

    def scans(self) -> Iterator[Scan]:
        """The scans in file order (:meth:`scan` of each)."""
        for i in range(len(self)):
            yield self.scan(i)


def geometry_table(
    angles_rad, beam_counts: np.ndarray, width: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The distinct geometries of scans with ``beam_counts (S,)`` and ``angles_rad`` ``(B,)`` (all
    scans) or ``(S,B)`` (one row each), ``B = width``: ``table (G,B)`` NaN-padded, ``beams (G,)``,
    ``index (S,)``, in order of first use."""
    angles = np.asarray(angles_rad, dtype=float)
    s = beam_counts.size
    if angles.shape not in ((width,), (s, width)):
        raise ValueError(
            f"angles_rad has shape {angles.shape}, expected (B,) or (S, B) with S={s}, B={width}"
        )
    rows = np.broadcast_to(angles, (s, width))
    keys = np.where(np.arange(width) < beam_counts[:, None], rows, 0.0)  # padding never tells rows apart
    keys = np.column_stack([beam_counts, keys])
    if s == 0:
        return np.zeros((0, width)), np.zeros(0, np.int64), np.zeros(0, np.int64)
    _, first, inverse = np.unique(keys, axis=0, return_index=True, return_inverse=True)
    order = np.argsort(first)  # np.unique sorts; first use is the friendlier order
    rank = np.empty_like(order)
    rank[order] = np.arange(order.size)
    picked = first[order]
    return rows[picked], beam_counts[picked], rank[inverse.reshape(-1)]


def _real(ranges_m: np.ndarray, beam_counts: np.ndarray) -> np.ndarray:
    """The readings that are beams, flat (padding dropped)."""
    return ranges_m[np.arange(ranges_m.shape[1]) < beam_counts[:, None]]
