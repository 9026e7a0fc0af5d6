"""Every development log, every seed: relations error, speed and memory beside the published figures.

    .venv/bin/python benchmarks/bench_logs.py DIR... [--seeds 0 1 2] [--particles 30] [--jobs 1]
        [--set SECTION.KEY=VALUE ...] [--keep OUTDIR] [--json PATH] [--limit N] [--no-live]

Each DIR holds a CARMEN log (``*.clf`` or ``*.clf.gz``) with its Kümmerle relations beside it
(``<stem>.relations``); a DIR may also be the log file itself. A log without relations is reported
and skipped. Every log × seed runs ``fleet-slam replay`` as its own process on one core
(``*_NUM_THREADS=1``), at most ``--jobs`` at once, so wall time and peak memory are per run; then
(unless ``--no-live``) ``fleet-slam replay --live 10`` as an agent runs, for what the robot would
publish while it runs: the worst snapshot, the online back end at the end, its CPU share.

One row per log, in the shape of Table II of Hess et al. (ICRA 2016): translational and rotational
error, mean over seeds of each run's mean ± mean over seeds of each run's std, and the worst seed's
mean; the filter alone (before the pose-graph back end); wall time (mean), real-time factor (the
worst seed's) and peak memory (the largest); then the published figures of other systems.
Writes ``benchmarks/results/bench_logs.json``; exits 1 if any run failed.

Example (the development set, see /work/shared/datasets/README.md):

    .venv/bin/python benchmarks/bench_logs.py datasets/intel datasets/aces datasets/mit-csail --jobs 2
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor, as_completed
from contextlib import nullcontext
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).resolve().parent))  # _results, also when imported by a test

from _results import save_results  # noqa: E402

LOG_SUFFIXES = (".clf.gz", ".clf")
ONE_CORE_ENV = {"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
STDERR_TAIL_LINES = 20
"""Lines of a failed run's stderr printed and kept in the JSON."""

# Translational error [m] mean ± std on the Kümmerle relations: scan matching, RBPF (GMapping,
# 50 particles) and graph mapping from Kümmerle et al., "On measuring the accuracy of SLAM
# algorithms", Autonomous Robots 27(4), 2009; Cartographer (with its rotational error [deg] and
# wall time [s]) from Hess et al., "Real-Time Loop Closure in 2D LIDAR SLAM", ICRA 2016, Table II
# and §VI. Copied from /work/shared/datasets/README.md. Keyed by the log's stem.
PUBLISHED: dict[str, dict[str, list[float]]] = {
    "intel": {
        "scan_matching_m": [0.220, 0.296],
        "gmapping_m": [0.070, 0.083],
        "graph_mapping_m": [0.031, 0.026],
        "cartographer_m": [0.0229, 0.0239],
        "cartographer_deg": [0.453, 1.335],
        "cartographer_wall_s": [179.0],
    },
    "aces": {
        "scan_matching_m": [0.173, 0.614],
        "gmapping_m": [0.060, 0.049],
        "graph_mapping_m": [0.044, 0.044],
        "cartographer_m": [0.0375, 0.0426],
        "cartographer_deg": [0.373, 0.469],
        "cartographer_wall_s": [41.0],
    },
    "mit-csail": {
        "scan_matching_m": [0.106, 0.325],
        "gmapping_m": [0.049, 0.049],
        "graph_mapping_m": [0.004, 0.009],
        "cartographer_m": [0.0319, 0.0363],
        "cartographer_deg": [0.369, 0.365],
    },
}
_PUBLISHED_DECIMALS = {"cartographer_m": 4}  # as printed in the source; the others 3


class BenchInputError(ValueError):
    """A path or option the benchmark cannot use; the message names it."""


@dataclass(frozen=True)
class LogEntry:
    """One log to run: ``name`` is its stem (``intel`` for ``intel.clf.gz``)."""

    name: str
    log: Path
    relations: Path


# --- discovery --------------------------------------------------------------------------------


def log_stem(path: Path) -> str | None:
    """``intel`` for ``intel.clf`` or ``intel.clf.gz``; None for any other file name."""
    for suffix in LOG_SUFFIXES:
        if path.name.endswith(suffix) and len(path.name) > len(suffix):
            return path.name[: -len(suffix)]
    return None


