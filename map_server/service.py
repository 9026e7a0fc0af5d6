"""`fleet-slam server` / `python -m map_server`: the map server process."""

from __future__ import annotations

import argparse
import logging
import threading

DEFAULT_FLEET = "default"  # = shared.keys.DEFAULT_FLEET (not imported: instant --help)


# what `fleet-slam --help` says of the command, and `python -m` of the service run alone
SUMMARY = "the map server: fuse robots' maps, publish and serve the fused map"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--connect", action="append", default=None, help="router endpoint (tcp/127.0.0.1:7447)")
    p.add_argument("--bus-config", default=None, metavar="FILE", help="zenoh config file (TLS; deploy/)")
    p.add_argument("--state", default=None, help="state directory: persist the fused state, resume from it")
    p.add_argument("--fleet", default=DEFAULT_FLEET, help="fleet id (key prefix fleet/<id>/)")
    p.add_argument("--id", dest="server_id", default="server", help="server id in the fused map")
    p.add_argument(
        "--min-gap", type=float, default=0.05, help="seconds between fusions at least (coalescing)"
    )
    p.add_argument(
        "--set", action="append", default=[], metavar="SECTION.KEY=VALUE",
        help="override a fleet parameter (map_server/config.py: FleetConfig), e.g. mature_window_s=45 "
        "or alignment.min_overlap_m=40",
    )  # fmt: skip
    p.add_argument("--verbose", action="store_true", help="log every rejected message")


def run(args: argparse.Namespace) -> int:
    from map_server.store import StateLock, Store
    from shared.bus import stop_on_signals

    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO, format="%(asctime)s %(name)s: %(message)s"
    )
    if args.min_gap < 0:
        raise ValueError(f"--min-gap must be >= 0, got {args.min_gap}")
    fleet_cfg = fleet_config(args.set)  # a bad override fails before the state is locked or the bus joined
    lock = StateLock(args.state) if args.state else None  # first: a second server exits 2 at once
    if lock is not None and lock.stale:
        print(
            f"server {args.server_id}: {args.state}: taking over the state from {lock.stale} "
            "(gone without releasing it)",
            flush=True,
        )
    stop = threading.Event()
    stop_on_signals(stop)
    try:
        return _serve(args, stop, Store(args.state) if args.state else None, fleet_cfg)
    finally:
        if lock is not None:
            lock.release()


def fleet_config(overrides: list[str]):
    """The fleet's parameters: the defaults with ``--set`` overrides (shared.config)."""
    from map_server.config import FleetConfig
    from shared.config import apply_overrides

    return apply_overrides(FleetConfig(), overrides)


def _serve(args: argparse.Namespace, stop: threading.Event, store, fleet_cfg) -> int:
    from map_server.server import MapServer, ServerConfig
    from shared.bus import Bus, client_config
    from shared.keys import Keys

    bus_cfg = client_config(args.connect, args.bus_config)
    with Bus(bus_cfg, cancel=stop) as bus:
        server = MapServer(
            bus,
            Keys(args.fleet),
            ServerConfig(min_fuse_gap_s=args.min_gap),
            fleet_cfg=fleet_cfg,
            store=store,
            server_id=args.server_id,
        )
        print(f"server {args.server_id}: running (state: {args.state or 'none'})", flush=True)
        server.run(stop)
    print(f"server {args.server_id}: stopped after {server.fusions} fusions", flush=True)
    return 0
