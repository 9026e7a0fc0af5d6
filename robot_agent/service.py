"""`fleet-slam agent` / `python -m robot_agent`: one robot agent process.

A live simulated robot in a built-in world (patrolling its route, or exploring from its own map),
or a CARMEN log (optionally a piece of it, ``--from``/``--to`` scan indices) replayed at
``--speed`` × real time. Publishes on the bus until the source ends or SIGINT/SIGTERM, then
writes its trajectory (and, simulated, the true one) to ``--out``.
"""

from __future__ import annotations

import argparse
import itertools
import json
import math
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # the parser is built without the heavy imports (instant --help)
    import numpy as np

    from robot_agent.slam.fastslam import Estimate, FastSLAM
    from robot_agent.sources.base import Scan

DEFAULT_FLEET = "default"  # = shared.keys.DEFAULT_FLEET

EXPLORER_MAP_EVERY = 5  # scans between rebuilding the map the explorer plans on
# a simulated robot keeps its scans (ranges as float32) for the map rebuilt along the corrected
# path at the end of its run; beyond this many (1.1 h at 5 Hz, ~14 MB at 180 beams) it stops
# keeping them: the online back end goes on, and its final map is the corrected one, not rebuilt
MAX_KEPT_SCANS = 20_000
SIM_HISTORY_SCANS = 18_000  # a simulated robot runs without end: the filter keeps its path for
# the newest this many scans (1 h at 5 scans/s), and so does the truth beside it; older corrected
# poses live on in the back end's keyframes, older places in the map


def final_correction(core, timeout_s: float) -> tuple:
    """The online back end's last update at the end of a run (within ``timeout_s``): whether it
    came in time, and the stamps, the filter's own path and the corrected path of the best
    particle (the filter continued from the corrections), in the robot's map frame."""
    slam, corrector = core.slam, core.corrector
    done = corrector.finish(timeout_s)
    stamps, now = slam.best_trajectory()
    first_scan = slam.trajectory.first_scan
    return done, stamps, corrector.raw_path(now, first_scan), corrector.corrected_path(now, first_scan)


def rebuild_along(core, scan_log, first: int, filter_poses, poses, cfg):
    """The map rebuilt along the corrected path ``poses`` from the scans ``scan_log[first:]``, put
    in ``core`` to be published next (with the back end's graph); the path moved by the start
    gauge — so that the map frame stays the robot's start frame, what a prior gives, where the
    back end's own gauge put it (its first keyframe's scan: BackendConfig.gauge) — is returned."""
    from robot_agent.backend import remap
    from shared.geometry import compose, inverse

    start = compose(filter_poses[0], inverse(poses[0]))
    if core.corrector.correction.gauge is not None:
        start = compose(core.corrector.correction.gauge, start)
    poses = compose(start, poses)
    graph = (core.corrector.correction, start, core.slam.trajectory.first_scan)
    core.rebuilt(remap(scan_log, first, poses, cfg), poses[-1], graph)
    return poses


def endless_config(cfg):
    """``cfg`` for a source without end (a simulated robot): the path kept for the newest
    SIM_HISTORY_SCANS scans, unless ``--set filter.history_scans`` chose."""
    import dataclasses

    if cfg.filter.history_scans:
        return cfg
    return dataclasses.replace(cfg, filter=dataclasses.replace(cfg.filter, history_scans=SIM_HISTORY_SCANS))


FINAL_UPDATE_STOPPED_S = 5.0  # stopped: the online back end's last update waited for at most this
FINAL_UPDATE_S = 120.0  # the source ended: this long


def parse_pose(text: str, what: str = "pose") -> np.ndarray:
    """``"x,y,theta"`` (m, m, rad) -> array (3,); ValueError naming ``what`` otherwise."""
    import numpy as np

    try:
        v = np.array([float(t) for t in text.split(",")])
    except ValueError:
        raise ValueError(f"{what}: expected X,Y,THETA (m, m, rad), got {text!r}") from None
    if v.shape != (3,) or not np.all(np.isfinite(v)):
        raise ValueError(f"{what}: expected three finite numbers X,Y,THETA, got {text!r}")
    return v


