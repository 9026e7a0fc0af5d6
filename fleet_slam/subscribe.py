"""`fleet-slam subscribe`: one line per fused-map update; ``--save`` writes it; ``--once`` queries."""

from __future__ import annotations

import argparse
import threading
from pathlib import Path

from fleet_slam.watch import FusedWatcher, Update
from shared.messages import FusedMap


def describe(f: FusedMap) -> str:
    robots = " ".join(f"{r.robot}:{r.status}{'' if r.online else '(offline)'}" for r in f.robots)
    return f"v{f.version} {len(f.seg)} segments, {len(f.robots)} robots [{robots}]"


def save(path: str, f: FusedMap) -> None:
    from fleet_slam.report import fused_geojson
    from shared.viz import Picture, SegmentLayer, save_geojson, save_svg

    if path.endswith(".svg"):
        save_svg(path, Picture([SegmentLayer(f.seg, "#222222", 0.05, "fused map")], title=describe(f)))
    else:
        save_geojson(path, fused_geojson(f))


def run(args: argparse.Namespace) -> int:
    from shared.bus import Bus, client_config, stop_on_signals
    from shared.keys import Keys

    stop = threading.Event()
    stop_on_signals(stop)
    seen = threading.Semaphore(0)

    def on_update(u: Update) -> None:
        print(f"{u.via}: {describe(u.fused)}", flush=True)
        if args.save:
            save(args.save, u.fused)
        seen.release()

    bus_cfg = client_config(args.connect, args.bus_config)
    with Bus(bus_cfg, cancel=stop) as bus:
        watcher = FusedWatcher(bus, Keys(args.fleet), on_update=None if args.once else on_update)
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
