"""`fleet-slam` — one entry point; heavy imports live inside the commands so `--help` is instant."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

from shared.entry import run_command


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
        live=args.live,
        strict=args.strict,
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
    for row in m.get("live", []):
        if row["n"]:
            print(
                f"  live after {row['scans']} scans ({row['at_s']:.0f} s): "
                f"trans {row['trans_mean_m']:.3f} m, rot {row['rot_mean_deg']:.2f}° (n={row['n']}; "
                f"filter alone {row['filter_trans_mean_m']:.3f} m)"
            )
    if "relations_online" in m:
        r = m["relations_online"]
        print(
            f"  online back end at the end: trans {r['trans_mean_m']:.3f} m, rot {r['rot_mean_deg']:.2f}°; "
            f"{m['online_backend_s']:.1f} s of updates "
            f"({100 * m['online_backend_share']:.1f} % of the log's time)"
        )
    if "relations_note" in m:
        print(f"relations error: none — {m['relations_note']}")
    print(f"wrote {args.out}/")
    return 0


def _cmd_agent(args: argparse.Namespace) -> int:
    from robot_agent.service import run

    return run(args)


def _cmd_server(args: argparse.Namespace) -> int:
    from map_server.service import run

    return run(args)


def _cmd_router(args: argparse.Namespace) -> int:
    from shared.bus import router_main

    return router_main(args.listen, args.bus_config)


def _cmd_subscribe(args: argparse.Namespace) -> int:
    from fleet_slam.subscribe import run

    return run(args)


def _cmd_view(args: argparse.Namespace) -> int:
    from fleet_slam.view import run

    return run(args)


def _cmd_export(args: argparse.Namespace) -> int:
    from fleet_slam.export import run

    return run(args)


def _cmd_demo(args: argparse.Namespace) -> int:
    from fleet_slam.demo import DemoConfig, run_demo
    from fleet_slam.summary import print_summary

    cfg = DemoConfig(
        out=args.out,
        robots=args.robots,
        world=args.world,
        duration_s=args.duration,
        seed=args.seed,
        unknown_starts=args.unknown_starts,
        particles=args.particles,
        speed=args.speed if args.speed is not None else (0.0 if args.log else 1.0),
        log=args.log,
        split=args.split,
        relations=args.relations,
        view=args.view,
        server_set=tuple(args.server_set),
    )
    print_summary(run_demo(cfg), cfg)
    return 0


def _add_fleet_commands(sub) -> None:
    from map_server import service as server
    from robot_agent import service as agent

    d = sub.add_parser(
        "demo",
        help="the main job on one machine: router, map server and N agents as processes on loopback",
        description="Start an embedded zenoh router, the map server and N simulated agents (or K agents "
        "replaying pieces of a real log) as separate processes on 127.0.0.1, show progress, then write "
        "map.geojson/.svg/.png (fused map and paths), world.geojson, per-robot poses/TUM, metrics.json.",
    )
    d.add_argument("--robots", type=int, default=3, help="simulated robots (1-4)")
    d.add_argument("--world", default="office", help="built-in world: office, warehouse, campus")
    d.add_argument("--duration", type=float, default=175.0, help="simulated seconds")
    d.add_argument("--seed", type=int, default=0, help="random seed")
    d.add_argument("--unknown-starts", action="store_true", help="hide the start poses from the server")
    d.add_argument("--particles", type=int, default=None, help="particles per agent (default 30)")
    d.add_argument("--speed", type=float, default=None, help="source s per wall s (sim: 1; log: 0 = max)")
    d.add_argument("--log", default=None, help="a real CARMEN log cut into --split pieces, one agent each")
    d.add_argument("--split", type=int, default=3, help="pieces of --log")
    d.add_argument("--relations", default=None, help="--log: relations file to score the global poses")
    d.add_argument("--out", default="out/demo", help="output directory")
    d.add_argument("--view", action="store_true", help="serve the live web view while the fleet runs")
    d.add_argument(
        "--server-set", action="append", default=[], metavar="SECTION.KEY=VALUE",
        help="override a map-server parameter (the server's --set)",
    )  # fmt: skip
    d.set_defaults(func=_cmd_demo)

    a = sub.add_parser("agent", help=agent.SUMMARY)
    agent.add_arguments(a)
    a.set_defaults(func=_cmd_agent)
    sv = sub.add_parser("server", help=server.SUMMARY)
    server.add_arguments(sv)
    sv.set_defaults(func=_cmd_server)
    ro = sub.add_parser("router", help="a zenoh router process (loopback by default)")
    ro.add_argument("--listen", action="append", default=None, help="endpoint (default tcp/127.0.0.1:7447)")
    ro.add_argument(
        "--bus-config", default=None, metavar="FILE", help="zenoh JSON5 config: TLS, access control (deploy/)"
    )
    ro.set_defaults(func=_cmd_router)
    su = sub.add_parser("subscribe", help="print every fused-map update; optionally save it")
    su.add_argument("--connect", action="append", default=None, help="router endpoint (tcp/127.0.0.1:7447)")
    su.add_argument("--bus-config", default=None, metavar="FILE", help="zenoh config file (TLS; deploy/)")
    su.add_argument("--fleet", default="default", help="fleet id")
    su.add_argument("--once", action="store_true", help="take the latest fused map by query and exit")
    su.add_argument(
        "--save", default=None,
        help="write the map to FILE on every update: .geojson, .svg, or .yaml (a nav2 occupancy grid, "
        "FILE.pgm beside it)",
    )  # fmt: skip
    su.add_argument("--resolution", type=float, default=0.05, help="--save .yaml: metres per cell")
    su.add_argument("--count", type=int, default=None, help="exit after this many updates")
    su.set_defaults(func=_cmd_subscribe)
    ex = sub.add_parser(
        "export", help="write the server's fused map as files: a nav2 occupancy grid, GeoJSON or SVG",
        description="Query the running server for the fused map (and the fleet's free space) and write it. "
        "--format nav2: OUT.yaml + OUT.pgm as nav2's map_server loads them (mode trinary: walls "
        "occupied, the space robots saw free free, the rest unknown); OUT may be a directory (map.yaml).",
    )  # fmt: skip
    ex.add_argument("out", metavar="OUT", help="map.yaml (nav2), map.geojson, map.svg, or a directory")
    ex.add_argument("--format", choices=("nav2", "geojson", "svg"), default="nav2", help="what to write")
    ex.add_argument("--resolution", type=float, default=0.05, help="nav2: metres per cell (default 0.05)")
    ex.add_argument("--connect", action="append", default=None, help="router endpoint (tcp/127.0.0.1:7447)")
    ex.add_argument("--bus-config", default=None, metavar="FILE", help="zenoh config file (TLS; deploy/)")
    ex.add_argument("--fleet", default="default", help="fleet id")
    ex.add_argument("--timeout", type=float, default=5.0, help="seconds to wait for the server's answer")
    ex.set_defaults(func=_cmd_export)
    vw = sub.add_parser(
        "view", help="a live web view of the fleet: fused map, robots, paths, status (loopback page)",
        description="Serve a page that shows the fused map as it changes (pushed, no reloading): segments, "
        "the fleet's free space, each robot's pose and recent path, its alignment status and transform "
        "uncertainty, the map version and age; pan (drag) and zoom (wheel). Nothing is loaded from the "
        "internet.",
    )  # fmt: skip
    vw.add_argument("--connect", action="append", default=None, help="router endpoint (tcp/127.0.0.1:7447)")
    vw.add_argument("--listen", default="127.0.0.1:8090", help="HOST:PORT of the page (port 0: any free one)")
    vw.add_argument("--bus-config", default=None, metavar="FILE", help="zenoh config file (TLS; deploy/)")
    vw.add_argument("--fleet", default="default", help="fleet id")
    vw.set_defaults(func=_cmd_view)


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
        "--strict",
        action="store_true",
        help="refuse a log whose last line is cut short or that has laser lines without beams "
        "(by default they are left out with a warning)",
    )
    r.add_argument(
        "--live",
        type=int,
        nargs="?",
        const=10,
        default=0,
        metavar="K",
        help="also run the online back end as an agent does and score, at every K-th part of the run "
        "(default 10), the trajectory the robot would publish at that moment, on the relations before it "
        "(metrics.json: live, live_worst_trans_m, relations_online)",
    )
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
    _add_fleet_commands(sub)
    return p


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    return run_command(args.command, args.func, args)


if __name__ == "__main__":
    sys.exit(main())
