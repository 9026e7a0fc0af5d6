"""`fleet-slam view`: a live web view of the fleet, served on loopback by the standard library.

The process subscribes to the fused map, the fleet's free space and every robot's pose, and
serves one page (``view.html``, no assets from elsewhere, no build step) that draws them on a
canvas with pan and zoom. Updates are pushed as server-sent events on ``/events``:

- ``map``   the fused map: segments, version, the robots' status, transform and its sigma, with
  ``received_ms`` (this process's wall clock when it arrived);
- ``free``  the fleet's free space (polygons in the global frame);
- ``pose``  a robot's pose in its own map frame (the page places it with the robot's transform,
  so a path stays consistent when a transform changes), at most ``POSE_HZ`` per robot.

``/state`` answers the same as one JSON document. Each client has a bounded queue: a client that
does not keep up loses the oldest events, never the process's memory; a new map or free space
replaces a queued one.
"""

from __future__ import annotations

import argparse
import json
import logging
import queue
import threading
import time
from collections import deque
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import numpy as np

from shared import codec
from shared.messages import FusedFree, FusedMap, PoseUpdate, WireFormatError

log = logging.getLogger("fleet_slam.view")

PAGE = Path(__file__).with_name("view.html")
POSE_HZ = 5.0  # pose events per robot per second at most
PATH_POSES = 600  # recent poses per robot kept for a new page (2 minutes at 5 Hz)
CLIENT_QUEUE = 512  # events waiting per client
KEEPALIVE_S = 15.0
MAX_CLIENTS = 32


def map_event(f: FusedMap, received_ms: float) -> dict:
    robots = [
        {
            "robot": r.robot, "status": r.status, "online": r.online, "session": r.session,
            "n_elements": r.n_elements, "transform": [round(float(v), 5) for v in r.transform],
            "sigma": [round(float(v), 5) for v in r.sigma], "aligned_at_s": r.aligned_at_s,
        }
        for r in f.robots
    ]  # fmt: skip
    return {
        "version": f.version, "server": f.server, "session": f.session, "stamp_s": f.stamp_s,
        "received_ms": received_ms, "segments": np.round(f.seg.reshape(-1, 4), 3).tolist(), "robots": robots,
    }  # fmt: skip


def free_event(f: FusedFree, received_ms: float) -> dict:
    polys = [
        [np.round(outer, 2).ravel().tolist(), [np.round(h, 2).ravel().tolist() for h in holes]]
        for outer, holes in f.polygons()
    ]
    return {
        "version": f.version, "map_version": f.map_version, "received_ms": received_ms, "polygons": polys,
        "walls": np.round(f.walls.reshape(-1, 4), 3).tolist(),
    }  # fmt: skip


