"""The map server's driver: subscribe, validate, fuse, persist, publish, answer queries.

Zenoh callbacks only decode, validate and queue (under a lock); one loop applies the queue to the
pure :class:`map_server.fleet.Fleet`, fuses when a map is complete but at most once per
``min_fuse_gap_s`` (a burst of maps is coalesced into one fusion), persists the state and only
then publishes the fused map —
what any subscriber has seen is on disk. A restarted server resumes from ``--state`` and pulls the
latest map of every live agent (their queryables) to catch up on what it missed, and so again
for every robot that comes back online (an agent restart, or all of them after a router restart).
"""

from __future__ import annotations

import dataclasses
import logging
import resource
import threading
import time
import uuid
from collections import Counter, deque
from collections.abc import Callable
from dataclasses import dataclass, field

import msgpack
import numpy as np

from map_server.config import FleetConfig
from map_server.fleet import Fleet
from map_server.freespace import FreeFusionConfig, FreeSpaces
from map_server.store import StateError, Store
from shared import codec
from shared.keys import Keys
from shared.memory import Trimmer
from shared.messages import (
    MAX_ROBOTS,
    FreeSpace,
    FusedFree,
    FusedMap,
    PoseUpdate,
    RobotMap,
    RobotPath,
    WireFormatError,
)

log = logging.getLogger("fleet_slam.server")


@dataclass(frozen=True)
class ServerConfig:
    # A complete robot map wakes the loop at once; fusions are at least this far apart, so a burst
    # of maps (many robots, or one overloaded moment) is coalesced into one fusion.
    min_fuse_gap_s: float = 0.05
    idle_period_s: float = 0.5  # without new maps: poses and presence are applied this often
    # the fleet's graph is matched and solved after a fusion has gone out (Fleet.fuse), at most
    # this often: a solve takes the whole graph (16 robots: 5-15 ms, plus 0.3 ms a keyframe
    # matched) while a new map needs only the last solution to be placed; what the graph moves
    # goes out with the next fusion
    graph_every_s: float = 0.2
    pull_timeout_s: float = 3.0  # waiting for agents' latest maps at start-up
    log_rejections_every_s: float = 10.0  # rejected messages are counted; a summary is logged this often
    status_every_s: float = 10.0  # a status line (queue depth, fusion time, memory) is logged this often
    # messages refused after the last fusion (nothing else changed) go out with the fused map
    # again, as a new version, at most this often: its figures are what a subscriber sees of them
    refusals_every_s: float = 2.0
    timing_window: int = 200  # fusion times kept for the status percentiles
    # the free space is fused on a thread of its own (GEOS releases the GIL) when the last fusion
    # took this long or more — MIT-CSAIL's three pieces take 0.5-3 s, which in the loop held the
    # maps' fusions — else in the loop (a few simulated robots': a thread would only contend for
    # the GIL with the maps' fusions); inf: always in the loop
    free_thread_above_s: float = 0.1
    free: FreeFusionConfig = field(default_factory=FreeFusionConfig)  # the fleet's free space


