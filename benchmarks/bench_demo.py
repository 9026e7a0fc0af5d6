"""The fleet demo over several seeds: alignment verdicts, transform errors, fused-map quality.

    .venv/bin/python benchmarks/bench_demo.py [--seeds 0 1 ... 9] [--unknown-starts]
        [--robots 3] [--world office] [--duration 175] [--out out/bench_demo]

Each seed is one full `fleet-slam demo` (router, server, agents as processes on loopback, about
3 minutes at the default duration). Prints one row per seed — every robot's status and transform
error (and, in brackets, with fitted map frames: the server's error alone), fused precision and
completeness, wrong merges — and writes benchmarks/results/bench_demo.json.
A wrong merge is a merged robot whose transform is off by more than 0.3 m or 3° (fleet_slam/report.py).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from _results import save_results  # noqa: E402

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


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seeds", type=int, nargs="+", default=list(range(10)))
    p.add_argument("--unknown-starts", action="store_true")
    p.add_argument("--robots", type=int, default=3)
    p.add_argument("--world", default="office")
    p.add_argument("--duration", type=float, default=175.0)
    p.add_argument("--out", default="out/bench_demo")
    args = p.parse_args()
    results = {}
    print("seed  fused precision/completeness, wrong merges, per robot: status transform-error @first-merge")
    for seed in args.seeds:
        cfg = DemoConfig(
            out=f"{args.out}/seed{seed}", robots=args.robots, world=args.world, duration_s=args.duration,
            seed=seed, unknown_starts=args.unknown_starts, progress=False,
        )  # fmt: skip
        m = run_demo(cfg)
        results[seed] = m
        print(row(seed, m), flush=True)
    wrong = sum(len(m["wrong_merges"]) for m in results.values())
    unaligned = sum(r["status"] == "unaligned" for m in results.values() for r in m["robots"].values())
    print(f"{len(results)} runs: {wrong} wrong merges, {unaligned} robots left unaligned")
    save_results(
        ROOT / "benchmarks" / "results" / "bench_demo.json",
        "bench_demo",
        {"args": vars(args), "runs": results},
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
