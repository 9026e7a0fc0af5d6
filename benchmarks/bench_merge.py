"""Merge delay: how long after the evidence is there the fleet places a robot (issue 21, item 2).

    .venv/bin/python benchmarks/bench_merge.py [--worlds office warehouse] [--seeds 0 ... 9]
        [--robots 3] [--duration 175] [--cache DIR] [--jobs 2] [--set KEY=VALUE ...]

Each seed's simulated robots (unknown starts: no priors) are first run as the demo's agents run
them (route i, seed ``100 * seed + i``, the online back end beside each, maps at 1 Hz when they
changed) and every map they would publish is recorded with its time (cached in ``--cache``). Then,
without processes or network, in simulated time:

- **evidence**: every map of every robot but the reference is matched, by the server's own
  matcher (``alignment.estimate_alignment``, one attempt's verification: corners, overlap, rival
  ratio, places contradicted by the free space seen set aside), against the maps of the same
  moment placed where they truly are: of the reference and of the robots whose own evidence came
  before (``--evidence chain``, the default: what a server that placed every robot the moment its
  evidence was there would have had placed), or of every other robot (``--evidence all``: a
  lower bound no server reaches — it matches against robots nobody has placed yet). The
  *evidence time* is the first snapshot at which the verdict is "aligned" at the true place
  (within 0.3 m / 3°, as a wrong merge is counted); a verdict "aligned" somewhere else is a *false
  verdict* — what a policy that took every verdict at once would have merged wrongly.
  The false verdicts are counted up to 60 s after the evidence (printed: all / after the evidence).
- **the fleet**: the maps go into ``map_server.fleet.Fleet`` in time order (a fusion after each,
  as the server does when it is idle), with the defaults or ``--set`` overrides of FleetConfig
  (``confirmations=1``, ``alignment.min_share=0.3``, ...); when each robot is placed, whether
  correctly, and where its first keyframe ends (the fleet's graph) against the truth; and its
  worst place at any time while placed (its placement, or its first keyframe where the graph bent
  it), against the truth in the reference of that moment: a robot placed well first and moved
  elsewhere later — placed again, or bent there — is counted beyond the wrong-merge bound (0.3 m /
  3°), and beyond 3× it (another place, not a young map's drift).

- **against the truth** (each robot's true path simulated again): the *floor* — the final error a
  merge would have that placed every robot's map where it truly lies as a whole (its keyframes
  fitted rigidly to its true path; the error counts the first keyframe against the reference's, so
  an agent whose map turned 0.3° from its first pose leaves 5 cm at 10 m to any merge) — and the
  keyframes' error (ATE, RMSE) in the fleet's graph (the whole fleet fitted to the truth at once)
  against in the robot's own map (fitted alone): what the merge costs or gains over the agents.

- **the fused map against the true walls**: the server's last fused map, in the world by the
  reference's true start, every 0.1 m along it the distance to the nearest true wall (median, 90th
  percentile, share within 0.05 m): what a user sees of all the errors above at once. And each
  placed robot's walls so, where the fleet has them against its own map at its true start (what a
  rigid merge that knew every robot's true transform would show): is the fusion as accurate as
  one robot?

- **the graph's edges against the truth**: each robot's own edges and the constraints tying it to
  the others, their median error and χ (the error in units of the edge's stated uncertainty) — a
  robot's final error is what these leave along the edges between its first keyframe and the
  reference's. Ties held as walls (``graph.line_ties``, the default) are solved as their walls,
  not as the fit's relative pose: each wall's point against its line where the truth puts their
  keyframes is printed too. With ``--decompose`` the final graph is solved again with every tie
  at the truth (held as walls: each line through its point at the truth) and with every robot's
  own edges at the truth: which of the two leaves the error.

Prints one row per robot (evidence, false verdicts, placed, delay, final error, floor, its own map
frame against its true start, ATE fleet / own, χ of its own edges / of its ties) and a summary:
median and worst delay, wrong merges,
robots never placed (or placed and undone by the end), how many final errors exceed issue 21's bound
(0.05 m / 0.5°), how many floors do and how many robots' own map frames do; writes
benchmarks/results/bench_merge.json.
Live timing (a fusion takes time, messages queue) is not in this figure: bench_demo.py measures
the whole fleet on loopback.
"""

from __future__ import annotations

import argparse
import copy
import itertools
import json
import sys
import time
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from _results import save_results  # noqa: E402

from fleet_slam.report import WRONG_MERGE_DEG, WRONG_MERGE_M  # noqa: E402
from map_server.alignment import estimate_alignment  # noqa: E402
from map_server.config import FleetConfig  # noqa: E402
from map_server.contradiction import Check, own_noise, placed_noise, shrink, shrink_placed  # noqa: E402
from map_server.fleet import Fleet  # noqa: E402
from map_server.freespace import FreeSpaces  # noqa: E402
from map_server.fusion import fuse_particles, merge_segments  # noqa: E402
from map_server.posegraph import _among  # noqa: E402
from shared import codec  # noqa: E402
from shared.config import apply_overrides  # noqa: E402
from shared.geometry import apply_segments, compose, inverse, relative, transform_points, wrap_angle  # noqa: E402
from shared.messages import FreeSpace, RobotMap  # noqa: E402
from shared.metrics import align_se2, ate, nearest_segment, poses_at, sample_segments  # noqa: E402
from shared.posegraph import LineTies, line_residuals  # noqa: E402

CACHE_FORMAT = 3  # 2: with the free space; 3: the end of the run (corrected, rebuilt maps)


# -- recording -----------------------------------------------------------------------------------


