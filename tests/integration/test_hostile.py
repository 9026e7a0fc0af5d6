"""Hostile input on a live fleet: thousands of bad messages while real agents map (issue 5, item 1).

Real processes on loopback — router, map server, two simulated agents with priors — and, in the
test process, a recorder of every legitimate map chunk and pose the agents put, and a hostile
publisher that floods the robots' map and pose keys (and a ghost robot's) with messages the server
must refuse: random bytes, cut payloads, flipped bytes, unknown schema versions, invalid fields,
the wrong kind, a robot's message on another robot's key, replays, altered copies and older
sequence numbers of what the agents sent (only of what the server had for at least
``SETTLED_S``, so each is stale by construction, never a forgery that could win a race).

"The fused map is the same as without them", soundly despite live timing:

- the server counts exactly as many rejections as hostile messages were sent (no legitimate one
  refused, no hostile one taken), and its log names the reasons;
- its final fused map holds the two robots only, each at the last map its agent published;
- that map is, to float32, the fusion of those legitimate maps (recorded by the test) under the
  transforms the server reports — computed offline with the server's own pure fusion functions;
- every robot's pose is its transform composed with a pose its agent sent.
"""

from __future__ import annotations

import dataclasses
import threading
import time
from collections import Counter

import msgpack
import numpy as np
import pytest

from fleet_slam.procs import ProcGroup, python_module
from fleet_slam.watch import FusedWatcher, fetch_paths
from map_server.config import FleetConfig
from map_server.fusion import fuse_particles, merge_segments
from map_server.posegraph import RobotGraph
from shared import codec
from shared.bus import Bus, BusConfig
from shared.geometry import apply_segments, compose, inverse, transform_points
from shared.keys import Keys
from shared.messages import GRAPH_FIELDS, FusedMap, PoseUpdate, RobotMap, RobotPath, WireFormatError
from tests.netutil import loopback_endpoint, wait_for, wait_while_progressing

pytestmark = [pytest.mark.integration, pytest.mark.timeout(180)]

STARTUP_S = 30.0
SIM_S = 30.0  # simulated seconds per agent, at 1x
N_HOSTILE = 2500  # hostile messages sent while the agents map
FLOOD_S = 12.0  # ... spread over this long
SETTLED_S = 0.5  # a legitimate message is replayed or altered only this long after it was recorded
POSE_MARGIN = 10  # ... and a pose only when this many newer ones were recorded (poses may be dropped)
ROBOTS = ("robot1", "robot2")
PRIORS = ("9.0,4.5,0.0", "15.0,5.5,-1.5707963267948966")  # the office routes' true starts
KEYS = Keys()
REASONS_LOGGED = (  # texts the server's first warnings of each reason must show
    "malformed msgpack", "unknown schema version", "stale", "published on the key of", "kind: expected",
)  # fmt: skip


def agent_argv(i: int, endpoint: str) -> list[str]:
    args = ["--robot", ROBOTS[i], "--world", "office", "--route", i, "--prior", PRIORS[i]]
    args += ["--duration", SIM_S, "--particles", 10, "--connect", endpoint]
    return python_module("robot_agent", *args)


