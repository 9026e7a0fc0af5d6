"""The agent process: a scan source -> FastSLAM -> poses and trusted maps on the bus (docs/design.md).

:class:`AgentCore` turns scans into wire messages and knows nothing of zenoh; :func:`run_agent`
drives it from a source at the source's own pace (``speed`` × real time), publishes on a
:class:`shared.bus.Bus`, answers queries for its latest map (so a restarted server can pull it),
holds a liveliness token, and writes its trajectory when asked.

Frames: the filter starts at the origin of the robot's *map frame*. A start-pose prior (the map
frame in the global frame), when given, travels with every map so the server can place the robot.
A robot that joins a fleet (``--join``) finds its map frame in the fused map first
(:class:`~robot_agent.join.Joiner`, fed from :meth:`AgentCore.step`): from then on that transform
travels as its prior, marked ``joined``, and the server places it there once it checked it.
"""

from __future__ import annotations

import dataclasses
import logging
import threading
import time
import uuid
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field

import numpy as np

from robot_agent.backend.live import LiveCorrector, graph_fields
from robot_agent.freespace import FreeSpaceConfig, FreeSpaceViews
from robot_agent.health import LaserHealth
from robot_agent.join import Joiner
from robot_agent.publish import MapArrays, PublishConfig, top_particle_maps
from robot_agent.slam.fastslam import Estimate, FastSLAM
from robot_agent.slam.relocalize import ScanRays
from robot_agent.sources.base import Scan
from shared import codec
from shared.keys import Keys
from shared.memory import Trimmer
from shared.messages import FreeSpace, PoseUpdate, RobotMap, ring_subset

log = logging.getLogger("fleet_slam.agent")

DEFAULT_PRIOR_SIGMA = np.array([0.05, 0.05, np.radians(1.0)])  # a surveyed start pose
SCANS_AGAIN = 16  # keyframe scans sent before that a map with a new graph carries again, in turn


@dataclass(frozen=True)
class AgentConfig:
    pose_period_s: float = 0.2  # source time between pose updates (5 Hz)
    map_period_s: float = 1.0  # source time between map publications (only when the map changed)
    speed: float = 1.0  # source seconds per wall second; 0 = as fast as possible
    publish: PublishConfig = field(default_factory=PublishConfig)
    free_period_s: float = 15.0  # source time between free-space publications (only when changed)
    free: FreeSpaceConfig = field(default_factory=FreeSpaceConfig)