# what `fleet-slam --help` says of the command, and `python -m` of the service run alone
SUMMARY = "one robot agent: FastSLAM on a simulated robot or a log, on the bus"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--robot", required=True, help="robot id ([A-Za-z0-9_-], at most 64)")
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--world", help="a built-in world to simulate: office, warehouse, campus")
    src.add_argument("--log", help="a CARMEN log (.clf, .clf.gz) to replay")
    p.add_argument("--route", type=int, default=0, help="simulated: which of the world's routes (0-3)")
    p.add_argument("--start", default=None, help="simulated: start pose X,Y,THETA (default: the route's)")
    p.add_argument("--explore", action="store_true", help="simulated: explore instead of the route")
    p.add_argument("--duration", type=float, default=None, help="simulated seconds (default: until stopped)")
    p.add_argument("--from", dest="first", type=int, default=0, help="log: first scan index")
    p.add_argument("--to", dest="last", type=int, default=None, help="log: end scan index (exclusive)")
    p.add_argument(
        "--strict",
        action="store_true",
        help="log: refuse it if its last line is cut short or it has laser lines without beams "
        "(by default they are left out with a warning)",
    )
    p.add_argument("--prior", default=None, help="X,Y,THETA: start in the global frame, for the server")
    p.add_argument(
        "--join",
        action="store_true",
        help="take the fleet's fused map at start, find the robot in it and map in its frame (else map "
        "on its own: merged as any robot)",
    )
    p.add_argument("--speed", type=float, default=1.0, help="source seconds per wall second (0: no waiting)")
    p.add_argument("--particles", type=int, default=None, help="particles (default 30)")
    p.add_argument("--seed", type=int, default=0, help="random seed (filter; simulated noise)")
    p.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE", help="SLAM parameter")
    p.add_argument("--connect", action="append", default=None, help="router endpoint (tcp/127.0.0.1:7447)")
    p.add_argument("--bus-config", default=None, metavar="FILE", help="zenoh config file (TLS; deploy/)")
    p.add_argument("--fleet", default=DEFAULT_FLEET, help="fleet id (key prefix fleet/<id>/)")
    p.add_argument("--out", default=None, help="write <robot>.poses.txt, .tum (and .truth.txt) here")
    p.add_argument(
        "--snapshot-at",
        type=float,
        default=None,
        metavar="F",
        help="log: when this share of the scans is done, write the trajectory published then to "
        "--out (<robot>.snapshot.poses.txt, .snapshot.json: the moment, time.monotonic())",
    )


