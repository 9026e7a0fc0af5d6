"""What every benchmark writes: its figures plus where they were measured (one JSON file each).

The scripts run as ``python benchmarks/bench_x.py``, so this module is importable as ``_results``.
"""

from __future__ import annotations

import json
import os
import platform
import subprocess
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def commit() -> str:
    """``git describe --always --dirty`` of the checkout ("unknown" outside git)."""
    try:
        run = subprocess.run(["git", "-C", str(ROOT), "describe", "--always", "--dirty"], capture_output=True)
    except OSError:
        return "unknown"
    return run.stdout.decode().strip() or "unknown"


def save_results(path: str | Path, benchmark: str, payload: dict) -> Path:
    """Write ``payload`` with the benchmark's name, commit, Python, numpy, machine and CPU count."""
    path = Path(path)
    doc = {
        "benchmark": benchmark, "commit": commit(), "python": platform.python_version(),
        "numpy": np.__version__, "machine": platform.machine(), "cpus": os.cpu_count(), **payload,
    }  # fmt: skip
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(doc, indent=1, default=float))
    print(f"wrote {path}")
    return path
