"""The demo's outputs and metrics (docs/design.md; keys documented in the README).

Frames: the server's *global* frame is the prior frame (known starts: the world frame) or the
reference robot's map frame (unknown starts). For a simulated fleet the true pose of the global
frame in the world, ``G``, follows from the reference robot's true start; every estimate is
scored in the world frame through ``G``: a robot's transform error compares its estimated
transform with the truth ``G⁻¹ ∘ start``; its ATE compares ``G ∘ T ∘ local poses`` with its true
path (no further alignment: that is what a user of the fused map gets).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from fleet_slam.watch import Update
from shared.geometry import apply_segments, compose, identity, inverse
from shared.messages import FusedFree, FusedMap
from shared.metrics import (
    Relations,
    RelationsError,
    ate,
    map_quality,
    read_poses,
    read_relations,
    relations_error,
    transform_error,
    write_poses,
    write_tum,
)
from shared.viz import (
    PathLayer,
    Picture,
    SegmentLayer,
    robot_colour,
    save_geojson,
    save_picture,
    segments_geojson,
)

WRONG_MERGE_M = 0.3  # a merged robot whose transform is off by more than this ...
WRONG_MERGE_DEG = 3.0  # ... or this is a wrong merge


def _first_merges(updates: list[Update], t0: float) -> dict[str, float]:
    first: dict[str, float] = {}
    for u in updates:
        for r in u.fused.robots:
            if r.merged and r.robot not in first:
                first[r.robot] = u.wall_s - t0
    return first


def _frames(final: FusedMap, paths: dict | None) -> dict[str, np.ndarray]:
    """Where each merged robot's map frame (its start frame) is in the global frame: the first
    keyframe's placement by the fleet's graph (``paths``, RobotPath per robot) — the status's
    transform is its newest keyframe's, where the robot is now — else the status's transform
    (a map placed as a whole)."""
    out = {}
    for s in final.robots:
        p = (paths or {}).get(s.robot)
        if p is not None and p.robot_session == s.session:
            out[s.robot] = compose(p.pose[0], inverse(p.local[0]))
        else:
            out[s.robot] = s.transform
    return out


def _global_frame_in_world(final: FusedMap, starts: dict[str, np.ndarray], frames: dict) -> np.ndarray:
    ref = next((r for r in final.robots if r.status == "reference"), None)
    if ref is None or ref.robot not in starts:
        return identity()
    return compose(starts[ref.robot], inverse(frames[ref.robot]))


def _slam_fits(agents_dir: Path, names, local: dict) -> dict:
    """Per simulated robot: its true path ``(stamps, poses)`` and the rigid fit of its SLAM path
    to it (:func:`shared.metrics.ate`, read once for every score below). The fit's alignment is
    where the robot's map frame sits in the world by its whole trajectory rather than by its start
    pose: a SLAM's map drifts away from its first pose by a few tenths of a degree (nothing holds
    it there but the first scans), and the start-based transform error charges that drift — the
    reference robot's too, to every other robot — to the server."""
    out = {}
    for n in names:
        t_stamps, truth = read_poses(agents_dir / f"{n}.truth.txt")
        out[n] = ((t_stamps, truth), ate(*local[n], t_stamps, truth))
    return out


def _global_frame_fitted(final: FusedMap, fits: dict, frames: dict) -> np.ndarray | None:
    """The global frame in the world by the fitted map frames (see _slam_fits): the world in a
    prior frame, the reference's fitted map frame otherwise; None if there is no truth."""
    if not fits:
        return None
    ref = next((r for r in final.robots if r.status == "reference"), None)
    if ref is None:
        return identity()
    if ref.robot not in fits:
        return None
    return compose(fits[ref.robot][1].alignment, inverse(frames[ref.robot]))


def fused_geojson(final: FusedMap) -> dict:
    props = [{"support": int(final.support[i]), "robots": final.provenance(i)} for i in range(len(final.seg))]
    return segments_geojson(final.seg, props, kind="fused")


