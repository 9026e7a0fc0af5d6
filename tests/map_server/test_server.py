"""The server's driver without zenoh: validation at the door, counted rejections, persistence
before publication, resume from the state directory."""

import numpy as np

from map_server.server import MapServer, ServerConfig
from map_server.store import Store
from shared import codec
from shared.keys import Keys
from shared.messages import PoseUpdate

KEYS = Keys()


class FakeBus:
    def __init__(self):
        self.puts = []

    def put(self, key, payload, reliable=True):
        self.puts.append((key, payload))


def robot_map(robot="robot1", seq=0, n=40, prior=(0.0, 0.0, 0.0)):
    """A room's walls as a robot map (one particle)."""
    t = np.linspace(0.0, 1.0, n // 4, endpoint=False)
    seg = []
    for (x0, y0), (x1, y1) in [((0, 0), (8, 0)), ((8, 0), (8, 6)), ((8, 6), (0, 6)), ((0, 6), (0, 0))]:
        a = np.array([x0, y0]) + np.outer(t, [x1 - x0, y1 - y0])
        b = a + np.array([x1 - x0, y1 - y0]) / (n // 4) * 0.9
        seg += list(np.stack([a, b], axis=1))
    seg = np.array(seg)
    k = len(seg)
    return codec.robot_map_chunks(
        robot, "s1", seq, 10.0 + seq, np.array([1.0]), np.zeros((1, 3)), seg, np.arange(k),
        np.ones(k, np.int64), np.full(k, 0.8), np.full(k, 10), np.full(k, 50),
        prior=np.array(prior), prior_sigma=np.array([0.05, 0.05, 0.02]),
    )  # fmt: skip


def test_hostile_messages_are_counted_and_change_nothing():
    server = MapServer(FakeBus(), KEYS)
    server.on_map(KEYS.robot_map("robot1"), b"\xc1garbage")
    server.on_map(KEYS.robot_map("robot2"), codec.encode(robot_map("robot1")[0]))  # someone else's key
    server.on_map("fleet/default/elsewhere", codec.encode(robot_map()[0]))
    server.on_pose(KEYS.robot_pose("robot1"), codec.encode(robot_map()[0]))  # a map on the pose key
    assert server.rejected == {"map": 3, "pose": 1}
    assert server.tick() is None and server.fleet.latest() is None


def test_a_stale_pose_is_rejected():
    server = MapServer(FakeBus(), KEYS)
    for seq in (3, 2):
        server.on_pose(
            KEYS.robot_pose("robot1"), codec.encode(PoseUpdate("robot1", "s1", seq, 1.0, np.zeros(3)))
        )
    assert server.received["pose"] == 1 and server.rejected["pose"] == 1


def test_fused_map_is_persisted_before_it_is_published_and_restored(tmp_path):
    bus = FakeBus()
    server = MapServer(bus, KEYS, store=Store(tmp_path))

    def persisted_then_published(key, payload, reliable=True):
        assert Store(tmp_path).load() is not None  # on disk before anyone sees it
        bus.puts.append((key, payload))

    bus.put = persisted_then_published
    for chunk in robot_map():
        server.on_map(KEYS.robot_map("robot1"), codec.encode(chunk))
    fused = server.tick()
    assert fused is not None and len(fused.seg) > 0 and bus.puts
    assert [k for k, _ in server.answer_fused(KEYS.fused)] == [KEYS.fused]
    again = MapServer(FakeBus(), KEYS, store=Store(tmp_path)).fleet.latest()
    assert again.version == fused.version and np.allclose(again.seg, fused.seg, atol=1e-4)


def test_rejections_are_counted_by_reason_and_status_reports_the_queue():
    server = MapServer(FakeBus(), KEYS)
    server.on_map(KEYS.robot_map("robot1"), b"\xc1garbage")
    server.on_map(KEYS.robot_map("robot1"), b"\xc1garbage")
    server.on_map(KEYS.robot_map("robot2"), codec.encode(robot_map("robot1")[0]))
    reasons = server.status()["reasons"]
    assert sum(reasons.values()) == 3 and len(reasons) == 2, reasons
    for chunk in robot_map():
        server.on_map(KEYS.robot_map("robot1"), codec.encode(chunk))
    assert server.status()["queue"]["waiting_maps"] == 1
    fused = server.tick()
    st = server.status()
    assert st["queue"]["maps"] == 1 and st["queue"]["waiting_maps"] == 0
    assert st["fusions"] == 1 and st["fuse_ms"]["max"] > 0
    assert fused.extra["server_rejected"] == 3.0 and fused.extra["server_queue_maps"] == 1.0


def test_messages_refused_after_the_last_fusion_go_out_with_the_fused_map_again():
    bus = FakeBus()
    server = MapServer(bus, KEYS, ServerConfig(refusals_every_s=0.0))
    for chunk in robot_map():
        server.on_map(KEYS.robot_map("robot1"), codec.encode(chunk))
    first = server.tick()
    assert first is not None and first.extra["server_rejected"] == 0.0
    assert server.tick() is None  # nothing changed, nothing refused: nothing put
    server.on_map(KEYS.robot_map("robot1"), b"\xc1garbage")
    server.on_map(KEYS.robot_map("robot1"), b"\xc1garbage")
    again = server.tick()  # the maps unchanged, the figures not: the fused map put as a new version
    assert again is not None and again.version == first.version + 1
    assert again.extra["server_rejected"] == 2.0
    np.testing.assert_array_equal(again.seg, first.seg)
    assert codec.decode(bus.puts[-1][1]).version == again.version
    assert server.status()["fusions"] == 1  # (no fusion)
    assert server.tick() is None  # counted once
    held = MapServer(FakeBus(), KEYS, ServerConfig(refusals_every_s=3600.0))
    for chunk in robot_map():
        held.on_map(KEYS.robot_map("robot1"), codec.encode(chunk))
    held.tick()
    held.on_map(KEYS.robot_map("robot1"), b"\xc1garbage")
    assert held.tick() is None  # within refusals_every_s of the last put: not yet


def test_published_maps_carry_the_server_process_session():
    first, second = MapServer(FakeBus(), KEYS), MapServer(FakeBus(), KEYS)
    for server in (first, second):
        for chunk in robot_map():
            server.on_map(KEYS.robot_map("robot1"), codec.encode(chunk))
        server.tick()
    sessions = [codec.decode(s.bus.puts[-1][1]).session for s in (first, second)]
    assert sessions == [first.session, second.session] and sessions[0] != sessions[1]
