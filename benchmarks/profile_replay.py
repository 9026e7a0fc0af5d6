"""Where `fleet-slam replay` spends its time, per log: py-spy samples the whole run (filter, back
end, the map rebuilt along the corrected path), then the functions are ranked by self time and by
inclusive time (the project's own). Issue 22 asks for these tables before and after each speed
change.

    .venv/bin/python benchmarks/profile_replay.py ../shared/datasets/intel ../shared/datasets/aces \\
        ../shared/datasets/mit-csail --limit 5000 --json benchmarks/results/profile_replay.json

A log is a directory holding ``<name>.clf`` (or the file itself). py-spy must be installed
(``pip install py-spy``); it samples the replay's process 50 times a second (``--rate``).
"""

from __future__ import annotations

import argparse
import collections
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

from _results import save_results


def log_path(p: str) -> Path:
    path = Path(p)
    if path.is_dir():
        found = sorted(path.glob("*.clf")) + sorted(path.glob("*.clf.gz"))
        if not found:
            raise SystemExit(f"{path}: no .clf in it")
        return found[0]
    return path


def frame_name(frame: str) -> str:
    m = re.match(r"(.*) \((.*):(\d+)\)", frame)
    if not m:
        return frame
    fn, file, _ = m.groups()
    file = file.split("site-packages/")[-1]
    for root in ("robot_agent/", "shared/", "map_server/", "fleet_slam/"):
        if root in file:
            file = root + file.split(root, 1)[1]
    return f"{fn} ({file})"


def rank(raw: Path, top: int) -> dict:
    """Self and inclusive shares from py-spy's collapsed stacks (``a;b;c count`` lines)."""
    own, incl = collections.Counter(), collections.Counter()
    total = 0
    for line in raw.read_text().splitlines():
        stack, _, n = line.rpartition(" ")
        if not stack:
            continue
        n = int(n)
        total += n
        names = [frame_name(f) for f in stack.split(";")]
        own[names[-1]] += n
        for name in set(names):
            incl[name] += n
    project = [(k, v) for k, v in incl.most_common() if any(r in k for r in ("robot_agent/", "shared/"))]
    return {
        "samples": total,
        "self": [(k, v / total) for k, v in own.most_common(top)],
        "inclusive": [(k, v / total) for k, v in project[:top]],
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("logs", nargs="+")
    ap.add_argument("--limit", type=int, default=None, help="only the first N scans of each log")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--rate", type=int, default=50, help="samples per second")
    ap.add_argument("--top", type=int, default=15)
    ap.add_argument("--json", default=None, help="write the tables here")
    args = ap.parse_args()
    spy = shutil.which("py-spy") or str(Path(sys.executable).with_name("py-spy"))
    if not Path(spy).exists():
        raise SystemExit("py-spy is not installed: pip install py-spy")
    out = {}
    with tempfile.TemporaryDirectory() as tmp:
        for p in args.logs:
            path = log_path(p)
            raw = Path(tmp) / f"{path.stem}.txt"
            replay = [sys.executable, "-m", "fleet_slam.cli", "replay", str(path), "--seed", str(args.seed)]
            replay += ["--out", str(Path(tmp) / path.stem)]
            cmd = [spy, "record", "-r", str(args.rate), "-f", "raw", "-o", str(raw), "--", *replay]
            if args.limit:
                cmd += ["--limit", str(args.limit)]
            subprocess.run(cmd, check=True, capture_output=True)
            table = rank(raw, args.top)
            out[path.stem] = table
            print(f"\n{path.stem}: {table['samples']} samples ({table['samples'] / args.rate:.0f} s)")
            print("  self time                                             | inclusive (project)")
            for (a, sa), (b, sb) in zip(table["self"], table["inclusive"], strict=False):
                print(f"  {100 * sa:5.1f} %  {a[:46]:46s} | {100 * sb:5.1f} %  {b[:60]}")
    if args.json:
        save_results(args.json, "profile_replay", {"limit": args.limit, "seed": args.seed, "logs": out})
    return 0


if __name__ == "__main__":
    sys.exit(main())