class SimSource:
    """A live simulated robot: scans, truth per scan, and (exploring) velocity from the filter."""

    def __init__(self, args: argparse.Namespace, slam: FastSLAM):
        import numpy as np

        from robot_agent.sim import LiveSim, builtin_world

        world = builtin_world(args.world)
        start = None if args.start is None else parse_pose(args.start, "--start")
        self.sim = LiveSim(world, args.route, seed=args.seed, start=start)
        self.duration_s = args.duration
        from robot_agent.slam.trajectory import GrowingArray

        self.stamps = GrowingArray()  # every scan's (32 bytes a scan with the truth) ...
        self.truth = GrowingArray((3,))
        # ... kept as long as the filter's path
        self.history = 0 if slam is None else slam.cfg.filter.history_scans
        self.explorer = None
        self.core = None  # the agent's (set once made): its filter maps, the explorer reads it
        self._map = np.zeros((0, 2, 2))
        self._ranges: list[np.ndarray] = []  # every scan's, for the back end (MAX_KEPT_SCANS)
        self._odometry: list[np.ndarray] = []
        self._first: Scan | None = None
        if args.explore:
            from robot_agent.explore import Explorer

            self.explorer = Explorer()

    def scans(self) -> Iterator[Scan]:
        import numpy as np

        for scan in self.sim.scans(self.duration_s):
            self.truth.append(self.sim.truth)
            self.stamps.append(scan.stamp_s)
            if self.history and len(self.stamps) > self.history * 5 // 4:
                self.stamps.drop_front(len(self.stamps) - self.history)
                self.truth.drop_front(len(self.truth) - self.history)
            if self._first is None:
                self._first = scan
            if len(self._ranges) < MAX_KEPT_SCANS:
                self._ranges.append(np.asarray(scan.ranges_m, dtype=np.float32))
                self._odometry.append(np.asarray(scan.odometry, dtype=float))
            yield scan

    def recorded_log(self):
        """The scans so far as a :class:`~robot_agent.sources.LaserLog` (what the back end
        reads), or ``None`` when there are none or more than MAX_KEPT_SCANS were made."""
        from robot_agent.sources import LaserLog

        if self._first is None or len(self._ranges) != len(self.stamps):
            return None
        f = self._first  # the sim's beams, laser mount and range are the same in every scan
        return LaserLog.from_arrays(
            self.stamps.view(), self._ranges, f.angles_rad, self._odometry, f.laser_offset, f.range_max_m
        )

    def on_estimate(self, scan: Scan, est: Estimate) -> None:
        if self.explorer is None:
            return
        if len(self.stamps) % EXPLORER_MAP_EVERY == 1:
            gm, _ = self.core.slam.published_map()
            self._map = gm.seg
        v, w = self.explorer.command(
            scan.stamp_s, est.pose, self._map, scan.ranges_m, scan.angles_rad, scan.laser_offset,
            scan.range_max_m,
        )  # fmt: skip
        self.sim.set_velocity(v, w)

    def write_truth(self, out: Path, robot: str) -> None:
        from shared.metrics import write_poses

        write_poses(out / f"{robot}.truth.txt", self.stamps.view(), self.truth.view())


class SnapshotWriter:
    """At scan ``at``: the trajectory the robot publishes then (the filter's path as the online
    back end's latest correction moves it) to ``out``, with the moment (``time.monotonic()``)."""

    def __init__(self, out: Path, robot: str, at: int):
        self.out, self.robot, self.at = out, robot, at

    def __call__(self, core) -> None:
        if core.scans != self.at:
            return
        from shared.metrics import write_poses

        stamps, poses = core.slam.best_trajectory()
        if core.corrector is not None:
            poses = core.corrector.corrected_path(poses, core.slam.trajectory.first_scan)
        self.out.mkdir(parents=True, exist_ok=True)
        write_poses(self.out / f"{self.robot}.snapshot.poses.txt", stamps, poses)
        info = {"monotonic_s": time.monotonic(), "scans": core.scans}
        (self.out / f"{self.robot}.snapshot.json").write_text(json.dumps(info))


STUCK_QUIET_SCANS = 50  # scans without a stuck step that end a run of them


