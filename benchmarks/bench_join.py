"""Joining a mapped building (``fleet-slam agent --join``; issue 21, item 3): how often and how soon
a robot finds itself in the fused map, and how often it takes a wrong place.

    .venv/bin/python benchmarks/bench_join.py [--worlds office warehouse] [--first-s 120]
        [--join-s 120] [--jobs 2]

For every ordered pair (a, b) of a world's routes, without processes or network: robot a's route is
mapped for ``--first-s`` simulated seconds by its agent (AgentCore, no back end); its published
map is the fleet's fused map (robot a the reference: its start frame is the global frame) and its
free space is the server's (the contradiction check). Robot b's agent then starts with the Joiner
(robot_agent/join.py) on that fused map, its scans fed in time order for ``--join-s``; each map it
publishes goes into ``map_server.fleet.Fleet`` with its free space and a fusion after it, to the
end. A row per pair: when the agent took a place (and how far from the truth), when and where the
fleet placed robot b, where it is at the end, or why the agent found no place. A *wrong join* (or
placement) is a place farther than 0.3 m / 3° from the truth (as a wrong merge is counted); a
wrong placement is *undone* when the fleet unplaces the robot or moves it to the truth.

Prints the table and a summary; writes benchmarks/results/bench_join.json.
"""

from __future__ import annotations

import argparse
import itertools
import sys
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from _results import save_results  # noqa: E402

from fleet_slam.report import WRONG_MERGE_DEG, WRONG_MERGE_M  # noqa: E402
from map_server.config import FleetConfig  # noqa: E402
from map_server.fleet import Fleet  # noqa: E402
from map_server.freespace import FreeSpaces  # noqa: E402
from robot_agent.agent import AgentConfig, AgentCore  # noqa: E402
from robot_agent.join import Joiner  # noqa: E402
from robot_agent.sim import SimConfig, builtin_world, simulate_robot  # noqa: E402
from robot_agent.slam.fastslam import FastSLAM, SlamConfig  # noqa: E402
from shared import codec  # noqa: E402
from shared.geometry import relative  # noqa: E402


def fused_of(world_name: str, route: int, first_s: float) -> tuple[Fleet, FreeSpaces]:
    """A fleet holding robot ``route``'s published map and free space after ``first_s`` of its
    route (the reference), with the free spaces the server would hold (the contradiction check)."""
    sim = simulate_robot(builtin_world(world_name), route, first_s, 0, SimConfig())
    core = AgentCore("robot1", FastSLAM(SlamConfig(), np.random.default_rng(0)), AgentConfig(speed=0))
    for scan in sim.to_log().scans():
        core.step(scan)
    core.map_messages(force=True)
    core.free_message(force=True)
    fleet, free = Fleet(FleetConfig(), "bench"), FreeSpaces()
    fleet.free_of = free.area
    free.put(core.free_whole)
    fleet.put_map(codec.join(core.map_whole), 0.0)
    fleet.fuse(0.0)
    return fleet, free


def _off(truth: np.ndarray, t: np.ndarray) -> tuple[float, float, bool]:
    """How far ``t`` is from ``truth``: metres, degrees (signed), and whether that is a wrong merge."""
    e = relative(truth, t)
    m, deg = float(np.hypot(e[0], e[1])), float(np.degrees(e[2]))
    return m, deg, bool(m > WRONG_MERGE_M or abs(deg) > WRONG_MERGE_DEG)