class AgentCore:
    """Scans in, wire messages out: the bus-free part of an agent (testable without zenoh)."""

    def __init__(
        self,
        robot: str,
        slam: FastSLAM,
        cfg: AgentConfig = AgentConfig(),
        prior: np.ndarray | None = None,
        prior_sigma: np.ndarray | None = None,
        session: str | None = None,
        corrector: LiveCorrector | None = None,
        new_corrector: Callable[[FastSLAM], LiveCorrector] | None = None,
    ):
        self.robot = robot
        self.corrector = corrector  # the online back end: applied to what is published
        self.new_corrector = new_corrector  # makes the next session's (default: none)
        self.slam = slam
        self.cfg = cfg
        self.session = session or uuid.uuid4().hex[:16]
        self.prior = None if prior is None else np.asarray(prior, float)
        self.prior_sigma = (
            None if prior is None else np.asarray(DEFAULT_PRIOR_SIGMA if prior_sigma is None else prior_sigma)
        )
        self.map_seq = 0
        self.pose_seq = 0
        self.scans = 0
        self.estimate: Estimate | None = None
        self._fingerprint: bytes | None = None
        self._graph: dict = {}  # the pose graph of the map being published (LiveCorrector.graph_fields)
        self._rebuilt_graph: tuple | None = None  # the graph of a map rebuilt along it (rebuilt())
        self._graph_sent: tuple = (None, None)  # the graph last sent and the map seq that carried it
        self._scans_sent: set[int] = set()  # keyframes whose scans went out in this session ...
        self._scan_roll = 0  # ... and where the next map's few old ones (SCANS_AGAIN) start
        self._rebuilt_scans: dict = {}  # the keyframe scans of a map rebuilt along its graph
        self.map_whole: list[RobotMap] = []  # the latest map with its graph (what a query gets)
        self._next_pose_s = -np.inf
        self._next_map_s = -np.inf
        self._last_stamp_s = 0.0
        self._trimmer = Trimmer()  # freed memory back to the system now and then (runs for days)
        self.health = LaserHealth()  # unusable readings counted, a blind laser noticed
        self.first_scan = 0  # the run's scan at which this session's filter started
        # the sessions this run ended because its filter lost the robot: (session, first scan,
        # last scan, the filter's statistics)
        self.ended: list[tuple[str, int, int, dict]] = []
        self.ended_paths: list[tuple[np.ndarray, np.ndarray]] = []  # their stamps (S,), poses (S,3)
        self.free = FreeSpaceViews(cfg.free)  # the space the laser saw free, per view
        self.free_seq = 0
        self.free_whole: FreeSpace | None = None  # the whole free space as of the last message
        self._free_sent = 0  # views whose rings went out (a message carries only newer views' rings)
        self._next_free_s = -np.inf
        self._free_fingerprint: bytes | None = None
        self._in_doubt = False
        self.joiner: Joiner | None = None  # finds the map frame in the fused map (--join)

    def step(self, scan: Scan) -> Estimate:
        self.health.add(scan.ranges_m, scan.range_max_m)
        self.estimate = self.slam.step(
            scan.stamp_s, scan.odometry, scan.ranges_m, scan.angles_rad, scan.laser_offset, scan.range_max_m
        )
        self.scans += 1
        self._last_stamp_s = max(self._last_stamp_s, float(scan.stamp_s))
        if self.corrector is not None:
            self.corrector.on_scan(
                scan.stamp_s,
                scan.odometry,
                scan.ranges_m,
                scan.angles_rad,
                scan.laser_offset,
                scan.range_max_m,
            )
            if self.corrector.tick():
                self._next_map_s = -np.inf  # a new correction: the corrected map goes out now
        self._free_view(scan)
        if self.joiner is not None and self.joiner.due(float(scan.stamp_s)):
            self._join(scan)
        if self.slam.lost:
            self.new_session()
        self._trimmer.maybe()
        return self.estimate

    def _join(self, scan: Scan) -> None:
        """An attempt to find the filter's map in the fused map; when it is taken, its transform is
        the prior (``joined``) of every map from now on, and the map and free space go out now."""
        gm, _ = self.slam.published_map()
        keep = gm.hits >= self.joiner.cfg.min_hits
        usable = min(self.slam.cfg.extraction.max_usable_range_m, scan.range_max_m)
        rays = ScanRays(scan.ranges_m, scan.angles_rad, scan.laser_offset, usable)
        if self.joiner.step(float(scan.stamp_s), gm.seg[keep], gm.facing[keep], self.estimate.pose, rays):
            self.prior = self.joiner.transform.copy()
            self.prior_sigma = np.asarray(self.joiner.cfg.sigma, float)
            self._next_map_s = self._next_free_s = -np.inf
            log.info("%s: joined the fused map: %s", self.robot, self.joiner.last.reason)

    @property
    def joined(self) -> bool:
        """Whether the prior is the map frame's place in the fused map (--join found it)."""
        return self.joiner is not None and self.joiner.transform is not None

    def _free_view(self, scan: Scan) -> None:
        """The scan's free space kept as a view when it adds some; none while the filter doubts
        odometry, and the views since the doubt began are forgotten (their poses are suspect)."""
        doubt = self.slam.doubt
        if doubt is not None:
            if not self._in_doubt:
                self.free.drop_from(doubt.scan)
                self._free_sent = min(self._free_sent, len(self.free))  # (a later view takes its place)
                self._in_doubt = True
            return
        self._in_doubt = False
        self.free.add(
            len(self.slam.trajectory) - 1, self.estimate.pose, scan.ranges_m, scan.angles_rad,
            scan.laser_offset, scan.range_max_m,
        )  # fmt: skip

    def new_session(self) -> None:
        """The filter lost the robot — moved where its map does not reach, or a map it cannot
        find itself in (:mod:`robot_agent.slam.kidnap`): what it mapped stays as published (the
        server keeps an ended session's map where it placed it), and mapping starts again in a
        new frame, as a new session the server places like any robot. Its map was held since the
        doubt began, so nothing the robot saw after it was moved went into it."""
        old = self.slam
        self.ended.append((self.session, self.first_scan, self.scans - 1, dict(old.stats)))
        stamps, poses = old.best_trajectory()  # as published: with the back end's last correction
        if self.corrector is not None and len(poses):
            poses = self.corrector.corrected_path(poses, old.trajectory.first_scan)
        self.ended_paths.append((stamps, poses))
        log.warning(
            "%s: lost at scan %d; session %s ends, a new one begins", self.robot, self.scans - 1, self.session
        )
        self.slam = FastSLAM(old.cfg, old.rng)
        self.session = uuid.uuid4().hex[:16]
        self.first_scan = self.scans
        self.prior = self.prior_sigma = None  # the new frame is nowhere known
        self.joiner = None
        self._fingerprint, self._rebuilt_graph, self._graph_sent = None, None, (None, None)
        self._scans_sent, self._scan_roll, self._rebuilt_scans = set(), 0, {}
        self._next_map_s = -np.inf
        self.free = FreeSpaceViews(self.cfg.free)  # (the ended session's went out with its map)
        self.free_seq, self._free_fingerprint, self._next_free_s = 0, None, -np.inf
        self.free_whole, self._free_sent = None, 0
        if self.corrector is not None:
            self.corrector.close()
            self.corrector = None if self.new_corrector is None else self.new_corrector(self.slam)

    def published_pose(self) -> np.ndarray:
        """The current pose as published: the filter's, corrected by the online back end."""
        pose = self.estimate.pose
        return pose if self.corrector is None else self.corrector.pose(pose)

    def rebuilt(self, slam: FastSLAM, pose: np.ndarray, graph: tuple | None = None) -> None:
        """The back end corrected the path and ``slam`` holds the map rebuilt along it: publish
        that map and ``pose (3,)``, the corrected current pose, next (both due at once).
        ``graph``: ``(correction, gauge, first)``, the back end's last correction, whose graph
        goes out with the map (its frame moved by ``gauge``; ``slam``'s scan ``i`` is this
        session's scan ``first + i``)."""
        self.slam = slam
        if self.corrector is not None:
            self._rebuilt_scans = self.corrector.scans
        self.corrector = None  # the rebuilt map and pose are in the corrected frame already
        self._rebuilt_graph = graph
        if self.estimate is not None:
            self.estimate = dataclasses.replace(self.estimate, pose=np.asarray(pose, float).copy())
        self._next_pose_s = self._next_map_s = self._next_free_s = -np.inf

    def pose_message(self) -> PoseUpdate | None:
        """A pose update when one is due (every ``pose_period_s`` of source time)."""
        if self.estimate is None or self._last_stamp_s < self._next_pose_s:
            return None
        self._next_pose_s = self._last_stamp_s + self.cfg.pose_period_s
        msg = PoseUpdate(
            self.robot,
            self.session,
            self.pose_seq,
            self._last_stamp_s,
            self.published_pose(),
            dict(
                self.health.status(),
                odometry_doubt=float(self.slam.doubt is not None),  # is the robot where it thinks?
                sessions_ended=float(len(self.ended)),  # the filter lost the robot this often
            ),
        )
        self.pose_seq += 1
        return msg

    def map_messages(self, force: bool = False) -> list[RobotMap] | None:
        """The map's chunks when due (``map_period_s``) and changed since the last ones (or ``force``)."""
        if self.estimate is None or (not force and self._last_stamp_s < self._next_map_s):
            return None
        if self.slam.doubt is not None and not force:  # the map as it was before the doubt stands:
            return None  # the back end's corrections meanwhile may follow the robot's path elsewhere
        self._next_map_s = self._last_stamp_s + self.cfg.map_period_s
        arrays = top_particle_maps(self.slam, self.cfg.publish)
        self._graph = {}
        born = self.slam.step_index - arrays.age
        graph = None  # the graph object the map's graph fields come from
        if self.corrector is not None:  # every element moved with the keyframe it was made from
            self._graph = self.corrector.graph_fields(born)
            graph = self.corrector.correction.graph
            arrays = dataclasses.replace(
                arrays,
                seg=self.corrector.segments(arrays.seg, born),
                particle_poses=np.array([self.corrector.pose(p) for p in arrays.particle_poses]).reshape(
                    -1, 3
                ),
            )
        elif self._rebuilt_graph is not None:
            c, gauge, first = self._rebuilt_graph
            scans = first + self.slam.trajectory.scan_of_step(np.maximum(born, 1))
            self._graph = graph_fields(c, scans, gauge)
            graph = self._rebuilt_graph
        fp = arrays.fingerprint()
        if fp == self._fingerprint and not force:
            return None
        self._fingerprint = fp
        if not self._graph:
            graph = None
        if graph is None or graph is not self._graph_sent[0]:  # a new graph: it goes out now
            self._graph_sent = (graph, None if graph is None else self.map_seq)
        if self._graph:
            self._graph["graph_seq"] = self._graph_sent[1]
        graph = self._graph
        if "kf_id" in graph:  # the whole carries every keyframe's scan
            self._graph = graph | self._scan_fields(graph["kf_id"], whole=True)
        chunks = self.map_whole = self._chunks(arrays)
        if self._graph and self._graph_sent[1] != self.map_seq:  # unchanged since it went out: the
            # anchors name it, the receiver has it (the queryable answers with the whole)
            self._graph = {"anchor": graph["anchor"], "graph_seq": self._graph_sent[1]}
            chunks = self._chunks(arrays)
        elif "kf_id" in graph:  # a new graph: the scans of its new keyframes, and a few sent before
            self._graph = graph | self._scan_fields(graph["kf_id"], whole=False)
            chunks = self._chunks(arrays)
        self.map_seq += 1
        return chunks

    def free_message(self, force: bool = False) -> FreeSpace | None:
        """The free space when due (``free_period_s``) and changed (a new view, or a correction
        that moved one by a centimetre or a milliradian), or ``force``d; each view anchored at its
        scan's pose on the path as published (the back end's latest correction, or the rebuilt
        path). Every view's pose, but only the rings of views not sent before (``rings_from``);
        :attr:`free_whole` is the whole of it, for the queryable."""
        if self.estimate is None or not len(self.free):
            return None
        if not force and (self._last_stamp_s < self._next_free_s or self.slam.doubt is not None):
            return None
        self._next_free_s = self._last_stamp_s + self.cfg.free_period_s
        _, path = self.slam.best_trajectory()
        first = self.slam.trajectory.first_scan
        if self.corrector is not None and len(path):
            path = self.corrector.corrected_path(path, first)
        poses = self.free.refresh(path, first)
        fp = np.concatenate([np.rint(poses[:, :2] * 100), np.rint(poses[:, 2:] * 1000)], axis=1)
        fp = fp.astype(np.int64).tobytes()
        if fp == self._free_fingerprint and not force:
            return None
        self._free_fingerprint = fp
        view_pose, offsets, ring_view, vertices, wall = self.free.arrays(poses)
        whole = FreeSpace(self.robot, self.session, self.free_seq, self._last_stamp_s, view_pose, offsets,
                          ring_view, vertices, wall)  # fmt: skip
        new = ring_view >= self._free_sent  # the rings of views not sent before
        take, new_offsets = ring_subset(offsets, new)
        msg = FreeSpace(
            self.robot, self.session, self.free_seq, self._last_stamp_s, view_pose, new_offsets,
            ring_view[new], vertices[take], wall[take], rings_from=self._free_sent,
        )  # fmt: skip
        self.free_whole, self._free_sent = whole, len(self.free)
        self.free_seq += 1
        return msg

    def _scan_fields(self, kf_id: np.ndarray, whole: bool) -> dict:
        """The keyframe scans of graph ``kf_id`` as map fields: every one (``whole``), or those not
        sent in this session and SCANS_AGAIN of those sent, in turn (a receiver that missed a
        map has them all again within a few graphs, without asking)."""
        scans = self.corrector.scans if self.corrector is not None else self._rebuilt_scans
        ids = [k for k in kf_id.tolist() if k in scans]
        if not whole:
            sent = [k for k in ids if k in self._scans_sent]
            if len(self._scans_sent) > 2 * len(ids):  # (bounded: keyframes leave the graph)
                self._scans_sent = set(sent)
            again = sent[self._scan_roll % len(sent) :][:SCANS_AGAIN] if sent else []
            self._scan_roll += len(again)
            ids = sorted([k for k in ids if k not in self._scans_sent] + again)
            self._scans_sent.update(ids)
        if not ids:
            return {}
        pts = [scans[k] for k in ids]
        return dict(
            scan_id=np.array(ids, np.int64), scan_count=np.array([len(p) for p in pts], np.int64),
            scan_xy=np.concatenate(pts).astype(float),
        )  # fmt: skip

    def _chunks(self, a: MapArrays) -> list[RobotMap]:
        return codec.robot_map_chunks(
            self.robot, self.session, self.map_seq, self._last_stamp_s,
            a.particle_weights, a.particle_poses, a.seg, a.element, a.members, a.trust, a.hits, a.age,
            prior=self.prior, prior_sigma=self.prior_sigma, joined=self.joined, **self._graph,
        )  # fmt: skip


