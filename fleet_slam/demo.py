"""`fleet-slam demo`: the whole fleet on one machine — an embedded zenoh router, the map server and
N agents, each a separate process on loopback — with a progress display, then the outputs of
docs/design.md (see :mod:`fleet_slam.report`).

Two kinds of fleet: simulated robots patrolling the routes of a built-in world (known starts are
sent as priors unless ``unknown_starts``), or a real CARMEN log cut into ``split`` consecutive
pieces, each replayed by its own agent that starts in its own frame with no prior.
"""

from __future__ import annotations

import itertools
import json
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from fleet_slam.procs import ProcGroup, free_port, python_module
from fleet_slam.watch import FusedWatcher, Update, fetch_paths

STARTUP_TIMEOUT_S = 60.0
SETTLE_QUIET_S = 3.0  # after the agents end: the fused map is final when quiet this long
SETTLE_TIMEOUT_S = 30.0
FREE_QUIET_S = 3.0  # the free space is final when its version holds this long (fused every 2 s at most)
FREE_TIMEOUT_S = 15.0
# --log: pieces replayed at full speed end within a minute or so, before the server calls their
# maps mature (grown <= 25 % over 30 s of its time) and confirms a match (two attempts ~10 s
# apart); the demo then waits this long at most for every piece to be placed
LOG_LINGER_S = 120.0


@dataclass(frozen=True)
class DemoConfig:
    out: str = "out/demo"
    robots: int = 3
    world: str = "office"
    duration_s: float = 175.0
    seed: int = 0
    unknown_starts: bool = False
    particles: int | None = None
    speed: float = 1.0  # simulated: 1 = real time; a log: 0 = as fast as the agents go
    log: str | None = None
    split: int = 3
    relations: str | None = None
    progress: bool | None = None  # None: when stderr is a terminal
    fleet: str = "default"
    view: bool = False  # serve the live web view (fleet-slam view) while the fleet runs
    view_listen: str = "127.0.0.1:8090"  # its address (a busy port: any free one)
    server_set: tuple[str, ...] = ()  # the map server's --set overrides (FleetConfig)

    def robot_names(self) -> list[str]:
        return [f"robot{i + 1}" for i in range(self.split if self.log else self.robots)]


def _agent_args(
    cfg: DemoConfig, i: int, name: str, endpoint: str, agents_dir: Path, split: LogSplit | None
) -> list[str]:
    args = ["--robot", name, "--connect", endpoint, "--fleet", cfg.fleet, "--out", agents_dir]
    args += ["--seed", cfg.seed * 100 + i, "--speed", cfg.speed]
    if cfg.particles is not None:
        args += ["--particles", cfg.particles]
    if cfg.log:
        a, b = split.pieces[i]
        return [*args, "--log", cfg.log, "--from", a, "--to", b, "--snapshot-at", 0.5]
    from robot_agent.sim import builtin_world

    world = builtin_world(cfg.world)
    args += ["--world", cfg.world, "--route", i, "--duration", cfg.duration_s]
    if not cfg.unknown_starts:
        args += ["--prior", ",".join(f"{v:.9g}" for v in world.starts[i])]
    return args


def log_pieces(n_scans: int, k: int) -> list[tuple[int, int]]:
    """``k`` consecutive scan ranges covering ``n_scans``."""
    if k < 1 or k > n_scans:
        raise ValueError(f"--split must be between 1 and the number of scans ({n_scans}), got {k}")
    edges = np.linspace(0, n_scans, k + 1).round().astype(int)
    return [(int(a), int(b)) for a, b in itertools.pairwise(edges)]


@dataclass(frozen=True)
class LogSplit:
    """A real log (read once) and the scan ranges of its pieces, one agent each."""

    log: object  # robot_agent.sources.LaserLog
    pieces: list[tuple[int, int]]


def _check(cfg: DemoConfig) -> LogSplit | None:
    if cfg.server_set:  # a bad override fails here, not in the server's log
        from map_server.service import fleet_config

        fleet_config(list(cfg.server_set))
    if cfg.log:
        from robot_agent.sources import read_log

        log = read_log(cfg.log, progress=False)
        return LogSplit(log, log_pieces(len(log), cfg.split))
    from robot_agent.sim import builtin_world

    world = builtin_world(cfg.world)
    if not 1 <= cfg.robots <= len(world.routes):
        raise ValueError(f"--robots must be 1..{len(world.routes)} for world {cfg.world!r}, got {cfg.robots}")
    if not cfg.duration_s > 0:
        raise ValueError(f"--duration must be positive, got {cfg.duration_s}")
    return None


