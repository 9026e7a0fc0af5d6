"""`fleet-slam sim`: simulate robots and write what a real robot would record, plus the truth.

Per robot ``<robot>.clf`` (CARMEN laser + odometry), ``<robot>.truth.txt`` (``timestamp x y
theta`` in the world frame), ``<robot>.relations`` (Kümmerle format, built from the truth), and
for the world ``world.geojson``, ``world.svg``, ``world.png`` (walls and true paths).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from robot_agent.sim import SimConfig, builtin_world, load_geojson, simulate_robot, to_geojson
from robot_agent.sources import write_log
from shared.metrics import make_relations, write_poses, write_relations
from shared.viz import PathLayer, Picture, SegmentLayer, robot_colour, save_geojson, save_picture


def robot_name(index: int) -> str:
    return f"robot{index + 1}"


def simulate_to_dir(
    world_name: str,
    n_robots: int,
    duration_s: float,
    seed: int,
    out_dir: str | Path,
    world_file: str | None = None,
    cfg: SimConfig | None = None,
) -> list[str]:
    """Simulate ``n_robots`` in a world and write all outputs; returns summary lines."""
    world = load_geojson(world_file) if world_file else builtin_world(world_name)
    if n_robots < 1 or n_robots > len(world.routes):
        raise ValueError(
            f"--robots must be between 1 and {len(world.routes)} for world {world.name!r}, got {n_robots}"
        )
    if not duration_s > 0:
        raise ValueError(f"--duration must be positive, got {duration_s}")
    cfg = cfg or SimConfig()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    pic = Picture(segments=[SegmentLayer(world.walls, "#222222", 0.08, "walls")], title=world.name)
    lines, meta = [], {"world": world.name, "seed": seed, "duration_s": duration_s, "robots": {}}
    for i in range(n_robots):
        name = robot_name(i)
        run = simulate_robot(world, i, duration_s, seed, cfg)
        log = run.to_log({"robot_name": name, "sim_world": world.name})
        write_log(out / f"{name}.clf", log)
        write_poses(out / f"{name}.truth.txt", run.stamps_s, run.truth)
        rel = make_relations(run.stamps_s, run.truth, np.random.default_rng([seed, i, 7]))
        write_relations(out / f"{name}.relations", rel)
        pic.paths.append(PathLayer(run.truth[:, :2], robot_colour(i), 0.05, f"{name} (true path)"))
        dist = float(np.sum(np.hypot(*np.diff(run.truth[:, :2], axis=0).T)))
        meta["robots"][name] = {"start": run.truth[0].tolist(), "scans": len(run.stamps_s), "path_m": dist}
        lines.append(f"{name}: {len(run.stamps_s)} scans, {dist:.1f} m driven, {len(rel)} relations")
    save_geojson(out / "world.geojson", to_geojson(world))
    save_picture(out / "world", pic)
    (out / "sim.json").write_text(json.dumps(meta, indent=2))
    lines.append(f"wrote {out}/ (logs, truth, relations, world.geojson, world.svg, world.png)")
    return lines
