"""`fleet-slam replay`: offline SLAM over a CARMEN log, with the outputs of docs/design.md."""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np

from robot_agent.backend import remap
from robot_agent.replay import replay
from robot_agent.slam.config import command_line_config
from robot_agent.sources import read_log
from shared.metrics import read_relations, relations_error, write_poses, write_tum
from shared.viz import PathLayer, Picture, SegmentLayer, save_geojson, save_picture, segments_geojson


def robot_name_of(path: str | Path) -> str:
    name = Path(path).name
    for suffix in (".gz", ".clf", ".log"):
        name = name.removesuffix(suffix)
    return name or "robot"


def live_scores(res, rel, log) -> list[dict]:
    """Each snapshot of ``res.live`` scored on the relations whose both ends lie before it."""
    out = []
    for snap in res.live:
        until = rel.until(snap.stamps_s.max() + 1e-6)
        row = {"scans": snap.scans, "at_s": float(snap.stamps_s.max() - res.stamps_s.min()), "n": len(until)}
        if len(until):
            err = relations_error(snap.stamps_s, snap.poses, until, *log.odometry_track())
            row |= {k: v for k, v in err.summary().items() if k != "n"}
            raw = relations_error(snap.stamps_s, snap.filter_poses, until, *log.odometry_track())
            row["filter_trans_mean_m"] = raw.summary()["trans_mean_m"]
        out.append(row)
    return out


def replay_to_dir(
    log_path: str,
    out_dir: str | Path,
    relations_path: str | None = None,
    particles: int | None = None,
    seed: int = 0,
    overrides: list[str] | None = None,
    limit: int | None = None,
    progress: bool | None = None,
    live: int = 0,
    strict: bool = False,
) -> dict:
    """Replay ``log_path`` and write the outputs of docs/design.md to ``out_dir``; the metrics. With
    ``live`` > 1 the run is cut into that many parts and the trajectory the robot would publish
    at the end of each is scored too (``metrics["live"]``, on the relations before that moment),
    and the online back end's path at the end (``metrics["relations_online"]``)."""
    cfg = command_line_config(overrides or [], particles)
    log = read_log(log_path, progress=progress, strict=strict)
    for warning in log.warnings:  # what the reader could not use and what it did instead
        print(f"warning: {warning}", file=sys.stderr)
    rel = read_relations(relations_path) if relations_path else None
    res = replay(log, cfg, seed=seed, progress=progress, limit=limit, snapshots=live)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    name = robot_name_of(log_path)
    write_poses(out / f"{name}.poses.txt", res.stamps_s, res.poses)
    write_tum(out / f"{name}.tum", res.stamps_s, res.poses)
    if res.filter_poses is not None:  # the filter's own path, before the back end
        write_poses(out / f"{name}.filter.poses.txt", res.stamps_s, res.filter_poses)

    slam = res.slam
    # the map the written poses agree with: rebuilt along the back end's path (as an agent
    # publishes it at the end of its run); the filter's own map keeps the drift it closed
    t0 = time.perf_counter()
    mapper = remap(log, 0, res.poses, res.slam.cfg) if res.backend_stats is not None else slam
    map_rebuild_s = time.perf_counter() - t0
    gm, keep = mapper.published_map()
    props = [
        {"trust": round(float(t), 3), "hits": int(h), "support": round(float(s), 3)}
        for t, h, s in zip(gm.trust[keep], gm.hits[keep], gm.support[keep], strict=True)
    ]
    save_geojson(out / "map.geojson", segments_geojson(gm.seg[keep], props))
    pic = Picture(
        [SegmentLayer(gm.seg[keep], "#222222", 0.05, "mapped segments")],
        [PathLayer(res.poses[:, :2], "#D55E00", 0.03, name)],
        title=f"{name}: {int(keep.sum())} segments, {res.scans} scans",
    )
    save_picture(out / "map", pic)

    online_s = (res.online_stats or {}).get("online_s", 0.0)
    filter_wall = res.wall_s - online_s
    duration = float(np.max(log.stamps_s[: res.scans]) - np.min(log.stamps_s[: res.scans]))
    metrics = {
        "log": str(log_path),
        "robot": name,
        "scans": res.scans,
        "processed_scans": slam.step_index,
        "particles": cfg.particles,
        "seed": seed,
        "wall_time_s": res.wall_s,
        "log_duration_s": duration,
        # the filter and the back end at the end; the online back end (--live) runs on its own
        # core in an agent: its time is online_backend_s, not counted here
        "real_time_factor": duration / filter_wall if filter_wall > 0 else None,
        # the same on the process's CPU time: what one free core would take (a loaded machine's
        # wall time is longer); with --live the online back end's thread is in it
        "cpu_time_s": res.cpu_s,
        "real_time_factor_cpu": duration / res.cpu_s if res.cpu_s > 0 and not live else None,
        "peak_rss_mb": res.peak_rss_bytes / 2**20,
        "map_segments": int(keep.sum()),
        "filter": dict(slam.stats),
        "backend_s": res.backend_s,
        "backend": res.backend_stats,
        "map_rebuild_s": map_rebuild_s,
        "log_warnings": list(log.warnings),
    }
    if res.online_stats is not None:
        metrics["online_backend"] = res.online_stats
        metrics["online_backend_s"] = online_s
        metrics["online_backend_share"] = online_s / duration if duration > 0 else None
    if rel is not None:
        rel = rel.until(res.stamps_s.max() + 1e-6)  # --limit: only relations inside the run
    if rel is not None and len(rel) == 0:
        metrics["relations_note"] = "no relation lies within the scans replayed"
    elif rel is not None:
        err = relations_error(res.stamps_s, res.poses, rel, *log.odometry_track())
        metrics["relations"] = err.summary()
        if res.backend_stats is not None:
            raw = relations_error(res.stamps_s, res.filter_poses, rel, *log.odometry_track())
            metrics["relations_filter_only"] = raw.summary()
        if res.online_poses is not None:  # the online back end's path at the end of the source
            metrics["relations_online"] = relations_error(
                res.stamps_s, res.online_poses, rel, *log.odometry_track()
            ).summary()
        if res.live:
            metrics["live"] = live_scores(res, rel, log)
            scored = [s for s in metrics["live"] if s["n"]]
            metrics["live_worst_trans_m"] = max((s["trans_mean_m"] for s in scored), default=None)
    (out / "metrics.json").write_text(json.dumps(metrics, indent=2))
    return metrics
