"""Joining a mapped building (``fleet-slam agent --join``; issue 21, item 3): how often and how soon
a robot finds itself in the fused map, and how often it takes a wrong place.

    .venv/bin/python benchmarks/bench_join.py [--worlds office warehouse] [--first-s 120]
        [--join-s 40] [--jobs 2]

For every ordered pair (a, b) of a world's routes, without processes or network: robot a's route is
mapped for ``--first-s`` simulated seconds (a FastSLAM replay; its published map is the fleet's
fused map, robot a the reference: its start frame is the global frame). Robot b's agent then starts
with the Joiner (robot_agent/join.py) on that fused map, its scans fed in time order for
``--join-s``; each map it publishes goes into ``map_server.fleet.Fleet`` with a fusion after it.
A row per pair: when the agent took a place (and how far from the truth), when and where the
fleet placed robot b, or why the agent found no place. A *wrong join* is a place farther than
0.3 m / 3° from the truth (as a wrong merge is counted).

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

from map_server.config import FleetConfig  # noqa: E402
from map_server.fleet import Fleet  # noqa: E402
from robot_agent.agent import AgentConfig, AgentCore  # noqa: E402
from robot_agent.join import Joiner  # noqa: E402
from robot_agent.publish import PublishConfig, top_particle_maps  # noqa: E402
from robot_agent.replay import replay  # noqa: E402
from robot_agent.sim import SimConfig, builtin_world, simulate_robot  # noqa: E402
from robot_agent.slam.fastslam import FastSLAM, SlamConfig  # noqa: E402
from shared.geometry import relative  # noqa: E402
from shared.messages import RobotMap  # noqa: E402

WRONG_M, WRONG_RAD = 0.3, np.radians(3.0)


def fused_of(world_name: str, route: int, first_s: float) -> Fleet:
    """A fleet holding robot ``route``'s published map after ``first_s`` of its route (reference)."""
    sim = simulate_robot(builtin_world(world_name), route, first_s, 0, SimConfig())
    slam = replay(sim.to_log(), SlamConfig(), seed=0, progress=False).slam
    a = top_particle_maps(slam, PublishConfig())
    m = RobotMap(
        "robot1", "s1", 1, first_s, 0, 1, a.particle_weights, a.particle_poses, a.seg, a.element, a.members,
        a.trust, a.hits, a.age,
    )  # fmt: skip
    fleet = Fleet(FleetConfig(), "bench")
    fleet.put_map(m, 0.0)
    fleet.fuse(0.0)
    return fleet


def run_pair(job: tuple) -> dict:
    world_name, a, b, first_s, join_s = job
    world = builtin_world(world_name)
    truth = relative(world.starts[a], world.starts[b])
    fleet = fused_of(world_name, a, first_s)
    fused = fleet.latest()
    core = AgentCore("robot2", FastSLAM(SlamConfig(), np.random.default_rng(b + 1)), AgentConfig(speed=0))
    core.joiner = Joiner(fused.seg)
    row = dict(world=world_name, mapped=a, joining=b, fused_segments=len(fused.seg), joined_s=None,
               join_error_m=None, join_error_deg=None, placed_s=None, placed_status=None, placed_error_m=None,
               placed_error_deg=None, reason="")  # fmt: skip
    sim = simulate_robot(world, b, join_s, b + 1, SimConfig())
    t0 = None
    for scan in sim.to_log().scans():
        t0 = scan.stamp_s if t0 is None else t0
        now = float(scan.stamp_s - t0)
        core.step(scan)
        if core.joined and row["joined_s"] is None:
            e = relative(truth, core.prior)
            row.update(
                joined_s=now, join_error_m=float(np.hypot(e[0], e[1])), join_error_deg=float(np.degrees(e[2]))
            )
        msgs = core.map_messages()
        if msgs and row["placed_s"] is None:
            fleet.put_map(msgs[0], now)
            f = fleet.fuse(now)
            s = f.robot("robot2") if f is not None else None
            if s is not None and s.status != "unaligned":
                e = relative(truth, s.transform)
                row.update(placed_s=now, placed_status=s.status, placed_error_m=float(np.hypot(e[0], e[1])),
                           placed_error_deg=float(np.degrees(e[2])))  # fmt: skip
    j = core.joiner
    row["reason"] = j.last.reason if j is not None and j.last is not None else ""
    row["wrong_join"] = row["joined_s"] is not None and (
        row["join_error_m"] > WRONG_M or abs(np.radians(row["join_error_deg"])) > WRONG_RAD
    )
    return row


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--worlds", nargs="+", default=["office", "warehouse"])
    p.add_argument("--first-s", type=float, default=120.0, help="simulated seconds of the mapped robot")
    p.add_argument("--join-s", type=float, default=40.0, help="simulated seconds of the joining robot")
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
        f"{'world':10s} {'map':>3s} {'join':>4s} {'joined':>7s} {'error':>14s} {'placed':>7s} {'as':>8s}  why"
    )
    for r in rows:
        joined = "-" if r["joined_s"] is None else f"{r['joined_s']:.1f} s"
        err = "" if r["joined_s"] is None else f"{r['join_error_m']:.3f} m {r['join_error_deg']:.2f}°"
        placed = "-" if r["placed_s"] is None else f"{r['placed_s']:.1f} s"
        why = ("WRONG " if r["wrong_join"] else "") + r["reason"]
        print(f"{r['world']:10s} {r['mapped']:3d} {r['joining']:4d} {joined:>7s} {err:>14s} {placed:>7s} "
              f"{r['placed_status'] or '-':>8s}  {why}")  # fmt: skip
    right = [r for r in rows if r["joined_s"] is not None and not r["wrong_join"]]
    wrong = [r for r in rows if r["wrong_join"]]
    alone = [r for r in rows if r["joined_s"] is None]
    times = [r["joined_s"] for r in right]
    print(
        f"{len(rows)} joins: {len(right)} at the true place"
        + (f" ({min(times):.0f}-{max(times):.0f} s after the start)" if times else "")
        + f", {len(wrong)} wrong, {len(alone)} found no place (mapped alone)"
    )
    save_results(args.out, "bench_join", dict(args={k: str(v) for k, v in vars(args).items()}, results=rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
