"""Lidar simulation speed per built-in world, on one core.

For each world: the robots' true poses along their patrol routes (sampled at the scan rate),
then ``--scans`` simulated scans (ray casting + noise) timed as one batch. Prints a table and
writes JSON. Target: >= 500 scans/s with 181 beams in ``campus``.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_var] = "1"  # one core, before numpy loads

import argparse  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
from _results import save_results  # noqa: E402

from robot_agent.sim import (  # noqa: E402
    BUILTIN_WORLDS,
    LidarConfig,
    SimConfig,
    beam_angles,
    builtin_world,
    simulate_scans,
)
from robot_agent.sim.lidar import MAX_PAIRS_PER_CHUNK, walls_in_range  # noqa: E402
from robot_agent.sim.robot import drive_route  # noqa: E402

TARGET_SCANS_PER_S = 500.0  # in campus, 181 beams
REPEATS = 3  # best of


def route_poses(world, n_scans: int, cfg: SimConfig) -> np.ndarray:
    """``n_scans`` true poses at the scan rate, taken round-robin from every robot's route."""
    per_robot = -(-n_scans // world.num_robots)
    duration_s = per_robot / cfg.lidar.rate_hz
    poses = [
        drive_route(r, s, cfg.robot, duration_s)[0][:: cfg.steps_per_scan][:per_robot]
        for r, s in zip(world.routes, world.starts, strict=True)
    ]
    return np.stack(poses, axis=1).reshape(-1, 3)[:n_scans]


def bench_world(name: str, n_scans: int, beams: int) -> dict:
    world = builtin_world(name)
    cfg = SimConfig(lidar=LidarConfig(beams=beams))
    poses = route_poses(world, n_scans, cfg)
    best = np.inf
    for _ in range(REPEATS):
        rng = np.random.default_rng(0)
        t0 = time.perf_counter()
        ranges = simulate_scans(rng, poses, world.walls, cfg.lidar)
        best = min(best, time.perf_counter() - t0)
    directions = poses[:, 2:3] + beam_angles(cfg.lidar)
    _, near = walls_in_range(poses[:, :2], world.walls, cfg.lidar.range_max_m, directions)
    return {
        "world": name,
        "walls": len(world.walls),
        "scans": len(poses),
        "beams": beams,
        "seconds": best,
        "scans_per_s": len(poses) / best,
        "mean_walls_in_range": float(near.mean()),
        "hit_fraction": float(np.mean(ranges < cfg.lidar.range_max_m)),
    }


def main(n_scans: int, beams: int, out: Path) -> list[dict]:
    rows = [bench_world(name, n_scans, beams) for name in BUILTIN_WORLDS]
    try:
        from rich.console import Console
        from rich.table import Table

        table = Table(title=f"lidar simulation, {beams} beams, one core")
        for col in ("world", "walls", "in range", "scans", "s", "scans/s"):
            table.add_column(col, justify="right")
        for r in rows:
            table.add_row(
                r["world"],
                str(r["walls"]),
                f"{r['mean_walls_in_range']:.0f}",
                str(r["scans"]),
                f"{r['seconds']:.3f}",
                f"{r['scans_per_s']:.0f}",
            )
        Console().print(table)
    except ImportError:
        for r in rows:
            print(f"{r['world']:10s} {r['walls']:5d} walls {r['scans_per_s']:8.0f} scans/s")
    campus = next(r for r in rows if r["world"] == "campus")
    verdict = "meets" if campus["scans_per_s"] >= TARGET_SCANS_PER_S else "MISSES"
    print(f"campus: {campus['scans_per_s']:.0f} scans/s {verdict} the target of {TARGET_SCANS_PER_S:.0f}")
    payload = {
        "max_pairs_per_chunk": MAX_PAIRS_PER_CHUNK,
        "target_scans_per_s_campus": TARGET_SCANS_PER_S,
        "results": rows,
    }
    save_results(out, "bench_sim", payload)
    return rows


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scans", type=int, default=2000, help="scans per world (default 2000)")
    parser.add_argument("--beams", type=int, default=181, help="beams per scan (default 181)")
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/bench_sim.json"))
    args = parser.parse_args()
    main(args.scans, args.beams, args.out)
