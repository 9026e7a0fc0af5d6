"""Cut the head of a CARMEN log and its relations into a small test excerpt (tests/data/*_head.*).

    .venv/bin/python benchmarks/make_excerpt.py LOG RELATIONS N OUT_PREFIX

Writes ``OUT_PREFIX.clf.gz``: the log's lines unchanged from the first through its N-th laser line
(header comments, PARAM lines and the ODOM lines between the scans), gzipped with ``mtime=0`` so the
bytes are reproducible; and ``OUT_PREFIX.relations``: the relation lines, unchanged, whose ``t1``
and ``t2`` are both timestamps of scans in the excerpt. Then prints what the excerpt covers
(scans, seconds, metres driven, degrees turned). ``make_excerpt.py intel.clf intel.relations 1500
tests/data/intel_head`` rebuilds ``intel_head.*`` byte for byte.

    .venv/bin/python benchmarks/make_excerpt.py datasets/aces/aces.clf datasets/aces/aces.relations \\
        675 tests/data/aces_head
"""

from __future__ import annotations

import argparse
import gzip
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from robot_agent.sources import read_log  # noqa: E402

LASER_KINDS = (b"FLASER", b"ROBOTLASER1")
"""Laser lines the project reads; the first kind met is the log's (as in robot_agent.sources)."""
STAMP_TOL_S = 1e-3
"""A relation time this close to a scan's ipc timestamp is that scan (files differ in decimals)."""


def read_lines(path: Path) -> list[bytes]:
    """The log's lines as bytes, line endings kept (plain or gzip, told by the magic bytes)."""
    data = path.read_bytes()
    if data[:2] == b"\x1f\x8b":
        data = gzip.decompress(data)
    return data.splitlines(keepends=True)


def laser_lines(lines: list[bytes]) -> list[int]:
    """Indices of the laser lines of the log's laser kind."""
    kind = next((p[0] for p in (line.split() for line in lines) if p and p[0] in LASER_KINDS), None)
    return [i for i, line in enumerate(lines) if line.split()[:1] == [kind]]


def ipc_stamp(line: bytes) -> float:
    """A CARMEN message's ipc timestamp: third field from the end."""
    return float(line.split()[-3])


def cut(lines: list[bytes], n_scans: int) -> tuple[list[bytes], np.ndarray, np.ndarray]:
    """The lines through the N-th laser line, the excerpt's scan stamps and the later scans' stamps."""
    lasers = laser_lines(lines)
    if not 1 <= n_scans <= len(lasers):
        raise ValueError(f"N must be in [1, {len(lasers)}] (laser lines of the log), got {n_scans}")
    end = lasers[n_scans - 1] + 1
    stamps = np.array([ipc_stamp(lines[i]) for i in lasers])
    return lines[:end], stamps[:n_scans], stamps[n_scans:]


def is_scan_time(times_s: np.ndarray, stamps_s: np.ndarray, tol_s: float = STAMP_TOL_S) -> np.ndarray:
    """``(T,)`` bool: each time is within ``tol_s`` of one of the scan stamps ``(S,)`` (any order)."""
    ordered = np.sort(stamps_s)
    j = np.clip(np.searchsorted(ordered, times_s), 1, len(ordered) - 1) if len(ordered) > 1 else 0
    nearest = np.minimum(np.abs(ordered[j - 1] - times_s), np.abs(ordered[j] - times_s))
    return nearest <= tol_s


def relations_within(rel_lines: list[str], stamps_s: np.ndarray) -> list[str]:
    """The relation lines whose t1 and t2 are both scans of the excerpt ``stamps_s (S,)``.

    By scan, not by time span: Intel's ipc timestamps step back, so a later scan can fall
    inside the excerpt's span (its 1500-scan head has two).
    """
    rows = [line for line in rel_lines if line.split() and not line.split()[0].startswith("#")]
    times = np.array([[float(x) for x in line.split()[:2]] for line in rows]).reshape(-1, 2)
    keep = is_scan_time(times[:, 0], stamps_s) & is_scan_time(times[:, 1], stamps_s)
    return [line for line, k in zip(rows, keep, strict=True) if k]


def coverage(path: Path) -> dict:
    """What the written excerpt covers, read back by the project's reader."""
    log = read_log(path, progress=False)
    step = np.diff(log.odometry, axis=0)
    turn = np.abs((step[:, 2] + np.pi) % (2 * np.pi) - np.pi)
    return {
        "scans": len(log),
        "odom_lines": len(log.odom_stamps_s),
        "duration_s": log.duration_s,
        "driven_m": float(np.hypot(step[:, 0], step[:, 1]).sum()),
        "turned_deg": float(np.degrees(turn.sum())),
        "range_max_m": log.range_max_m,
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("log", type=Path, help="CARMEN log (.clf or .clf.gz)")
    ap.add_argument("relations", type=Path, help="its relations file")
    ap.add_argument("n", type=int, help="laser scans to keep")
    ap.add_argument("out_prefix", help="writes OUT_PREFIX.clf.gz and OUT_PREFIX.relations")
    args = ap.parse_args(argv)

    head, stamps, later = cut(read_lines(args.log), args.n)
    out_log = Path(f"{args.out_prefix}.clf.gz")
    out_log.parent.mkdir(parents=True, exist_ok=True)
    with gzip.GzipFile(out_log, "wb", compresslevel=9, mtime=0) as out:
        out.write(b"".join(head))
    rel = relations_within(args.relations.read_text().splitlines(keepends=True), stamps)
    Path(f"{args.out_prefix}.relations").write_text("".join(rel))

    c = coverage(out_log)
    print(
        f"{out_log}: lines 1-{len(head)} of {args.log.name}, {c['scans']} scans, {c['odom_lines']} ODOM "
        f"lines, {c['duration_s']:.1f} s, {c['driven_m']:.1f} m driven, {c['turned_deg']:.0f}° turned "
        f"(sum of |dtheta|), range max {c['range_max_m']:.2f} m; last scan at {stamps[-1]:.6f}"
    )
    inside = np.count_nonzero((later >= stamps.min()) & (later <= stamps.max()))
    print(
        f"{args.out_prefix}.relations: {len(rel)} relations between scans of the excerpt "
        f"({inside} later scans fall inside its time span)"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