def discover(paths: list[str | Path]) -> tuple[list[LogEntry], list[str]]:
    """The logs with relations under ``paths`` (directories or log files), and one message per
    log or directory skipped. Raises BenchInputError for a missing path or two logs of one stem."""
    entries: dict[str, LogEntry] = {}
    skipped: list[str] = []
    for raw in paths:
        path = Path(raw)
        if not path.exists():
            raise BenchInputError(f"no such file or directory: {path}")
        if path.is_dir():
            logs = sorted(p for p in path.iterdir() if p.is_file() and log_stem(p))
            if not logs:
                skipped.append(f"{path}: no *.clf or *.clf.gz log")
        elif log_stem(path):
            logs = [path]
        else:
            raise BenchInputError(f"{path}: not a directory nor a *.clf / *.clf.gz log")
        for log in logs:
            stem = log_stem(log)
            relations = log.with_name(f"{stem}.relations")
            if not relations.is_file():
                skipped.append(f"{log}: no relations file {relations.name} beside it")
                continue
            other = entries.get(stem)
            if other is not None and other.log.resolve() != log.resolve():
                raise BenchInputError(f"two logs named {stem}: {other.log} and {log}")
            entries[stem] = LogEntry(stem, log, relations)
    return list(entries.values()), skipped


# --- one run ----------------------------------------------------------------------------------


# what a --live run adds to the plain run's metrics: what the robot publishes while it runs
LIVE_KEYS = ("live", "live_worst_trans_m", "relations_online", "online_backend", "online_backend_s",
             "online_backend_share")  # fmt: skip


def replay_command(
    entry: LogEntry, seed: int, out_dir: Path, args: argparse.Namespace, live: bool = False
) -> list[str]:
    """``fleet-slam replay`` for one log and seed, with this interpreter; ``live``: with the
    online back end beside the filter as an agent runs it (``--live 10``: the trajectory it
    would publish at every tenth), which the filter continues from."""
    cmd = [sys.executable, "-m", "fleet_slam.cli", "replay", str(entry.log.resolve())]
    cmd += ["--relations", str(entry.relations.resolve()), "--seed", str(seed)]
    cmd += ["--particles", str(args.particles)]
    cmd += ["--out", str(out_dir.resolve())] + (["--live", "10"] if live else [])
    for override in args.set:
        cmd += ["--set", override]
    if args.limit is not None:
        cmd += ["--limit", str(args.limit)]
    return cmd


def child_env() -> dict[str, str]:
    """One core per run, and this checkout's code first on the path (a worktree beats the venv; the
    run starts in this checkout too: ``python -m`` puts the working directory before the path)."""
    env = dict(os.environ) | ONE_CORE_ENV
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(ROOT), env.get("PYTHONPATH", "")) if p)
    return env


def run_one(entry: LogEntry, seed: int, args: argparse.Namespace) -> dict:
    """Replay one log with one seed as ``fleet-slam replay`` does (its metrics.json, or the
    failure), then, unless ``--no-live``, again as an agent runs (``--live``): what the robot
    would publish while it runs joins the metrics (:data:`LIVE_KEYS`; that run's offline figure
    as ``relations_live_run``). Two runs: a filter that continues from the online corrections
    is not the filter that ``replay`` runs."""
    run = _run_once(entry, seed, args, live=False)
    if "metrics" not in run or not getattr(args, "live", True):
        return run
    live = _run_once(entry, seed, args, live=True)
    if "metrics" not in live:
        return dict(live, seed=seed)  # a failed live run fails the pair
    m = live["metrics"]
    run["metrics"].update({k: m[k] for k in LIVE_KEYS if k in m})
    if "relations" in m:
        run["metrics"]["relations_live_run"] = m["relations"]
    run["process_wall_s"] += live["process_wall_s"]
    return run


def _run_once(entry: LogEntry, seed: int, args: argparse.Namespace, live: bool) -> dict:
    kept = Path(args.keep) / entry.name / f"seed{seed}{'-live' if live else ''}" if args.keep else None
    with nullcontext(kept) if kept else tempfile.TemporaryDirectory(prefix="bench_logs_") as out:
        out_dir = Path(out)
        (out_dir / "metrics.json").unlink(missing_ok=True)  # a kept directory's earlier run
        t0 = time.perf_counter()
        proc = subprocess.run(
            replay_command(entry, seed, out_dir, args, live),
            env=child_env(),
            cwd=ROOT,
            capture_output=True,
            text=True,
        )
        run = {"log": entry.name, "seed": seed, "returncode": proc.returncode}
        run["process_wall_s"] = time.perf_counter() - t0  # with loading the log and the pictures
        metrics_path = out_dir / "metrics.json"
        if proc.returncode == 0 and metrics_path.is_file():
            run["metrics"] = json.loads(metrics_path.read_text())
        else:
            run["stderr_tail"] = proc.stderr.splitlines()[-STDERR_TAIL_LINES:]
        if args.keep:
            run["out_dir"] = str(out_dir)
    return run


