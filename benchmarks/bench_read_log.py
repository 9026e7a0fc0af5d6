"""CARMEN log reading speed: :func:`read_log` on the development logs, best of ``--repeats``.

    .venv/bin/python benchmarks/bench_read_log.py [logs ...] [--repeats 3]

The timing ``tests/sources/test_carmen.py`` used to assert (a wall-clock bound is no test: it
fails on a busy machine and passes a slow reader on a fast one). Prints a table and writes
``benchmarks/results/bench_read_log.json``. The reader's docstring once gave about 0.5 s for the
full Intel log (40,557 lines, 13,631 FLASER, 16 MB).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from _results import save_results  # noqa: E402

from robot_agent.sources import read_log  # noqa: E402

DATASETS = ROOT.parent / "shared" / "datasets"
"""The development logs, next to the checkout (``/work/shared/datasets``)."""


def bench_log(path: Path, repeats: int) -> dict:
    best = np.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        log = read_log(path, progress=False)
        best = min(best, time.perf_counter() - t0)
    counts = np.unique(log.beam_counts)
    return {
        "log": path.name,
        "bytes": path.stat().st_size,
        "kind": log.kind,
        "scans": len(log),
        "odom_lines": len(log.odom_stamps_s),
        "beams": "/".join(map(str, counts.tolist())),
        "geometries": len(log.geometry_beams),
        "range_max_m": log.range_max_m,
        "read_s": best,
        "scans_per_s": len(log) / best,
        "mb_per_s": path.stat().st_size / best / 1e6,
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("logs", nargs="*", type=Path, help="CARMEN logs (default: every *.clf under --datasets)")
    ap.add_argument("--datasets", type=Path, default=DATASETS)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "bench_read_log.json"))
    args = ap.parse_args(argv)
    logs = args.logs or sorted(args.datasets.glob("*/*.clf"))
    if not logs:
        print(f"no logs given and none under {args.datasets}")
        return 1
    rows = [bench_log(path, args.repeats) for path in logs]
    cols = ["log", "kind", "scans", "beams", "geometries", "range_max_m", "read_s", "scans_per_s", "mb_per_s"]
    print("  ".join(f"{c:>12}" for c in cols))
    for r in rows:
        print("  ".join(f"{r[c]:>12.3f}" if isinstance(r[c], float) else f"{r[c]!s:>12}" for c in cols))
    save_results(args.out, "bench_read_log", {"repeats": args.repeats, "rows": rows})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
