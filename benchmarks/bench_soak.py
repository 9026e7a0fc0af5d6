"""A simulated agent for a long time, faster than real time: does its memory stay bounded, and
does its online back end still find and close loops at the end?

    .venv/bin/python benchmarks/bench_soak.py [--hours 24] [--world office] [--route 0]
        [--explore] [--particles 10] [--seed 0] [--every-min 30] [--json PATH]

The agent's own parts, as ``fleet-slam agent --world W`` runs them, without the bus: the
simulated robot and its scan store (:class:`robot_agent.service.SimSource`), the filter, the
online back end in its own process (:class:`~robot_agent.backend.live.ProcessRunner`), the pose
and map messages encoded as the publisher sends them (only the latest kept). Every
``--every-min`` simulated minutes: resident memory of the agent and of its back-end process
(``VmRSS``), the back end's keyframes (in the graph, retired), the loops it took in since the last
row, the filter's open trajectory steps. Prints a table and writes
``benchmarks/results/bench_soak.json``.
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from _results import save_results  # noqa: E402

from robot_agent.agent import AgentConfig, AgentCore  # noqa: E402
from robot_agent.backend.live import LiveCorrector, ProcessRunner  # noqa: E402
from robot_agent.service import SimSource, endless_config  # noqa: E402
from robot_agent.slam.config import command_line_config  # noqa: E402
from robot_agent.slam.fastslam import FastSLAM  # noqa: E402
from shared import codec  # noqa: E402
from shared.memory import release_free_memory, resident_mb  # noqa: E402

SAMPLE_EVERY = 200  # scans between samples of resident memory


rss_mb = resident_mb


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--hours", type=float, default=24.0)
    p.add_argument("--world", default="office")
    p.add_argument("--route", type=int, default=0)
    p.add_argument("--explore", action="store_true")
    p.add_argument("--particles", type=int, default=10)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--every-min", type=float, default=30.0)
    p.add_argument("--set", nargs="*", default=[], metavar="SECTION.KEY=VALUE")
    p.add_argument("--json", default=str(ROOT / "benchmarks" / "results" / "bench_soak.json"))
    args = p.parse_args(argv)

    cfg = endless_config(command_line_config(args.set, args.particles))  # as the agent does
    slam = FastSLAM(cfg, np.random.default_rng(args.seed))
    runner = ProcessRunner(cfg)
    corrector = LiveCorrector(slam, runner)
    core = AgentCore("soak", slam, AgentConfig(speed=0), corrector=corrector)
    src_args = argparse.Namespace(
        world=args.world, route=args.route, seed=args.seed, start=None, duration=args.hours * 3600.0,
        explore=args.explore,
    )  # fmt: skip
    sim = SimSource(src_args, slam)
    sim.core = core  # (the explorer reads the filter's map, as the agent's service sets it)
    rows: list[dict] = []
    latest: list[bytes] = []  # what the publisher keeps: the last map's payloads
    every_s = 60.0 * args.every_min
    next_s = every_s
    t0_wall = time.perf_counter()
    t0_src = None
    loops_before = 0
    peak_agent = peak_backend = 0.0
    try:
        for scan in sim.scans():
            est = core.step(scan)
            sim.on_estimate(scan, est)
            if (pose := core.pose_message()) is not None:
                codec.encode(pose)
            if (chunks := core.map_messages()) is not None:
                latest = [codec.encode(c) for c in chunks]
            t0_src = scan.stamp_s if t0_src is None else t0_src
            if core.scans % SAMPLE_EVERY == 0:  # resident memory between rows: its peak
                peak_agent = max(peak_agent, rss_mb())
                peak_backend = max(peak_backend, rss_mb(runner.pid))
            if scan.stamp_s - t0_src >= next_s:
                next_s += every_s
                st = corrector.stats
                admitted = st.get("loops_admitted", 0)
                row = {
                    "sim_h": (scan.stamp_s - t0_src) / 3600.0,
                    "wall_s": time.perf_counter() - t0_wall,
                    "scans": core.scans,
                    "rss_agent_mb": rss_mb(),
                    "rss_backend_mb": rss_mb(runner.pid),
                    "rss_agent_peak_mb": peak_agent,  # the highest sample since the last row
                    "rss_backend_peak_mb": peak_backend,
                    "keyframes": st.get("keyframes", 0),
                    "retired": st.get("retired", 0),
                    "loops_in_graph": st.get("loops", 0),
                    "loops_taken_since_last_row": admitted - loops_before,
                    "updates": corrector.updates,
                    "update_s_max": st.get("update_s_max", 0.0),
                    "update_s_max_since_last_row": corrector.update_s_recent,
                    "open_steps": slam.trajectory.open_steps,
                    "kept_scans": slam.trajectory.kept_scans,
                    "retired_thinned": st.get("retired_thinned", 0),
                    "retired_forgotten": st.get("forgotten", 0),
                    "jump_edges": st.get("jumps", 0),  # their keyframes stay in the graph
                    "optimizations": st.get("optimizations", 0),
                    "optimizations_warm": st.get("optimizations_warm", 0),  # narrow kernel only
                    "optimizations_cut": st.get("optimize_cut", 0),  # stopped at their deadline
                    "virtual_edges": st.get("virtual_edges", 0),  # edges carried from retired ones
                    "loop_hints_kept": len(slam.loop_hints),
                    "map_bytes": sum(len(b) for b in latest),
                }
                row["rss_total_mb"] = row["rss_agent_mb"] + row["rss_backend_mb"]
                row["rss_total_peak_mb"] = peak_agent + peak_backend
                release_free_memory()  # what the agent holds (its own trims come every 10 s)
                row["rss_agent_held_mb"] = rss_mb()
                peak_agent = peak_backend = 0.0
                corrector.update_s_recent = 0.0
                loops_before = admitted
                rows.append(row)
                print(_line(row), flush=True)
                save_results(args.json, "bench_soak", _summary(args, rows, done=False))  # so far
    finally:
        corrector.close()
    out = _summary(args, rows, done=True)
    save_results(args.json, "bench_soak", out)
    return 0


def _summary(args, rows: list[dict], done: bool) -> dict:
    out = {"settings": vars(args), "finished": done, "rows": rows}
    one = next((r for r in rows if r["sim_h"] >= 1.0 - 1e-6), None)
    if one is not None and rows:
        out["rss_total_1h_mb"] = one["rss_total_mb"]
        out["rss_total_end_mb"] = rows[-1]["rss_total_mb"]
        out["rss_end_over_1h"] = rows[-1]["rss_total_mb"] / one["rss_total_mb"]
        out["rss_peak_1h_mb"] = one["rss_total_peak_mb"]
        out["rss_peak_end_mb"] = rows[-1]["rss_total_peak_mb"]
        out["rss_peak_end_over_1h"] = rows[-1]["rss_total_peak_mb"] / one["rss_total_peak_mb"]
        if done:
            print(
                f"resident memory: {one['rss_total_mb']:.0f} MB after {one['sim_h']:.1f} h, "
                f"{rows[-1]['rss_total_mb']:.0f} MB after {rows[-1]['sim_h']:.1f} h "
                f"({100 * (out['rss_end_over_1h'] - 1):+.1f} %); peak between rows "
                f"{one['rss_total_peak_mb']:.0f} -> {rows[-1]['rss_total_peak_mb']:.0f} MB "
                f"({100 * (out['rss_peak_end_over_1h'] - 1):+.1f} %); loops taken in the last row: "
                f"{rows[-1]['loops_taken_since_last_row']}"
            )
    return out


def _line(r: dict) -> str:
    return (
        f"{r['sim_h']:6.2f} h sim, {r['wall_s']:7.0f} s wall: RSS agent {r['rss_agent_mb']:.0f} MB "
        f"(peak {r['rss_agent_peak_mb']:.0f}, held {r['rss_agent_held_mb']:.0f}) + back end "
        f"{r['rss_backend_mb']:.0f} MB (peak {r['rss_backend_peak_mb']:.0f}); "
        f"keyframes {r['keyframes']} (+{r['retired']} retired), "
        f"loops {r['loops_in_graph']} in the graph, {r['loops_taken_since_last_row']} taken since; "
        f"longest update {r['update_s_max_since_last_row']:.2f} s (since the last row); "
        f"{r['open_steps']} open steps, "
        f"{r['kept_scans']} scans kept"
    )


if __name__ == "__main__":
    raise SystemExit(main())
