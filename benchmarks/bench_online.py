"""The online back end's cost to the filter, as an agent runs it: per-scan filter time with and
without it, the back end's own CPU, and what it made of the run.

    .venv/bin/python benchmarks/bench_online.py LOG [--relations REL] [--limit N] [--particles 30]
        [--seed 0] [--modes off process inline] [--json PATH]

Each mode feeds the log's scans, as fast as they go, to an agent's bus-free core
(:class:`robot_agent.agent.AgentCore`: filter, pose and map messages as published, no zenoh):
``off`` without the online back end, ``process`` with it in its own process (what ``fleet-slam
agent`` runs), ``inline`` with it in the filter's thread (for comparison: what it would cost
there). Per-scan time is the time of ``AgentCore.step`` (the filter, plus handing scans to the
back end); the back end's CPU is the child process's user + system time. The filter's thread is
pinned to one core and the back end's process to another when the machine has two.
Prints a table and writes ``benchmarks/results/bench_online.json``.
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import resource
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from _results import save_results  # noqa: E402

from robot_agent.agent import AgentConfig, AgentCore  # noqa: E402
from robot_agent.backend.live import InlineRunner, LiveCorrector, ProcessRunner  # noqa: E402
from robot_agent.slam.config import command_line_config  # noqa: E402
from robot_agent.slam.fastslam import FastSLAM  # noqa: E402
from robot_agent.sources import read_log  # noqa: E402
from shared.metrics import read_relations, relations_error  # noqa: E402


def children_cpu_s() -> float:
    ru = resource.getrusage(resource.RUSAGE_CHILDREN)
    return ru.ru_utime + ru.ru_stime


def run_mode(mode: str, log, rel, overrides: list[str], particles: int, seed: int, limit: int | None) -> dict:
    cfg = command_line_config(overrides, particles)
    slam = FastSLAM(cfg, np.random.default_rng(seed))
    cpus = sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else []
    runner = None
    if mode == "process":
        runner = ProcessRunner(cfg)
        if len(cpus) >= 2:
            os.sched_setaffinity(runner.pid, {cpus[1]})
    elif mode == "inline":
        runner = InlineRunner(cfg)
    if len(cpus) >= 2:
        os.sched_setaffinity(0, {cpus[0]})
    corrector = None if runner is None else LiveCorrector(slam, runner)
    core = AgentCore("bench", slam, AgentConfig(speed=0), corrector=corrector)
    n = len(log) if limit is None else min(limit, len(log))
    step_s = np.zeros(n)
    cpu0 = children_cpu_s()
    t0 = time.perf_counter()
    for i, scan in enumerate(log.scans()):
        if i >= n:
            break
        t = time.perf_counter()
        core.step(scan)
        step_s[i] = time.perf_counter() - t
        core.pose_message()
        core.map_messages()
    wall = time.perf_counter() - t0
    out = {"mode": mode, "scans": n, "wall_s": wall, "step_ms_mean": 1e3 * step_s.mean(),
           "step_ms_p95": 1e3 * float(np.percentile(step_s, 95))}  # fmt: skip
    stamps, filter_poses = slam.best_trajectory()
    poses = filter_poses
    if corrector is not None:
        t = time.perf_counter()
        done = corrector.finish(600.0)
        out["final_update_s"] = time.perf_counter() - t
        out["final_in_time"] = done
        stamps, now = slam.best_trajectory()  # the filter continued from the corrections
        filter_poses = corrector.raw_path(now)
        poses = corrector.corrected_path(now)
        out["updates"] = corrector.updates
        out["loops"] = corrector.stats.get("loops")
        out["keyframes"] = corrector.stats.get("keyframes")
        out["update_s_max"] = corrector.stats.get("update_s_max")
        corrector.close()
    if mode == "process":
        out["backend_cpu_s"] = children_cpu_s() - cpu0
    elif mode == "inline":
        out["backend_cpu_s"] = corrector.stats.get("update_s_total")
    duration = float(np.ptp(log.stamps_s[:n]))
    out["log_duration_s"] = duration
    if "backend_cpu_s" in out:
        out["backend_share_of_log_time"] = out["backend_cpu_s"] / duration
    if rel is not None:
        r = rel.until(stamps.max() + 1e-6)
        out["relations"] = relations_error(stamps, poses, r, *log.odometry_track()).summary()
        out["relations_filter_only"] = relations_error(
            stamps, filter_poses, r, *log.odometry_track()
        ).summary()
    if len(cpus) >= 2:
        os.sched_setaffinity(0, set(cpus))
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("log")
    p.add_argument("--relations", default=None)
    p.add_argument("--limit", type=int, default=None)
    p.add_argument("--particles", type=int, default=30)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--set", nargs="*", default=[], metavar="SECTION.KEY=VALUE")
    p.add_argument("--modes", nargs="+", default=["off", "process"], choices=["off", "process", "inline"])
    p.add_argument("--json", default=str(ROOT / "benchmarks" / "results" / "bench_online.json"))
    args = p.parse_args(argv)
    log = read_log(args.log, progress=False)
    rel = read_relations(args.relations) if args.relations else None
    rows = []
    for mode in args.modes:
        row = run_mode(mode, log, rel, args.set, args.particles, args.seed, args.limit)
        rows.append(row)
        print(_line(row), flush=True)
    off = next((r for r in rows if r["mode"] == "off"), None)
    if off is not None:
        for r in rows:
            r["step_cost_vs_off"] = r["step_ms_mean"] / off["step_ms_mean"]
    _table(rows)
    save_results(args.json, "bench_online", {"log": args.log, "settings": vars(args), "modes": rows})
    return 0


def _line(r: dict) -> str:
    s = f"{r['mode']:>8}: {r['scans']} scans, step {r['step_ms_mean']:.2f} ms (p95 {r['step_ms_p95']:.2f})"
    if "backend_cpu_s" in r:
        share = 100 * r["backend_share_of_log_time"]
        s += f", back end {r['backend_cpu_s']:.1f} s CPU ({share:.1f} % of log time)"
    if "relations" in r:
        fixed, alone = r["relations"]["trans_mean_m"], r["relations_filter_only"]["trans_mean_m"]
        s += f", relations {fixed:.3f} m (filter alone {alone:.3f})"
    return s


def _table(rows: list[dict]) -> None:
    from rich.console import Console
    from rich.table import Table

    console = Console()
    if not console.is_terminal:
        console.width = 200
    t = Table(title="online back end: the filter's per-scan cost and the back end's CPU")
    for h in ("mode", "scans", "step ms\nmean", "step ms\np95", "÷ off", "back end\nCPU s", "% of\nlog time",
              "updates", "loops", "final\nupdate s", "relations\nm", "filter\nalone m"):  # fmt: skip
        t.add_column(h, justify="right")

    def f(v, fmt=".2f"):
        return "—" if v is None else format(v, fmt)

    for r in rows:
        t.add_row(
            r["mode"], str(r["scans"]), f(r["step_ms_mean"]), f(r["step_ms_p95"]),
            f(r.get("step_cost_vs_off"), ".3f"), f(r.get("backend_cpu_s"), ".1f"),
            f(100 * r["backend_share_of_log_time"] if "backend_share_of_log_time" in r else None, ".1f"),
            f(r.get("updates"), "d"), f(r.get("loops"), "d"), f(r.get("final_update_s"), ".1f"),
            f(r.get("relations", {}).get("trans_mean_m"), ".3f"),
            f(r.get("relations_filter_only", {}).get("trans_mean_m"), ".3f"),
        )  # fmt: skip
    console.print(t)


if __name__ == "__main__":
    raise SystemExit(main())
