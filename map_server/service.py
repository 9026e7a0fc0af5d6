"""`fleet-slam server` / `python -m map_server`: the map server process."""

from __future__ import annotations

import argparse
import logging
import threading

DEFAULT_FLEET = "default"  # = shared.keys.DEFAULT_FLEET (not imported: instant --help)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--connect", action="append", default=None, help="router endpoint (tcp/127.0.0.1:7447)")
    p.add_argument("--bus-config", default=None, metavar="FILE", help="zenoh config file (TLS; deploy/)")
    p.add_argument("--state", default=None, help="state directory: persist the fused state, resume from it")
    p.add_argument("--fleet", default=DEFAULT_FLEET, help="fleet id (key prefix fleet/<id>/)")
    p.add_argument("--id", dest="server_id", default="server", help="server id in the fused map")
    p.add_argument(
        "--min-gap", type=float, default=0.05, help="seconds between fusions at least (coalescing)"
    )
    p.add_argument("--verbose", action="store_true", help="log every rejected message")


def run(args: argparse.Namespace) -> int:
    from map_server.server import MapServer, ServerConfig
    from map_server.store import Store
    from shared.bus import Bus, client_config, stop_on_signals
    from shared.keys import Keys

    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO, format="%(asctime)s %(name)s: %(message)s"
    )
    if args.min_gap < 0:
        raise ValueError(f"--min-gap must be >= 0, got {args.min_gap}")
    stop = threading.Event()
    stop_on_signals(stop)
    store = Store(args.state) if args.state else None
    bus_cfg = client_config(args.connect, args.bus_config)
    with Bus(bus_cfg, cancel=stop) as bus:
        server = MapServer(
            bus,
            Keys(args.fleet),
            ServerConfig(min_fuse_gap_s=args.min_gap),
            store=store,
            server_id=args.server_id,
        )
        print(f"server {args.server_id}: running (state: {args.state or 'none'})", flush=True)
        server.run(stop)
    print(f"server {args.server_id}: stopped after {server.fusions} fusions", flush=True)
    return 0