class Publisher:
    """The agent's side of the bus: puts, the map queryable, the liveliness token, byte counts."""

    def __init__(self, bus, keys: Keys, core: AgentCore):
        self.bus, self.keys, self.core = bus, keys, core
        self.bytes_sent = {"map": 0, "pose": 0, "free": 0}
        self.messages_sent = {"map": 0, "pose": 0, "free": 0}
        self._lock = threading.Lock()
        self._latest: list[bytes] = []
        self._latest_free: list[bytes] = []
        bus.declare_alive(keys.robot_alive(core.robot))
        bus.serve(keys.robot_map(core.robot), self._answer)
        bus.serve(keys.robot_free(core.robot), self._answer_free)

    def _answer(self, _key: str) -> list[tuple[str, bytes]]:
        with self._lock:
            return [(self.keys.robot_map(self.core.robot), b) for b in self._latest]

    def _answer_free(self, _key: str) -> list[tuple[str, bytes]]:
        with self._lock:
            return [(self.keys.robot_free(self.core.robot), b) for b in self._latest_free]

    def publish(self, force_map: bool = False) -> None:
        pose = self.core.pose_message()
        if pose is not None:
            self._put("pose", self.keys.robot_pose(self.core.robot), [codec.encode(pose)], reliable=False)
        chunks = self.core.map_messages(force=force_map)
        if chunks is not None:
            payloads = [codec.encode(c) for c in chunks]
            whole = self.core.map_whole
            whole = payloads if whole is chunks else [codec.encode(c) for c in whole]
            with self._lock:
                self._latest = whole  # what a query gets: the map with its graph, same seq
            self._put("map", self.keys.robot_map(self.core.robot), payloads, reliable=True)
        free = self.core.free_message(force=force_map)
        if free is not None:
            whole = codec.encode(self.core.free_whole)  # what a query gets: the whole, same seq
            with self._lock:
                self._latest_free = [whole]
            self._put("free", self.keys.robot_free(self.core.robot), [codec.encode(free)], reliable=True)

    def _put(self, what: str, key: str, payloads: list[bytes], reliable: bool) -> None:
        for p in payloads:
            self.bus.put(key, p, reliable=reliable)
            self.bytes_sent[what] += len(p)
            self.messages_sent[what] += 1