FREE_BLOB = "free~"  # a robot session's free space in a snapshot: free~<robot>~<session>
GRAPH_BLOB = "graph~"  # the fleet graph's solution (Fleet.graph_state, encode_graph_state)


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
        self.free = FreeSpaces(cfg.free)  # the robots' free space, and its union
        self.fleet.free_of = self.free.area  # a found place is checked against the free space seen
        self._frees: list[FreeSpace] = []  # queued free-space messages
        self._latest_free: list[bytes] = []
        self._stored_free: dict[str, tuple[int, bytes]] = {}  # blob name -> (seq, encoded)
        self._maps: list[RobotMap] = []  # queued complete maps
        self._poses: list[PoseUpdate] = []
        self._presence: list[tuple[str, bool]] = []
        self._assembler = codec.Assembler()
        self._pose_filter = codec.SeqFilter()
        self.rejected: Counter[str] = Counter()  # by message kind: map, pose, presence
        self.reasons: Counter[str] = Counter()  # by "kind: reason" (the field at fault, or the chunk check)
        self.received: Counter[str] = Counter()
        self.fuse_ms: deque[float] = deque(maxlen=cfg.timing_window)  # recent fusion times (fuse+persist)
        self.bend_ms: deque[float] = deque(maxlen=cfg.timing_window)  # ... and the graph's after them
        self.trial_ms: deque[float] = deque(maxlen=cfg.timing_window)  # ... and its trials' steps
        self.free_ms: deque[float] = deque(maxlen=cfg.timing_window)  # the free space's fusions
        self._free_job: _FreeJob | None = None  # the free space's fusion under way (_tick_free)
        self._bend_s = -np.inf  # time.monotonic() of the graph's last bend (_bend)
        self._bent = False  # it ran in the last tick: its result goes out with the next fusion
        self.backlog = {"maps": 0, "poses": 0, "max_maps": 0, "max_poses": 0}  # queue depth at each tick
        self.maps_applied = 0  # complete maps applied (>= fusions: a burst is coalesced into one fusion)
        self._last_status_s = time.monotonic()
        self._latest: list[bytes] = []
        self._paths: list[RobotPath] = []  # where the fleet's graph put each placed robot (on query)
        self._stored: dict[str, tuple[tuple[str, int], bytes]] = {}  # robot -> ((session, seq), blob)
        self.fusions = 0
        self._published_rejected = 0  # the refusals counted in the last fused map put
        self._published_s = -np.inf  # time.monotonic() of that put
        self.session = uuid.uuid4().hex[:16]  # this process: receivers see a restart, not stale versions
        self._robot_ids: set[str] = set()  # every robot id admitted (fleet's and queued)
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
        try:  # the checksums hold, but the content must be a state this build reads too
            self.fleet, maps, frees = decode_state(meta, blobs, self.fleet_cfg, self.server_id, self.free)
            self._stored_free = {name: (m.seq, blobs[name]) for name, m in frees.items()}
            self._time_offset = float(meta.get("now_s", 0.0))
        except (KeyError, TypeError, ValueError) as exc:
            raise StateError(f"{self.store.index}: cannot be restored ({type(exc).__name__}: {exc})") from exc
        self._stored = {name: ((m.session, m.seq), blobs[name]) for name, m in maps.items()}
        self._robot_ids = set(self.fleet.robots) | set(self.fleet.retired)
        latest = self.fleet.latest()
        if latest is not None:
            self._latest = self._payloads(latest)
            self._paths = self.fleet.paths(latest.version, self.session)
        if self.free.latest:  # the fleet's free space as the restored placements put it
            version, seg = (0, None) if latest is None else (latest.version, latest.seg)
            fused = self.free.fuse(self.fleet.placements(), self.server_id, version, self.now_s(), seg)
            self._latest_free = [self._free_payload(fused)]
        log.info(
            "restored %d robots (%d retired sessions), fused version %s", len(self.fleet.robots),
            sum(map(len, self.fleet.retired.values())), None if latest is None else latest.version,
        )  # fmt: skip

    def _persist(self) -> None:
        if self.store is None:
            return
        meta, maps = self.fleet.snapshot()
        for robot, m in maps.items():  # encode a robot's map only when it changed
            if robot not in self._stored or self._stored[robot][0] != (m.session, m.seq):
                self._stored[robot] = ((m.session, m.seq), codec.encode_stored_map(m))
        for gone in set(self._stored) - set(maps):  # replaced or dropped maps
            del self._stored[gone]
        blobs = {robot: self._stored[robot][1] for robot in maps}
        frees = {f"{FREE_BLOB}{r}~{ses}": m for (r, ses), m in self.free.latest.items()}
        for name, m in frees.items():
            if name not in self._stored_free or self._stored_free[name][0] != m.seq:
                self._stored_free[name] = (m.seq, codec.encode(m))
        for gone in set(self._stored_free) - set(frees):
            del self._stored_free[gone]
        blobs.update({name: b for name, (_, b) in self._stored_free.items()})
        graph = self.fleet.graph_state()
        if graph:
            blobs[GRAPH_BLOB] = encode_graph_state(graph)
        self.store.save({"fleet": meta, "now_s": self.now_s(), "server": self.server_id}, blobs)

    # -- bus callbacks (zenoh threads): decode, validate, queue ----------------------------------

    def _reject(self, what: str, key: str, exc: Exception) -> None:
        """Count a refused message under its kind and reason; the first of each reason is logged as a
        warning with its full text, the rest at debug level (a flood must not flood the log)."""
        reason = f"{what}: {_reason(exc)}"
        self.rejected[what] += 1
        self.reasons[reason] += 1
        if self.reasons[reason] == 1:
            log.warning("rejected %s on %s: %s (further ones counted)", what, str(key)[:120], exc)
        else:
            log.debug("rejected %s on %s: %s", what, str(key)[:120], exc)

    def _decode(self, key: str, payload: bytes, kind: type):
        """The message of type ``kind`` on a robot's ``key``; its robot id must be the key's."""
        robot = self.keys.robot_of(key)
        msg = codec.decode(payload, expect=kind)
        if msg.robot != robot:
            raise WireFormatError(f"robot: {msg.robot!r} published on the key of {robot!r}")
        return msg

    def _admit(self, robot: str) -> None:
        """Under the lock: a robot id the fleet knows, or room for one more (a fused map holds at
        most MAX_ROBOTS; a flood of made-up ids is refused at the door, not fused)."""
        if robot not in self._robot_ids:
            if len(self._robot_ids) >= MAX_ROBOTS:
                raise WireFormatError(f"robot: {robot!r} is one robot too many (at most {MAX_ROBOTS})")
            self._robot_ids.add(robot)

    def on_map(self, key: str, payload: bytes, pulled: bool = False) -> None:
        """A map chunk put by an agent, or ``pulled`` from its queryable: a pulled chunk the server
        already has (it came by put as well) is not a rejection."""
        try:
            msg = self._decode(key, payload, RobotMap)
            with self._lock:
                self._admit(msg.robot)
                done = self._assembler.add(msg)
                if done is not None:
                    self._maps.append(done)
                    self._wake.set()
                self.received["map_chunk"] += 1
        except WireFormatError as exc:
            if pulled and getattr(exc, "reason", None) in ("stale", "duplicate"):
                return
            with self._lock:
                self._reject("map", key, exc)

    def on_pose(self, key: str, payload: bytes) -> None:
        try:
            msg = self._decode(key, payload, PoseUpdate)
            with self._lock:
                self._admit(msg.robot)
                self._pose_filter.check(msg)
                self._poses.append(msg)
                self.received["pose"] += 1
        except WireFormatError as exc:
            with self._lock:
                self._reject("pose", key, exc)

    def on_free(self, key: str, payload: bytes, pulled: bool = False) -> None:
        """A robot's free space, put or ``pulled``: queued (the newest of each session is kept)."""
        try:
            msg = self._decode(key, payload, FreeSpace)
            with self._lock:
                self._admit(msg.robot)
                self._frees.append(msg)
                self.received["free"] += 1
        except WireFormatError as exc:
            with self._lock:
                self._reject("free", key, exc)

    def answer_free(self, _key: str) -> list[tuple[str, bytes]]:
        with self._lock:
            return [(self.keys.fused_free, b) for b in self._latest_free]

    def on_presence(self, key: str, alive: bool) -> None:
        with self._lock:
            try:
                robot = self.keys.robot_of(key)
                self._admit(robot)
            except WireFormatError as exc:
                self._reject("presence", key, exc)
                return
            self._presence.append((robot, alive))

    def answer_fused(self, _key: str) -> list[tuple[str, bytes]]:
        with self._lock:
            return [(self.keys.fused, b) for b in self._latest]

    def answer_paths(self, key: str) -> list[tuple[str, bytes]]:
        """Each asked placed robot's keyframes where the fleet's graph puts them (RobotPath)."""
        with self._lock:
            paths = list(self._paths)
        asked = str(key).rsplit("/", 1)[-1]
        return [
            (self.keys.robot_path(p.robot), codec.encode(p)) for p in paths if asked in ("*", "**", p.robot)
        ]

    # -- the loop ----------------------------------------------------------------------------------

    def start(self) -> None:
        """Declare subscriptions and the queryable, then pull the agents' latest maps."""
        self.bus.subscribe(self.keys.all_maps, self.on_map)
        self.bus.subscribe(self.keys.all_poses, self.on_pose)
        self.bus.watch_alive(self.keys.all_alive, self.on_presence)
        self.bus.subscribe(self.keys.all_free, self.on_free)
        self.bus.serve(self.keys.fused, self.answer_fused)
        self.bus.serve(self.keys.fused_free, self.answer_free)
        self.bus.serve(self.keys.all_paths, self.answer_paths)
        for key, payload in self.bus.get(self.keys.all_maps, timeout_s=self.cfg.pull_timeout_s):
            self.on_map(key, payload, pulled=True)
        for key, payload in self.bus.get(self.keys.all_free, timeout_s=self.cfg.pull_timeout_s):
            self.on_free(key, payload, pulled=True)

    def tick(self) -> FusedMap | None:
        """Apply the queued messages, fuse if anything changed, persist, publish. Returns the new
        fused map (or ``None``)."""
        now = self.now_s()
        with self._lock:
            maps, poses, presence = self._maps, self._poses, self._presence
            self._maps, self._poses, self._presence = [], [], []
            frees, self._frees = self._frees, []
        b = self.backlog
        b["maps"], b["poses"] = len(maps), len(poses)
        b["max_maps"], b["max_poses"] = max(b["max_maps"], len(maps)), max(b["max_poses"], len(poses))
        self.maps_applied += len(maps)
        t0 = time.perf_counter()
        for robot, alive in presence:
            self.fleet.set_online(robot, alive)
        for m in maps:
            self.fleet.put_map(m, now)
        for p in poses:
            self.fleet.put_pose(p, now)
        back = sorted({robot for robot, alive in presence if alive})
        if back:
            self._pull_maps(back)
        fused = self.fleet.fuse(now, bend=False)  # (the graph after publishing: _bend)
        gaps = sorted({m.robot for m in frees if self.free.put(m) == "gap"})
        if gaps:  # a message missed: the agents' queryables answer with the whole free space
            self._pull_maps(gaps, maps=False)
        self.free.keep_only(self._free_sessions())
        again = fused is None and (fused := self._refusals_due(now)) is not None
        if fused is None:
            self._tick_free(now)
            self._bend()
            return None
        if not again:  # (the fused map put again for its figures is no fusion)
            self.fusions += 1
        fused = dataclasses.replace(fused, extra={**fused.extra, **self._stats_extra()})
        self._published_rejected, self._published_s = int(fused.extra["server_rejected"]), time.monotonic()
        self._persist()  # before publishing: what anyone has seen survives a crash
        if not again:
            self.fuse_ms.append((time.perf_counter() - t0) * 1e3)
        payloads = self._payloads(fused)
        paths = self.fleet.paths(fused.version, self.session)
        with self._lock:
            self._latest, self._paths = payloads, paths
        for p in payloads:
            self.bus.put(self.keys.fused, p, reliable=True)
        self._tick_free(now)
        self._bend()
        return fused

    def _refusals_due(self, now_s: float) -> FusedMap | None:
        """The fused map again as a new version when messages were refused since the last one put
        and ``refusals_every_s`` passed: a subscriber sees the server's figures in the fused map,
        and a flood that ends after the last fusion (the agents done) would never be counted there."""
        with self._lock:
            rejected = sum(self.rejected.values())
        if rejected == self._published_rejected or self.fleet.latest() is None:
            return None
        if time.monotonic() - self._published_s < self.cfg.refusals_every_s:
            return None  # (looked at again at the next tick: idle_period_s)
        return self.fleet.republish(now_s)

    def _bend(self) -> None:
        """The fleet's graph matched and solved once the fused map is out (Fleet.fuse), if it has
        work and ``graph_every_s`` passed since the last time; what it moves goes out with the
        next fusion (the loop does not sleep while the graph owes work: ``owes``). Then the
        graph's trials under way (Fleet.try_places), a step of them: both cut short when a map
        waits."""
        self._bent = False
        if self.fleet.graph_stale and time.monotonic() - self._bend_s >= self.cfg.graph_every_s:
            t0 = time.perf_counter()
            self.fleet.bend(stop=self._map_waits)  # (cut short for a map: the rest in the next bend)
            self._bend_s = time.monotonic()
            self._bent = True
            self.bend_ms.append((time.perf_counter() - t0) * 1e3)
        if self.fleet.trials.busy:  # the graph's trials of robots at places (map_server/trials.py)
            t0 = time.perf_counter()
            self.fleet.try_places(stop=self._map_waits)
            self.trial_ms.append((time.perf_counter() - t0) * 1e3)

    def _map_waits(self) -> bool:
        with self._lock:
            return bool(self._maps)

    @property
    def owes(self) -> bool:
        """Whether the loop should come back at the fusion pace rather than wait for a map: the
        fleet has work spread over fusions (Fleet.pending_work), its graph has work, or the
        graph's last result has not been through a fusion yet."""
        return self.fleet.pending_work or self._bent or self.fleet.graph_stale

    # -- free space ------------------------------------------------------------------------------

    def _free_sessions(self) -> set[tuple[str, str]]:
        """The (robot, session)s whose free space is kept: those whose map the fleet keeps, and
        for a robot with no map yet its newest session's (its map may be on the way)."""
        keep = self.fleet.sessions()
        newest: dict[str, tuple[float, str]] = {}
        for (robot, ses), m in self.free.latest.items():
            r = self.fleet.robots.get(robot)
            if (r is None or r.map is None) and m.stamp_s >= newest.get(robot, (-1.0, ""))[0]:
                newest[robot] = (m.stamp_s, ses)
        return keep | {(robot, ses) for robot, (_, ses) in newest.items()}

    def _free_payload(self, f: FusedFree) -> bytes:
        return codec.encode(dataclasses.replace(f, session=self.session))

    def _tick_free(self, now: float) -> None:
        """Fuse and publish the free space when it or a placement changed (at most every
        ``free.min_gap_s``, or ``free.gap_per_cost`` times what the last took): in the loop, or on
        a thread of its own when the last took ``free_thread_above_s`` or more (published at the
        first tick after it ends); persisted first, like the map."""
        job = self._free_job
        if job is None:
            placements = self.fleet.placements()
            if not self.free.due(placements, self.now_s()):
                return
            latest = self.fleet.latest()
            version, seg = (0, None) if latest is None else (latest.version, latest.seg)
            job = _FreeJob(
                self.free.begin(placements, self.now_s()), seg, version, self.now_s(), self.free.compute
            )
            if self.free.cost_s >= self.cfg.free_thread_above_s:
                self._free_job = job
                job.thread.start()
                return
            job.run()
        elif job.thread.is_alive():
            return
        self._free_job = None
        if job.error is not None:  # (nothing lost: the messages are kept, it is tried again)
            log.error("fusing the free space failed: %s", job.error)
            self.free.changed = True
            return
        self._publish_free(job)

    def _publish_free(self, job: _FreeJob) -> None:
        fused = self.free.finish(job.computed, self.server_id, job.version, job.now_s)
        self.free.cost_s = job.cost_s  # (the next one waits gap_per_cost times this)
        self.free_ms.append(job.cost_s * 1e3)
        self._persist()
        payload = self._free_payload(fused)
        with self._lock:
            self._latest_free = [payload]
        self.bus.put(self.keys.fused_free, payload, reliable=True)

    def _pull_maps(self, robots: list[str], maps: bool = True) -> None:
        """Pull ``robots``' latest maps and free space (their queryables; ``maps=False``: the free
        space only) on a thread of its own, queued like puts.

        A robot that comes (back) online may have put its last map while the server could not
        hear it — a router restart drops every put in flight and shows every token leave and come
        back — and an agent puts a map only when it changed."""

        def pull() -> None:
            try:
                for robot in robots:
                    for key, payload in (
                        self.bus.get(self.keys.robot_map(robot), timeout_s=self.cfg.pull_timeout_s)
                        if maps
                        else ()
                    ):
                        self.on_map(key, payload, pulled=True)
                    for key, payload in self.bus.get(
                        self.keys.robot_free(robot), timeout_s=self.cfg.pull_timeout_s
                    ):
                        self.on_free(key, payload, pulled=True)
            except Exception as exc:  # e.g. the bus closed at shutdown: the next put catches up
                log.warning("pulling the maps of %s failed: %s", robots, exc)

        threading.Thread(target=pull, name="pull-maps", daemon=True).start()

    def run(self, stop: threading.Event) -> None:
        self.start()
        trimmer = Trimmer()  # freed memory back to the system now and then (runs for days)
        while not stop.is_set():
            t = time.monotonic()
            self._wake.clear()
            self.tick()
            self._log_status()
            trimmer.maybe()
            if not self.owes:  # a settle (or the graph's work) under way goes on at the fusion pace
                self._wake.wait(self.cfg.idle_period_s)  # a new map (or stop) ends the wait early
            stop.wait(max(0.0, self.cfg.min_fuse_gap_s - (time.monotonic() - t)))
        self.tick()
        if self._free_job is not None:  # (its thread ends by itself: seconds at most)
            self._free_job.thread.join()
            self._tick_free(self.now_s())

    def _payloads(self, fused: FusedMap) -> list[bytes]:
        """The fused map as encoded chunks, stamped with this server process's session."""
        fused = dataclasses.replace(fused, session=self.session)
        return [codec.encode(c) for c in codec.split_fused_map(fused)]

    # -- status --------------------------------------------------------------------------------

    def status(self) -> dict:
        """Health figures: queue depth (messages waiting at the last tick, and the most ever), fusion
        time (fuse + persist, recent window), maps applied per fusion (> 1: coalescing), counts of
        received and rejected messages, peak memory."""
        with self._lock:
            waiting = {"maps": len(self._maps), "poses": len(self._poses)}
            received, rejected, reasons = dict(self.received), dict(self.rejected), dict(self.reasons)
        return {
            "fusions": self.fusions,
            "maps_applied": self.maps_applied,
            "maps_per_fusion": self.maps_applied / max(1, self.fusions),
            "queue": dict(self.backlog, waiting_maps=waiting["maps"], waiting_poses=waiting["poses"]),
            "fuse_ms": _timings(self.fuse_ms),
            "bend_ms": _timings(self.bend_ms),  # the fleet graph's, after publishing
            "trial_ms": _timings(self.trial_ms),  # its trials' steps, after publishing
            "free_ms": _timings(self.free_ms),  # the free space's fusions, after publishing
            "received": received,
            "rejected": rejected,
            "reasons": reasons,
            "peak_rss_mb": _peak_rss_mb(),
        }

    def _stats_extra(self) -> dict:
        """The figures of :meth:`status` a subscriber sees in ``FusedMap.extra`` (named numbers);
        the fusion time is the previous fusion's (this one is still running)."""
        st = self.status()
        return {
            "server_fusions": float(st["fusions"]),
            "server_queue_maps": float(st["queue"]["maps"]),
            "server_queue_poses": float(st["queue"]["poses"]),
            "server_fuse_ms_last": float(st["fuse_ms"]["last"]),
            "server_fuse_ms_max": float(st["fuse_ms"]["max"]),
            "server_bend_ms_last": float(st["bend_ms"]["last"]),
            "server_bend_ms_max": float(st["bend_ms"]["max"]),
            "server_maps_per_fusion": float(st["maps_per_fusion"]),
            "server_maps_applied": float(st["maps_applied"]),
            "server_rejected": float(sum(st["rejected"].values())),
            "server_peak_rss_mb": st["peak_rss_mb"],
        }

    def _log_status(self) -> None:
        now = time.monotonic()
        if now - self._last_status_s >= self.cfg.status_every_s:
            self._last_status_s = now
            st = self.status()
            q, f, b, t, fr = st["queue"], st["fuse_ms"], st["bend_ms"], st["trial_ms"], st["free_ms"]
            log.info(
                "status: %d fusions (%.1f maps each), queue %d maps %d poses (max %d/%d), "
                "fusion p50 %.1f p95 %.1f max %.1f ms, graph after it p50 %.1f p95 %.1f ms, "
                "its trials max %.1f ms a step, free space p50 %.1f max %.1f ms, peak rss %.0f MB",
                st["fusions"],
                st["maps_per_fusion"],
                q["maps"],
                q["poses"],
                q["max_maps"],
                q["max_poses"],
                f["p50"],
                f["p95"],
                f["max"],
                b["p50"],
                b["p95"],
                t["max"],
                fr["p50"],
                fr["max"],
                st["peak_rss_mb"],
            )
        if self.rejected and now - self._last_log_s >= self.cfg.log_rejections_every_s:
            self._last_log_s = now
            log.warning("rejected messages so far: %s", dict(self.reasons))