def write_report(
    cfg, out: Path, final: FusedMap, updates: list[Update], t0: float, agents_dir: Path, split,
    free: FusedFree | None = None, paths: dict | None = None,
):  # fmt: skip
    names = cfg.robot_names()
    first = _first_merges(updates, t0)
    starts, world = {}, None
    if not cfg.log:
        from robot_agent.sim import builtin_world, to_geojson

        world = builtin_world(cfg.world)
        starts = {n: np.asarray(world.starts[i], float) for i, n in enumerate(names)}
        save_geojson(out / "world.geojson", to_geojson(world))
    local = {n: read_poses(agents_dir / f"{n}.poses.txt") for n in names}
    fits = _slam_fits(agents_dir, names, local) if starts else {}
    frames = _frames(final, paths)
    g = _global_frame_in_world(final, starts, frames)
    g_fit = _global_frame_fitted(final, fits, frames)
    pic = Picture(title=f"fused map v{final.version}: {len(final.seg)} segments, {len(names)} robots")
    if world is not None:
        pic.segments.append(
            SegmentLayer(apply_segments(inverse(g), world.walls), "#BBBBBB", 0.12, "true walls")
        )
    pic.segments.append(SegmentLayer(final.seg, "#222222", 0.05, "fused map"))
    robots, all_stamps, all_poses, merged_names = {}, [], [], []
    for i, name in enumerate(names):
        status = final.robot(name)
        stamps, own = local[name]
        info = json_or_empty(agents_dir / f"{name}.agent.json")
        r = {
            "status": status.status if status else "unknown",
            "time_to_first_merge_s": first.get(name),
            "scans": len(stamps),
            "bytes_per_s": _bytes_per_s(info),
        }
        merged = status is not None and status.merged
        path = (paths or {}).get(name)
        if path is not None and path.robot_session == status.session and merged and len(own):
            poses = path.apply(stamps, own)  # each pose moved with its keyframe (the fleet's graph)
        else:
            poses = compose(status.transform, own) if merged else own
        r["frame"] = "global" if merged else "local (unaligned)"
        write_poses(out / f"{name}.poses.txt", stamps, poses)
        write_tum(out / f"{name}.tum", stamps, poses)
        if merged:
            all_stamps.append(stamps)
            all_poses.append(poses)
            merged_names.append(name)
            pic.paths.append(PathLayer(poses[:, :2], robot_colour(i), 0.04, name))
            r["transform"] = frames[name].tolist()
            r["transform_sigma"] = status.sigma.tolist()
        if name in starts:
            frame = frames.get(name, np.zeros(3))
            r.update(_sim_scores(starts[name], g, g_fit, frame, stamps, poses, merged, *fits[name]))
        robots[name] = r
    save_geojson(out / "map.geojson", fused_geojson(final))
    save_picture(out / "map", pic)
    metrics = {"robots": robots, "fused_segments": len(final.seg), "fused_version": final.version}
    grid = _save_grid(out, final, free)
    metrics["grid"] = {"resolution_m": grid.resolution_m, "shape": list(grid.cells.shape)}
    if world is not None:
        metrics.update(_fused_quality(world, final, g, g_fit, [fits[n][0][1] for n in names]))
        true_paths = [fits[n][0][1] for n in names]
        metrics["grid"].update(_grid_quality(world, grid, g, true_paths))
        if g_fit is not None:  # the grid in the world placed by the fitted global frame (see _slam_fits)
            fit = _grid_quality(world, grid, g_fit, true_paths)
            metrics["grid"].update({f"{k}_fit": v for k, v in fit.items() if not k.endswith("_cells")})
    metrics["all_merged"] = all(r["status"] in ("reference", "prior", "aligned") for r in robots.values())
    if split is not None and all_stamps:
        metrics.update(_log_scores(cfg, out, all_stamps, all_poses, split, merged_names))
        for a, b in metrics.get("wrong_piece_pairs", []):
            for n in (a, b):  # a pair of pieces placed apart from each other: both flagged
                robots[n]["wrong_merge"] = True
    metrics["wrong_merges"] = [n for n, r in robots.items() if r.get("wrong_merge")]
    if split is not None and cfg.relations:
        half = _half_time(cfg, agents_dir, names, updates, t0, split)
        if half is not None:
            metrics["half_time"] = half
    return metrics