def record(world_name: str, route: int, seed: int, duration_s: float, path: Path) -> Path:
    """One simulated robot as the demo runs it (fleet_slam/demo.py, robot_agent/service.py), its
    back end inline: every map it would publish, whole, with the source time."""
    from robot_agent.agent import AgentConfig, AgentCore
    from robot_agent.backend.live import InlineRunner, LiveCorrector
    from robot_agent.service import endless_config, final_correction, rebuild_along
    from robot_agent.sim import LiveSim, builtin_world
    from robot_agent.slam.config import command_line_config
    from robot_agent.slam.fastslam import FastSLAM
    from robot_agent.sources import LaserLog

    world = builtin_world(world_name)
    cfg = endless_config(command_line_config())
    slam = FastSLAM(cfg, np.random.default_rng(seed))
    core = AgentCore(
        f"robot{route + 1}", slam, AgentConfig(), corrector=LiveCorrector(slam, InlineRunner(cfg))
    )
    blobs, stamps, t0 = [], [], None
    free_blobs, free_stamps = [], []
    scans = []

    def publish(t: float, force: bool = False) -> None:
        core.pose_message()
        if core.map_messages(force=force) is not None:
            blobs.append(codec.encode_stored_map(codec.join(core.map_whole)))
            stamps.append(t)  # s since the robot started
        if core.free_message(force=force) is not None:
            free_blobs.append(codec.encode(core.free_whole))
            free_stamps.append(t)

    for scan in LiveSim(world, route, seed=seed).scans(duration_s):
        t0 = scan.stamp_s if t0 is None else t0
        scans.append(scan)
        core.step(scan)
        publish(scan.stamp_s - t0)
    # the end of the run as robot_agent/service.py does it: the back end's last correction, then
    # the map rebuilt along the corrected path, each published at once
    t_end = scans[-1].stamp_s - t0
    _, _, filter_poses, poses = final_correction(core, 60.0)
    publish(t_end, force=True)
    f = scans[0]
    log = LaserLog.from_arrays(
        np.array([x.stamp_s for x in scans]), np.array([x.ranges_m for x in scans]), f.angles_rad,
        np.array([x.odometry for x in scans]), f.laser_offset, f.range_max_m,
    )  # fmt: skip
    rebuild_along(core, log, core.first_scan, filter_poses, poses, cfg)
    publish(t_end, force=True)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp.npz")
    np.savez(
        tmp, blob=np.frombuffer(b"".join(blobs), np.uint8), offsets=np.cumsum([0] + [len(b) for b in blobs]),
        stamps=np.array(stamps), start=np.asarray(world.starts[route], float),
        free=np.frombuffer(b"".join(free_blobs), np.uint8),
        free_offsets=np.cumsum([0] + [len(b) for b in free_blobs]),
        free_stamps=np.array(free_stamps),
    )  # fmt: skip
    tmp.replace(path)
    return path


@dataclass
class Rec:
    stamps: np.ndarray
    maps: list[RobotMap]
    start: np.ndarray
    free_stamps: np.ndarray
    free: list[FreeSpace]


def load(path: Path) -> Rec:
    with np.load(path, allow_pickle=False) as z:
        blob, off = z["blob"].tobytes(), z["offsets"]
        maps = [codec.decode_stored_map(blob[a:b]) for a, b in itertools.pairwise(off)]
        fb, fo = z["free"].tobytes(), z["free_offsets"]
        free = [codec.decode(fb[a:b], expect=FreeSpace) for a, b in itertools.pairwise(fo)]
        return Rec(z["stamps"], maps, z["start"], z["free_stamps"], free)


def cache_path(cache: Path, world: str, route: int, seed: int, duration_s: float) -> Path:
    return cache / f"v{CACHE_FORMAT}-{world}-r{route}-s{seed}-{duration_s:g}s.npz"


def _record_job(job: tuple) -> Path:
    return record(*job)


# -- evidence and replay ---------------------------------------------------------------------------


ERROR_BOUND_M, ERROR_BOUND_DEG = 0.05, 0.5  # issue 21: every robot's transform at the end within these