class ViewState:
    """What the page shows, fed by the bus callbacks (any thread), read by the HTTP handlers."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.map: dict | None = None
        self.free: dict | None = None
        self.paths: dict[str, deque] = {}  # robot -> recent poses (session, x, y, th, stamp)
        self._last_pose_s: dict[str, float] = {}
        self._clients: set[queue.Queue] = set()
        self.events = 0

    # -- producers ---------------------------------------------------------------------------
    def on_map(self, f: FusedMap) -> None:
        ev = map_event(f, time.time() * 1e3)
        with self._lock:
            self.map = ev
        self._push("map", ev)

    def on_free(self, f: FusedFree) -> None:
        ev = free_event(f, time.time() * 1e3)
        with self._lock:
            self.free = ev
        self._push("free", ev)

    def on_pose(self, p: PoseUpdate) -> None:
        now = time.monotonic()
        with self._lock:
            if now - self._last_pose_s.get(p.robot, -1e9) < 1.0 / POSE_HZ * 0.8:
                return
            self._last_pose_s[p.robot] = now
            row = [p.session, *(round(float(v), 4) for v in p.pose), p.stamp_s]
            self.paths.setdefault(p.robot, deque(maxlen=PATH_POSES)).append(row)
        doubt = p.status.get("odometry_doubt", 0.0)
        self._push("pose", {"robot": p.robot, "pose": row, "odometry_doubt": doubt})

    # -- clients -----------------------------------------------------------------------------
    def snapshot(self) -> dict:
        with self._lock:
            return {"map": self.map, "free": self.free, "paths": {r: list(d) for r, d in self.paths.items()}}

    def join(self) -> queue.Queue | None:
        q: queue.Queue = queue.Queue(maxsize=CLIENT_QUEUE)
        with self._lock:
            if len(self._clients) >= MAX_CLIENTS:
                return None
            self._clients.add(q)
        return q

    def leave(self, q: queue.Queue) -> None:
        with self._lock:
            self._clients.discard(q)

    def _push(self, kind: str, data: dict) -> None:
        text = f"event: {kind}\ndata: {json.dumps(data, separators=(',', ':'))}\n\n".encode()
        with self._lock:
            clients = list(self._clients)
            self.events += 1
        for q in clients:
            while True:
                try:
                    q.put_nowait(text)
                    break
                except queue.Full:  # a slow page loses its oldest events, not our memory
                    try:
                        q.get_nowait()
                    except queue.Empty:
                        pass


def make_handler(state: ViewState, stop: threading.Event) -> type[BaseHTTPRequestHandler]:
    page = PAGE.read_bytes()

    class Handler(BaseHTTPRequestHandler):
        server_version = "fleet-slam-view"

        def log_message(self, fmt, *args) -> None:  # quiet: one line per request is noise here
            log.debug("%s - " + fmt, self.address_string(), *args)

        def _send(self, code: int, body: bytes, ctype: str) -> None:
            self.send_response(code)
            self.send_header("Content-Type", ctype)
            self.send_header("Content-Length", str(len(body)))
            self.send_header("Cache-Control", "no-store")
            self.end_headers()
            self.wfile.write(body)

        def do_GET(self) -> None:
            path = self.path.split("?", 1)[0]
            if path in ("/", "/index.html"):
                self._send(200, page, "text/html; charset=utf-8")
            elif path == "/state":
                self._send(200, json.dumps(state.snapshot()).encode(), "application/json")
            elif path == "/events":
                self._events()
            else:
                self._send(404, b"not found\n", "text/plain")

        def _events(self) -> None:
            q = state.join()
            if q is None:
                self._send(503, b"too many viewers\n", "text/plain")
                return
            try:
                self.send_response(200)
                self.send_header("Content-Type", "text/event-stream")
                self.send_header("Cache-Control", "no-store")
                self.end_headers()
                snap = state.snapshot()  # what exists now, then every change
                first = json.dumps(snap, separators=(",", ":"))
                self.wfile.write(f"event: state\ndata: {first}\n\n".encode())
                self.wfile.flush()
                last = time.monotonic()
                while not stop.is_set():
                    try:
                        self.wfile.write(q.get(timeout=0.5))
                    except queue.Empty:
                        if time.monotonic() - last < KEEPALIVE_S:
                            continue
                        self.wfile.write(b": keep-alive\n\n")
                    self.wfile.flush()
                    last = time.monotonic()
            except (BrokenPipeError, ConnectionResetError, TimeoutError):
                pass  # the page went away
            finally:
                state.leave(q)

    return Handler


def parse_listen(text: str) -> tuple[str, int]:
    host, sep, port = text.rpartition(":")
    if not sep or not host or not port.isdigit() or not 0 <= int(port) < 65536:
        raise ValueError(f"--listen: expected HOST:PORT (e.g. 127.0.0.1:8090), got {text!r}")
    return host, int(port)


def run(args: argparse.Namespace) -> int:
    from fleet_slam.export import FreeWatcher
    from fleet_slam.watch import FusedWatcher
    from shared.bus import Bus, client_config, stop_on_signals
    from shared.keys import Keys

    host, port = parse_listen(args.listen)
    stop = threading.Event()
    stop_on_signals(stop)
    state = ViewState()
    keys = Keys(args.fleet)
    httpd = ThreadingHTTPServer((host, port), make_handler(state, stop))
    httpd.daemon_threads = True
    serving = threading.Thread(target=httpd.serve_forever, kwargs={"poll_interval": 0.2}, daemon=True)
    try:
        with Bus(client_config(args.connect, args.bus_config), cancel=stop) as bus:

            def on_pose(_key: str, payload: bytes) -> None:
                try:
                    state.on_pose(codec.decode(payload, expect=PoseUpdate))
                except WireFormatError:
                    pass

            fused = FusedWatcher(bus, keys, on_update=lambda u: state.on_map(u.fused), history=1)
            free = FreeWatcher(bus, keys, on_update=state.on_free)
            bus.subscribe(keys.all_poses, on_pose)
            fused.start(query_timeout_s=1.0)
            free.start(query_timeout_s=1.0)
            serving.start()
            h, p = httpd.server_address[:2]
            print(f"view: http://{h}:{p}/ (fleet {args.fleet})", flush=True)
            while not stop.wait(0.5):
                pass
    finally:
        stop.set()
        if serving.is_alive():
            httpd.shutdown()
        httpd.server_close()
    return 0