def _half_time(cfg, agents_dir: Path, names, updates: list[Update], t0: float, split) -> dict | None:
    """The fleet as a user saw it at half time: each piece's trajectory published when half its
    scans were done (``--snapshot-at``), in the global frame of the fused map the server had
    published by the moment the last piece got there, scored on the relations both of whose ends
    lie in the merged pieces' snapshots."""
    snaps = {}
    for n in names:
        info = json_or_empty(agents_dir / f"{n}.snapshot.json")
        if "monotonic_s" not in info:
            return None
        snaps[n] = (info["monotonic_s"], *read_poses(agents_dir / f"{n}.snapshot.poses.txt"))
    moment = max(t for t, _, _ in snaps.values())
    before = [u for u in updates if u.wall_s <= moment]
    if not before:
        return {"at_s": moment - t0, "fused_version": None, "merged": []}
    fused = before[-1].fused
    stamps, poses, merged = [], [], []
    for n, (_, st, own) in snaps.items():
        status = fused.robot(n)
        if status is not None and status.merged:
            merged.append(n)
            stamps.append(st)
            poses.append(compose(status.transform, own))
    out = {"at_s": moment - t0, "fused_version": fused.version, "merged": merged}
    if not merged:
        return out
    rel = read_relations(cfg.relations)
    keep = (_piece_of(rel.t1_s, stamps) >= 0) & (_piece_of(rel.t2_s, stamps) >= 0)
    out["relations_scored"] = int(keep.sum())
    if keep.any():
        sub = Relations(rel.t1_s[keep], rel.t2_s[keep], rel.delta[keep])
        st, ps = np.concatenate(stamps), np.concatenate(poses)
        out["relations"] = relations_error(st, ps, sub, *split.log.odometry_track()).summary()
    return out


def json_or_empty(path: Path) -> dict:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return {}


def _bytes_per_s(info: dict) -> dict | None:
    span = info.get("source_duration_s") or 0.0
    if not span:
        return None
    sent = info.get("bytes_sent", {})
    return {k: v / span for k, v in sent.items()} | {"total": sum(sent.values()) / span}


def _sim_scores(start, g, g_fit, frame, stamps, poses, merged, truth, fit) -> dict:
    """A simulated robot's scores: ``frame`` where its map frame was placed (_frames), ``truth``
    its true ``(stamps, poses)``, ``fit`` its SLAM path's rigid fit to them (_slam_fits)."""
    r = {"ate_slam_m": fit.rmse_m}  # SLAM alone (best alignment)
    if merged:
        true_t = compose(inverse(g), start)
        dt, dr = transform_error(frame, true_t)
        r["transform_error_m"], r["transform_error_deg"] = dt, dr
        r["ate_m"] = ate(stamps, compose(g, poses), *truth, align=False).rmse_m
        r["wrong_merge"] = bool(dt > WRONG_MERGE_M or dr > WRONG_MERGE_DEG)
        if g_fit is not None:
            dt, dr = transform_error(frame, compose(inverse(g_fit), fit.alignment))
            r["transform_error_fit_m"], r["transform_error_fit_deg"] = dt, dr
    return r


def _fused_quality(world, final: FusedMap, g, g_fit, true_paths: list[np.ndarray]) -> dict:
    """The fused map in the world placed by the global frame's start-based pose ``g`` and, as
    ``*_fit``, by its fitted pose ``g_fit`` (see _slam_fits); ``true_paths`` the robots' true
    poses, for the walls they saw."""
    from robot_agent.sim import LidarConfig
    from robot_agent.sim.evaluate import seen_wall_points

    seen = np.concatenate([seen_wall_points(world, path, LidarConfig()) for path in true_paths])
    q = map_quality(apply_segments(g, final.seg), world.walls, seen_points=seen)
    out = {
        "fused_precision": q.precision,
        "fused_completeness": q.completeness,
        "fused_length_m": q.mapped_length_m,
    }
    if g_fit is not None:
        q = map_quality(apply_segments(g_fit, final.seg), world.walls, seen_points=seen)
        out |= {"fused_precision_fit": q.precision, "fused_completeness_fit": q.completeness}
    return out


