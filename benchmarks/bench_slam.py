"""SLAM accuracy and speed: a real log (Intel by default) and simulated worlds, with ablations.

    .venv/bin/python benchmarks/bench_slam.py [--log intel.clf --relations intel.relations]
        [--particles 30] [--seeds 0 1 2] [--worlds office warehouse] [--duration 300]
        [--ablations all no-proposal no-consensus no-relocalization no-backend] [--limit N]

Prints one table per source and writes ``benchmarks/results/bench_slam.json``. One core.
Real logs: Kümmerle relations error and real-time factor. Simulation: ATE RMSE, map precision
and completeness against the true walls, and whether the loop closed (robot_agent/sim/evaluate.py).
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from _results import save_results  # noqa: E402

from robot_agent.replay import replay  # noqa: E402
from robot_agent.sim import SimConfig, builtin_world, simulate_robot  # noqa: E402
from robot_agent.sim.evaluate import score_run  # noqa: E402
from robot_agent.slam.config import apply_overrides  # noqa: E402
from robot_agent.slam.fastslam import SlamConfig  # noqa: E402
from robot_agent.sources import LaserLog, read_log  # noqa: E402
from shared.metrics import read_relations, relations_error  # noqa: E402

ABLATIONS = {
    "all": [],
    "no-proposal": ["proposal.enabled=false"],
    "no-consensus": ["consensus.enabled=false"],
    "no-relocalization": ["relocalization.enabled=false"],
    "no-backend": ["backend.enabled=false"],
}
DEFAULT_INTEL = ROOT.parent / "shared" / "datasets" / "intel"


def run_log(log: LaserLog, rel, cfg: SlamConfig, seed: int, limit: int | None) -> dict:
    res = replay(log, cfg, seed=seed, progress=False, limit=limit)
    n = res.scans
    duration = float(np.ptp(log.stamps_s[:n]))
    out = {"scans": n, "wall_s": res.wall_s, "real_time_factor": duration / res.wall_s}
    if rel is not None:
        rel = rel.until(res.stamps_s.max() + 1e-6)
        err = relations_error(res.stamps_s, res.poses, rel, *log.odometry_track())
        out |= {
            k: v
            for k, v in err.summary().items()
            if k in ("n", "trans_mean_m", "trans_std_m", "rot_mean_deg")
        }
    return out | {"stats": dict(res.slam.stats), "_res": res}


def run_sim(world_name: str, seed: int, duration_s: float, cfg: SlamConfig) -> dict:
    world = builtin_world(world_name)
    sim = simulate_robot(world, 0, duration_s, seed, SimConfig())
    log = sim.to_log()
    r = run_log(log, None, cfg, seed, None)
    res = r.pop("_res")
    gm, keep = res.slam.published_map()
    score = score_run(sim, world, res.stamps_s, res.poses, gm.seg[keep], map_poses=res.filter_poses)
    return r | score.as_dict()


def table(title: str, rows: list[dict], cols: list[str]) -> None:
    from rich.console import Console
    from rich.table import Table

    t = Table(title=title)
    for c in cols:
        t.add_column(c, justify="right")
    for r in rows:
        t.add_row(*[f"{r[c]:.3f}" if isinstance(r.get(c), float) else str(r.get(c, "")) for c in cols])
    Console().print(t)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--log", default=str(DEFAULT_INTEL / "intel.clf"))
    ap.add_argument("--relations", default=str(DEFAULT_INTEL / "intel.relations"))
    ap.add_argument("--particles", type=int, default=30)
    ap.add_argument("--seeds", type=int, nargs="+", default=[0])
    ap.add_argument("--worlds", nargs="*", default=["office", "warehouse"])
    ap.add_argument("--duration", type=float, default=300.0)
    ap.add_argument("--ablations", nargs="+", default=list(ABLATIONS), choices=list(ABLATIONS))
    ap.add_argument("--limit", type=int, default=None, help="only the first N scans of the log")
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "bench_slam.json"))
    args = ap.parse_args(argv)

    results: dict = {"particles": args.particles, "seeds": args.seeds, "log": {}, "sim": {}}
    if args.log and Path(args.log).exists():
        log = read_log(args.log, progress=False)
        rel = read_relations(args.relations) if args.relations and Path(args.relations).exists() else None
        rows = []
        for name in args.ablations:
            cfg = apply_overrides(SlamConfig(), [f"particles={args.particles}", *ABLATIONS[name]])
            for seed in args.seeds:
                r = run_log(log, rel, cfg, seed, args.limit)
                r.pop("_res")
                rows.append({"ablation": name, "seed": seed} | r)
        results["log"] = {"path": args.log, "rows": rows}
        table(
            f"{Path(args.log).name}: {args.particles} particles",
            rows,
            [
                "ablation",
                "seed",
                "n",
                "trans_mean_m",
                "trans_std_m",
                "rot_mean_deg",
                "wall_s",
                "real_time_factor",
            ],
        )
    else:
        print(f"no log at {args.log}: skipping the real-data part", file=sys.stderr)
    rows = []
    for world in args.worlds:
        for name in args.ablations:
            cfg = apply_overrides(SlamConfig(), [f"particles={args.particles}", *ABLATIONS[name]])
            for seed in args.seeds:
                rows.append(
                    {"world": world, "ablation": name, "seed": seed}
                    | run_sim(world, seed, args.duration, cfg)
                )
    results["sim"] = {"duration_s": args.duration, "rows": rows}
    if rows:
        table(
            f"simulated, {args.duration:.0f} s, {args.particles} particles",
            rows,
            [
                "world",
                "ablation",
                "seed",
                "ate_rmse_m",
                "precision",
                "completeness",
                "loop_closed",
                "real_time_factor",
            ],
        )
    save_results(args.out, "bench_slam", results)
    return 0


if __name__ == "__main__":
    sys.exit(main())