class OdometryReport:
    """One line per odometry jump the scans contradicted (:attr:`FastSLAM.odometry_jumps`), one
    per run of steps the scans moved while odometry stood (:attr:`FastSLAM.odometry_stuck`:
    said at its first step, and when it ends, with how many steps and how far), one per doubt
    whether the robot was moved unseen and one at its end (:attr:`FastSLAM.kidnap_events`:
    found elsewhere in the map, odometry erred, or lost — a new session)."""

    def __init__(self, robot: str):
        self.robot = robot
        self._slam = None
        self._said = 0
        self._stuck_said = 0
        self._stuck_run: list = []  # the steps of the run of stuck steps going on
        self._kidnap_said = 0

    def __call__(self, core) -> None:
        slam = core.slam
        if slam is not self._slam:  # a new session (the filter lost the robot): counts restart
            if self._slam is not None and core.ended:
                self._kidnap(core, self._slam, core.ended[-1][1])
                print(
                    f"agent {self.robot}: warning: lost at scan {core.ended[-1][2]}: the robot is nowhere "
                    f"in its map and its estimate fits nothing; session {core.ended[-1][0]} ends with "
                    f"the map as it was before the doubt, a new one begins (session {core.session})",
                    flush=True,
                )
            self._slam, self._said, self._stuck_said, self._stuck_run, self._kidnap_said = slam, 0, 0, [], 0
        self._kidnap(core, slam, core.first_scan)
        n = slam.stats.get("odometry_jumps", 0)
        if n != self._said:
            for scan, u, there, stay in list(slam.odometry_jumps)[-(n - self._said) :]:
                print(
                    f"agent {self.robot}: warning: odometry jumped {math.hypot(u[0], u[1]):.1f} m and "
                    f"{math.degrees(u[2]):.0f}° at scan {scan}; the scan fits the map where the robot "
                    f"was ({stay:.2f} of its points) and not where odometry put it ({there:.2f}): that "
                    "increment is not used",
                    flush=True,
                )
            self._said = n
        self._stuck(slam)

    def _kidnap(self, core, slam, first: int) -> None:
        """One line per doubt and one per its end (:mod:`robot_agent.slam.kidnap`); scans are
        counted over the run (``first``: the session's first)."""
        st = slam.stats
        n = (
            st.get("kidnap_doubts", 0)
            + st.get("kidnappings", 0)
            + st.get("kidnap_cleared", 0)
            + st.get("lost", 0)
        )
        new = list(slam.kidnap_events)[-(n - self._kidnap_said) :] if n > self._kidnap_said else []
        self._kidnap_said = n
        for scan, what, move in new:
            at = first + scan
            if what == "doubt":
                print(
                    f"agent {self.robot}: warning: from scan {at} the scans disagree with odometry (moved "
                    "without odometry seeing it?): the map is held while the agent looks for where it is",
                    flush=True,
                )
            elif what == "moved":
                print(
                    f"agent {self.robot}: warning: the robot was moved: found at scan {at} "
                    f"{math.hypot(move[0], move[1]):.1f} m and {math.degrees(move[2]):.0f}° from where "
                    "odometry put it, in its own map; it goes on from there",
                    flush=True,
                )
            elif what == "cleared":
                print(
                    f"agent {self.robot}: odometry erred, the robot was not moved (scan {at}: its estimate "
                    "fitted the map throughout): mapping goes on",
                    flush=True,
                )

    def _stuck(self, slam) -> None:
        n = slam.stats.get("odometry_stuck", 0)
        new = list(slam.odometry_stuck)[-(n - self._stuck_said) :] if n > self._stuck_said else []
        self._stuck_said = n
        for scan, _, u in new:
            if not self._stuck_run:
                print(
                    f"agent {self.robot}: warning: odometry stands while the scans move (scan {scan}: "
                    f"{math.hypot(u[0], u[1]):.2f} m, {math.degrees(u[2]):.0f}°): a stuck wheel? the "
                    "scans drive the steps until odometry moves again",
                    flush=True,
                )
            self._stuck_run.append((scan, u))
        last = self._stuck_run[-1][0] if self._stuck_run else None
        if last is not None and len(slam.trajectory) - 1 - last > STUCK_QUIET_SCANS:
            moved = sum(math.hypot(u[0], u[1]) for _, u in self._stuck_run)
            print(
                f"agent {self.robot}: odometry moves again (from scan {last}): {len(self._stuck_run)} "
                f"steps, {moved:.1f} m driven by the scans",
                flush=True,
            )
            self._stuck_run = []


