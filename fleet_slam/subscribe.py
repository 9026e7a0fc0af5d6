"""`fleet-slam subscribe`: one line per fused-map update; ``--save`` writes it (``.geojson``, ``.svg``,
or ``.yaml``: a nav2 occupancy grid with the fleet's free space); ``--once`` queries."""

from __future__ import annotations

import argparse
import threading
from pathlib import Path

from fleet_slam.export import describe, save
from fleet_slam.watch import FusedWatcher, Update

HISTORY = 16  # updates a subscriber keeps (it prints each as it comes): it may run for days


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
