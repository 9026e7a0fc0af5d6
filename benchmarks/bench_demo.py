"""The fleet demo over several seeds (simulated worlds) or over real logs cut into pieces: alignment
verdicts, transform errors, fused-map quality, relations error across pieces.

    .venv/bin/python benchmarks/bench_demo.py [--seeds 0 1 ... 9] [--unknown-starts]
        [--robots 3] [--world office] [--duration 175] [--out out/bench_demo]
    .venv/bin/python benchmarks/bench_demo.py --logs DIR... [--splits 2 3] [--seeds 0]
        [--server-set SECTION.KEY=VALUE ...]

Each seed is one full `fleet-slam demo` (router, server, agents as processes on loopback, about
3 minutes at the default duration). Prints one row per seed — every robot's status and transform
error (and, in brackets, with fitted map frames: the server's error alone), fused precision and
completeness, wrong merges — and writes benchmarks/results/bench_demo.json.
A wrong merge is a merged robot whose transform is off by more than 0.3 m or 3° (fleet_slam/report.py).

``--logs``: each DIR holds a CARMEN log with its reference relations (``<stem>.relations``, as
bench_logs.py takes them); the log is cut into each of ``--splits`` consecutive pieces, one agent
each, no priors, replayed as fast as the agents go (``fleet-slam demo --log … --split K``). One row
per log × split × seed: pieces placed, wrong merges (a pair of pieces whose relations across them
are off by more than 0.3 m or 3°, median), the relations error over the merged pieces and across
pieces, and when each piece was first merged (s after the agents started).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from _results import save_results  # noqa: E402
from bench_logs import discover  # noqa: E402

from fleet_slam.demo import DemoConfig, run_demo  # noqa: E402


def row(seed: int, m: dict) -> str:
    robots = []
    for name, r in m["robots"].items():
        err = r.get("transform_error_m")
        robots.append(
            f"{name}:{r['status'][:3]}"
            + ("" if err is None else f" {err:.3f}m/{r['transform_error_deg']:.2f}°")
            + ("" if "transform_error_fit_m" not in r else f" (fit {r['transform_error_fit_m']:.3f}m)")
            + ("" if r.get("time_to_first_merge_s") is None else f" @{r['time_to_first_merge_s']:.0f}s")
        )
    nan = float("nan")
    quality = f"P {m.get('fused_precision', nan):.3f}  C {m.get('fused_completeness', nan):.3f}"
    if "fused_completeness_fit" in m:
        quality += f" (fit P {m['fused_precision_fit']:.3f} C {m['fused_completeness_fit']:.3f})"
    return f"{seed:4d}  {quality}  wrong {len(m['wrong_merges'])}  " + "  ".join(robots)


def log_row(name: str, split: int, seed: int, m: dict) -> str:
    placed = sum(r["status"] in ("reference", "prior", "aligned") for r in m["robots"].values())
    nan = float("nan")
    e, a = m.get("relations", {}), m.get("relations_across", {})
    merges = " ".join(
        f"{n}@{r['time_to_first_merge_s']:.0f}s"
        if r.get("time_to_first_merge_s") is not None
        else f"{n}:{r['status']}"  # (never merged: its status whole)
        for n, r in m["robots"].items()
    )
    return (
        f"{name:10s} {split:5d} {seed:4d}  {placed}/{split} placed  wrong {len(m['wrong_merges'])}  "
        f"all {e.get('trans_mean_m', nan):.3f} m {e.get('rot_mean_deg', nan):.2f}° (n={e.get('n', 0)})  "
        f"across {a.get('trans_mean_m', nan):.3f} m {a.get('rot_mean_deg', nan):.2f}° (n={a.get('n', 0)})  "
        + merges
    )


def run_cases(cases: list, result_name: str, args) -> dict:
    """Run every ``(key, DemoConfig, row)`` case as a demo, print ``row(metrics)`` as each ends,
    and save all metrics under ``result_name``."""
    results = {}
    for key, cfg, row_of in cases:
        results[key] = run_demo(cfg)
        print(row_of(results[key]), flush=True)
    save_results(
        ROOT / "benchmarks" / "results" / f"{result_name}.json",
        result_name,
        {"args": vars(args), "runs": results},
    )
    return results


def main_logs(args) -> int:
    entries, skipped = discover(args.logs)  # bench_logs.py's: a log with its relations beside it
    for why in skipped:
        print(f"skipped: {why}")
    if not entries:
        raise SystemExit("no log with relations to cut into pieces")
    print("log        split seed  pieces placed, wrong merges, relations error (all merged, across pieces),")
    print("                       first merge per piece (s after the agents started)")
    cases = [
        (f"{e.name}/split{k}/seed{seed}",
         DemoConfig(out=f"{args.out}/{e.name}-split{k}-seed{seed}", log=str(e.log), split=k,
                    relations=str(e.relations), speed=0.0, seed=seed, progress=False,
                    server_set=tuple(args.server_set)),
         lambda m, e=e, k=k, seed=seed: log_row(e.name, k, seed, m))
        for e in entries for k in args.splits for seed in args.seeds
    ]  # fmt: skip
    results = run_cases(cases, "bench_demo_logs", args)
    wrong = sum(len(m["wrong_merges"]) for m in results.values())
    print(f"{len(results)} runs: {wrong} pieces in wrong merges")
    return 0


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seeds", type=int, nargs="+", default=None, help="0-9 (--logs: 0)")
    p.add_argument("--unknown-starts", action="store_true")
    p.add_argument("--robots", type=int, default=3)
    p.add_argument("--world", default="office")
    p.add_argument("--duration", type=float, default=175.0)
    p.add_argument("--out", default="out/bench_demo")
    p.add_argument("--logs", nargs="+", default=None, help="real logs (directories or files) cut into pieces")
    p.add_argument("--splits", type=int, nargs="+", default=[2, 3], help="--logs: pieces per log")
    p.add_argument("--server-set", action="append", default=[], metavar="SECTION.KEY=VALUE",
                   help="a map-server (FleetConfig) override, e.g. mature_window_s=20")  # fmt: skip
    args = p.parse_args()
    if args.seeds is None:
        args.seeds = [0] if args.logs else list(range(10))
    if args.logs:
        return main_logs(args)
    print("seed  fused precision/completeness, wrong merges, per robot: status transform-error @first-merge")
    cases = [
        (seed,
         DemoConfig(out=f"{args.out}/seed{seed}", robots=args.robots, world=args.world,
                    duration_s=args.duration, seed=seed, unknown_starts=args.unknown_starts, progress=False,
                    server_set=tuple(args.server_set)),
         lambda m, seed=seed: row(seed, m))
        for seed in args.seeds
    ]  # fmt: skip
    results = run_cases(cases, "bench_demo", args)
    wrong = sum(len(m["wrong_merges"]) for m in results.values())
    unaligned = sum(r["status"] == "unaligned" for m in results.values() for r in m["robots"].values())
    print(f"{len(results)} runs: {wrong} wrong merges, {unaligned} robots left unaligned")
    return 0


if __name__ == "__main__":
    sys.exit(main())