GRID_RESOLUTION_M = 0.05


def _save_grid(out: Path, final: FusedMap, free: FusedFree | None):
    """``map.yaml`` + ``map.pgm``: the fused map as a nav2 occupancy grid (the segments and the
    walls seen that they lack, over the fleet's free space)."""
    from shared.occupancy import fused_geometry, grid_walls, occupancy_grid
    from shared.viz import save_nav2

    grid = occupancy_grid(grid_walls(final.seg, free), fused_geometry(free), GRID_RESOLUTION_M)
    save_nav2(out / "map.yaml", grid)
    return grid


def _grid_quality(world, grid, g, true_paths: list[np.ndarray]) -> dict:
    """The exported grid against the world, in the global frame (``g``: its pose in the world):
    true wall cells occupied (within a cell), covered cells free, wall cells marked free."""
    from dataclasses import asdict

    from robot_agent.sim import LidarConfig
    from robot_agent.sim.evaluate import true_beams
    from shared.geometry import apply_points
    from shared.occupancy import grid_quality

    beams = [true_beams(world, path, LidarConfig()) for path in true_paths]
    to_global = inverse(g)
    origins = apply_points(to_global, np.concatenate([b[0] for b in beams]))
    ends = apply_points(to_global, np.concatenate([b[1] for b in beams]))
    hit = np.concatenate([b[2] for b in beams])
    return asdict(grid_quality(grid, apply_segments(to_global, world.walls), origins, ends, hit))


def _piece_of(t: np.ndarray, stamps: list[np.ndarray]) -> np.ndarray:
    """Which of the pieces (their ``stamps``) each time ``t`` falls in, within half a second of
    its span (the first such piece); -1 for none."""
    at = np.full(len(t), -1)
    for k, s in enumerate(stamps):
        at[(at < 0) & (t >= s.min() - 0.5) & (t <= s.max() + 0.5)] = k
    return at


def _log_scores(cfg, out: Path, all_stamps, all_poses, split, names: list[str]) -> dict:
    """A real log's pieces (``names``: the merged ones, their stamps and global poses) scored on
    the reference relations both of whose ends fall in merged pieces: all of them, and those
    *across* pieces (one end in each: how well the pieces were placed against each other). A pair
    of pieces whose across relations are off by more than a wrong merge's bounds (median) is
    listed in ``wrong_piece_pairs``: one was placed apart from the other."""
    stamps = np.concatenate(all_stamps)
    poses = np.concatenate(all_poses)
    write_poses(out / "fleet.poses.txt", stamps, poses)
    res = {"pieces": [list(p) for p in split.pieces]}
    if cfg.relations:
        rel = read_relations(cfg.relations)
        # only relations whose both ends fall in a merged piece: the others have no global pose
        p1, p2 = _piece_of(rel.t1_s, all_stamps), _piece_of(rel.t2_s, all_stamps)
        keep = (p1 >= 0) & (p2 >= 0)
        res["relations_total"] = len(rel.t1_s)
        res["relations_scored"] = int(keep.sum())
        res["wrong_piece_pairs"] = []
        if keep.any():
            sub = Relations(rel.t1_s[keep], rel.t2_s[keep], rel.delta[keep])
            err = relations_error(stamps, poses, sub, *split.log.odometry_track())
            res["relations"] = err.summary()
            across = p1[keep] != p2[keep]
            res["relations_across_scored"] = int(across.sum())
            if across.any():
                res["relations_across"] = RelationsError(err.trans_m[across], err.rot_deg[across]).summary()
            lo, hi = np.minimum(p1[keep], p2[keep]), np.maximum(p1[keep], p2[keep])
            for i, j in sorted({(int(a), int(b)) for a, b in zip(lo[across], hi[across], strict=True)}):
                pair = across & (lo == i) & (hi == j)
                dt, dr = float(np.median(err.trans_m[pair])), float(np.median(err.rot_deg[pair]))
                if dt > WRONG_MERGE_M or dr > WRONG_MERGE_DEG:
                    res["wrong_piece_pairs"].append([names[i], names[j]])
    return res
