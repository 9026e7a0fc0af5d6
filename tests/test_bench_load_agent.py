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