class Recorder:
    """Every legitimate map chunk and pose as the agents put them (the first copy of each identity,
    never a payload the hostile publisher sent), with the time it was recorded."""

    def __init__(self, hostile: set[bytes]):
        self.hostile, self.lock = hostile, threading.Lock()
        self.maps: dict[tuple, dict[int, tuple[bytes, RobotMap, float]]] = {}  # (robot, session, seq)
        self.poses: dict[tuple, tuple[bytes, PoseUpdate, float]] = {}

    def on_sample(self, key: str, payload: bytes) -> None:
        with self.lock:
            if payload in self.hostile:
                return
        try:
            robot = KEYS.robot_of(key)
            msg = codec.decode(payload, expect=RobotMap if key.endswith("/map") else PoseUpdate)
        except WireFormatError:
            return
        if robot not in ROBOTS or msg.robot != robot:
            return
        now = time.monotonic()
        with self.lock:
            if isinstance(msg, RobotMap):
                self.maps.setdefault((robot, msg.session, msg.seq), {}).setdefault(
                    msg.chunk, (payload, msg, now)
                )
            else:
                self.poses.setdefault((robot, msg.session, msg.seq), (payload, msg, now))

    def settled(self, now: float) -> tuple[list, list]:
        """Map chunks recorded at least SETTLED_S ago; poses with POSE_MARGIN newer ones recorded."""
        with self.lock:
            maps = [
                (k, c) for k, chunks in self.maps.items() for c in chunks.values() if now - c[2] >= SETTLED_S
            ]
            newest = Counter()
            for robot, session, seq in self.poses:
                newest[(robot, session)] = max(newest[(robot, session)], seq)
            poses = [
                (k, p)
                for k, p in self.poses.items()
                if now - p[2] >= SETTLED_S and k[2] <= newest[k[:2]] - POSE_MARGIN
            ]
        return maps, poses

    def whole_map(self, robot: str, session: str, seq: int) -> RobotMap:
        with self.lock:
            chunks = self.maps[(robot, session, seq)]
        msgs = [chunks[i][1] for i in sorted(chunks)]
        assert len(msgs) == msgs[0].n_chunks, f"{robot} map {seq}: chunks {sorted(chunks)} recorded"
        return codec.join(msgs)

    def last_map_seq(self, robot: str) -> tuple[str, int]:
        with self.lock:
            return max((k[2], k[1]) for k in self.maps if k[0] == robot)[::-1]


class Flood:
    """Sends hostile messages built from what the recorder has, each refused by construction."""

    KINDS = (
        "garbage",
        "truncated",
        "flipped",
        "schema",
        "field",
        "kind",
        "mismatch",
        "replay",
        "altered",
        "older",
    )

    def __init__(self, bus: Bus, recorder: Recorder, seed: int = 0):
        self.bus, self.rec, self.rng = bus, recorder, np.random.default_rng(seed)
        self.sent: Counter[str] = Counter()  # by kind
        self.errors: list[str] = []

    def run(self, n: int, duration_s: float) -> None:
        t0 = time.monotonic()
        i = 0
        while i < n:
            made = self.make(self.KINDS[self.rng.integers(len(self.KINDS))])
            if made is None:
                continue
            kind, key, payload = made
            with self.rec.lock:
                self.rec.hostile.add(payload)
            self.bus.put(key, payload, reliable=True)  # blocking: every one reaches the server
            self.sent[kind] += 1
            i += 1
            ahead = t0 + duration_s * i / n - time.monotonic()
            if ahead > 0:
                time.sleep(ahead)

    def make(self, kind: str) -> tuple[str, str, bytes] | None:
        rng = self.rng
        maps, poses = self.rec.settled(time.monotonic())
        if not maps or not poses:
            return None
        is_map = bool(rng.integers(2))
        pool = maps if is_map else poses
        (robot, _, seq), (payload, msg, _) = pool[rng.integers(len(pool))]
        key = KEYS.robot_map(robot) if is_map else KEYS.robot_pose(robot)
        other_key = KEYS.robot_pose(robot) if is_map else KEYS.robot_map(robot)
        if kind == "garbage":
            target = str(rng.choice([*ROBOTS, "ghost1"]))
            key = KEYS.robot_map(target) if rng.integers(2) else KEYS.robot_pose(target)
            junk = rng.bytes(int(rng.integers(0, 200)))
            return (kind, key, junk) if refused(junk) else None
        if kind == "truncated":
            return kind, key, payload[: int(rng.integers(0, len(payload)))]
        if kind == "flipped":
            raw = bytearray(payload)
            for j in rng.integers(0, len(raw), int(rng.integers(1, 4))):
                raw[j] ^= int(rng.integers(1, 256))
            return (kind, key, bytes(raw)) if refused(bytes(raw)) else None
        if kind in ("schema", "field"):
            fields = msgpack.unpackb(payload)
            if kind == "schema":
                fields["schema"] = [0, 2, 99, -1, "1", 1.5, None][rng.integers(7)]
            else:
                name = sorted(fields)[rng.integers(len(fields))]
                fields[name] = [None, -1, 2**64 - 1, float("nan"), float("inf"), "x", b"\x00" * 5, []][
                    rng.integers(8)
                ]
            bad = msgpack.packb(fields)
            return (kind, key, bad) if refused(bad) else None
        if kind == "kind":  # a pose on a map key, a map on a pose key
            return kind, other_key, payload
        if kind == "mismatch":  # a robot's message on another robot's key
            if rng.integers(2):  # well-formed and fresh, of a robot nobody runs: taken but for the key
                ghost = dataclasses.replace(msg, robot="ghost2", session=rng.bytes(8).hex())
                return kind, key, codec.encode(ghost)
            target = str(rng.choice([r for r in (*ROBOTS, "ghost1") if r != robot]))
            return kind, KEYS.robot_map(target) if is_map else KEYS.robot_pose(target), payload
        if kind == "replay":
            return kind, key, payload
        if kind == "altered":  # the same identity (robot, session, seq, chunk), another content
            if is_map:
                return kind, key, codec.encode(dataclasses.replace(msg, seg=msg.seg + 0.5))
            return kind, key, codec.encode(dataclasses.replace(msg, pose=msg.pose + 1.0))
        if seq == 0:  # older: a seq below a settled one of the same session
            return None
        older = int(rng.integers(0, seq))
        changes = {"seq": older}
        if getattr(msg, "graph_seq", None) is not None:  # a map names its graph by a seq not after its own
            changes["graph_seq"] = min(msg.graph_seq, older)
        return kind, key, codec.encode(dataclasses.replace(msg, **changes))


