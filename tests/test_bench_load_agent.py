"""The benchmarks' load agent (benchmarks/bench_fleet.py ``ReplayCore``) drives the agent's real
``Publisher``: it must provide everything the Publisher takes from an agent core (issue 23's free
space once broke every load agent at its first publish, and the load benchmark with it)."""

from pathlib import Path

import numpy as np
import pytest

from robot_agent.agent import Publisher
from shared import codec
from shared.keys import Keys
from tests.benchscripts import bench_script
from tests.map_server.test_server import robot_map


@pytest.fixture(scope="module")
def bench():
    with bench_script("bench_fleet") as module:
        yield module


class FakeBus:
    def __init__(self):
        self.puts, self.served, self.alive = [], {}, []

    def declare_alive(self, key):
        self.alive.append(key)

    def serve(self, key, handler):
        self.served[key] = handler

    def put(self, key, payload, reliable=True):
        self.puts.append((key, payload))


def test_a_load_agent_publishes_maps_and_poses_through_the_agents_publisher(bench):
    m = codec.Assembler().add(robot_map("rec", 0)[0])
    rec = bench.Recording(
        "office", 0, 0, 60.0, np.zeros(3), 30.0, [m, m], np.array([100, 100]), np.array([10, 20]),
        np.array([50]), np.zeros((4, 3)), np.zeros((4, 3)), np.zeros(3), Path("rec.npz"),
    )  # fmt: skip
    core = bench.ReplayCore(rec, "robot07", np.array([1.0, 2.0, 0.5]), map_every=5, first_map=0)
    bus, keys = FakeBus(), Keys("load")
    pub = Publisher(bus, keys, core)
    for _ in range(10):
        pub.publish()
    kinds = [k.rsplit("/", 1)[1] for k, _ in bus.puts]
    assert kinds.count("pose") == 10 and kinds.count("map") == 2 and "free" not in kinds
    maps = [codec.decode(p) for k, p in bus.puts if k == keys.robot_map("robot07")]
    assert [x.seq for x in maps] == [1, 2] and all(x.robot == "robot07" for x in maps)
    np.testing.assert_array_equal(maps[0].prior, [1.0, 2.0, 0.5])
    last = [(k, p) for k, p in bus.puts if k == keys.robot_map("robot07")][-1]
    assert bus.served[keys.robot_map("robot07")]("") == [last]  # the queryable answers the latest


def test_latency_after_a_departure_counts_only_the_maps_put_after_it(bench):
    """``--leave``: the latency of the maps put after the agents left is given apart, and the
    rebuilds of the server's graph counted as the fused maps say they begin and end."""
    from types import SimpleNamespace

    def update(wall_s, seq, rebuilding=0.0):
        status = SimpleNamespace(map_seq=seq)
        fused = SimpleNamespace(
            robot=lambda name: status if name == "r1" else None,
            extra={"graph_rebuilding": rebuilding},
            seg=np.zeros((0, 2, 2)),
        )
        return SimpleNamespace(wall_s=wall_s, fused=fused)

    # r1 puts maps 1-4 at 0, 1, 2, 3 s; each is fused 0.1 s later, but map 3 only 0.5 s later;
    # the graph is matched anew from the second fused map to the fourth
    updates = [update(0.1, 1), update(1.1, 2, 1.0), update(2.5, 3, 1.0), update(3.1, 4)]
    log = "stopped after 4"
    run = bench.LatencyRun(
        2, {"r1": (np.array([1, 2, 3, 4]), np.array([0.0, 1.0, 2.0, 3.0]))}, updates, (0.0, 4.0), log,
        None, left_at=1.5,
    )  # fmt: skip
    s = bench.latency_stats(run)
    assert s["maps_put"] == 4 and s["missing"] == 0
    assert s["after_leave_p50_ms"] == pytest.approx(300.0) and s["after_leave_p95_ms"] == pytest.approx(480.0)
    assert s["p50_ms"] == pytest.approx(100.0)
    assert (s["graph_rebuilds_begun"], s["graph_rebuilds_whole"]) == (1, 1)
    none = bench.latency_stats(bench.LatencyRun(2, run.put_times, updates, (0.0, 4.0), log))
    assert none["after_leave_p95_ms"] is None
