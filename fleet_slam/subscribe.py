"""`fleet-slam subscribe`: one line per fused-map update; ``--save`` writes it (``.geojson``, ``.svg``,
or ``.yaml``: a nav2 occupancy grid with the fleet's free space); ``--once`` queries."""

from __future__ import annotations

import argparse
import threading
from pathlib import Path

from fleet_slam.watch import FusedWatcher, Update
from shared.messages import FusedMap


def describe(f: FusedMap) -> str:
    robots = " ".join(f"{r.robot}:{r.status}{'' if r.online else '(offline)'}" for r in f.robots)
    return f"v{f.version} {len(f.seg)} segments, {len(f.robots)} robots [{robots}]"


HISTORY = 16  # updates a subscriber keeps (it prints each as it comes): it may run for days


def save(path: str, f: FusedMap) -> None:
    """``path`` (``.svg``, else GeoJSON) replaced at once by the map: written beside it, then
    renamed over it, so a reader sees the old file or the new one, never half of one."""
    import os
    import tempfile

    from fleet_slam.report import fused_geojson
    from shared.viz import Picture, SegmentLayer, save_geojson, save_svg

    target = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", suffix=target.suffix or ".tmp", dir=target.parent)
    os.close(fd)
    try:
        if path.endswith(".svg"):
            save_svg(tmp, Picture([SegmentLayer(f.seg, "#222222", 0.05, "fused map")], title=describe(f)))
        else:
            save_geojson(tmp, fused_geojson(f))
        os.chmod(tmp, 0o644)
        os.replace(tmp, target)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def run(args: argparse.Namespace) -> int:
    from shared.bus import Bus, client_config, stop_on_signals
    from shared.keys import Keys

    stop = threading.Event()
    stop_on_signals(stop)
    seen = threading.Semaphore(0)
    grid = bool(args.save) and Path(args.save).suffix in (".yaml", ".yml")
    free = None

    def on_update(u: Update) -> None:
        print(f"{u.via}: {describe(u.fused)}", flush=True)
        if grid:
            from fleet_slam.export import save_nav2_map

            save_nav2_map(args.save, u.fused, free.latest if free is not None else None, args.resolution)
        elif args.save:
            save(args.save, u.fused)
        seen.release()

    bus_cfg = client_config(args.connect, args.bus_config)
    with Bus(bus_cfg, cancel=stop) as bus:
        if grid:  # the free space first: the first map saved has it
            from fleet_slam.export import FreeWatcher

            free = FreeWatcher(bus, Keys(args.fleet))
            free.start(query_timeout_s=2.0)
        watcher = FusedWatcher(
            bus,
            Keys(args.fleet),
            on_update=None if args.once else on_update,
            history=HISTORY,
            on_refused=lambda text: print(f"warning: {text}", flush=True),
        )
        if args.once:
            f = watcher.fetch(timeout_s=5.0)
            if f is None:
                print("no fused map (is the server running?)", flush=True)
                return 1
            on_update(Update(0.0, f, "query"))
            return 0
        watcher.start()
        n = 0
        while not stop.is_set() and (args.count is None or n < args.count):
            if seen.acquire(timeout=0.2):
                n += 1
    if args.save:
        print(f"saved {Path(args.save)}", flush=True)
    return 0