def run_all(entries: list[LogEntry], args: argparse.Namespace) -> list[dict]:
    """Every log × seed, at most ``args.jobs`` at once; a progress line as each finishes."""
    tasks = [(e, s) for e in entries for s in args.seeds]
    runs = []
    with ThreadPoolExecutor(max_workers=args.jobs) as pool:
        futures = [pool.submit(run_one, e, s, args) for e, s in tasks]
        for done, future in enumerate(as_completed(futures), 1):
            run = future.result()
            print(f"[{done}/{len(tasks)}] {progress_line(run)}", flush=True)
            runs.append(run)
    order = {(e.name, s): i for i, (e, s) in enumerate(tasks)}
    return sorted(runs, key=lambda r: order[r["log"], r["seed"]])


def progress_line(run: dict) -> str:
    head = f"{run['log']} seed {run['seed']}"
    if "metrics" not in run:
        return f"{head}: FAILED (exit {run['returncode']}) after {run['process_wall_s']:.1f} s"
    m = run["metrics"]
    trans = f"trans {m['relations']['trans_mean_m']:.3f} m" if "relations" in m else "no relations"
    return f"{head}: {trans}, wall {m['wall_time_s']:.1f} s"


# --- aggregation ------------------------------------------------------------------------------


def _mean(values: list[float]) -> float | None:
    return sum(values) / len(values) if values else None


def aggregate(runs: list[dict]) -> dict:
    """One log's figures over its seeds (failed runs left out, counted in ``failed``).

    Errors: mean over seeds of each run's mean, mean over seeds of each run's std, and the worst
    (largest) seed mean. Wall: mean; real-time factor: the smallest; peak memory: the largest.
    """
    ok = [r["metrics"] for r in runs if "metrics" in r]
    rel = [m["relations"] for m in ok if "relations" in m]
    flt = [m["relations_filter_only"]["trans_mean_m"] for m in ok if "relations_filter_only" in m]
    rtf = [m["real_time_factor"] for m in ok if m.get("real_time_factor") is not None]
    out = {"runs": len(ok), "failed": len(runs) - len(ok), "n_relations": rel[0]["n"] if rel else None}
    for kind, unit in (("trans", "m"), ("rot", "deg")):
        means = [r[f"{kind}_mean_{unit}"] for r in rel]
        out[f"{kind}_mean_{unit}"] = _mean(means)
        out[f"{kind}_std_{unit}"] = _mean([r[f"{kind}_std_{unit}"] for r in rel])
        out[f"{kind}_worst_mean_{unit}"] = max(means, default=None)
    out["filter_only_trans_mean_m"] = _mean(flt)
    live = [m["live_worst_trans_m"] for m in ok if m.get("live_worst_trans_m") is not None]
    out["live_worst_trans_m"] = max(live, default=None)  # the worst snapshot of any seed
    # the online back end (what an agent publishes): its path at the end, the worst snapshot
    # against it and it against the offline back end's, each the worst seed's ratio
    online = [m for m in ok if "relations_online" in m and "relations" in m]
    ends = [m["relations_online"]["trans_mean_m"] for m in online]
    out["online_end_trans_mean_m"] = _mean(ends)
    out["live_over_end_worst"] = max(
        (
            m["live_worst_trans_m"] / e
            for m, e in zip(online, ends, strict=True)
            if m.get("live_worst_trans_m")
        ),
        default=None,
    )
    out["online_over_offline_worst"] = max(
        (e / m["relations"]["trans_mean_m"] for m, e in zip(online, ends, strict=True)), default=None
    )
    out["online_backend_share_max"] = max(
        (m["online_backend_share"] for m in online if m.get("online_backend_share") is not None), default=None
    )
    out["wall_time_s"] = _mean([m["wall_time_s"] for m in ok])
    out["real_time_factor_min"] = min(rtf, default=None)
    cpu = [m["real_time_factor_cpu"] for m in ok if m.get("real_time_factor_cpu") is not None]
    out["real_time_factor_cpu_min"] = min(cpu, default=None)
    out["peak_rss_mb_max"] = max((m["peak_rss_mb"] for m in ok), default=None)
    out["backend_s"] = _mean([m["backend_s"] for m in ok if m.get("backend_s") is not None])
    return out


