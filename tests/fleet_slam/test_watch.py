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
