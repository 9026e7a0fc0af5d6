"""`fleet-slam export`: the fused map as files, taken from a running server by query.

``--format nav2 OUT``: ``OUT`` (``map.yaml``, or a directory that gets ``map.yaml``) and the PGM
beside it — walls occupied, the space robots saw free free, the rest unknown, as nav2's
``map_server`` loads it (``shared/viz.py``). ``--format geojson|svg``: the segments.
"""

from __future__ import annotations

import argparse
import threading
from pathlib import Path

from shared import codec
from shared.messages import FusedFree, FusedMap, WireFormatError


def describe(f: FusedMap) -> str:
    robots = " ".join(f"{r.robot}:{r.status}{'' if r.online else '(offline)'}" for r in f.robots)
    return f"v{f.version} {len(f.seg)} segments, {len(f.robots)} robots [{robots}]"


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


class FreeWatcher:
    """The latest fused free space: by query, then every put (the newest version of the newest
    server session wins; a receiver takes a new session as a restart)."""

    def __init__(self, bus, keys, on_update=None):
        self.bus, self.keys, self.on_update = bus, keys, on_update
        self.latest: FusedFree | None = None
        self.rejected = 0
        self._lock = threading.Lock()

    def start(self, query_timeout_s: float = 2.0) -> FusedFree | None:
        self.bus.subscribe(self.keys.fused_free, lambda _k, p: self._take(p))
        return self.fetch(query_timeout_s)

    def fetch(self, timeout_s: float = 2.0) -> FusedFree | None:
        for _key, payload in self.bus.get(self.keys.fused_free, timeout_s=timeout_s):
            self._take(payload)
        return self.latest

    def _take(self, payload: bytes) -> None:
        try:
            msg = codec.decode(payload, expect=FusedFree)
        except WireFormatError:
            with self._lock:
                self.rejected += 1
            return
        with self._lock:
            old = self.latest
            newer = old is None or msg.session != old.session or msg.version > old.version
            if newer:
                self.latest = msg
        if newer and self.on_update is not None:
            self.on_update(msg)


def nav2_target(out: str) -> Path:
    """``out`` as the YAML path of a nav2 map: a ``.yaml``/``.yml`` file, else a directory that
    gets ``map.yaml``."""
    p = Path(out)
    if p.suffix in (".yaml", ".yml"):
        p.parent.mkdir(parents=True, exist_ok=True)
        return p
    p.mkdir(parents=True, exist_ok=True)
    return p / "map.yaml"


def save_nav2_map(out: str, fused: FusedMap, free: FusedFree | None, resolution_m: float) -> tuple:
    """The fused segments over the fused free space as a nav2 map pair; returns (pgm, yaml)."""
    from shared.occupancy import fused_geometry, grid_walls, occupancy_grid
    from shared.viz import save_nav2

    grid = occupancy_grid(grid_walls(fused.seg, free), fused_geometry(free), resolution_m)
    return save_nav2(nav2_target(out), grid)


def run(args: argparse.Namespace) -> int:
    from fleet_slam.watch import FusedWatcher
    from shared.bus import Bus, client_config, stop_on_signals
    from shared.keys import Keys

    if args.resolution <= 0:
        raise ValueError(f"--resolution must be positive, got {args.resolution}")
    stop = threading.Event()
    stop_on_signals(stop)
    keys = Keys(args.fleet)
    with Bus(client_config(args.connect, args.bus_config), cancel=stop) as bus:
        fused = FusedWatcher(bus, keys).fetch(timeout_s=args.timeout)
        if fused is None:
            print("no fused map (is the server running?)", flush=True)
            return 1
        free = FreeWatcher(bus, keys).fetch(timeout_s=args.timeout) if args.format == "nav2" else None
    print(describe(fused), flush=True)
    if args.format == "nav2":
        if free is None:
            print("warning: no free space from the server: the grid has walls and unknown only", flush=True)
        pgm, yaml = save_nav2_map(args.out, fused, free, args.resolution)
        print(f"saved {yaml} and {pgm}", flush=True)
    else:
        path = args.out if Path(args.out).suffix else str(Path(args.out) / f"map.{args.format}")
        Path(path).parent.mkdir(parents=True, exist_ok=True)
        save(path, fused)
        print(f"saved {path}", flush=True)
    return 0