# --- report -----------------------------------------------------------------------------------


def _num(value: float | None, fmt: str = ".3f") -> str:
    return "—" if value is None else format(value, fmt)


def _percent(share: float | None) -> float | None:
    return None if share is None else 100 * share


def _pm(mean: float | None, std: float | None, decimals: int = 3) -> str:
    return "—" if mean is None else f"{mean:.{decimals}f} ± {std:.{decimals}f}"


def published_cells(name: str) -> list[str]:
    """GMapping, graph mapping and Cartographer cells for the log ``name`` ("—" if unknown)."""
    pub = PUBLISHED.get(name, {})
    cells = []
    for key in ("gmapping_m", "graph_mapping_m", "cartographer_m"):
        cell = _pm(*pub[key], _PUBLISHED_DECIMALS.get(key, 3)) if key in pub else "—"
        if key == "cartographer_m" and "cartographer_deg" in pub:
            cell += f"\n{_pm(*pub['cartographer_deg'])}°"
        cells.append(cell)
    return cells


def print_table(rows: list[tuple[str, dict]], title: str) -> None:
    from rich.console import Console
    from rich.table import Table

    console = Console()
    if not console.is_terminal:  # a log file or a pipe: room for every column, no folding
        console.width = 220
    table = Table(title=title)
    for header in (
        "log", "seeds", "relations", "trans. error m\nmean ± std", "worst\nseed m",
        "rot. error °\nmean ± std", "worst\nseed °", "filter\nalone m", "worst live\nsnapshot m",
        "online at\nend m", "live ÷ end\n(worst)", "online ÷\noffline", "online\nCPU %", "wall s\n(mean)",
        "× real time\n(worst)", "× on CPU\n(worst)", "peak MB\n(max)", "GMapping m\n(50 particles)",
        "graph\nmapping m", "Cartographer\nm, °",
    ):  # fmt: skip
        table.add_column(header, justify="left" if header == "log" else "right")
    for name, a in rows:
        seeds = f"{a['runs']}" + (f" ({a['failed']} failed)" if a["failed"] else "")
        table.add_row(
            name, seeds, _num(a["n_relations"], "d"),
            _pm(a["trans_mean_m"], a["trans_std_m"]), _num(a["trans_worst_mean_m"]),
            _pm(a["rot_mean_deg"], a["rot_std_deg"], 2), _num(a["rot_worst_mean_deg"], ".2f"),
            _num(a["filter_only_trans_mean_m"]), _num(a["live_worst_trans_m"]),
            _num(a.get("online_end_trans_mean_m")), _num(a.get("live_over_end_worst"), ".2f"),
            _num(a.get("online_over_offline_worst"), ".3f"),
            _num(_percent(a.get("online_backend_share_max")), ".1f"),
            _num(a["wall_time_s"], ".1f"),
            _num(a["real_time_factor_min"], ".1f"), _num(a.get("real_time_factor_cpu_min"), ".1f"),
            _num(a["peak_rss_mb_max"], ".0f"),
            *published_cells(name),
        )  # fmt: skip
    console.print(table)


def run_line(run: dict, name_width: int = 0) -> str:
    """One line per run: every figure of its metrics.json that the table folds away."""
    head = f"{run['log']:>{name_width}} seed {run['seed']}:"
    if "metrics" not in run:
        return f"{head} FAILED (exit {run['returncode']})"
    m = run["metrics"]
    parts = [f"{m['scans']} scans"]
    if "relations" in m:
        r = m["relations"]
        parts.append(
            f"trans {r['trans_mean_m']:.3f} ± {r['trans_std_m']:.3f} m (max {r['trans_max_m']:.2f}), "
            f"rot {r['rot_mean_deg']:.2f} ± {r['rot_std_deg']:.2f}° (n={r['n']})"
        )
    if "relations_filter_only" in m:
        f = m["relations_filter_only"]
        parts.append(f"filter alone {f['trans_mean_m']:.3f} ± {f['trans_std_m']:.3f} m")
    if m.get("live_worst_trans_m") is not None:
        parts.append(f"worst live snapshot {m['live_worst_trans_m']:.3f} m")
    if "relations_online" in m:
        parts.append(
            f"online back end at the end {m['relations_online']['trans_mean_m']:.3f} m "
            f"({m['online_backend_s']:.1f} s of updates)"
        )
    parts.append(f"wall {m['wall_time_s']:.1f} s ({m['real_time_factor']:.1f}× real time)")
    if m.get("real_time_factor_cpu") is not None:
        parts.append(f"CPU {m['cpu_time_s']:.1f} s ({m['real_time_factor_cpu']:.1f}× on CPU time)")
    if m.get("backend_s") is not None:
        parts.append(f"back end {m['backend_s']:.1f} s")
    parts.append(f"peak {m['peak_rss_mb']:.0f} MB")
    return f"{head} " + ", ".join(parts)