def _error(t: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    d = relative(truth, t)
    return float(np.hypot(d[0], d[1])), float(np.degrees(abs(d[2])))


def true_path(world_name: str, route: int, seed: int, duration_s: float) -> tuple[np.ndarray, np.ndarray]:
    """A recorded robot's true poses (N,3) at its scans' stamps (N,) [s], simulated again without
    its laser: the route follower steers by the true pose, so the truth does not depend on the
    noise drawn (the same to the bit as beside the scans, in a third of the time)."""
    from robot_agent.sim import LiveSim, builtin_world

    sim = LiveSim(builtin_world(world_name), route, seed=seed)
    end, stamps, poses = sim.stamp_s + duration_s + 1e-9, [], []
    while sim.stamp_s <= end:
        stamps.append(sim.stamp_s)
        poses.append(sim.truth)
        for _ in range(sim.cfg.steps_per_scan):
            sim.step()
    return np.array(stamps), np.array(poses)


def wall_error(seg: np.ndarray, walls: np.ndarray, step_m: float = 0.1) -> dict:
    """How far a map's segments ``(N,2,2)`` lie from the true walls ``(W,2,2)`` (both in the world
    frame): every ``step_m`` along them, the distance to the nearest wall; its median, 90th
    percentile and the share within 0.05 m (the transform bound), over the map's length."""
    if not len(seg):
        return dict(wall_median_m=None, wall_p90_m=None, wall_within=None)
    dist, _ = nearest_segment(sample_segments(seg, step_m)[0], walls)
    return dict(
        wall_median_m=float(np.median(dist)),
        wall_p90_m=float(np.percentile(dist, 90)),
        wall_within=float(np.mean(dist <= ERROR_BOUND_M)),
    )


def _against_truth(paths_now: dict, names: list[str], ref: str, truth: dict, true: list) -> dict:
    """Each bent robot's keyframes against its true path: ``own_ate_m`` (its own map, placed as
    well as it can be rigidly: the agent's accuracy), ``fleet_ate_m`` (where the fleet's graph
    puts them, the whole fleet aligned to the truth at once: the fused map's), and ``floor_m`` /
    ``floor_deg``: the final error (its first keyframe against the reference's, the start
    relation) of a merge that placed each map where it truly lies as a whole — what the agents'
    own maps leave to any rigid merge (an agent whose map turned 0.3° from its first pose puts
    its start 5 cm from where its walls say it is); ``frame_m`` / ``frame_deg``: the robot's own
    share of that — its map frame as the fit of its keyframes to its true path has it, against
    its true start (the floor of a pair is about the two robots' frames composed)."""
    fits, out = {}, {}
    for n, p in paths_now.items():
        if len(p.local) >= 3:  # (a map placed as a whole has no path to compare)
            fits[n] = ate(p.kf_stamp, p.local, *true[names.index(n)])
    if not fits:
        return out
    xy, target, owner = [], [], []
    for n in fits:
        p = paths_now[n]
        xy.append(p.pose[:, :2])
        target.append(poses_at(*true[names.index(n)], p.kf_stamp)[:, :2])  # (as ate matches them)
        owner += [n] * len(p.pose)
    xy, target, owner = np.concatenate(xy), np.concatenate(target), np.array(owner)
    e = np.hypot(*(transform_points(align_se2(xy, target), xy) - target).T)
    for n, a in fits.items():
        row = out[n] = dict(own_ate_m=a.rmse_m, fleet_ate_m=float(np.sqrt(np.mean(e[owner == n] ** 2))))
        row["frame_m"], row["frame_deg"] = _error(a.alignment, true[names.index(n)][1][0])
        if ref in fits:
            row["floor_m"], row["floor_deg"] = _error(
                compose(inverse(fits[ref].alignment), a.alignment), truth[n]
            )
    return out


def _tie_at(c, n: str, graphs: dict) -> tuple[int, int] | None:
    """Constraint ``c`` on robot ``n``: the positions of its two keyframes in their robots' graphs
    (``graphs``: robot -> RobotGraph), None when either robot or keyframe is not there."""
    if n not in graphs or c.other not in graphs:
        return None
    og, g = graphs[c.other], graphs[n]
    ai, bi = int(np.searchsorted(og.ids, c.a_id)), int(np.searchsorted(g.ids, c.b_id))
    if ai >= len(og.ids) or og.ids[ai] != c.a_id or bi >= len(g.ids) or g.ids[bi] != c.b_id:
        return None  # (a keyframe no longer in its robot's graph)
    return ai, bi


def _walls_at_truth(c, n: str, graphs: dict, true_kf: dict) -> tuple[np.ndarray, np.ndarray]:
    """Constraint ``c`` on robot ``n`` held as walls (``c.lines``, map_server.posegraph.Walls):
    which of its points have both keyframes in their robots' graphs, and each point's signed
    distance from its line where the truth puts those keyframes (``shared.posegraph``'s residual)."""
    t = c.lines
    found_b, ib = _among(graphs[n].ids, t.mine)
    found_a, ia = _among(graphs[c.other].ids, t.theirs)
    ok = found_a & found_b
    at = np.arange(len(ok))
    x = np.concatenate([true_kf[c.other][ia], true_kf[n][ib]])
    r = line_residuals(x, LineTies(at, len(ok) + at, t.p, t.n, t.d, t.w, np.zeros(len(ok))))[0]
    return ok, r


def _edges_against_truth(graphs: dict, constraints: dict, true_kf: dict) -> dict:
    """The fleet graph's edges against the truth, per robot (``true_kf``: robot -> its true poses
    at its keyframes): its own edges (the relative poses its own solution gives) and the constraints
    tying its keyframes to the others' — the median error of each (m, |°|) and the median of
    ``sqrt(eᵀ I e / 3)``, the error in units of the edge's own stated uncertainty (1: as stated;
    under 1: the graph trusts the edge less than it deserves). A robot's final error is the sum of
    both along the edges between its first keyframe and the reference's."""

    def stats(z, info, tz) -> tuple[float, float, float]:
        e = z - tz
        e[:, 2] = wrap_angle(e[:, 2])
        chi = np.sqrt(np.einsum("ei,eij,ej->e", e, info, e) / 3.0)
        return (float(np.median(np.hypot(e[:, 0], e[:, 1]))), float(np.degrees(np.median(np.abs(e[:, 2])))),
                float(np.median(chi)))  # fmt: skip

    out = {}
    for n, g in graphs.items():
        row = out[n] = {}
        if n not in true_kf:
            continue
        tk = true_kf[n]
        if len(g.a):
            row["own_edge_m"], row["own_edge_deg"], row["own_edge_chi"] = stats(
                g.z, g.info, relative(tk[g.a], tk[g.b])
            )
        z, info, tz, off, off_chi = [], [], [], [], []
        for c in constraints.get(n, {}).values():
            at = _tie_at(c, n, graphs) if c.other in true_kf else None
            if at is None:
                continue
            ai, bi = at
            z.append(c.z)
            info.append(c.info)
            tz.append(relative(true_kf[c.other][ai], tk[bi]))
            if c.lines is not None:  # (held as walls: each point's distance from its line at the truth)
                ok, r = _walls_at_truth(c, n, graphs, true_kf)
                off.append(np.abs(r[ok]))
                off_chi.append(np.abs(r[ok]) * np.sqrt(c.lines.w[ok]))
        row["constraints"] = len(z)
        if z:
            row["constraint_m"], row["constraint_deg"], row["constraint_chi"] = stats(
                np.array(z, float), np.array(info), np.array(tz)
            )
        if off:
            row["wall_tie_m"] = float(np.median(np.concatenate(off)))
            row["wall_tie_chi"] = float(np.median(np.concatenate(off_chi)))
    return out


def decompose(graph, items: list, true_kf: dict, ref: str) -> dict:
    """Where each robot's final error comes from: the fleet's graph (``graph``: a FleetGraph at its
    final state, not changed; ``items``: its placed robots, map_server.posegraph.Placed) solved
    again as it is, with every tie between robots set to the truth (what the robots' own edges
    leave), with every robot's own edges set to the truth (what the ties leave), and with both.
    Robot -> ``{as_is, true_ties, true_own, both}``, each ``(m, deg)``: its first keyframe against
    the reference's (``true_kf``: each robot's true poses at its keyframes)."""
    items = [it for it in items if not it.graph.rigid and it.robot in true_kf]
    if ref not in {it.robot for it in items}:
        return {}
    graphs = {it.robot: it.graph for it in items}

    def true_tie(c, n):
        at = _tie_at(c, n, graphs)
        if at is None:
            return c
        c = replace(c, z=relative(true_kf[c.other][at[0]], true_kf[n][at[1]]))
        if c.lines is None:
            return c
        # ties held as walls (GraphConfig.line_ties): each line through its point at the truth
        ok, r = _walls_at_truth(c, n, graphs, true_kf)
        return replace(c, lines=c.lines._replace(d=np.where(ok, c.lines.d + r, c.lines.d)))

    own = []
    for it in items:
        tk, g = true_kf[it.robot], it.graph
        own.append(replace(it, graph=replace(g, z=relative(tk[g.a], tk[g.b]))))
    out: dict[str, dict] = {}
    for name, ties, placed in (("as_is", False, items), ("true_ties", True, items), ("true_own", False, own),
                               ("both", True, own)):  # fmt: skip
        g = copy.deepcopy(graph)
        if ties:
            g.constraints = {n: {k: true_tie(c, n) for k, c in cs.items()} for n, cs in g.constraints.items()}
        x = g.solve(placed)
        for it in placed:
            if it.robot != ref:
                out.setdefault(it.robot, {})[name] = _error(
                    relative(x[ref][0], x[it.robot][0]), relative(true_kf[ref][0], true_kf[it.robot][0])
                )
    return out


def _over(errors: list[tuple[float, float]]) -> int:
    """How many ``(m, deg)`` errors exceed issue 21's bound."""
    return sum(m > ERROR_BOUND_M or deg > ERROR_BOUND_DEG for m, deg in errors)


def _m_deg(row: dict, key: str) -> str:
    """A row's ``<key>_m`` / ``<key>_deg`` error as printed ("-" when the row has none)."""
    return "-" if f"{key}_m" not in row else f"{row[f'{key}_m']:.3f}m/{row[f'{key}_deg']:.2f}°"


FAR = 3.0  # a place this many times the wrong-merge bound off: another place, not a drifted map's


def held_text(row: dict) -> str:
    """A bench row's worst place while placed, as printed."""
    m, deg, t = row["worst_held_m"], row["worst_held_deg"], row["worst_held_s"]
    return f" held {m:.2f} m / {deg:.1f}° off at {t:g} s"


def _bounds_off(m: float, deg: float) -> float:
    """How far a place is off, in units of the wrong-merge bound (over 1: a wrong merge)."""
    return max(m / WRONG_MERGE_M, deg / WRONG_MERGE_DEG)


def _held_wrong(row: dict, times: float) -> bool:
    """Whether the robot's worst place while placed (bench row) was ``times`` the wrong-merge
    bound off (or more)."""
    return "worst_held_m" in row and _bounds_off(row["worst_held_m"], row["worst_held_deg"]) >= times


def _worst_held(held: list[tuple], truth_of: Callable[[str], np.ndarray]) -> tuple | None:
    """A robot's worst place while it was placed: ``held`` its places after each fusion, ``(time,
    the reference then, its placement, its map frame where the graph put its first keyframe or
    None)``; ``truth_of(reference)`` its true map frame in that reference's. ``(m, deg, time)`` of
    the place farthest off in units of the wrong-merge bound, None if never placed."""
    places = [
        (*_error(frame, truth_of(reference)), t)
        for t, reference, placement, bent in held
        for frame in (placement, bent)
        if frame is not None
    ]
    return max(places, key=lambda e: _bounds_off(e[0], e[1]), default=None)


def _wrong(t: np.ndarray, truth: np.ndarray) -> bool:
    return _bounds_off(*_error(t, truth)) > 1.0


def run_seed(
    world: str,
    seed: int,
    robots: int,
    paths: list[Path],
    sets: list[str],
    known: dict | None = None,
    evidence: str = "chain",
    decomposed: bool = False,
) -> dict:
    """Evidence and the fleet's placements for one seed's recorded robots (``known``: the
    evidence rows of an earlier run on the same recordings, not measured again; ``decomposed``:
    each robot's final error decomposed, :func:`decompose`)."""
    cfg = apply_overrides(FleetConfig(), sets)
    recs = [load(p) for p in paths]
    names = [f"robot{i + 1}" for i in range(robots)]
    events = sorted(
        [(float(t), 1, i, k) for i, r in enumerate(recs) for k, t in enumerate(r.stamps)]
        + [(float(t), 0, i, k) for i, r in enumerate(recs) for k, t in enumerate(r.free_stamps)]
    )  # a free space before the map of the same moment (the agent publishes both together)

    # the fleet, in simulated time
    fleet = Fleet(cfg, "bench")
    free = FreeSpaces()
    fleet.free_of = free.area
    placed_at: dict[str, float] = {}
    first_place: dict[str, np.ndarray] = {}
    # every place a robot had after each fusion, while placed: (time, the reference then, its
    # placement, its map frame where the graph puts its first keyframe or None) — a robot placed
    # well and later moved elsewhere (placed again, or bent there) is a wrong merge as well
    held: dict[str, list[tuple]] = {}

    def _truth(reference: str, n: str) -> np.ndarray:  # robot n's map frame in the reference's
        return compose(inverse(recs[names.index(reference)].start), recs[names.index(n)].start)

    t0 = time.perf_counter()

    def fuse(t: float) -> None:
        fleet.fuse(t)
        for n, r in fleet.robots.items():
            if r.alignment.placed and n not in placed_at:
                placed_at[n] = t
                first_place[n] = r.alignment.transform.copy()
            if r.alignment.placed and fleet.reference is not None and n != fleet.reference:
                bent = None
                if r.bent is not None and r.graph is not None and r.bent_x is not None:
                    bent = compose(r.bent_x[0], inverse(r.graph.pose[0]))
                held.setdefault(n, []).append((t, fleet.reference, r.alignment.transform.copy(), bent))

    for t, is_map, i, k in events:
        if not is_map:
            free.put(recs[i].free[k])
            continue
        fleet.put_map(recs[i].maps[k], t)
        fuse(t)
    t_end = events[-1][0] if events else 0.0
    for n in names:  # the agents finish: each leaves (the server solves its graph again, settles)
        fleet.set_online(n, False)
    for extra in range(1, 31):  # the server goes on fusing (server.py: every idle period) ...
        fuse(t_end + extra)
        if not fleet.pending_work and all(r.pending is None for r in fleet.robots.values()):
            break  # ... and a candidate awaiting confirmation gets its next attempt (retry_interval_s)
    fuse_s = time.perf_counter() - t0
    ref = fleet.reference or names[0]
    iref = names.index(ref)
    truth = {n: _truth(ref, n) for n in names}
    latest = fleet.latest()
    paths_now = {p.robot: p for p in fleet.paths(latest.version if latest is not None else 0)}

    # evidence: each robot's maps against the others' of the same moment, placed at the truth
    layers: dict[tuple[int, int], object] = {}
    areas: dict[tuple[int, int], object] = {}
    ccfg = cfg.contradiction

    def layer(i: int, k: int):
        if (i, k) not in layers:
            layers[(i, k)] = fuse_particles(recs[i].maps[k], cfg.fusion)
        return layers[(i, k)]

    def area(i: int, t: float):
        k = int(np.searchsorted(recs[i].free_stamps, t, side="right") - 1)
        if k < 0:
            return None
        if (i, k) not in areas:
            one = FreeSpaces()
            one.put(recs[i].free[k])
            m = recs[i].free[k]
            areas[(i, k)] = one.area(m.robot, m.session)
        return areas[(i, k)]

    def match(i: int, k: int, t: float, pool: list[int]):
        """Robot ``i``'s map ``k`` against the maps of the robots in ``pool`` at ``t``, placed at
        the truth: the verdict and the contradiction (m) at its place, or None."""
        others = []
        for j in pool:
            kj = np.searchsorted(recs[j].stamps, t, side="right") - 1
            if kj >= 0:
                others.append((j, layer(j, kj)))
        if not others:
            return None
        seg = np.concatenate([apply_segments(truth[names[j]], lj.seg) for j, lj in others])
        w = np.concatenate([lj.weight for _, lj in others])
        owner = np.concatenate([np.full(len(lj), j) for j, lj in others])
        merged = merge_segments(seg, w, owner, cfg.fusion)[0]
        if len(layer(i, k)) == 0 or len(merged) == 0:
            return None

        def checked():
            """contradiction.Check's arguments, as Placer.veto gives them."""
            seen = [(j, lj, a) for j, lj in others if (a := area(j, t)) is not None]
            grid = ccfg.grid
            theirs = shrink_placed([(a, truth[names[j]]) for j, _, a in seen], *grid)
            noise = placed_noise(
                [(own_noise(lj.seg, shrink(a, *grid), ccfg.step_m), truth[names[j]]) for j, lj, a in seen]
            )
            return layer(i, k).seg, shrink(area(i, t), *grid), merged, theirs, ccfg, noise

        check = Check(*checked()) if ccfg.enabled else None
        a = estimate_alignment(layer(i, k).seg, merged, cfg.alignment, veto=check)
        if a.status != "aligned":
            return None
        check = check or Check(*checked())  # contradiction (m), matched (m), the maps' own (m)
        return a, (check.contradicted_m(a.transform), a.score_m, check.noise_m(a.transform))

    # evidence, in time order over every robot's maps: "chain" matches a robot against the
    # reference and the robots whose own evidence came before (what a server that placed each
    # robot as soon as its evidence was there would have placed); "all" against every other robot
    found = {iref}  # the robots (indices) whose evidence came: the reference's is its own map
    ev = {i: dict(evidence_s=None, false_verdicts=0, false_after=0, first_false_s=None,
                  contradiction_true=[], contradiction_false=[], verdicts=[])
          for i, n in enumerate(names) if n != ref and known is None}  # fmt: skip
    snaps = sorted((float(t), i, k) for i in ev for k, t in enumerate(recs[i].stamps))
    for t, i, k in snaps:
        e = ev[i]
        if e["evidence_s"] is not None and t - e["evidence_s"] > 60.0:
            continue  # enough seen after the evidence (false verdicts: before and shortly after)
        pool = [j for j in range(robots) if j != i and (evidence == "all" or j in found)]
        hit = match(i, k, t, pool)
        if hit is None:
            continue
        a, contradicted = hit
        bad = _wrong(a.transform, truth[names[i]])
        e["verdicts"].append(
            (t, not bad, round(a.rival_ratio, 2), round(a.score_m, 1), round(a.inlier_share, 2),
             *np.round(a.transform, 3).tolist())
        )  # fmt: skip
        if bad:
            e["false_verdicts"] += 1
            e["first_false_s"] = t if e["first_false_s"] is None else e["first_false_s"]
            e["false_after"] += e["evidence_s"] is not None
            e["contradiction_false"].append(contradicted)
        else:
            e["contradiction_true"].append(contradicted)
            if e["evidence_s"] is None:
                e["evidence_s"] = t
                found.add(i)

    true = [true_path(world, i, 100 * seed + i, float(recs[i].stamps[-1]) + 1.0) for i in range(robots)]
    against = _against_truth(paths_now, names, ref, truth, true)
    graphs = {n: fleet.robots[n].graph for n in paths_now}
    graphs = {n: g for n, g in graphs.items() if g is not None and not g.rigid}
    true_kf = {n: poses_at(*true[names.index(n)], paths_now[n].kf_stamp) for n in graphs}
    for n, row in _edges_against_truth(graphs, fleet.graph.constraints, true_kf).items():
        against.setdefault(n, {}).update(row)
    if decomposed:
        for n, row in decompose(fleet.graph, fleet.graph_items(), true_kf, ref).items():
            against.setdefault(n, {})["decomposed"] = row
    out = {}
    for i, n in enumerate(names):
        row = dict(robot=n, reference=n == ref, placed_s=placed_at.get(n)) | against.get(n, {})
        if n in fleet.robots and not fleet.robots[n].alignment.placed:
            row["reason"] = fleet.robots[n].alignment.reason
        if n in first_place:
            row["wrong_merge"] = _wrong(first_place[n], truth[n])
        worst = _worst_held(held.get(n, []), lambda reference, n=n: _truth(reference, n))
        if worst is not None:
            row["worst_held_m"], row["worst_held_deg"], row["worst_held_s"] = worst
        if n in paths_now:
            p = paths_now[n]
            frame = compose(p.pose[0], inverse(p.local[0]))  # its map frame by its first keyframe
            row["error_m"], row["error_deg"] = _error(frame, truth[n])
        if n != ref:
            if known is not None:
                keep = ("evidence_s", "false_verdicts", "false_after", "first_false_s", "verdicts")
                row.update({k: known[n][k] for k in keep if k in known.get(n, {})})
            else:
                row.update(ev[i])
            if row.get("evidence_s") is not None and row["placed_s"] is not None:
                row["delay_s"] = row["placed_s"] - row["evidence_s"]
        out[n] = row
    from robot_agent.sim import builtin_world

    walls = builtin_world(world).walls
    for i, n in enumerate(names):  # each robot's walls: its own map at its true start, and where
        r = fleet.robots.get(n)  # the fleet has them (bent, or placed as a whole)
        if r is None or r.layer is None or not len(r.layer) or not r.alignment.placed:
            continue
        mine = r.bent.seg if r.bent is not None else apply_segments(r.alignment.transform, r.layer.seg)
        for key, seg in (("own", apply_segments(recs[i].start, r.layer.seg)),
                         ("fleet", apply_segments(recs[iref].start, mine))):  # fmt: skip
            out[n] |= {f"{key}_{k}": v for k, v in wall_error(seg, walls).items()}
    fused = np.zeros((0, 2, 2)) if latest is None else apply_segments(recs[iref].start, latest.seg)
    return dict(world=world, seed=seed, fuse_s=fuse_s, robots=out) | wall_error(fused, walls)


def contra_text(r: dict) -> str:
    """Contradiction (m) at the true verdicts (largest) and at the false ones (smallest)."""
    ct, cf = r.get("contradiction_true", []), r.get("contradiction_false", [])
    if not ct and not cf:
        return ""
    t = max(ct, default=None, key=lambda c: c[0])
    f = min(cf, default=None, key=lambda c: c[0])

    def one(c) -> str:  # contradicted / matched (own contradiction)
        return "-" if c is None else f"{c[0]:.1f}m/{c[1]:.0f}m" + (f"({c[2]:.1f})" if len(c) > 2 else "")

    return f"  contradicted: true max {one(t)}  false min {one(f)}"


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--worlds", nargs="+", default=["office", "warehouse"])
    p.add_argument("--seeds", type=int, nargs="+", default=list(range(10)))
    p.add_argument("--robots", type=int, default=3)
    p.add_argument("--duration", type=float, default=175.0)
    p.add_argument("--cache", type=Path, default=ROOT / "benchmarks" / "results" / "bench_merge_maps")
    p.add_argument("--jobs", type=int, default=2)
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="a FleetConfig override")
    p.add_argument("--evidence-from", type=Path, default=None,
                   help="a bench_merge JSON of the same recordings and matcher: its evidence")  # fmt: skip
    p.add_argument("--evidence", choices=["chain", "all"], default="chain",
                   help="match each robot against the reference and the robots evidenced before it "
                        "(chain), or against every other robot (all)")  # fmt: skip
    p.add_argument(
        "--decompose", action="store_true", help="each final error with the ties, or own edges, at the truth"
    )
    p.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results" / "bench_merge.json")
    args = p.parse_args()
    apply_overrides(FleetConfig(), args.set)  # a bad override fails before any work

    runs = [(w, s) for w in args.worlds for s in args.seeds]
    paths = {
        (w, s): [cache_path(args.cache, w, i, 100 * s + i, args.duration) for i in range(args.robots)]
        for w, s in runs
    }
    todo = [(w, i, 100 * s + i, args.duration, cp) for (w, s), ps in paths.items() for i, cp in enumerate(ps)
            if not cp.exists()]  # fmt: skip
    with ProcessPoolExecutor(args.jobs) as pool:
        if todo:
            print(
                f"recording {len(todo)} simulated robots ({args.duration:g} s each) into {args.cache} ...",
                flush=True,
            )
            list(pool.map(_record_job, todo))
        known = {}
        if args.evidence_from is not None:
            for res in json.loads(args.evidence_from.read_text())["results"]:
                known[(res["world"], res["seed"])] = res["robots"]
        futures = [
            pool.submit(
                run_seed,
                w,
                s,
                args.robots,
                paths[(w, s)],
                args.set,
                known.get((w, s)) if known else None,
                args.evidence,
                args.decompose,
            )
            for w, s in runs
        ]
        results = [f.result() for f in futures]

    print(f"{'world':9} {'seed':>4} {'robot':7} {'evidence':>8} {'false':>9} {'placed':>6} {'delay':>6} "
          f"{'error':>14} {'floor':>14} {'own frame':>14} {'ATE fleet/own':>13} "
          f"{'χ own/ties':>10}  wrong")  # fmt: skip
    delays, wrong, unplaced, unplaced_end, errors, floors, ates, frames = [], 0, 0, 0, [], [], [], []
    wrong_held = far_held = 0
    held_worst = 0.0
    edges: dict[str, list[float]] = {}  # own_edge_* / constraint_* -> each robot's median
    for res in results:
        for n, r in res["robots"].items():

            def f(v, fmt="{:.0f}"):
                return "-" if v is None else fmt.format(v)

            err, flo, fr = (_m_deg(r, key) for key in ("error", "floor", "frame"))
            at = "-" if "own_ate_m" not in r else f"{r['fleet_ate_m']:.3f}/{r['own_ate_m']:.3f}"
            chi = f"{f(r.get('own_edge_chi'), '{:.2f}')}/{f(r.get('constraint_chi'), '{:.2f}')}"
            for key in ("own_edge", "constraint", "wall_tie"):
                for unit in ("m", "deg", "chi"):
                    if f"{key}_{unit}" in r:
                        edges.setdefault(f"{key}_{unit}", []).append(r[f"{key}_{unit}"])
            print(
                f"{res['world']:9} {res['seed']:4d} {n:7} {f(r.get('evidence_s')):>8} "
                f"{r.get('false_verdicts', 0):5d}/{r.get('false_after', 0):<3d} "
                f"{f(r['placed_s']):>6} {f(r.get('delay_s')):>6} {err:>14} {flo:>14} {fr:>14} {at:>13} "
                f"{chi:>10}  "
                + ("REFERENCE" if r["reference"] else ("WRONG" if r.get("wrong_merge") else ""))
                + (held_text(r) if _held_wrong(r, 1.0) else "")
                + contra_text(r)
                + (f"  unplaced: {r['reason']}" if r.get("reason") else "")
            )
            if "own_ate_m" in r:
                ates.append((r["fleet_ate_m"], r["own_ate_m"]))
            if "frame_m" in r:
                frames.append((r["frame_m"], r["frame_deg"]))
            if r["reference"]:
                continue
            if "floor_m" in r:
                floors.append((r["floor_m"], r["floor_deg"]))
            wrong += bool(r.get("wrong_merge"))
            wrong_held += _held_wrong(r, 1.0)
            far_held += _held_wrong(r, FAR)
            held_worst = max(held_worst, r.get("worst_held_m", 0.0))
            unplaced += r["placed_s"] is None
            if r.get("delay_s") is not None:
                delays.append(r["delay_s"])
            if "error_m" in r:
                errors.append((r["error_m"], r["error_deg"]))
            else:
                unplaced_end += r["placed_s"] is not None  # placed once, not at the end (undone)
    over, floor_over, frames_over = _over(errors), _over(floors), _over(frames)
    summary = dict(
        runs=len(results), wrong_merges=wrong, held_over_wrong_bound=wrong_held, held_far=far_held,
        held_worst_m=held_worst, unplaced=unplaced, unplaced_at_end=unplaced_end,
        errors_over_bound=over, errors_scored=len(errors),
        error_mean_m=float(np.mean([e[0] for e in errors])) if errors else None,
        delay_median_s=float(np.median(delays)) if delays else None,
        delay_max_s=float(np.max(delays)) if delays else None,
        error_max_m=max((e[0] for e in errors), default=None),
        error_max_deg=max((e[1] for e in errors), default=None),
        floors_over_bound=floor_over, floors_scored=len(floors),
        floor_max_m=max((e[0] for e in floors), default=None),
        frames_over_bound=frames_over, frames_scored=len(frames),
        frame_max_m=max((e[0] for e in frames), default=None),
        frame_mean_m=float(np.mean([e[0] for e in frames])) if frames else None,
        fleet_ate_mean_m=float(np.mean([a[0] for a in ates])) if ates else None,
        own_ate_mean_m=float(np.mean([a[1] for a in ates])) if ates else None,
    ) | {f"{k}_median": float(np.median(v)) for k, v in edges.items()}  # fmt: skip
    print(
        f"{len(results)} runs: {wrong} wrong merges; robots placed (or bent) at some time beyond the "
        f"wrong-merge bound {wrong_held}, beyond {FAR:g}× it {far_held} (worst {held_worst:.2f} m); "
        f"{unplaced} robots never placed, {unplaced_end} placed "
        f"but not at the end; delay from evidence to merge median {summary['delay_median_s']} s, worst "
        f"{summary['delay_max_s']} s; final errors over {ERROR_BOUND_M} m / {ERROR_BOUND_DEG}°: {over} of "
        f"{len(errors)} (mean {summary['error_mean_m'] or 0:.3f} m), worst {summary['error_max_m']} m / "
        f"{summary['error_max_deg']}°; a merge placing every map where it truly lies as a whole would be "
        f"over the bound {floor_over} of {len(floors)} times (worst {summary['floor_max_m'] or 0:.3f} m: the "
        f"agents' own maps: {frames_over} of {len(frames)} robots' own map frames are over it, mean "
        f"{summary['frame_mean_m'] or 0:.3f} m, worst {summary['frame_max_m'] or 0:.3f} m); keyframes "
        f"against the truth (ATE, RMSE, mean) "
        f"{summary['fleet_ate_mean_m'] or 0:.3f} m in the fleet's graph, "
        f"{summary['own_ate_mean_m'] or 0:.3f} m in the robots' own maps"
    )
    own = [r for res in results for r in res["robots"].values() if "own_wall_within" in r]
    if own:
        for side in ("own", "fleet"):
            for key in ("wall_median_m", "wall_p90_m", "wall_within"):
                summary[f"{side}_{key}_mean"] = float(np.mean([r[f"{side}_{key}"] for r in own]))
        print(
            f"each placed robot's walls against the true walls (mean over {len(own)} robots): its own map at "
            f"its true start median {summary['own_wall_median_m_mean']:.4f} m, 90th percentile "
            f"{summary['own_wall_p90_m_mean']:.4f} m, {summary['own_wall_within_mean']:.1%} within "
            f"{ERROR_BOUND_M} m; where the fleet has them {summary['fleet_wall_median_m_mean']:.4f} m, "
            f"{summary['fleet_wall_p90_m_mean']:.4f} m, {summary['fleet_wall_within_mean']:.1%}"
        )
    walls = [res for res in results if res.get("wall_median_m") is not None]
    if walls:
        for key in ("wall_median_m", "wall_p90_m", "wall_within"):
            summary[f"{key}_mean"] = float(np.mean([res[key] for res in walls]))
        print(
            f"the fused maps against the true walls (mean over {len(walls)} runs): median "
            f"{summary['wall_median_m_mean']:.4f} m, 90th percentile {summary['wall_p90_m_mean']:.4f} m, "
            f"{summary['wall_within_mean']:.1%} of their length within {ERROR_BOUND_M} m"
        )
    decomposed = [(res["world"], res["seed"], n, r["decomposed"]) for res in results
                  for n, r in res["robots"].items() if "decomposed" in r]  # fmt: skip
    if decomposed:
        print("each final error solved again (first keyframe against the reference's): as it is / every tie "
              "between robots at the truth / every robot's own edges at the truth / both")  # fmt: skip
        for world, seed, n, d in decomposed:
            cells = (f"{d[k][0]:.3f}m {d[k][1]:.2f}°" for k in ("as_is", "true_ties", "true_own", "both"))
            print(f"  {world:9} {seed:4d} {n:7} " + " / ".join(cells))
        for key in ("as_is", "true_ties", "true_own"):
            summary[f"decomposed_{key}_over_bound"] = _over([d[key] for *_, d in decomposed])
        print(
            f"over the bound: as it is {summary['decomposed_as_is_over_bound']}, with true ties "
            f"{summary['decomposed_true_ties_over_bound']}, with true own edges "
            f"{summary['decomposed_true_own_over_bound']} of {len(decomposed)}"
        )
    if "constraint_m_median" in summary and "own_edge_m_median" in summary:
        print(
            "the graph's edges against the truth (median over robots of each robot's median): its own "
            f"{summary['own_edge_m_median']:.4f} m / {summary['own_edge_deg_median']:.3f}°, χ "
            f"{summary['own_edge_chi_median']:.2f}; the ties between robots "
            f"{summary['constraint_m_median']:.4f} m / "
            f"{summary['constraint_deg_median']:.3f}°, χ {summary['constraint_chi_median']:.2f} "
            "(χ: the error in units of the edge's stated uncertainty)"
            + (
                f"; held as walls (graph.line_ties), each wall's point from its line at the truth "
                f"{summary['wall_tie_m_median']:.4f} m, χ {summary['wall_tie_chi_median']:.2f}"
                if "wall_tie_m_median" in summary
                else ""
            )
        )
    args_out = vars(args) | {
        "cache": str(args.cache),
        "out": str(args.out),
        "evidence_from": str(args.evidence_from),
    }
    save_results(args.out, "bench_merge", dict(args=args_out,
                                               summary=summary, results=results))  # fmt: skip
    return 1 if wrong else 0


if __name__ == "__main__":
    sys.exit(main())