def refused(payload: bytes) -> bool:
    try:
        codec.decode(payload)
    except WireFormatError:
        return True
    return False


def offline_fusion(
    fused: FusedMap, maps: dict[str, RobotMap], paths: dict[str, RobotPath]
) -> tuple[np.ndarray, np.ndarray, list]:
    """The fused segments, support and provenance that ``maps`` give where the server reports
    their keyframes (map_server.fleet's build: per robot the cross-particle layer, each row moved
    into the global frame with its keyframe as the fleet's graph placed it, then the merge across
    robots)."""
    cfg = FleetConfig().fusion
    rows = {r.robot: i for i, r in enumerate(fused.robots)}
    placed = sorted(r.robot for r in fused.robots if r.merged)
    layers = [fuse_particles(maps[name], cfg) for name in placed]
    seg = []
    for name, layer in zip(placed, layers, strict=True):
        path = paths[name]
        if len(path.pose) == 1:  # placed as a whole: its map frame at the transform
            np.testing.assert_allclose(path.pose[0], fused.robot(name).transform, rtol=0, atol=1e-9)
            seg.append(apply_segments(path.pose[0], layer.seg))
            continue
        graph = RobotGraph.of(maps[name], layer)
        np.testing.assert_allclose(path.local, graph.pose, rtol=0, atol=1e-12)
        move = compose(path.pose, inverse(path.local))[graph.row_kf]
        seg.append(transform_points(move[:, None, :], layer.seg))
    w = [layer.weight for layer in layers]
    owner = [np.full(len(layer), rows[name]) for name, layer in zip(placed, layers, strict=True)]
    fseg, support, off, prov = merge_segments(
        np.concatenate(seg), np.concatenate(w), np.concatenate(owner), cfg
    )
    provenance = [sorted(fused.robots[j].robot for j in prov[off[i] : off[i + 1]]) for i in range(len(fseg))]
    return fseg, support, provenance