# --- command line -----------------------------------------------------------------------------


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(
        prog="bench_logs.py", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("paths", nargs="*", metavar="DIR", help="a log's directory, or the log file itself")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--particles", type=int, default=30)
    ap.add_argument("--jobs", type=int, default=1, help="runs at once (each on one core)")
    ap.add_argument(
        "--set", nargs="+", action="extend", default=[], metavar="SECTION.KEY=VALUE", help="SLAM override"
    )
    ap.add_argument("--keep", default=None, metavar="OUTDIR", help="keep each run as OUTDIR/<log>/seed<K>/")
    ap.add_argument("--json", default=str(ROOT / "benchmarks" / "results" / "bench_logs.json"))
    ap.add_argument("--limit", type=int, default=None, help="only the first N scans of every log")
    ap.add_argument(
        "--no-live", dest="live", action="store_false", help="without the second, agent-like run (--live)"
    )
    args = ap.parse_args(argv)
    bad = [s for s in args.set if "=" not in s]
    if bad:  # --set takes several values, so a DIR after it lands here
        ap.error(f"--set needs SECTION.KEY=VALUE, got {bad[0]!r} (put DIRs before --set)")
    if not args.paths:
        ap.error(
            "give at least one DIR holding a log (*.clf or *.clf.gz) and its <stem>.relations, e.g.\n"
            "  bench_logs.py /path/to/datasets/intel /path/to/datasets/aces /path/to/datasets/mit-csail"
        )
    if args.jobs < 1:
        ap.error(f"--jobs must be at least 1, got {args.jobs}")
    if len(set(args.seeds)) != len(args.seeds):
        ap.error(f"--seeds repeats a seed: {args.seeds}")
    return args


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    try:
        entries, skipped = discover(args.paths)
        from robot_agent.slam.config import command_line_config

        command_line_config(args.set, args.particles)  # a bad override fails here, not in every run
    except ValueError as exc:
        print(f"bench_logs.py: error: {exc}", file=sys.stderr)
        return 2
    for message in skipped:
        print(f"skipped {message}", file=sys.stderr)
    if not entries:
        print("bench_logs.py: no log with relations to run", file=sys.stderr)
        return 1
    print(f"{len(entries)} logs × {len(args.seeds)} seeds, {args.particles} particles, {args.jobs} at once")
    runs = run_all(entries, args)

    rows = [(e.name, aggregate([r for r in runs if r["log"] == e.name])) for e in entries]
    limit = f", first {args.limit} scans (published: whole logs)" if args.limit else ""
    overrides = f", {' '.join(args.set)}" if args.set else ""
    print_table(rows, f"{args.particles} particles, seeds {args.seeds}{overrides}{limit}")
    width = max(len(e.name) for e in entries)
    for run in runs:
        print(run_line(run, width))
    failed = [r for r in runs if "metrics" not in r]
    for run in failed:
        print(f"\n{run['log']} seed {run['seed']} failed (exit {run['returncode']}):", file=sys.stderr)
        print("\n".join(run["stderr_tail"]), file=sys.stderr)

    settings = {"seeds": args.seeds, "particles": args.particles, "overrides": args.set, "limit": args.limit}
    logs = [
        {"name": e.name, "log": str(e.log), "relations": str(e.relations), "aggregate": agg,
         "published": PUBLISHED.get(e.name), "runs": [r for r in runs if r["log"] == e.name]}
        for e, (_, agg) in zip(entries, rows, strict=True)
    ]  # fmt: skip
    payload = {"settings": settings | {"jobs": args.jobs}, "logs": logs, "skipped": skipped}
    save_results(args.json, "bench_logs", payload | {"published": PUBLISHED})
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