class LaserReport:
    """What the laser gave that could not be used: one line at most every ``every_s`` of wall time
    while scans hold unusable readings (counts by kind since the last line), and a warning as the
    laser goes mostly blind (and a line when it sees again)."""

    def __init__(self, robot: str, every_s: float = 10.0, clock=time.monotonic):
        self.robot, self.every_s, self.clock = robot, every_s, clock
        self._next = 0.0
        self._said = {"scans": 0, "unusable": 0, "by_kind": {}}
        self._blind = False

    def __call__(self, core) -> None:
        h = core.health
        if h.blind != self._blind:
            self._blind = h.blind
            if h.blind:
                print(
                    f"agent {self.robot}: warning: the laser is mostly blind: "
                    f"{100 * h.recent_share:.0f} % of its readings over the last scans are unusable "
                    "(the map and pose rest on what is left, and on odometry)",
                    flush=True,
                )
            else:
                print(f"agent {self.robot}: the laser sees again", flush=True)
        now = self.clock()
        if h.unusable == self._said["unusable"] or now < self._next:
            return
        self._next = now + self.every_s
        new = {k: v - self._said["by_kind"].get(k, 0) for k, v in h.by_kind.items()}
        kinds = ", ".join(f"{k} {v}" for k, v in new.items() if v)
        scans = h.scans_with_unusable - self._said["scans"]
        bad = h.unusable - self._said["unusable"]
        print(
            f"agent {self.robot}: {bad} unusable laser readings in {scans} scans since the last report "
            f"({kinds}); the last scan {h.last_unusable} of {h.last_readings}; dropped",
            flush=True,
        )
        self._said = {"scans": h.scans_with_unusable, "unusable": h.unusable, "by_kind": dict(h.by_kind)}


JOIN_QUERY_S = 5.0  # --join: how long the agent waits for the server's fused map at its start


def fetch_fused(bus, keys, robot: str, timeout_s: float = JOIN_QUERY_S):
    """``--join``: the fleet's fused map by query (the server's queryable), or None (said why)."""
    from fleet_slam.watch import FusedWatcher

    fused = FusedWatcher(bus, keys).fetch(timeout_s)
    if fused is None or not len(fused.seg):
        why = "no fused map answered (is the server running?)" if fused is None else "the fused map is empty"
        print(f"agent {robot}: --join: {why}; mapping on its own", flush=True)
        return None
    print(f"agent {robot}: --join: fused map version {fused.version}, {len(fused.seg)} segments", flush=True)
    return fused


class JoinReport:
    """Says once whether the robot found itself in the fused map (--join), and where."""

    def __init__(self, robot: str):
        self.robot, self.said = robot, False

    def __call__(self, core) -> None:
        j = core.joiner
        if self.said or j is None or not j.done:
            return
        self.said = True
        if j.transform is not None:
            x, y, t = j.transform
            print(
                f"agent {self.robot}: joined the fused map after {j.attempts} attempts: map frame at "
                f"{x:.2f},{y:.2f},{t:.4f} ({j.last.reason})",
                flush=True,
            )
        else:
            why = j.last.reason if j.last is not None else "no attempt"
            print(f"agent {self.robot}: --join: not found in the fused map ({why}); maps alone", flush=True)


class BackendReport:
    """One line when the online back end's loops change, at most every ``every_s`` of wall time
    (the agent's back end, ``core.corrector``: a new session has a new one)."""

    def __init__(self, robot: str, every_s: float = 10.0):
        self.robot, self.every_s = robot, every_s
        self.corrector = None
        self._loops = 0
        self._next = 0.0
        self._failures = 0

    def __call__(self, core) -> None:
        if core.corrector is not self.corrector:  # a new session's back end
            self.corrector, self._loops, self._failures = core.corrector, 0, 0
        if self.corrector is None:
            return
        if self.corrector.failures != self._failures:  # every one: they should never happen
            self._failures = self.corrector.failures
            print(
                f"agent {self.robot}: warning: the online back end could not update "
                f"({self._failures} so far): {self.corrector.last_failure}; the map keeps the last "
                "correction",
                flush=True,
            )
        loops = self.corrector.stats.get("loops", 0)
        now = time.monotonic()
        if loops != self._loops and now >= self._next:
            self._loops, self._next = loops, now + self.every_s
            st = self.corrector.stats
            bounds = ""  # what the bounds of a run without end dropped so far
            forgot = core.slam.stats.get("scans_forgotten", 0)
            if forgot or st.get("retired_thinned", 0):
                bounds = (
                    f"; bounds: path of the oldest {forgot} scans forgotten, "
                    f"{st.get('retired_thinned', 0)} keyframes thinned from the graph"
                )
            print(
                f"agent {self.robot}: online back end: {loops} loops, {st.get('keyframes', 0)} keyframes, "
                f"{self.corrector.updates} updates (longest {st.get('update_s_max', 0.0):.2f} s){bounds}",
                flush=True,
            )


