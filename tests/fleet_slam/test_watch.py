"""FusedWatcher without zenoh: assembling, stale versions, waiting for a condition."""

import dataclasses
import threading

import numpy as np

from fleet_slam.watch import FusedWatcher
from shared import codec
from shared.keys import Keys
from tests.shared.test_codec import fused_map


def test_wait_for_returns_once_the_condition_holds_and_times_out_otherwise():
    w = FusedWatcher(bus=None, keys=Keys())
    rng = np.random.default_rng(3)
    maps = [dataclasses.replace(fused_map(rng, version=v), session="run1") for v in (1, 2, 3)]
    assert w.wait_for(lambda f: f.version >= 1, timeout_s=0.05) is None  # nothing yet: times out

    def feed():
        for m in maps:
            w._on_payload(codec.encode(m), "put")

    t = threading.Timer(0.1, feed)
    t.start()
    got = w.wait_for(lambda f: f.version == 3, timeout_s=5.0)
    t.join()
    assert got is not None and got.version == 3 and [u.fused.version for u in w.updates] == [1, 2, 3]
    w._on_payload(codec.encode(maps[0]), "query")  # an older version after a newer one: ignored
    assert w.latest.version == 3 and len(w.updates) == 3
    assert w.wait_for(lambda f: f.version == 4, timeout_s=0.05).version == 3  # timed out: the latest


def test_quiet_waits_while_the_server_says_its_graph_is_matched_anew():
    """While the server's fleet graph is matched anew (a robot left) it publishes nothing new —
    the maps keep the last whole bend — so "no new map for a while" is not settled while the
    latest map says so (``extra["graph_rebuilding"]``): the wait goes on to the map that ends
    it (or the timeout)."""
    import time

    w = FusedWatcher(bus=None, keys=Keys())
    rng = np.random.default_rng(4)
    base = dataclasses.replace(fused_map(rng, version=1), session="run1")
    held = dataclasses.replace(base, extra={**base.extra, "graph_rebuilding": 1.0})
    whole = dataclasses.replace(base, version=2, extra={**base.extra, "graph_rebuilding": 0.0})
    w._on_payload(codec.encode(held), "put")
    t0 = time.monotonic()
    assert w.wait_quiet(0.05, timeout_s=0.3).version == 1  # timed out on the held bend
    assert time.monotonic() - t0 >= 0.3
    t = threading.Timer(0.2, lambda: w._on_payload(codec.encode(whole), "put"))
    t.start()
    got = w.wait_quiet(0.05, timeout_s=5.0)
    t.join()
    assert got.version == 2
    w2 = FusedWatcher(bus=None, keys=Keys())  # a map that says nothing of it (an older server): quiet
    w2._on_payload(codec.encode(base), "put")
    t0 = time.monotonic()
    assert w2.wait_quiet(0.05, timeout_s=5.0).version == 1 and time.monotonic() - t0 < 1.0
