"""Fleet benchmarks: fusion time vs robots and segments; agent-put -> fused-map latency on loopback;
bytes per robot per second against a 5 cm occupancy grid of the same area.

    .venv/bin/python benchmarks/bench_fleet.py [--only fusion|latency|bytes] [--quick]
        [--robots 1 2 4 8 16 32 100] [--sizes 100 300 1000] [--reps 12] [--no-priors-max 16]
        [--agents 1 4 8 16] [--seconds 40] [--min-gap 0.05] [--leave K] [--profile] [--cache DIR]
        [--refresh] [--workdir DIR] [--out FILE]

Maps are real agent maps: simulated robots (worlds office, warehouse, campus; routes 0-3; seeds 0
and 1; 60 s each) run FastSLAM through ``AgentCore``, and every map publication, pose update and
scan is recorded once, two robots at a time, and cached in ``--cache`` (``--refresh`` records
again). A map's *segments* are its rows as sent: the versions of its elements held by the K = 5
top particles (2 to 4 rows per distinct element in these maps).

fusion   ``Fleet.fuse`` in this process. A robot map of S segments is a row of real maps laid side
         by side (:func:`tiles_for`); robot i starts its row at the i-th recorded map, so the
         robots' maps overlap like robots sharing one building. With start priors: the first
         fusion (places every robot, refining its prior), the steady state (one robot's new map:
         its cross-particle fusion + the merge of what it changed) and the fusions that re-refine
         priors (Fleet refines a few due robots per fusion: ``refine_budget_segments``); "all" is
         every fusion after one robot's new map, both kinds. ``--robots``/``--sizes`` pick cases
         (e.g. ``--robots 100 --sizes 1000``). Without priors (up to ``--no-priors-max`` robots):
         the fusion in which every robot but the reference gets an alignment attempt, and each
         attempt alone.
latency  Real processes on loopback: a router, the map server (``--state`` in ``--workdir``), N
         load agents (one process each: ``robot_agent.agent.Publisher`` replaying a recording)
         publishing maps at 1 Hz and poses at 5 Hz with start priors, and this process subscribed
         to the fused map. Latency of map ``seq`` of robot r = arrival here of the first fused map
         with ``RobotStatus(r).map_seq >= seq`` - the agent's ``time.monotonic()`` just before its
         first put of that map (CLOCK_MONOTONIC is system-wide). ``--profile`` samples the server
         with py-spy and splits its fusion loop into parts. ``--leave K``: K agents stop halfway
         through the window (a departure makes the server match and solve its fleet graph anew,
         the last bend held meanwhile); the latency of the maps put after it is given apart.
bytes    Encoded size (all chunks) of a map of 1,000 segments (and one of 1,000 distinct elements)
         against the raw 5 cm grid of the same area (1 byte per cell) and that grid compressed
         (zlib level 6, PNG), the grid either clean (the world's free space + the segments: the
         best case for a grid) or built from the robot's own scans; then a live agent's map + pose
         bytes per second against the grid of each published map sent at the same rate.

Prints tables and writes ``benchmarks/results/bench_fleet.json``.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import io
import itertools
import json
import os
import shutil
import subprocess
import sys
import threading
import time
import uuid
import zlib
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from _results import save_results  # noqa: E402

from shared import codec  # noqa: E402
from shared.chunks import PER_ELEMENT  # noqa: E402
from shared.geometry import apply_segments, compose, inverse  # noqa: E402
from shared.messages import PoseUpdate, RobotMap  # noqa: E402

WORLDS = ("office", "warehouse", "campus")
RUNS = tuple((w, r, s) for s in (0, 1) for w in WORLDS for r in range(4))  # (world, route, seed)
RECORD_S = 60.0  # simulated seconds per recorded robot
TILE_GAP_M = 5.0  # between two maps laid side by side in a tiled map
WORLD_GAP_M = 20.0  # between the worlds in the latency run's global frame (no cross-world merging)
ELEMENT_STRIDE = 1 << 32  # element ids of the k-th tile start at k * ELEMENT_STRIDE
CELL_M = 0.05  # the occupancy grid the maps are compared with
GRID_FREE, GRID_OCCUPIED, GRID_UNKNOWN = 0, 100, 255  # one byte per cell (ROS OccupancyGrid values)
LOGODDS_HIT, LOGODDS_PASS = 0.85, -0.4  # a beam ending in / passing through a cell (as in gmapping)
LOGODDS_THRESHOLD = 0.62  # |log-odds| past which a cell is occupied / free (p = 0.65 / 0.35)
SCAN_CHUNK = 4  # scans rasterized at once (bounds the temporaries to ~100 MB)
PRIOR_SIGMA = np.array([0.05, 0.05, np.radians(1.0)])  # = robot_agent.agent.DEFAULT_PRIOR_SIGMA
STARTUP_TIMEOUT_S = 60.0
FIRST_REPLAYED_MAP = 10  # load agents replay their recorded maps from the 10th (about 10 s in)
PROFILE_RATE_HZ = 200  # py-spy samples per second (--profile)
CACHE_FORMAT = 4  # of the recordings in --cache (in their file names); 3: maps with the pose graph;
# 4: every map stored whole (its graph in it, as a query gets it)


# -- recorded agent runs ----------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class Recording:
    """One simulated robot as its agent published it: ``maps`` every map publication (assembled,
    in the robot's map frame, whose pose in the world is ``start (3,)``), ``map_bytes (M,)`` the
    wire size of each (all chunks), ``map_scans (M,)`` scans processed before each, ``pose_bytes
    (Q,)`` the size of each pose update, and the scans themselves: ``ranges (S,B)`` over
    ``angles (B,)`` taken at ``scan_poses (S,3)`` (the filter's estimate, map frame)."""

    world: str
    route: int
    seed: int
    duration_s: float
    start: np.ndarray
    range_max_m: float
    maps: list[RobotMap]
    map_bytes: np.ndarray
    map_scans: np.ndarray
    pose_bytes: np.ndarray
    scan_poses: np.ndarray
    ranges: np.ndarray
    angles: np.ndarray
    path: Path

    @property
    def name(self) -> str:
        return f"{self.world}-r{self.route}-s{self.seed}"


def record_run(world_name: str, route: int, seed: int, duration_s: float, path: Path) -> Path:
    """Run one simulated robot's agent core (its default cadence: maps at 1 Hz when changed,
    poses at 5 Hz, K top particles; its online back end beside it, in this process: the maps
    carry its pose graph) and save what it would publish to ``path`` (npz, no pickle)."""
    from robot_agent.agent import AgentCore
    from robot_agent.backend.live import InlineRunner, LiveCorrector
    from robot_agent.sim import LiveSim, builtin_world
    from robot_agent.slam.fastslam import FastSLAM, SlamConfig

    world = builtin_world(world_name)
    start = np.asarray(world.starts[route], float)
    sim = LiveSim(world, route, seed=seed)
    slam = FastSLAM(SlamConfig(), np.random.default_rng([seed, route, 7]))
    corrector = LiveCorrector(slam, InlineRunner(slam.cfg))
    core = AgentCore(f"{world_name}{route}", slam, prior=start, corrector=corrector)  # priors in every map
    blobs, map_bytes, map_scans, pose_bytes, poses, ranges = [], [], [], [], [], []
    for scan in sim.scans(duration_s):
        est = core.step(scan)
        poses.append(est.pose)
        ranges.append(scan.ranges_m.astype(np.float32))
        pose = core.pose_message()
        if pose is not None:
            pose_bytes.append(len(codec.encode(pose)))
        chunks = core.map_messages()
        if chunks is not None:
            map_bytes.append(sum(len(codec.encode(c)) for c in chunks))
            map_scans.append(core.scans)
            blobs.append(codec.encode_stored_map(codec.join(core.map_whole)))  # with its graph
    meta = dict(world=world_name, route=route, seed=seed, duration_s=duration_s, start=start.tolist(),
                range_max_m=float(scan.range_max_m))  # fmt: skip
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp.npz")
    np.savez(
        tmp, meta=np.array(json.dumps(meta)), blob=np.frombuffer(b"".join(blobs), np.uint8),
        offsets=np.cumsum([0] + [len(b) for b in blobs]), map_bytes=np.array(map_bytes, np.int64),
        map_scans=np.array(map_scans, np.int64), pose_bytes=np.array(pose_bytes, np.int64),
        scan_poses=np.array(poses), ranges=np.array(ranges), angles=scan.angles_rad,
    )  # fmt: skip
    tmp.replace(path)
    return path


def load_recording(path: Path) -> Recording:
    with np.load(path, allow_pickle=False) as z:
        meta = json.loads(str(z["meta"]))
        blob, off = z["blob"].tobytes(), z["offsets"]
        maps = [codec.decode_stored_map(blob[a:b]) for a, b in itertools.pairwise(off)]
        return Recording(
            meta["world"], meta["route"], meta["seed"], meta["duration_s"], np.array(meta["start"]),
            meta["range_max_m"], maps, z["map_bytes"], z["map_scans"], z["pose_bytes"], z["scan_poses"],
            z["ranges"], z["angles"], path,
        )  # fmt: skip


def recording_path(cache: Path, spec: tuple, duration_s: float) -> Path:
    world, route, seed = spec
    return cache / f"v{CACHE_FORMAT}-{world}-r{route}-s{seed}-{duration_s:g}s.npz"


def recordings(cache: Path, n_runs: int, duration_s: float, refresh: bool) -> list[Recording]:
    """The first ``n_runs`` of :data:`RUNS`, recorded where missing (two processes at a time)."""
    specs = RUNS[:n_runs]
    paths = [recording_path(cache, s, duration_s) for s in specs]
    todo = [(s, p) for s, p in zip(specs, paths, strict=True) if refresh or not p.exists()]
    if todo:
        print(f"recording {len(todo)} simulated agents ({duration_s:g} s each) into {cache} ...", flush=True)
        t0 = time.monotonic()
        with ProcessPoolExecutor(max_workers=min(2, os.cpu_count() or 1)) as pool:
            futures = [pool.submit(record_run, *s, duration_s, p) for s, p in todo]
            for f in futures:
                f.result()
        print(f"recorded in {time.monotonic() - t0:.0f} s", flush=True)
    return [load_recording(p) for p in paths]


# -- maps built from recordings ---------------------------------------------------------------------


def final_map(rec: Recording) -> RobotMap:
    return rec.maps[-1]


def _bbox(seg: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    pts = seg.reshape(-1, 2)
    return pts.min(axis=0), pts.max(axis=0)


@dataclass(frozen=True)
class Tile:
    """A real map laid into the tiled "building": ``rec``'s final map (its rows ``rows``, all of
    them when None) moved by ``shift (2,)`` (map frame -> building frame)."""

    rec: Recording
    rows: np.ndarray | None
    shift: np.ndarray

    def take(self, name: str) -> np.ndarray:
        v = getattr(final_map(self.rec), name)
        return v if self.rows is None else v[self.rows]


def tiles_for(recs: list[Recording], first: int, n: int, count: str = "rows") -> list[Tile]:
    """Tiles ``first, first+1, ...`` of the row (tile j is recording ``j % len(recs)``) until they
    hold ``n`` rows (element versions, as sent) or ``n`` distinct elements (``count="elements"``);
    the last tile is cut. Tile j's place in the row depends only on j."""
    widths = [_extent(final_map(r))[0] + TILE_GAP_M for r in recs]
    out, left, j = [], n, first
    while left > 0:
        rec = recs[j % len(recs)]
        m = final_map(rec)
        x0 = sum(widths[k % len(recs)] for k in range(j))
        lo, _ = _bbox(m.seg)
        ids = np.unique(m.element)
        have = len(m.seg) if count == "rows" else len(ids)
        rows = None
        if have > left:  # cut: the first rows, or every row of the first elements
            rows = np.arange(left) if count == "rows" else np.flatnonzero(np.isin(m.element, ids[:left]))
        out.append(Tile(rec, rows, np.array([x0, 0.0]) - lo))
        left -= min(have, left)
        j += 1
    return out


def _extent(m: RobotMap) -> np.ndarray:
    lo, hi = _bbox(m.seg)
    return hi - lo


def tiled_map(tiles: list[Tile], robot: str, frame: np.ndarray, prior: bool) -> RobotMap:
    """A robot map of real elements: ``tiles`` (:func:`tiles_for`) concatenated in the building
    frame and expressed in the robot's map frame, whose pose in the building is ``frame (3,)``
    (sent as the start prior when ``prior``). Particle weights and poses are the first tile's;
    every tile keeps its own elements' trust, hits, age and particle membership (all recordings
    send the same K particles)."""
    to_robot = inverse(frame)
    head = final_map(tiles[0].rec)
    parts = {k: [] for k in PER_ELEMENT}
    for j, t in enumerate(tiles):
        m = final_map(t.rec)
        if m.n_particles != head.n_particles:
            raise ValueError(
                f"{t.rec.name}: {m.n_particles} particles, the first tile has {head.n_particles}"
            )
        for k in PER_ELEMENT:
            parts[k].append(t.take(k))
        parts["seg"][-1] = apply_segments(to_robot, parts["seg"][-1] + t.shift)
        parts["element"][-1] = parts["element"][-1] + j * ELEMENT_STRIDE
    poses = head.particle_poses.copy()
    poses[:, :2] += tiles[0].shift
    return dataclasses.replace(
        head, robot=robot, session=uuid.uuid4().hex[:16], seq=1, chunk=0, n_chunks=1,
        particle_poses=compose(to_robot, poses),
        prior=frame if prior else None, prior_sigma=PRIOR_SIGMA if prior else None,
        **{k: np.concatenate(v) for k, v in parts.items()},
    )  # fmt: skip


def robot_frames(n: int, seed: int = 0) -> np.ndarray:
    """``(n,3)`` robot map frames in the building frame: anywhere, any heading (seeded)."""
    rng = np.random.default_rng(seed)
    return np.column_stack([rng.uniform(-50, 50, n), rng.uniform(-50, 50, n), rng.uniform(-np.pi, np.pi, n)])


# -- section 1: fusion time --------------------------------------------------------------------------


@contextlib.contextmanager
def timed_alignments():
    """Time every ``estimate_alignment`` call that ``Fleet.fuse`` makes: yields a list that fills
    with ``(seconds, with_prior, status)``."""
    import map_server.fleet as fleet_mod

    original = fleet_mod.estimate_alignment
    calls: list[tuple[float, bool, str]] = []

    def timed(robot_seg, placed_seg, cfg, prior=None, *args, **kwargs):
        t = time.perf_counter()
        a = original(robot_seg, placed_seg, cfg, prior, *args, **kwargs)
        calls.append((time.perf_counter() - t, prior is not None, a.status))
        return a

    fleet_mod.estimate_alignment = timed
    try:
        yield calls
    finally:
        fleet_mod.estimate_alignment = original


def _fuse_timed(fleet, now_s: float):
    t = time.perf_counter()
    out = fleet.fuse(now_s)
    return time.perf_counter() - t, out


def _renumbered(m: RobotMap, seq: int) -> RobotMap:
    return dataclasses.replace(m, seq=seq)


def fusion_with_priors(maps: list[RobotMap], reps: int) -> dict:
    """The first fusion (every robot placed by its prior, refined against the others), then
    ``reps`` fusions one (server) second apart, each after one robot's new map (round robin): the
    steady state, and every ``FleetConfig.retry_interval_s`` a round that re-refines the priors
    against the others (``Fleet`` does it while the placed maps change)."""
    from map_server.config import FleetConfig
    from map_server.fleet import Fleet

    fleet = Fleet(FleetConfig(), "bench")
    for m in maps:
        fleet.put_map(m, 0.0)
    with timed_alignments() as first_calls:
        first_s, fused = _fuse_timed(fleet, 0.0)
    unplaced = [s.robot for s in fused.robots if not s.merged]
    if unplaced:
        raise RuntimeError(f"robots not placed by their priors: {unplaced}")
    seqs = [m.seq for m in maps]
    plain, rounds, refinements, all_ms = [], [], [], []
    for j in range(reps):
        i = j % len(maps)
        seqs[i] += 1
        fleet.put_map(_renumbered(maps[i], seqs[i]), 1.0 + j)
        with timed_alignments() as calls:
            dt, out = _fuse_timed(fleet, 1.0 + j)
        (rounds if calls else plain).append(dt * 1e3)
        all_ms.append(dt * 1e3)
        refinements += [c[0] * 1e3 for c in calls]
    return {
        "segments_in": int(fused.extra.get("segments_in", -1)),
        "fused_segments": len(out.seg),
        "first_ms": first_s * 1e3,
        "first_refinements_ms": [c[0] * 1e3 for c in first_calls],
        "steady_ms": plain,
        "refine_round_ms": rounds,
        "refinement_ms": refinements,
        "all_ms": all_ms,
    }


def fusion_without_priors(maps: list[RobotMap], reps: int) -> dict:
    """``reps`` times: a fresh fleet fuses (the first robot becomes the reference; the others'
    maps are too young to be matched), then, once the maps are mature, fuses again: every other
    robot gets one alignment attempt against the reference's map."""
    from map_server.config import FleetConfig
    from map_server.fleet import Fleet

    maps = [dataclasses.replace(m, prior=None, prior_sigma=None) for m in maps]
    cfg = FleetConfig()
    firsts, with_attempts, attempts = [], [], []
    for _ in range(reps):
        fleet = Fleet(cfg, "bench")
        for m in maps:
            fleet.put_map(m, 0.0)
        firsts.append(_fuse_timed(fleet, 0.0)[0])
        later = cfg.mature_window_s + 1.0
        for m in maps:
            fleet.put_map(_renumbered(m, m.seq + 1), later)
        with timed_alignments() as calls:
            with_attempts.append(_fuse_timed(fleet, later)[0])
        attempts += calls
    return {
        "first_ms": [d * 1e3 for d in firsts],
        "fuse_with_attempts_ms": [d * 1e3 for d in with_attempts],
        "attempt_ms": [c[0] * 1e3 for c in attempts],
        "attempts": len(attempts),
        "attempts_matched": sum(c[2] == "aligned" for c in attempts),
    }


def bench_fusion(
    recs: list[Recording], robots: tuple, sizes: tuple, reps: int, align_reps: int, no_priors_max: int = 16
) -> list:
    """Every ``robots`` × ``sizes`` case with priors; without priors only up to ``no_priors_max``
    robots (every non-reference robot's attempt is a full search: minutes at 100 robots)."""
    rows = []
    for size in sizes:
        for n in robots:
            frames = robot_frames(n)
            maps = [tiled_map(tiles_for(recs, i, size), f"robot{i + 1}", frames[i], True) for i in range(n)]
            elements = float(np.mean([len(np.unique(m.element)) for m in maps]))
            row = {"robots": n, "segments_per_robot": size, "elements_per_robot": elements}
            row["priors"] = fusion_with_priors(maps, reps)
            no_priors = 1 < n <= no_priors_max and align_reps > 0
            row["no_priors"] = fusion_without_priors(maps, align_reps) if no_priors else None
            rows.append(row)
            print(f"  fusion: {n} robots x {size} segments done", flush=True)
    return rows


def _p(values, q: float) -> float | None:
    return float(np.percentile(values, q)) if len(values) else None


def print_fusion(rows: list) -> None:
    out = []
    for r in rows:
        p, a = r["priors"], r["no_priors"] or {}
        out.append({
            "robots": r["robots"], "seg/robot": r["segments_per_robot"], "elements": r["elements_per_robot"],
            "seg in (all)": p["segments_in"],
            "fused seg": p["fused_segments"], "first": p["first_ms"], "steady p50": _p(p["steady_ms"], 50),
            "steady p95": _p(p["steady_ms"], 95), "steady max": max(p["steady_ms"], default=None),
            "all p95": _p(p["steady_ms"] + p["refine_round_ms"], 95),
            "all max": max(p["steady_ms"] + p["refine_round_ms"], default=None),
            "re-refine rounds": len(p["refine_round_ms"]),
            "re-refine round": _p(p["refine_round_ms"], 50), "one refinement": _p(p["refinement_ms"], 50),
            "no-prior fusion": _p(a.get("fuse_with_attempts_ms", []), 50),
            "no-prior max": max(a.get("fuse_with_attempts_ms", []), default=None),
            "attempts": f"{a['attempts_matched']}/{a['attempts']}" if a else None,
            "attempt p50": _p(a.get("attempt_ms", []), 50),
            "attempt max": max(a.get("attempt_ms", []), default=None),
        })  # fmt: skip
    table(
        "Fleet.fuse wall time (ms); seg = rows as sent (K = 5), elements = distinct per robot, seg in = "
        "after cross-particle fusion, all robots. With priors: first = places every robot (each prior "
        "refined); steady = after one robot's new map, no refinement in it (p50, p95, max); re-refine "
        "round = a fusion that re-refines priors (how many: re-refine rounds; p50), one refinement = one "
        "robot's; all = every fusion after one robot's new map, both kinds (p95, max). Without priors: "
        "the fusion that makes one alignment attempt per non-reference robot (p50, max; matched/attempts), "
        "one attempt (p50, max)",
        out,
    )


# -- section 2: latency over zenoh, real processes -----------------------------------------------------


class _TimedBus:
    """The agent's bus, noting ``time.monotonic()`` just before the first put of each map."""

    def __init__(self, bus, map_key: str, core, log):
        self._bus, self._map_key, self._core, self._log = bus, map_key, core, log

    def put(self, key: str, payload: bytes, *, reliable: bool = True) -> None:
        if key == self._map_key and self._core.unlogged is not None:
            self._log.write(f"{self._core.unlogged} {time.monotonic():.6f}\n")
            self._log.flush()
            self._core.unlogged = None
        self._bus.put(key, payload, reliable=reliable)

    def __getattr__(self, name: str):
        return getattr(self._bus, name)


class ReplayCore:
    """An ``AgentCore`` stand-in for ``robot_agent.agent.Publisher``: replays a recording's maps
    (one per ``map_every`` ticks, back and forth from ``first_map`` on, so the map keeps changing
    as a live robot's does) and a pose per tick, under a new robot id, session and prior."""

    def __init__(self, rec: Recording, robot: str, prior: np.ndarray, map_every: int, first_map: int):
        self.rec, self.robot, self.prior, self.map_every = rec, robot, prior, map_every
        self.session = uuid.uuid4().hex[:16]
        n = len(rec.maps)
        lo = min(first_map, n - 1)
        self._order = list(range(lo, n)) + list(range(n - 2, lo, -1)) or [lo]
        self.ticks = self.map_seq = self.pose_seq = 0
        self.unlogged: int | None = None
        self.map_whole: list[RobotMap] = []

    def pose_message(self, force: bool = False) -> PoseUpdate:
        pose = self.rec.scan_poses[self.ticks % len(self.rec.scan_poses)]
        self.pose_seq += 1
        return PoseUpdate(self.robot, self.session, self.pose_seq, time.monotonic(), pose)

    free_whole = None  # no free space: the load is the maps and poses (free space adds ~3 % of
    # a robot's bytes: README, "Watching it, and a map for navigation")

    def free_message(self, force: bool = False) -> None:
        return None

    def map_messages(self, force: bool = False) -> list[RobotMap] | None:
        self.ticks += 1
        if not force and (self.ticks - 1) % self.map_every:
            return None
        m = self.rec.maps[self._order[self.map_seq % len(self._order)]]
        self.map_seq += 1
        self.unlogged = self.map_seq
        m = dataclasses.replace(
            m, robot=self.robot, session=self.session, seq=self.map_seq, stamp_s=time.monotonic(),
            prior=self.prior, prior_sigma=PRIOR_SIGMA,
            graph_seq=self.map_seq if m.has_graph else None,
        )  # fmt: skip
        self.map_whole = codec.split(m)  # every replayed map carries its graph: what a query gets too
        return self.map_whole


def load_agent_main(args: argparse.Namespace) -> int:
    """A load agent process: publish a recording at 1 Hz (maps) / 5 Hz (poses) until SIGTERM."""
    from robot_agent.agent import Publisher
    from shared.bus import Bus, BusConfig, stop_on_signals
    from shared.keys import Keys

    stop = threading.Event()
    stop_on_signals(stop)
    rec = load_recording(Path(args.recording))
    prior = np.array([float(v) for v in args.prior.split(",")])
    core = ReplayCore(rec, args.robot, prior, round(args.map_period / args.pose_period), args.first_map)
    keys = Keys(args.fleet)
    with Bus(BusConfig(connect=(args.connect,)), cancel=stop) as bus, open(args.puts, "w") as log:
        pub = Publisher(_TimedBus(bus, keys.robot_map(args.robot), core, log), keys, core)
        print(f"load agent {args.robot}: connected", flush=True)
        stop.wait(args.phase)
        next_s = time.monotonic()
        while not stop.is_set():
            pub.publish()
            next_s += args.pose_period
            stop.wait(max(0.0, next_s - time.monotonic()))
    print(f"load agent {args.robot}: {core.map_seq} maps, {pub.bytes_sent} bytes", flush=True)
    return 0


def latency_priors(recs: list[Recording]) -> list[np.ndarray]:
    """Each recording's map frame in the global frame: its world's start pose, the worlds laid
    side by side along x (``WORLD_GAP_M`` apart) so robots of one world overlap, worlds do not."""
    from robot_agent.sim import builtin_world

    offsets, x = {}, 0.0
    for w in WORLDS:
        b = builtin_world(w).bounds
        offsets[w] = np.array([x - b[0], -b[1], 0.0])
        x += b[2] - b[0] + WORLD_GAP_M
    return [compose(offsets[r.world], r.start) for r in recs]


@dataclass
class LatencyRun:
    agents: int
    put_times: dict  # robot -> (seqs (P,), monotonic put times (P,))
    updates: list  # fleet_slam.watch.Update, in arrival order
    window: tuple[float, float]
    server_log: str
    profile: Path | None = None  # py-spy raw samples of the server during the window
    left_at: float | None = None  # when ``--leave`` agents were stopped (monotonic), halfway through


def run_latency(
    recs: list[Recording], n: int, seconds: float, warmup_s: float, min_gap_s: float, workdir: Path,
    profile: bool = False, leave: int = 0,
) -> LatencyRun:  # fmt: skip
    """Router, server, ``n`` load agents (separate processes), this process watching the fused map;
    ``leave`` of them stopped halfway through the window (each departure makes the server match and
    solve its fleet graph anew: Fleet.fuse, the fused maps saying so)."""
    from fleet_slam.procs import ProcGroup, free_port, python_module
    from fleet_slam.watch import FusedWatcher
    from shared.bus import Bus, BusConfig
    from shared.keys import Keys

    run_dir = workdir / f"latency-{n}"
    shutil.rmtree(run_dir, ignore_errors=True)  # this benchmark's own earlier run
    run_dir.mkdir(parents=True)
    endpoint, fleet = f"tcp/127.0.0.1:{free_port()}", "bench"
    priors = latency_priors(recs)
    rng = np.random.default_rng(n)
    with ProcGroup(run_dir / "logs") as group:
        router = group.start("router", python_module("shared.bus", "router", "--listen", endpoint))
        _wait(router, "listening")
        server = group.start(
            "server",
            python_module("map_server", "--connect", endpoint, "--state", run_dir / "state", "--fleet", fleet,
                          "--min-gap", min_gap_s),
        )  # fmt: skip
        _wait(server, "running")
        with Bus(BusConfig(connect=(endpoint,))) as bus:
            watcher = FusedWatcher(bus, Keys(fleet))
            watcher.start(query_timeout_s=0.5)
            agents = []
            for i in range(n):
                robot = f"robot{i + 1:02d}"
                prior = ",".join(f"{v:.9g}" for v in priors[i])
                argv = [sys.executable, str(Path(__file__).resolve()), "load-agent", "--robot", robot,
                        "--connect", endpoint, "--fleet", fleet, "--recording", recs[i].path,
                        "--prior", prior,
                        "--puts", run_dir / f"{robot}.puts", "--phase", f"{rng.uniform(0, 1):.3f}",
                        "--first-map", FIRST_REPLAYED_MAP]  # fmt: skip
                agents.append(group.start(robot, [str(a) for a in argv]))
            for a in agents:
                _wait(a, "connected")
            _wait_placed(watcher, [a.name for a in agents])
            time.sleep(warmup_s)
            spy_out = run_dir / "server.pyspy.txt" if profile else None
            spy = start_profiler(server.popen.pid, seconds, spy_out) if profile else None
            left_at, stay = None, n - min(leave, n - 1)  # (one agent stays at least)
            try:
                t0 = time.monotonic()
                if leave:
                    time.sleep(seconds / 2)
                    left_at = time.monotonic()
                    for a in agents[stay:]:
                        a.stop()
                time.sleep(t0 + seconds - time.monotonic())
                t1 = time.monotonic()
            except BaseException:
                stop_profiler(spy, wait=False)
                raise
            stop_profiler(spy)
            time.sleep(2.0)  # maps put just before t1 may still arrive
            updates = list(watcher.updates)
            check_alive(agents[:stay])
            for a in agents:
                a.stop()
        server.stop()
        server_log = server.output()
    put_times = {a.name: _read_puts(run_dir / f"{a.name}.puts") for a in agents}
    has_profile = spy_out is not None and spy_out.exists()
    return LatencyRun(n, put_times, updates, (t0, t1), server_log, spy_out if has_profile else None, left_at)


def _wait(proc, text: str) -> None:
    if not proc.wait_for(text, STARTUP_TIMEOUT_S):
        raise RuntimeError(f"{proc.name} did not start; see {proc.log_path}:\n{proc.output()[-2000:]}")


def _wait_placed(watcher, robots: list[str], timeout_s: float = STARTUP_TIMEOUT_S) -> None:
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        f = watcher.latest
        if f is not None and all((r := f.robot(name)) is not None and r.merged for name in robots):
            return
        time.sleep(0.1)
    raise RuntimeError(f"not every robot was placed within {timeout_s:.0f} s")


def check_alive(agents: list) -> None:
    """A load agent that exited before it was stopped makes a run meaningless: say so."""
    dead = [a for a in agents if not a.running]
    if dead:
        raise RuntimeError(
            f"{len(dead)} of {len(agents)} load agents exited during the run; {dead[0].name} "
            f"({dead[0].log_path}):\n{dead[0].output()[-2000:]}"
        )


def _read_puts(path: Path) -> tuple[np.ndarray, np.ndarray]:
    rows = [line.split() for line in path.read_text().splitlines() if line.strip()]
    return np.array([int(r[0]) for r in rows], np.int64), np.array([float(r[1]) for r in rows])


def start_profiler(pid: int, seconds: float, out: Path) -> subprocess.Popen | None:
    """py-spy sampling ``pid`` (every thread, idle ones too, without pausing it) for ``seconds``."""
    exe = shutil.which("py-spy") or str(Path(sys.executable).with_name("py-spy"))
    if not Path(exe).exists():
        print("  py-spy not found: no server profile", flush=True)
        return None
    argv = [exe, "record", "--pid", str(pid), "--duration", str(max(1, round(seconds))), "--idle",
            "--threads", "--nonblocking", "--rate", str(PROFILE_RATE_HZ), "--format", "raw",
            "--output", str(out)]  # fmt: skip
    return subprocess.Popen(argv, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)


def stop_profiler(spy: subprocess.Popen | None, wait: bool = True) -> None:
    """Let py-spy finish its samples (or stop it now) and reap it."""
    if spy is None:
        return
    try:
        spy.wait(timeout=30 if wait else 0.01)
    except subprocess.TimeoutExpired:
        spy.kill()
        spy.wait()


# where the server's main thread spends the window: the first matching frame name decides
PROFILE_PARTS = (
    ("align", ("estimate_alignment (", "Fleet.global_segments (")),
    ("fuse", ("Fleet.fuse (",)),
    ("persist", ("MapServer._persist (",)),
    ("publish", ("Bus.put (", "encode (", "split_fused_map (")),
    ("tick other", ("MapServer.tick (",)),
    ("waiting", ("MapServer.run (",)),
)


def server_profile(path: Path, seconds: float, fusions: int) -> dict:
    """Milliseconds per fusion of the server's main thread (the fusion loop) by part, from py-spy's
    raw samples: align (alignment attempts and prior refinements), fuse (the rest of Fleet.fuse:
    cross-particle fusion and merge), persist (state to disk, fsync), publish (encode + put),
    waiting (for a map or the minimum gap)."""
    samples = dict.fromkeys([name for name, _ in PROFILE_PARTS], 0)
    for line in path.read_text().splitlines():
        stack, _, count = line.rpartition(" ")
        if "MainThread" not in stack.split(";", 1)[0]:
            continue
        part = next((name for name, marks in PROFILE_PARTS if any(m in stack for m in marks)), None)
        if part is not None:
            samples[part] += int(count)
    total = sum(samples.values())
    scale = seconds * 1e3 / max(total, 1) / max(fusions, 1)
    return {f"{k}_ms_per_fusion": v * scale for k, v in samples.items()} | {"samples": total}


def latency_stats(run: LatencyRun) -> dict:
    """Per map put in the window: first fused map (arrival) with that robot's ``map_seq >= seq``."""
    t0, t1 = run.window
    arrivals = np.array([u.wall_s for u in run.updates])
    lat, missing, after = [], 0, []
    for robot, (seqs, puts) in run.put_times.items():
        seen = np.array([(s.map_seq if (s := u.fused.robot(robot)) is not None else -1) for u in run.updates])
        best = np.maximum.accumulate(seen) if len(seen) else seen
        for seq, t_put in zip(seqs, puts, strict=True):
            if not t0 <= t_put < t1:
                continue
            i = np.searchsorted(best, seq)  # first update whose map_seq >= seq
            if i == len(best):
                missing += 1
            else:
                lat.append(arrivals[i] - t_put)
                after.append(run.left_at is not None and t_put >= run.left_at)
    lat_ms = np.array(lat) * 1e3
    after_ms = lat_ms[np.array(after, bool)] if lat else lat_ms
    rebuilding = np.array([u.fused.extra.get("graph_rebuilding", 0.0) > 0.0 for u in run.updates], float)
    in_window = [u for u in run.updates if t0 <= u.wall_s < t1]
    extra = {k: [u.fused.extra[k] for u in in_window if k in u.fused.extra] for k in _extra_keys(in_window)}
    fusions = next((int(w) for w in _words_after(run.server_log, "stopped after")), None)
    last = run.updates[-1].fused if run.updates else None
    return {
        "agents": run.agents,
        "maps_put": len(lat) + missing,
        "missing": missing,
        "p50_ms": _p(lat_ms, 50),
        "p95_ms": _p(lat_ms, 95),
        "max_ms": float(lat_ms.max()) if len(lat_ms) else None,
        "fused_maps_per_s": len(in_window) / (t1 - t0),
        "server_fusions": fusions,
        "fused_segments": len(last.seg) if last is not None else 0,
        "extra_p50": {k: _p(v, 50) for k, v in extra.items() if v},
        "server_profile": server_profile(run.profile, t1 - t0, len(in_window)) if run.profile else None,
        "latencies_ms": lat_ms.round(3).tolist(),
        # --leave: the maps put after the departures (the graph matched and solved anew meanwhile)
        "after_leave_p50_ms": _p(after_ms, 50) if run.left_at is not None else None,
        "after_leave_p95_ms": _p(after_ms, 95) if run.left_at is not None else None,
        # rebuilds of the fleet graph the fused maps said began and ended (extra graph_rebuilding)
        "graph_rebuilds_begun": int(np.sum(np.diff(rebuilding, prepend=0.0) > 0)),
        "graph_rebuilds_whole": int(np.sum(np.diff(rebuilding, prepend=0.0) < 0)),
    }


def _extra_keys(updates) -> set[str]:
    return {k for u in updates for k in u.fused.extra if k not in ("robots_merged", "segments_in")}


def _words_after(text: str, marker: str) -> list[str]:
    i = text.rfind(marker)
    return text[i + len(marker) :].split()[:1] if i >= 0 else []


def print_latency(rows: list, seconds: float) -> None:
    out = [
        {
            "agents": r["agents"], "maps put": r["maps_put"], "missing": r["missing"], "p50 ms": r["p50_ms"],
            "p95 ms": r["p95_ms"], "max ms": r["max_ms"], "fused/s": r["fused_maps_per_s"],
            "server fusions": r["server_fusions"], "fused seg": r["fused_segments"],
            **{f"{k} p50": v for k, v in r["extra_p50"].items()},
            **({"after leave p95 ms": r["after_leave_p95_ms"],
                "graph rebuilds (begun/whole)": f"{r['graph_rebuilds_begun']}/{r['graph_rebuilds_whole']}"}
               if r.get("after_leave_p95_ms") is not None else {}),
        }
        for r in rows
    ]  # fmt: skip
    exposed = any(r["extra_p50"] for r in rows)
    table(
        f"agent put -> fused map received (ms), loopback, one process per agent (maps 1 Hz, poses 5 Hz, "
        f"priors), {seconds:g} s per row; server fusions = whole run incl. start-up"
        + ("" if exposed else "; the server does not publish its fusion time"),
        out,
    )
    profiled = [r["agents"] for r in rows if r["server_profile"]]
    out = [
        {"agents": r["agents"], "fusions": round(r["fused_maps_per_s"] * seconds)}
        | {k.removesuffix("_ms_per_fusion"): v for k, v in r["server_profile"].items() if k != "samples"}
        for r in rows
        if r["server_profile"]
    ]
    if profiled:
        table("the server's fusion loop (main thread, py-spy) during the window: ms per fusion by part", out)


# -- section 3: bytes --------------------------------------------------------------------------------


class GridBox:
    """The ``CELL_M`` cells (rows = y) of the box ``lo..hi`` (2,) in a robot's map frame."""

    def __init__(self, lo: np.ndarray, hi: np.ndarray):
        self.lo = np.asarray(lo, float)
        self.shape = tuple(np.maximum(np.ceil((np.asarray(hi) - self.lo) / CELL_M).astype(int), 1)[::-1])

    def cells(self, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Flat cell indices of points ``(...,2)`` and whether each is inside."""
        ij = np.floor((pts - self.lo) / CELL_M).astype(np.int64)
        inside = (
            (ij[..., 0] >= 0)
            & (ij[..., 0] < self.shape[1])
            & (ij[..., 1] >= 0)
            & (ij[..., 1] < self.shape[0])
        )
        return ij[..., 1] * self.shape[1] + ij[..., 0], inside

    def crop(self, grid: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
        """The part of ``grid`` (over this box) that covers ``lo..hi``."""
        sub = GridBox(lo, hi)
        i0, j0 = np.floor((sub.lo - self.lo) / CELL_M).astype(int)
        return grid[j0 : j0 + sub.shape[0], i0 : i0 + sub.shape[1]]


def polygon_free(box: GridBox, free_local) -> np.ndarray:
    """Whether each cell centre of ``box`` lies in the free-space polygon ``free_local``."""
    import shapely

    shapely.prepare(free_local)
    xs = box.lo[0] + (np.arange(box.shape[1]) + 0.5) * CELL_M
    ys = box.lo[1] + (np.arange(box.shape[0]) + 0.5) * CELL_M
    out = np.zeros(box.shape, bool)
    for r0 in range(0, box.shape[0], 256):  # row blocks bound the temporaries
        yy, xx = np.meshgrid(ys[r0 : r0 + 256], xs, indexing="ij")
        out[r0 : r0 + 256] = shapely.contains_xy(free_local, xx, yy)
    return out


def clean_grid(seg: np.ndarray, free: np.ndarray, box: GridBox) -> np.ndarray:
    """The best case for a grid: free where the simulated world is free (its free-space polygon,
    clipped to the box: ``free``), occupied on the mapped segments, unknown elsewhere — the end
    state of a grid that has seen its whole box, with no noise, no ragged beam fans and
    straight walls, so its free and unknown areas are uniform and compress as well as a grid can."""
    grid = np.where(free, GRID_FREE, GRID_UNKNOWN).astype(np.uint8)
    if len(seg):
        length = np.hypot(*(seg[:, 1] - seg[:, 0]).T)
        steps = np.maximum(np.ceil(length / (CELL_M / 2)).astype(int), 1)
        t = np.concatenate([np.linspace(0, 1, k + 1) for k in steps])
        owner = np.repeat(np.arange(len(seg)), steps + 1)
        idx, inside = box.cells(seg[owner, 0] + t[:, None] * (seg[owner, 1] - seg[owner, 0]))
        grid.reshape(-1)[idx[inside]] = GRID_OCCUPIED
    return grid


class ScanCounts:
    """What a grid-mapping robot builds: per cell of ``box``, the beams that ended in it (hits)
    and passed through it, from its own scans at its own SLAM poses (the laser sits at the robot's
    origin in the simulator)."""

    def __init__(self, box: GridBox):
        self.box = box
        self.hits = np.zeros(box.shape[0] * box.shape[1], np.int32)
        self.passes = np.zeros_like(self.hits)

    def add(self, poses: np.ndarray, ranges: np.ndarray, angles: np.ndarray, range_max_m: float) -> None:
        n_cells = len(self.hits)
        t = np.arange(0.0, range_max_m, CELL_M / 2)  # samples along a beam
        for a in range(0, len(poses), SCAN_CHUNK):
            p, r = poses[a : a + SCAN_CHUNK], ranges[a : a + SCAN_CHUNK].astype(float)
            heading = p[:, None, 2] + angles[None]
            u = np.stack([np.cos(heading), np.sin(heading)], axis=-1)  # (S,B,2)
            hit = r < range_max_m  # no return: free up to range_max_m, nothing occupied
            ends, inside = self.box.cells(p[:, None, :2] + r[..., None] * u)
            self.hits += np.bincount(ends[hit & inside], minlength=n_cells).astype(np.int32)
            along = t[None, None, :] < (r - CELL_M / 2)[..., None]  # (S,B,T): before the hit cell
            pts = p[:, None, None, :2] + t[None, None, :, None] * u[:, :, None, :]
            idx, inside = self.box.cells(pts)
            self.passes += np.bincount(idx[along & inside], minlength=n_cells).astype(np.int32)

    def grid(self) -> np.ndarray:
        """Trinary like a saved map: log-odds of hits and passes past +-``LOGODDS_THRESHOLD``."""
        logodds = LOGODDS_HIT * self.hits + LOGODDS_PASS * self.passes
        grid = np.full(len(logodds), GRID_UNKNOWN, np.uint8)
        grid[logodds < -LOGODDS_THRESHOLD] = GRID_FREE
        grid[logodds > LOGODDS_THRESHOLD] = GRID_OCCUPIED
        return grid.reshape(self.box.shape)


def compressed(grid: np.ndarray) -> dict:
    from PIL import Image

    png = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(grid), mode="L").save(png, format="PNG", compress_level=6)
    return {"zlib6": len(zlib.compress(grid.tobytes(), 6)), "png": len(png.getvalue())}


def free_space_local(rec: Recording):
    """The world's free space in the recording's map frame (its start pose is the map frame)."""
    import shapely
    from shapely import affinity

    from robot_agent.sim import builtin_world, free_space

    inv = inverse(rec.start)
    c, s = np.cos(inv[2]), np.sin(inv[2])
    geom = affinity.affine_transform(free_space(builtin_world(rec.world)), [c, -s, s, c, inv[0], inv[1]])
    return shapely.make_valid(geom)


class RunGrids:
    """Both grids of one recording, over the union of its maps' boxes, as of any of its maps."""

    def __init__(self, rec: Recording):
        self.rec = rec
        boxes = [_bbox(m.seg) for m in rec.maps if len(m.seg)]
        self.box = GridBox(np.min([b[0] for b in boxes], axis=0), np.max([b[1] for b in boxes], axis=0))
        self.free = polygon_free(self.box, free_space_local(rec))
        self.counts = ScanCounts(self.box)
        self._scans = 0

    def at(self, k: int, rows: np.ndarray | None = None) -> dict:
        """Sizes of the grids of map ``k``'s box (of its ``rows`` only) when it was sent."""
        rec, m = self.rec, self.rec.maps[k]
        seg = m.seg if rows is None else m.seg[rows]
        upto = int(rec.map_scans[k])
        if upto < self._scans:
            raise ValueError("RunGrids.at: maps must be asked for in order")
        self.counts.add(rec.scan_poses[self._scans : upto], rec.ranges[self._scans : upto], rec.angles,
                        rec.range_max_m)  # fmt: skip
        self._scans = upto
        if len(seg) == 0:  # an empty map: no box, no grid
            return dict.fromkeys(
                ("raw", "area_m2", "clean_zlib6", "clean_png", "scans_zlib6", "scans_png"), 0
            )
        lo, hi = _bbox(seg)
        clean = self.box.crop(clean_grid(seg, self.free, self.box), lo, hi)
        scans = self.box.crop(self.counts.grid(), lo, hi)
        return {"raw": clean.size, "area_m2": float(np.prod(hi - lo)),
                **{f"clean_{k}": v for k, v in compressed(clean).items()},
                **{f"scans_{k}": v for k, v in compressed(scans).items()}}  # fmt: skip


def map_vs_grid(m: RobotMap, tiles: list[Tile]) -> dict:
    """Wire bytes of ``m`` (all chunks) against the grids of its tiles, each over its own bounding box
    (one grid per wing: the smallest grid that covers the same area; a grid of the whole row's box
    would be mostly unknown cells and flatter the segments)."""
    chunks = codec.split(m)
    sent = sum(len(codec.encode(c)) for c in chunks)
    total: dict = {}
    for t in tiles:
        g = RunGrids(t.rec).at(len(t.rec.maps) - 1, t.rows)
        total = {k: total.get(k, 0) + v for k, v in g.items()}
    head = {
        "segments": len(m.seg), "elements": len(np.unique(m.element)), "particles_sent": m.n_particles,
        "chunks": len(chunks), "map_bytes": sent,
        "map_zlib6_bytes": sum(len(zlib.compress(codec.encode(c), 6)) for c in chunks),
    }  # fmt: skip
    ratios = {f"ratio_{k}": v / sent for k, v in total.items() if k != "area_m2"}
    return head | {f"grid_{k}": v for k, v in total.items()} | ratios


def rate_vs_grid(rec: Recording) -> dict:
    """A live agent's bytes per second (maps at most 1 Hz when changed, poses at 5 Hz) against the
    grid of each published map's box sent instead of the map."""
    grids = RunGrids(rec)
    total: dict = {}
    for k in range(len(rec.maps)):
        total = {key: total.get(key, 0) + v for key, v in grids.at(k).items()}
    d, maps_b, poses_b = rec.duration_s, float(rec.map_bytes.sum()), float(rec.pose_bytes.sum())
    head = {
        "robot": rec.name, "seconds": d, "maps_sent": len(rec.maps),
        "final_segments": len(final_map(rec).seg),
        "map_Bps": maps_b / d, "pose_Bps": poses_b / d, "total_Bps": (maps_b + poses_b) / d,
    }  # fmt: skip
    return head | {f"grid_{k}_Bps": v / d for k, v in total.items() if k != "area_m2"}


def bench_bytes(recs: list[Recording], n: int, rate_routes: int) -> dict:
    """Big maps of ``n`` rows and of ``n`` elements, one real map per world, and the rates."""
    rows = []
    for count in ("rows", "elements"):
        tiles = tiles_for(recs, 0, n, count)
        big = tiled_map(tiles, "robot1", np.zeros(3), prior=True)
        rows.append(map_vs_grid(big, tiles) | {"map": f"{n} {count}: {len(tiles)} real maps side by side"})
    for rec in [r for r in recs if r.seed == 0 and r.route == 0]:
        rows.append(map_vs_grid(final_map(rec), [Tile(rec, None, np.zeros(2))]) | {"map": rec.name})
    print("  bytes: maps done", flush=True)
    rates = [rate_vs_grid(r) for r in recs if r.seed == 0 and r.route < rate_routes]
    return {"maps": rows, "rates": rates}


def print_bytes(res: dict) -> None:
    out = [
        {
            "map": r["map"], "segments": r["segments"], "elements": r["elements"], "K": r["particles_sent"],
            "area m2": r["grid_area_m2"], "map B": r["map_bytes"], "grid raw B": r["grid_raw"],
            "raw/map": r["ratio_raw"],
            "clean zlib6/map": r["ratio_clean_zlib6"], "clean png/map": r["ratio_clean_png"],
            "scans zlib6/map": r["ratio_scans_zlib6"], "scans png/map": r["ratio_scans_png"],
        }
        for r in res["maps"]
    ]  # fmt: skip
    table(
        f"robot map (all chunks, codec) vs the {CELL_M * 100:g} cm occupancy grid of the same area "
        "(1 B/cell): raw, and compressed when clean (world free space + segments) or built from the scans",
        out,
    )
    out = [
        {
            "robot": r["robot"], "maps": r["maps_sent"], "seg": r["final_segments"], "map B/s": r["map_Bps"],
            "pose B/s": r["pose_Bps"], "total B/s": r["total_Bps"], "grid raw B/s": r["grid_raw_Bps"],
            "raw/total": r["grid_raw_Bps"] / r["total_Bps"],
            "clean zlib6/total": r["grid_clean_zlib6_Bps"] / r["total_Bps"],
            "scans zlib6/total": r["grid_scans_zlib6_Bps"] / r["total_Bps"],
        }
        for r in res["rates"]
    ]  # fmt: skip
    if out:
        out.append(
            {"robot": "mean"} | {k: float(np.mean([o[k] for o in out])) for k in out[0] if k != "robot"}
        )
    table(
        "bytes per robot per second (AgentCore: maps at most 1 Hz when changed, poses 5 Hz) vs the grid of "
        "each published map's box sent instead",
        out,
    )


# -- output ----------------------------------------------------------------------------------------


def _fmt(v) -> str:
    if v is None:
        return "-"
    if isinstance(v, float):
        if not np.isfinite(v):
            return "-"
        return f"{v:.1f}" if abs(v) >= 10 else f"{v:.2f}"
    return str(v)


def table(title: str, rows: list[dict]) -> None:
    if not rows:
        return
    cols = list(dict.fromkeys(k for r in rows for k in r))
    try:
        from rich.console import Console
        from rich.table import Table
    except ImportError:
        print(title)
        print(" | ".join(cols))
        for r in rows:
            print(" | ".join(_fmt(r.get(c)) for c in cols))
        return
    t = Table(title=title)
    for c in cols:
        t.add_column(c, justify="right")
    for r in rows:
        t.add_row(*[_fmt(r.get(c)) for c in cols])
    Console(width=200).print(t)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--only", choices=("fusion", "latency", "bytes"), action="append", help="repeatable")
    ap.add_argument("--quick", action="store_true", help="a fast check: fewer cases, shorter runs")
    ap.add_argument("--agents", type=int, nargs="+", default=None, help="latency: agent counts (1 4 8 16)")
    ap.add_argument("--seconds", type=float, default=None, help="latency: measured seconds per count (40)")
    ap.add_argument("--warmup", type=float, default=5.0, help="latency: seconds after every robot is placed")
    ap.add_argument("--min-gap", type=float, default=0.05, help="the server's --min-gap (s between fusions)")
    ap.add_argument("--profile", action="store_true", help="latency: sample the server with py-spy")
    ap.add_argument(
        "--leave",
        type=int,
        default=0,
        help="latency: this many agents stop halfway through the window (the graph rebuilt)",
    )
    ap.add_argument("--robots", type=int, nargs="+", default=None, help="fusion: robot counts (1 2 4 8 16)")
    ap.add_argument(
        "--sizes", type=int, nargs="+", default=None, help="fusion: segments per robot (100 300 1000)"
    )
    ap.add_argument("--reps", type=int, default=None, help="fusion: fusions after one robot's new map (12)")
    ap.add_argument("--no-priors-max", type=int, default=16, help="fusion: most robots run without priors")
    ap.add_argument("--cache", type=Path, default=ROOT / "benchmarks" / "results" / "bench_fleet_maps")
    ap.add_argument("--refresh", action="store_true", help="record the simulated agents again")
    ap.add_argument("--workdir", type=Path, default=Path("/tmp/bench_fleet"), help="logs and server state")
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results" / "bench_fleet.json")
    args = ap.parse_args(argv)
    sections = args.only or ["fusion", "latency", "bytes"]
    q = args.quick
    agents = args.agents or ([1, 4] if q else [1, 4, 8, 16])
    seconds = args.seconds or (10.0 if q else 40.0)
    n_runs = max(8 if q else 16, max(agents) if "latency" in sections else 0)
    if n_runs > len(RUNS):
        ap.error(f"--agents: at most {len(RUNS)} distinct recorded robots")
    record_s = 30.0 if q else RECORD_S
    recs = recordings(args.cache, n_runs, record_s, args.refresh)
    results: dict = {
        "loadavg_at_start": os.getloadavg(), "quick": q,
        "recorded": [
            {"robot": r.name, "maps": len(r.maps), "final_rows": len(final_map(r).seg)} for r in recs
        ],
    }  # fmt: skip
    if "fusion" in sections:
        robots, sizes = ((1, 4), (100, 300)) if q else ((1, 2, 4, 8, 16, 32, 100), (100, 300, 1000))
        robots, sizes = tuple(args.robots or robots), tuple(args.sizes or sizes)
        reps = args.reps or (4 if q else 12)
        results["fusion"] = bench_fusion(
            recs, robots, sizes, reps=reps, align_reps=1 if q else 2, no_priors_max=args.no_priors_max
        )
        print_fusion(results["fusion"])
    if "latency" in sections:
        rows = []
        for n in agents:
            run = run_latency(
                recs, n, seconds, args.warmup, args.min_gap, args.workdir, args.profile, args.leave
            )
            rows.append(latency_stats(run))
            print(f"  latency: {n} agents done", flush=True)
        results["latency"] = {
            "seconds": seconds,
            "min_gap_s": args.min_gap,
            "leave": args.leave,
            "rows": rows,
        }
        print_latency(rows, seconds)
    if "bytes" in sections:
        results["bytes"] = bench_bytes(recs, 1000, rate_routes=1 if q else 2)
        print_bytes(results["bytes"])
    save_results(args.out, "bench_fleet", results)
    return 0


def load_agent_cli(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(prog="bench_fleet.py load-agent")
    ap.add_argument("--robot", required=True)
    ap.add_argument("--connect", required=True)
    ap.add_argument("--fleet", default="bench")
    ap.add_argument("--recording", required=True)
    ap.add_argument("--prior", required=True, help="X,Y,THETA")
    ap.add_argument("--puts", required=True, help="write 'seq monotonic_put_time' per map here")
    ap.add_argument("--phase", type=float, default=0.0, help="seconds to wait before the first put")
    ap.add_argument("--first-map", type=int, default=0, help="replay the recorded maps from this one")
    ap.add_argument("--map-period", type=float, default=1.0)
    ap.add_argument("--pose-period", type=float, default=0.2)
    return load_agent_main(ap.parse_args(argv))


if __name__ == "__main__":
    if len(sys.argv) > 1 and sys.argv[1] == "load-agent":
        sys.exit(load_agent_cli(sys.argv[2:]))
    sys.exit(main())