def test_thousands_of_hostile_messages_leave_the_fused_map_as_the_agents_made_it(tmp_path):
    endpoint = loopback_endpoint()
    hostile: set[bytes] = set()
    rec = Recorder(hostile)
    with ProcGroup(tmp_path / "logs") as group:
        router = group.start("router", python_module("shared.bus", "router", "--listen", endpoint))
        assert router.wait_for("listening", STARTUP_S), router.output()
        server = group.start("server", python_module("map_server", "--connect", endpoint))
        assert server.wait_for("running", STARTUP_S), server.output()
        with Bus(BusConfig(connect=(endpoint,))) as bus, Bus(BusConfig(connect=(endpoint,))) as evil:
            bus.subscribe(KEYS.all_maps, rec.on_sample)
            bus.subscribe(KEYS.all_poses, rec.on_sample)
            watcher = FusedWatcher(bus, KEYS)
            watcher.start(query_timeout_s=1.0)
            agents = [group.start(ROBOTS[i], agent_argv(i, endpoint)) for i in range(2)]
            flood = Flood(evil, rec)
            assert wait_for(lambda: all(rec.settled(time.monotonic())), STARTUP_S)  # maps and poses to use
            t0 = time.monotonic()
            flood.run(N_HOSTILE, FLOOD_S)
            flood_s = time.monotonic() - t0
            n_sent = sum(flood.sent.values())
            for a in agents:  # they go on mapping after the flood, then finish
                a.popen.wait(SIM_S * 3)
                assert a.popen.returncode == 0, a.output()[-2000:]

            # every hostile message refused and counted, no legitimate one (the fused map's figure);
            # under load the server may still be working through the backlog: wait while it counts
            def rejected() -> float | None:
                f = watcher.latest
                return None if f is None else f.extra.get("server_rejected")

            done = wait_while_progressing(rejected, lambda: rejected() == n_sent, 15.0, 180.0)
            assert done, f"{rejected()} of {n_sent} hostile messages counted as refused: {dict(flood.sent)}"
            fused = watcher.wait_quiet(2.0, 15.0)
            paths = fetch_paths(bus, KEYS)
    assert all(not p.running for p in group.procs)
    log = server.output()
    print(f"{n_sent} hostile messages in {flood_s:.1f} s: {dict(flood.sent)}; fused version {fused.version}")

    # the reasons are in the server's log (the first of each as a warning)
    assert "Traceback" not in log, log[-3000:]
    for text in REASONS_LOGGED:
        assert text in log, f"no warning with {text!r} in the server log"
    assert fused.extra["server_rejected"] == n_sent

    # the two robots only, each at the last map its agent published
    assert [r.robot for r in fused.robots] == list(ROBOTS)
    maps = {}
    for r in fused.robots:
        session, seq = rec.last_map_seq(r.robot)
        assert (r.session, r.map_seq) == (session, seq), (r.robot, r.session, r.map_seq, session, seq)
        assert r.status == "prior", (r.robot, r.status)
        m = rec.whole_map(r.robot, session, seq)
        if not m.has_graph and m.graph_seq is not None:  # its graph came with an earlier map
            carrier = rec.whole_map(r.robot, session, m.graph_seq)
            m = dataclasses.replace(m, **{f: getattr(carrier, f) for f in GRAPH_FIELDS})
        maps[r.robot] = m
    assert {p.version for p in paths.values()} == {fused.version}, (fused.version, paths)

    # the fused map is the fusion of those legitimate maps (float32 on the wire) where the
    # server's graph put their keyframes
    seg, support, provenance = offline_fusion(fused, maps, paths)
    assert fused.seg.shape == seg.shape and len(seg) > 20
    np.testing.assert_allclose(fused.seg, seg, rtol=0, atol=1e-4)
    np.testing.assert_array_equal(fused.support, support)
    assert [sorted(fused.provenance(i)) for i in range(len(seg))] == provenance

    # every pose shown is one its agent sent, in the global frame (hostile poses carry only the
    # stamps of recorded ones; a pose the recorder missed cannot be checked, nor be hostile)
    for r in fused.robots:
        m = maps[r.robot]
        sent = [
            p.pose for k, (_, p, _) in rec.poses.items() if k[0] == r.robot and p.stamp_s == r.pose_stamp_s
        ]
        if m.stamp_s == r.pose_stamp_s:  # the pose of the map's best particle
            sent.append(m.particle_poses[int(np.argmax(m.particle_weights))])
        assert not sent or any(np.allclose(r.pose, compose(r.transform, p), rtol=0, atol=1e-9) for p in sent)