def _reason(exc: Exception) -> str:
    """A short, countable reason: the chunk check that refused it, or the field a decoder named."""
    reason = getattr(exc, "reason", None)
    if reason:
        return str(reason)
    head = str(exc).split(":", 1)[0].strip()
    return head[:40] if head and len(head) <= 40 and " " not in head else "malformed"


def _peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # Linux: KiB


def encode_graph_state(graph: dict[str, tuple[str, int, np.ndarray]]) -> bytes:
    """The fleet graph's solution (:meth:`Fleet.graph_state`) as stored bytes: poses as <f8."""
    return msgpack.packb(
        {robot: [session, seq, np.asarray(x, "<f8").tobytes()] for robot, (session, seq, x) in graph.items()},
        use_bin_type=True,
    )


def decode_state(
    meta: dict, blobs: dict[str, bytes], cfg: FleetConfig, server_id: str, free: FreeSpaces
) -> tuple[Fleet, dict[str, RobotMap], dict[str, FreeSpace]]:
    """A saved state (Store.load: its meta and blobs) as the fleet it holds (Fleet.restore), its
    robots' free spaces put into ``free`` and the fleet reading them there; also the maps it was
    restored from (the robots' and the retired pieces') and the free spaces, each by blob name.
    Raises what the decoders raise on content this build cannot read."""
    frees = {n: codec.decode(b, expect=FreeSpace) for n, b in blobs.items() if n.startswith(FREE_BLOB)}
    for m in frees.values():
        free.put(m)
    graph = decode_graph_state(blobs.get(GRAPH_BLOB))
    maps = {n: codec.decode_stored_map(b) for n, b in blobs.items() if n not in frees and n != GRAPH_BLOB}
    fleet = Fleet.restore(meta["fleet"], maps, cfg, server_id, graph)
    fleet.free_of = free.area
    return fleet, maps, frees


