"""The server's driver through faults, without zenoh: a robot that comes back online has its
latest map pulled (after a router restart every token leaves and comes back, and a map put during
the outage was lost); a restarted agent's old map survives a server restart; a state that does not
restore is reported, not loaded."""

import threading
import time

import numpy as np
import pytest

from map_server.server import MapServer
from map_server.store import StateError, Store
from shared import codec
from shared.keys import Keys
from tests.netutil import wait_for

KEYS = Keys()


class PullBus:
    """Answers a map query with the robot's chunks (and a free-space query with nothing);
    records the queries."""

    def __init__(self, chunks):
        self.chunks, self.queries, self.puts = chunks, [], []
        self.lock = threading.Lock()

    def put(self, key, payload, reliable=True):
        self.puts.append((key, payload))

    def get(self, key_expr, timeout_s=2.0):
        with self.lock:
            self.queries.append(key_expr)
        if key_expr != KEYS.robot_map("robot1"):
            return []
        return [(KEYS.robot_map("robot1"), codec.encode(c)) for c in self.chunks]


def room_chunks(seq=1, session="s1"):
    seg = np.array([[[0, 0], [8, 0]], [[8, 0], [8, 6]], [[8, 6], [0, 6]], [[0, 6], [0, 0]]], float)
    k = len(seg)
    return codec.robot_map_chunks(
        "robot1", session, seq, 10.0, np.array([1.0]), np.zeros((1, 3)), seg, np.arange(k),
        np.ones(k, np.int64), np.full(k, 0.8), np.full(k, 10), np.full(k, 50),
        prior=np.zeros(3), prior_sigma=np.array([0.05, 0.05, 0.02]),
    )  # fmt: skip


def test_a_robot_back_online_has_its_map_pulled_and_a_known_map_is_not_a_rejection():
    bus = PullBus(room_chunks())
    server = MapServer(bus, KEYS)
    server.on_presence(KEYS.robot_alive("robot1"), False)
    server.on_presence(KEYS.robot_alive("robot1"), True)
    assert server.tick() is None  # nothing yet: the pull runs on its own thread
    assert wait_for(lambda: bus.queries == [KEYS.robot_map("robot1"), KEYS.robot_free("robot1")])
    assert wait_for(lambda: server.received["map_chunk"] == 1)
    fused = server.tick()
    assert fused is not None and len(fused.seg) == 4 and fused.robot("robot1").online
    server.on_presence(KEYS.robot_alive("robot1"), True)  # again, e.g. another router restart
    server.tick()
    assert wait_for(lambda: len(bus.queries) == 4)
    time.sleep(0.2)  # let the pull thread finish
    assert server.received["map_chunk"] == 1 and not server.rejected  # the same map: skipped
    bus.chunks = room_chunks(seq=2)  # a newer map the server missed
    server.on_presence(KEYS.robot_alive("robot1"), True)
    server.tick()
    assert wait_for(lambda: server.received["map_chunk"] == 2) and not server.rejected


def test_no_pull_without_a_robot_coming_online():
    bus = PullBus(room_chunks())
    server = MapServer(bus, KEYS)
    server.on_presence(KEYS.robot_alive("robot1"), False)
    server.tick()
    assert bus.queries == []


def test_a_restarted_agents_old_map_survives_a_server_restart(tmp_path):
    server = MapServer(PullBus([]), KEYS, store=Store(tmp_path))
    for session in ("s1", "s2"):  # the agent restarted: a new session
        for c in room_chunks(session=session):
            server.on_map(KEYS.robot_map("robot1"), codec.encode(c))
        fused = server.tick()
    assert fused.extra["retired_pieces"] == 1.0
    again = MapServer(PullBus([]), KEYS, store=Store(tmp_path))
    assert [p.session for p in again.fleet.retired["robot1"]] == ["s1"]
    latest = again.fleet.latest()
    assert latest.version == fused.version and np.array_equal(latest.seg, fused.seg)
    assert latest.robot("robot1").session == "s2"


def test_a_verified_state_that_does_not_restore_is_reported(tmp_path):
    server = MapServer(PullBus([]), KEYS, store=Store(tmp_path))
    for c in room_chunks():
        server.on_map(KEYS.robot_map("robot1"), codec.encode(c))
    server.tick()
    meta, blobs = Store(tmp_path).load()
    del meta["fleet"]["robots"]  # e.g. written by another build: checksums fine, content foreign
    Store(tmp_path).save(meta, blobs)
    with pytest.raises(StateError, match=r"state\.json: cannot be restored \(KeyError"):
        MapServer(PullBus([]), KEYS, store=Store(tmp_path))