def paced(scans: Iterator[Scan], speed: float, stop: threading.Event) -> Iterator[Scan]:
    """``scans`` at ``speed`` × their own clock (``0`` = no waiting); ends early when ``stop`` is set.
    The clock is the running maximum of the stamps (real logs step back in time)."""
    t0_wall = time.monotonic()
    t0_src: float | None = None
    latest = -np.inf
    for scan in scans:
        if stop.is_set():
            return
        latest = max(latest, scan.stamp_s)
        if t0_src is None:
            t0_src = latest
        if speed > 0:
            wait = t0_wall + (latest - t0_src) / speed - time.monotonic()
            if wait > 0 and stop.wait(wait):
                return
        yield scan


def run_agent(
    bus,
    keys: Keys,
    core: AgentCore,
    scans: Iterator[Scan],
    stop: threading.Event,
    on_estimate: Callable[[Scan, Estimate], None] | None = None,
    on_progress: Callable[[AgentCore], None] | None = None,
) -> Publisher:
    """Feed ``scans`` to ``core`` at ``core.cfg.speed`` and publish until the scans end or ``stop``.
    ``on_estimate`` lets a simulated robot react (e.g. an explorer sets its velocity)."""
    pub = Publisher(bus, keys, core)
    for scan in paced(scans, core.cfg.speed, stop):
        est = core.step(scan)
        if on_estimate is not None:
            on_estimate(scan, est)
        pub.publish()
        if on_progress is not None:
            on_progress(core)
    if core.estimate is not None:
        pub.publish(force_map=True)  # the final map, whatever the period
    log.info("%s: %d scans, %s bytes sent", core.robot, core.scans, pub.bytes_sent)
    return pub