def decode_graph_state(blob: bytes | None) -> dict[str, tuple[str, int, np.ndarray]] | None:
    """Inverse of :func:`encode_graph_state` (None stays None); damaged bytes raise ValueError."""
    if blob is None:
        return None
    items = msgpack.unpackb(blob, raw=False)
    if not isinstance(items, dict):
        raise ValueError(f"{GRAPH_BLOB}: not a map of robots ({type(items).__name__})")
    out = {}
    for robot, (session, seq, raw) in items.items():
        out[str(robot)] = (str(session), int(seq), np.frombuffer(raw, "<f8").reshape(-1, 3))
    return out


class _FreeJob:
    """One fusion of the free space (FreeSpaces.compute of what ``begin`` gave), on its own thread
    when the server runs it in the background; the result or the error is kept for the loop."""

    def __init__(self, parts: list, seg, version: int, now_s: float, compute: Callable):
        self.parts, self.seg, self.version, self.now_s, self._compute = parts, seg, version, now_s, compute
        self.computed: tuple | None = None
        self.cost_s = 0.0  # what it took
        self.error: BaseException | None = None
        self.thread = threading.Thread(target=self.run, name="free-space", daemon=True)

    def run(self) -> None:
        t0 = time.perf_counter()
        try:
            self.computed = self._compute(self.parts, self.seg)
            self.cost_s = time.perf_counter() - t0
        except Exception as e:  # (reported by the loop, which goes on)
            self.error = e


def _timings(recent: deque[float]) -> dict[str, float]:
    """Last, p50, p95 and max of recent timings (ms); zeros when there are none."""
    ms = sorted(recent)
    if not ms:
        return {"last": 0.0, "p50": 0.0, "p95": 0.0, "max": 0.0}
    p50, p95 = (ms[min(len(ms) - 1, int(q * len(ms)))] for q in (0.5, 0.95))
    return {"last": recent[-1], "p50": p50, "p95": p95, "max": ms[-1]}