def run_pair(job: tuple) -> dict:
    world_name, a, b, first_s, join_s = job
    world = builtin_world(world_name)
    truth = relative(world.starts[a], world.starts[b])
    fleet, free = fused_of(world_name, a, first_s)
    fused = fleet.latest()
    core = AgentCore("robot2", FastSLAM(SlamConfig(), np.random.default_rng(b + 1)), AgentConfig(speed=0))
    core.joiner = Joiner(fused.seg)
    row = dict(world=world_name, mapped=a, joining=b, fused_segments=len(fused.seg), joined_s=None,
               join_error_m=None, join_error_deg=None, wrong_join=False, placed_s=None, placed_status=None,
               placed_error_m=None, placed_error_deg=None, wrong_placed=False, undone_s=None,
               final_status="unaligned", final_error_m=None, final_error_deg=None, wrong_at_end=False,
               reason="")  # fmt: skip
    sim = simulate_robot(world, b, join_s, b + 1, SimConfig())
    t0 = None
    for scan in sim.to_log().scans():
        t0 = scan.stamp_s if t0 is None else t0
        now = float(scan.stamp_s - t0)
        core.step(scan)
        if core.joined and row["joined_s"] is None:
            m, deg, wrong = _off(truth, core.prior)
            row.update(joined_s=now, join_error_m=m, join_error_deg=deg, wrong_join=wrong)
        if not core.map_messages():
            continue
        if core.free_message() is not None:  # (the agent sends both together)
            free.put(core.free_whole)
        fleet.put_map(codec.join(core.map_whole), now)
        f = fleet.fuse(now)
        s = f.robot("robot2") if f is not None else None
        if s is None:
            continue
        placed = s.status != "unaligned"
        m, deg, wrong = _off(truth, s.transform) if placed else (None, None, False)
        if placed and row["placed_s"] is None:
            row.update(placed_s=now, placed_status=s.status, placed_error_m=m, placed_error_deg=deg,
                       wrong_placed=wrong)  # fmt: skip
        if row["wrong_placed"] and row["undone_s"] is None and not wrong:  # unplaced, or moved to the truth
            row["undone_s"] = now
        row.update(final_status=s.status, final_error_m=m, final_error_deg=deg, wrong_at_end=wrong)
    j = core.joiner
    row["reason"] = j.last.reason if j is not None and j.last is not None else ""
    return row


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--worlds", nargs="+", default=["office", "warehouse"])
    p.add_argument("--first-s", type=float, default=120.0, help="simulated seconds of the mapped robot")
    p.add_argument("--join-s", type=float, default=120.0, help="simulated seconds of the joining robot")
    p.add_argument("--jobs", type=int, default=2)
    p.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results" / "bench_join.json")
    args = p.parse_args()
    jobs = []
    for w in args.worlds:
        n = builtin_world(w).num_robots
        jobs += [(w, a, b, args.first_s, args.join_s) for a, b in itertools.permutations(range(n), 2)]
    with ProcessPoolExecutor(args.jobs) as ex:
        rows = list(ex.map(run_pair, jobs))
    print(
        f"{'world':10s} {'map':>3s} {'join':>4s} {'joined':>7s} {'error':>14s} {'placed':>7s} {'as':>8s} "
        f"{'at the end':>22s}  why"
    )
    for r in rows:
        joined = "-" if r["joined_s"] is None else f"{r['joined_s']:.1f} s"
        err = "" if r["joined_s"] is None else f"{r['join_error_m']:.3f} m {r['join_error_deg']:.2f}°"
        placed = "-" if r["placed_s"] is None else f"{r['placed_s']:.1f} s"
        why = ("WRONG " if r["wrong_join"] else "") + r["reason"]
        end = (
            r["final_status"]
            if r["final_error_m"] is None
            else (f"{r['final_status']} {r['final_error_m']:.2f} m {r['final_error_deg']:.1f}°")
        )
        if r["undone_s"] is not None:
            why = f"undone at {r['undone_s']:.0f} s; " + why
        print(f"{r['world']:10s} {r['mapped']:3d} {r['joining']:4d} {joined:>7s} {err:>14s} {placed:>7s} "
              f"{r['placed_status'] or '-':>8s} {end:>22s}  {why}")  # fmt: skip
    right = [r for r in rows if r["joined_s"] is not None and not r["wrong_join"]]
    wrong = [r for r in rows if r["wrong_join"]]
    alone = [r for r in rows if r["joined_s"] is None]
    times = [r["joined_s"] for r in right]
    print(
        f"{len(rows)} joins: {len(right)} at the true place"
        + (f" ({min(times):.0f}-{max(times):.0f} s after the start)" if times else "")
        + f", {len(wrong)} wrong, {len(alone)} found no place (mapped alone)"
    )
    wrong_placed = [r for r in rows if r["wrong_placed"]]
    print(
        f"the fleet placed {len(wrong_placed)} robots wrongly, "
        f"{sum(r['undone_s'] is not None for r in wrong_placed)} of them undone by the end "
        f"({args.join_s:g} s); {sum(r['wrong_at_end'] for r in rows)} wrong at the end"
    )
    save_results(args.out, "bench_join", dict(args={k: str(v) for k, v in vars(args).items()}, results=rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
