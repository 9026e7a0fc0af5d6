"""`fleet-slam` — one entry point; heavy imports live inside the commands so `--help` is instant."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable, Sequence

Command = Callable[[argparse.Namespace], int]


def _cmd_sim(args: argparse.Namespace) -> int:
    from fleet_slam.simrun import simulate_to_dir

    summary = simulate_to_dir(
        world_name=args.world,
        n_robots=args.robots,
        duration_s=args.duration,
        seed=args.seed,
        out_dir=args.out,
        world_file=args.world_file,
    )
    for line in summary:
        print(line)
    return 0


def _cmd_eval(args: argparse.Namespace) -> int:
    from robot_agent.sources import read_log
    from shared.metrics import read_poses, read_relations, relations_error

    log = read_log(args.log)
    rel = read_relations(args.relations)
    if args.poses:
        stamps, poses = read_poses(args.poses)
        what = args.poses
    else:
        stamps, poses, what = log.stamps_s, log.odometry, "raw odometry"
    err = relations_error(stamps, poses, rel, *log.odometry_track())
    print(f"{what}: {err}")
    return 0


def _cmd_replay(args: argparse.Namespace) -> int:
    from fleet_slam.replayrun import replay_to_dir

    m = replay_to_dir(
        args.log,
        args.out,
        relations_path=args.relations,
        particles=args.particles,
        seed=args.seed,
        overrides=args.set,
        limit=args.limit,
    )
    rtf = m["real_time_factor"]
    print(
        f"{m['robot']}: {m['scans']} scans ({m['processed_scans']} processed) in {m['wall_time_s']:.1f} s"
        f" ({rtf:.1f}x real time), {m['map_segments']} map segments, peak {m['peak_rss_mb']:.0f} MB"
    )
    if "relations" in m:
        r = m["relations"]
        print(
            f"relations error: trans {r['trans_mean_m']:.3f} ± {r['trans_std_m']:.3f} m, "
            f"rot {r['rot_mean_deg']:.2f} ± {r['rot_std_deg']:.2f}° (n={r['n']})"
        )
    print(f"wrote {args.out}/")
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="fleet-slam",
        description="Distributed multi-robot 2D mapping with geometric (line-segment) FastSLAM.",
    )
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")

    s = sub.add_parser(
        "sim",
        help="simulate robots in a world; write CARMEN logs, ground truth, relations and pictures",
        description="Simulate N robots patrolling a world. Writes per robot <robot>.clf (laser + "
        "odometry), <robot>.truth.txt (timestamp x y theta), <robot>.relations (Kümmerle format), "
        "and world.geojson, world.svg, world.png.",
    )
    s.add_argument("--world", default="office", help="built-in world: office, warehouse, campus")
    s.add_argument("--world-file", default=None, help="a GeoJSON world instead of a built-in one")
    s.add_argument("--robots", type=int, default=1, help="number of robots (1–4 for built-in routes)")
    s.add_argument("--duration", type=float, default=120.0, help="simulated seconds")
    s.add_argument("--seed", type=int, default=0, help="random seed (noise, slip bias)")
    s.add_argument("--out", required=True, help="output directory")
    s.set_defaults(func=_cmd_sim)

    r = sub.add_parser(
        "replay",
        help="offline single-robot SLAM over a CARMEN log",
        description="Run the geometric FastSLAM over LOG (.clf or .clf.gz). Writes <robot>.poses.txt "
        "(timestamp x y theta for every scan), <robot>.tum, map.geojson, map.svg, map.png and "
        "metrics.json to --out.",
    )
    r.add_argument("log", help="CARMEN log (.clf or .clf.gz)")
    r.add_argument("--relations", default=None, help="reference relations: print the relations error")
    r.add_argument("--particles", type=int, default=None, help="number of particles (default 30)")
    r.add_argument("--seed", type=int, default=0, help="random seed")
    r.add_argument("--out", default="out/replay", help="output directory")
    r.add_argument("--limit", type=int, default=None, help="only the first N scans")
    r.add_argument(
        "--set", action="append", default=[], metavar="SECTION.KEY=VALUE", help="override a SLAM parameter"
    )
    r.set_defaults(func=_cmd_replay)

    e = sub.add_parser(
        "eval",
        help="relations error of a trajectory (Kümmerle et al. 2009)",
        description="Relations error of POSES (timestamp x y theta per line) against REL for the "
        "CARMEN log LOG; without POSES, the raw odometry of the log is scored.",
    )
    e.add_argument("log", help="CARMEN log (.clf or .clf.gz)")
    e.add_argument("relations", help="relations file: t1 t2 dx dy dz droll dpitch dyaw")
    e.add_argument("poses", nargs="?", default=None, help="trajectory: timestamp x y theta")
    e.set_defaults(func=_cmd_eval)
    return p


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except KeyboardInterrupt:
        return 130
    except (ValueError, OSError) as exc:  # domain errors derive from ValueError
        print(f"fleet-slam {args.command}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
