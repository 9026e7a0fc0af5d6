"""The map server's driver: subscribe, validate, fuse, persist, publish, answer queries.

Zenoh callbacks only decode, validate and queue (under a lock); one loop applies the queue to the
pure :class:`map_server.fleet.Fleet`, fuses when a map is complete but at most once per
``min_fuse_gap_s`` (a burst of maps is coalesced into one fusion), persists the state and only
then publishes the fused map —
what any subscriber has seen is on disk. A restarted server resumes from ``--state`` and pulls the
latest map of every live agent (their queryables) to catch up on what it missed.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import Counter
from dataclasses import dataclass

from map_server.fleet import Fleet, FleetConfig
from map_server.store import Store
from shared import codec
from shared.keys import Keys
from shared.messages import FusedMap, PoseUpdate, RobotMap, WireFormatError

log = logging.getLogger("fleet_slam.server")


@dataclass(frozen=True)
class ServerConfig:
    # A complete robot map wakes the loop at once; fusions are at least this far apart, so a burst
    # of maps (many robots, or one overloaded moment) is coalesced into one fusion.
    min_fuse_gap_s: float = 0.05
    idle_period_s: float = 0.5  # without new maps: poses and presence are applied this often
    pull_timeout_s: float = 3.0  # waiting for agents' latest maps at start-up
    log_rejections_every_s: float = 10.0  # rejected messages are counted; a summary is logged this often


class MapServer:
    def __init__(
        self,
        bus,
        keys: Keys,
        cfg: ServerConfig = ServerConfig(),
        fleet_cfg: FleetConfig | None = None,
        store: Store | None = None,
        server_id: str | None = None,
    ):
        self.bus, self.keys, self.cfg, self.store = bus, keys, cfg, store
        self.fleet_cfg = fleet_cfg or FleetConfig()
        self.server_id = server_id or "server"
        self.fleet = Fleet(self.fleet_cfg, self.server_id)
        self._t0 = time.monotonic()
        self._time_offset = 0.0  # server time already spent before a restart (from the state)
        self._lock = threading.Lock()
        self._wake = threading.Event()
        self._maps: list[RobotMap] = []  # queued complete maps
        self._poses: list[PoseUpdate] = []
        self._presence: list[tuple[str, bool]] = []
        self._assembler = codec.Assembler()
        self._pose_filter = codec.SeqFilter()
        self.rejected: Counter[str] = Counter()
        self.received: Counter[str] = Counter()
        self._latest: list[bytes] = []
        self._stored: dict[str, tuple[tuple[str, int], bytes]] = {}  # robot -> ((session, seq), blob)
        self.fusions = 0
        self._last_log_s = 0.0
        if store is not None:
            self._restore()

    # -- time and state --------------------------------------------------------------------------

    def now_s(self) -> float:
        return time.monotonic() - self._t0 + self._time_offset

    def _restore(self) -> None:
        loaded = self.store.load()  # a damaged state raises StateError: reported, never loaded
        if loaded is None:
            return
        meta, blobs = loaded
        maps = {name: codec.decode_stored_map(blob) for name, blob in blobs.items()}
        self._stored = {name: ((m.session, m.seq), blobs[name]) for name, m in maps.items()}
        self.fleet = Fleet.restore(meta["fleet"], maps, self.fleet_cfg, self.server_id)
        self._time_offset = float(meta.get("now_s", 0.0))
        latest = self.fleet.latest()
        if latest is not None:
            self._latest = _payloads(latest)
        log.info(
            "restored %d robots, fused version %s", len(maps), None if latest is None else latest.version
        )

    def _persist(self) -> None:
        if self.store is None:
            return
        meta, maps = self.fleet.snapshot()
        for robot, m in maps.items():  # encode a robot's map only when it changed
            if robot not in self._stored or self._stored[robot][0] != (m.session, m.seq):
                self._stored[robot] = ((m.session, m.seq), codec.encode_stored_map(m))
        blobs = {robot: self._stored[robot][1] for robot in maps}
        self.store.save({"fleet": meta, "now_s": self.now_s(), "server": self.server_id}, blobs)

    # -- bus callbacks (zenoh threads): decode, validate, queue ----------------------------------

    def _reject(self, what: str, key: str, exc: Exception) -> None:
        self.rejected[what] += 1
        log.debug("rejected %s on %s: %s", what, key, exc)

    def _decode(self, key: str, payload: bytes, kind: type):
        """The message of type ``kind`` on a robot's ``key``; its robot id must be the key's."""
        robot = self.keys.robot_of(key)
        msg = codec.decode(payload, expect=kind)
        if msg.robot != robot:
            raise WireFormatError(f"robot {msg.robot!r} published on the key of {robot!r}")
        return msg

    def on_map(self, key: str, payload: bytes) -> None:
        try:
            msg = self._decode(key, payload, RobotMap)
            with self._lock:
                done = self._assembler.add(msg)
                if done is not None:
                    self._maps.append(done)
                    self._wake.set()
                self.received["map_chunk"] += 1
        except WireFormatError as exc:
            with self._lock:
                self._reject("map", key, exc)

    def on_pose(self, key: str, payload: bytes) -> None:
        try:
            msg = self._decode(key, payload, PoseUpdate)
            with self._lock:
                self._pose_filter.check(msg)
                self._poses.append(msg)
                self.received["pose"] += 1
        except WireFormatError as exc:
            with self._lock:
                self._reject("pose", key, exc)

    def on_presence(self, key: str, alive: bool) -> None:
        try:
            robot = self.keys.robot_of(key)
        except WireFormatError as exc:
            with self._lock:
                self._reject("presence", key, exc)
            return
        with self._lock:
            self._presence.append((robot, alive))

    def answer_fused(self, _key: str) -> list[tuple[str, bytes]]:
        with self._lock:
            return [(self.keys.fused, b) for b in self._latest]

    # -- the loop ----------------------------------------------------------------------------------

    def start(self) -> None:
        """Declare subscriptions and the queryable, then pull the agents' latest maps."""
        self.bus.subscribe(self.keys.all_maps, self.on_map)
        self.bus.subscribe(self.keys.all_poses, self.on_pose)
        self.bus.watch_alive(self.keys.all_alive, self.on_presence)
        self.bus.serve(self.keys.fused, self.answer_fused)
        for key, payload in self.bus.get(self.keys.all_maps, timeout_s=self.cfg.pull_timeout_s):
            self.on_map(key, payload)

    def tick(self) -> FusedMap | None:
        """Apply the queued messages, fuse if anything changed, persist, publish. Returns the new
        fused map (or ``None``)."""
        now = self.now_s()
        with self._lock:
            maps, poses, presence = self._maps, self._poses, self._presence
            self._maps, self._poses, self._presence = [], [], []
        for robot, alive in presence:
            self.fleet.set_online(robot, alive)
        for m in maps:
            self.fleet.put_map(m, now)
        for p in poses:
            self.fleet.put_pose(p, now)
        fused = self.fleet.fuse(now)
        if fused is None:
            return None
        self.fusions += 1
        self._persist()  # before publishing: what anyone has seen survives a crash
        payloads = _payloads(fused)
        with self._lock:
            self._latest = payloads
        for p in payloads:
            self.bus.put(self.keys.fused, p, reliable=True)
        return fused

    def run(self, stop: threading.Event) -> None:
        self.start()
        while not stop.is_set():
            t = time.monotonic()
            self._wake.clear()
            self.tick()
            self._log_rejections()
            self._wake.wait(self.cfg.idle_period_s)  # a new map (or stop) ends the wait early
            stop.wait(max(0.0, self.cfg.min_fuse_gap_s - (time.monotonic() - t)))
        self.tick()

    def _log_rejections(self) -> None:
        now = time.monotonic()
        if self.rejected and now - self._last_log_s >= self.cfg.log_rejections_every_s:
            self._last_log_s = now
            log.warning("rejected messages so far: %s", dict(self.rejected))


def _payloads(fused: FusedMap) -> list[bytes]:
    """The fused map as encoded chunks."""
    return [codec.encode(c) for c in codec.split_fused_map(fused)]