def run(args: argparse.Namespace) -> int:
    import numpy as np

    from robot_agent.agent import AgentConfig, AgentCore, run_agent
    from robot_agent.publish import PublishConfig
    from robot_agent.slam.config import command_line_config
    from robot_agent.slam.fastslam import FastSLAM
    from shared.bus import Bus, client_config, stop_on_signals
    from shared.keys import Keys
    from shared.metrics import write_poses, write_tum

    cfg = command_line_config(args.set, args.particles)
    if args.world is not None:
        cfg = endless_config(cfg)
    if args.speed < 0:
        raise ValueError(f"--speed must be >= 0, got {args.speed}")
    if args.snapshot_at is not None and not 0 < args.snapshot_at < 1:
        raise ValueError(f"--snapshot-at must be between 0 and 1, got {args.snapshot_at}")
    prior = None if args.prior is None else parse_pose(args.prior, "--prior")
    if prior is not None and getattr(args, "join", False):
        raise ValueError("--prior and --join: choose one (--join finds the map frame in the fused map)")
    slam = FastSLAM(cfg, np.random.default_rng(args.seed))
    corrector = None
    if cfg.backend.enabled:  # the online back end, in a process of its own
        from robot_agent.backend.live import LiveCorrector, ProcessRunner

        def new_corrector(s):
            return LiveCorrector(s, ProcessRunner(cfg))

        corrector = new_corrector(slam)
    core = AgentCore(
        args.robot,
        slam,
        AgentConfig(speed=args.speed, publish=PublishConfig()),
        prior=prior,
        corrector=corrector,
        new_corrector=None if corrector is None else new_corrector,
    )
    keys = Keys(args.fleet)
    sim = None
    if args.world is not None:
        sim = SimSource(args, slam)
        sim.core = core
        scans, on_estimate = sim.scans(), sim.on_estimate
    else:
        from robot_agent.sources import read_log

        laser_log = read_log(args.log, progress=False, strict=getattr(args, "strict", False))
        for warning in laser_log.warnings:  # what the reader could not use and what it did instead
            print(f"agent {args.robot}: warning: {warning}", flush=True)
        scans = itertools.islice(laser_log.scans(), args.first, args.last)
        on_estimate = None
    stop = threading.Event()
    stop_on_signals(stop)
    bus_cfg = client_config(args.connect, args.bus_config)
    t0 = time.monotonic()
    backend = None
    try:
        with Bus(bus_cfg, cancel=stop) as bus:
            print(f"agent {args.robot}: session {core.session}, connected", flush=True)
            if getattr(args, "join", False) and (fused := fetch_fused(bus, keys, args.robot)) is not None:
                from robot_agent.join import Joiner

                core.joiner = Joiner(fused.seg)
            hooks = [
                JoinReport(args.robot),
                BackendReport(args.robot),
                LaserReport(args.robot),
                OdometryReport(args.robot),
            ]
            if args.snapshot_at is not None and args.out and args.log is not None:
                n = (args.last if args.last is not None else len(laser_log)) - args.first
                hooks.append(SnapshotWriter(Path(args.out), args.robot, max(1, round(args.snapshot_at * n))))

            def on_progress(c) -> None:
                for hook in hooks:
                    hook(c)

            pub = run_agent(bus, keys, core, scans, stop, on_estimate, on_progress)
            slam, corrector = core.slam, core.corrector  # the last session's (the filter lost the
            # robot and began anew: core.ended)
            stamps, filter_poses = slam.best_trajectory()  # the best particle's, in the robot's map frame
            poses = filter_poses
            if corrector is not None and len(poses):
                # the last update of the online back end: bounded when stopped (SIGTERM/SIGINT:
                # the whole exit within 10 s), complete when the source ended
                timeout_s = FINAL_UPDATE_STOPPED_S if stop.is_set() else FINAL_UPDATE_S
                done, stamps, filter_poses, poses = final_correction(core, timeout_s)
                backend = dict(corrector.stats, final_update_in_time=done, updates=corrector.updates)
                pub.publish(force_map=True)  # the map and pose as the last correction moves them
                print(
                    f"agent {args.robot}: published the corrected map ({backend.get('loops', 0)} loops, "
                    f"{backend.get('keyframes', 0)} keyframes{'' if done else ', last update not in time'})",
                    flush=True,
                )
            # at the end of the source (not when stopped), with its scans at hand: the map rebuilt
            # along the corrected path, published last, so the server places the robot by the map
            # its written poses agree with
            first, scan_log = (0, sim.recorded_log()) if sim is not None else (args.first, laser_log)
            first += core.first_scan
            if corrector is not None and len(poses) and not stop.is_set() and scan_log is not None:
                poses = rebuild_along(core, scan_log, first, filter_poses, poses, cfg)
                pub.publish(force_map=True)
                print(f"agent {args.robot}: published the map rebuilt along the corrected path", flush=True)
            elif scan_log is None and len(poses) and not stop.is_set():  # a long simulated run
                print(
                    f"agent {args.robot}: more than {MAX_KEPT_SCANS} scans kept no longer: the final map "
                    "is the online back end's corrected one, not rebuilt",
                    flush=True,
                )
    finally:
        if core.corrector is not None:
            core.corrector.close()
    wall = time.monotonic() - t0
    if args.out:
        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        write_poses(out / f"{args.robot}.filter.poses.txt", stamps, filter_poses)
        write_poses(out / f"{args.robot}.poses.txt", stamps, poses)  # the last session's
        # each ended session's path, in its own frame
        for (ses, *_), (s_stamps, s_poses) in zip(core.ended, core.ended_paths, strict=True):
            write_poses(out / f"{args.robot}.{ses}.poses.txt", s_stamps, s_poses)
        write_tum(out / f"{args.robot}.tum", stamps, poses)
        if sim is not None:
            sim.write_truth(out, args.robot)
        span = float(np.ptp(stamps)) if len(stamps) else 0.0
        summary = {
            "robot": args.robot,
            "session": core.session,
            "scans": core.scans,
            "processed_scans": slam.step_index,
            "poses_from_scan": slam.trajectory.first_scan,  # a run without end writes its newest path
            "wall_time_s": wall,
            "source_duration_s": span,
            "bytes_sent": pub.bytes_sent,
            "messages_sent": pub.messages_sent,
            "map_seq": core.map_seq,
            "prior": None if prior is None else prior.tolist(),
            "joined": core.prior.tolist() if core.joined else None,  # the map frame in the fused map
            "filter": dict(slam.stats),
            "sessions_ended": [  # each one's path in <robot>.<session>.poses.txt
                dict(session=ses, first_scan=a, last_scan=b, filter=st) for ses, a, b, st in core.ended
            ],
            "backend": backend,
            "laser": dict(
                core.health.status(), **{f"unusable_{k}": v for k, v in core.health.by_kind.items()}
            ),
        }
        (out / f"{args.robot}.agent.json").write_text(json.dumps(summary, indent=2))
    print(f"agent {args.robot}: {core.scans} scans, {pub.bytes_sent['map']} map bytes, done", flush=True)
    return 0