def run_demo(cfg: DemoConfig) -> dict:
    """Run the fleet, write the outputs to ``cfg.out``, return the metrics."""
    from fleet_slam.report import write_report
    from shared.bus import Bus, BusConfig
    from shared.keys import Keys

    split = _check(cfg)
    out = Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    agents_dir = out / "agents"
    for stale in [*agents_dir.glob("*"), *(out / "state").glob("**/*")]:
        if stale.is_file():
            stale.unlink()
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    names = cfg.robot_names()
    show = sys.stderr.isatty() if cfg.progress is None else cfg.progress
    t_start = time.monotonic()
    with ProcGroup(out / "logs") as group:
        router = group.start("router", python_module("shared.bus", "router", "--listen", endpoint))
        if not router.wait_for("listening", STARTUP_TIMEOUT_S):
            raise RuntimeError(f"the router did not start; see {router.log_path}")
        server = group.start(
            "server",
            python_module(
                "map_server",
                "--connect",
                endpoint,
                "--state",
                out / "state",
                "--fleet",
                cfg.fleet,
                *(a for kv in cfg.server_set for a in ("--set", kv)),
            ),
        )
        if not server.wait_for("running", STARTUP_TIMEOUT_S):
            raise RuntimeError(f"the server did not start; see {server.log_path}")
        if cfg.view:
            _start_view(group, cfg, endpoint)
        with Bus(BusConfig(connect=(endpoint,))) as bus:
            watcher = FusedWatcher(bus, Keys(cfg.fleet))
            watcher.start(query_timeout_s=0.5)
            t_agents = time.monotonic()
            agents = [
                group.start(
                    n, python_module("robot_agent", *_agent_args(cfg, i, n, endpoint, agents_dir, split))
                )
                for i, n in enumerate(names)
            ]
            _follow(agents, watcher, cfg, show, t_agents)
            failed = [a.name for a in agents if a.popen.wait() != 0]
            if failed:
                raise RuntimeError(f"agents failed: {failed}; see {out / 'logs'}")
            if cfg.log:
                everyone = len(names)
                watcher.wait_for(lambda f: sum(r.merged for r in f.robots) == everyone, LOG_LINGER_S)
            final = watcher.wait_quiet(SETTLE_QUIET_S, SETTLE_TIMEOUT_S)
            final = watcher.fetch(2.0) or final
            paths = fetch_paths(bus, Keys(cfg.fleet))
            updates = list(watcher.updates)
            free = _settled_free(bus, Keys(cfg.fleet))
        server.stop()
        router.stop()
    if final is None:
        raise RuntimeError(f"no fused map was received; see {out / 'logs' / 'server.log'}")
    metrics = write_report(cfg, out, final, updates, t_agents, agents_dir, split, free, paths)
    metrics["wall_time_s"] = time.monotonic() - t_start
    metrics["config"] = asdict(cfg)
    (out / "metrics.json").write_text(json.dumps(metrics, indent=2))
    return metrics


def _start_view(group: ProcGroup, cfg: DemoConfig, endpoint: str) -> None:
    """The live web view as one more process of the fleet; prints its address."""
    import socket

    from fleet_slam.view import parse_listen

    host, port = parse_listen(cfg.view_listen)
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        try:
            s.bind((host, port))
        except OSError:
            port = 0  # taken: any free port (the view prints which)
    view = group.start(
        "view", python_module("fleet_slam.cli", "view", "--connect", endpoint, "--listen", f"{host}:{port}",
                              "--fleet", cfg.fleet),
    )  # fmt: skip
    if not view.wait_for("view: http", STARTUP_TIMEOUT_S):
        raise RuntimeError(f"the view did not start; see {view.log_path}")
    line = next(t for t in view.output().splitlines() if t.startswith("view: http"))
    print(f"live view: {line.split()[1]}  (open it in a browser; it stops with the demo)", flush=True)


def _settled_free(bus, keys):
    """The fleet's free space once the server has fused the last of it (its fusions are spaced
    ``min_gap_s`` = 2 s apart): the newest version, unchanged for FREE_QUIET_S."""
    from fleet_slam.export import FreeWatcher

    watcher = FreeWatcher(bus, keys)
    deadline = time.monotonic() + FREE_TIMEOUT_S
    last, since = None, time.monotonic()
    while time.monotonic() < deadline:
        f = watcher.fetch(1.0)
        key = None if f is None else (f.session, f.version)
        if key != last:
            last, since = key, time.monotonic()
        elif f is not None and time.monotonic() - since >= FREE_QUIET_S:
            break
        time.sleep(0.5)
    return watcher.latest


def _status_line(upd: Update | None, t0: float, names: list[str]) -> str:
    if upd is None:
        return "waiting for the first fused map"
    f = upd.fused
    parts = []
    for n in names:
        r = f.robot(n)
        parts.append(f"{n}:{r.status if r else '-'}")
    return f"t={upd.wall_s - t0:5.0f}s fused v{f.version}: {len(f.seg)} segments, " + " ".join(parts)


def _follow(agents, watcher: FusedWatcher, cfg: DemoConfig, show: bool, t0: float) -> None:
    """Wait for the agents to end, showing progress."""
    names = [a.name for a in agents]
    total = None if cfg.log else cfg.duration_s / max(cfg.speed, 1e-9)
    if show:
        from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

        with Progress(
            TextColumn("{task.description}"), BarColumn(), TimeElapsedColumn(), transient=False
        ) as bar:
            task = bar.add_task("fleet", total=total)
            while any(a.running for a in agents):
                latest = watcher.updates[-1] if watcher.updates else None
                bar.update(task, completed=time.monotonic() - t0, description=_status_line(latest, t0, names))
                time.sleep(0.5)
            bar.update(task, completed=total)
    else:
        last_print = 0.0
        while any(a.running for a in agents):
            if time.monotonic() - last_print >= 15.0:
                last_print = time.monotonic()
                latest = watcher.updates[-1] if watcher.updates else None
                print(_status_line(latest, t0, names), flush=True)
            time.sleep(0.5)
