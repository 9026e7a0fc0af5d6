"""Issue 24's rows 3-5, as an operator hit them with ``fleet-slam subscribe`` (the bus replaced
by a fake that delivers what the router would): a subscriber left running keeps a bounded
history, ``--save`` never exposes half a file, a forged version does not stop a subscriber."""

from __future__ import annotations

import argparse
import dataclasses
import json

import numpy as np
import pytest

import fleet_slam.subscribe as subscribe
import fleet_slam.watch as watch
from shared import codec
from tests.shared.test_codec import fused_map


class FakeBus:
    """Delivers ``payloads`` to the fused-map subscription as soon as it is made."""

    def __init__(self, payloads: list[bytes]):
        self.payloads = payloads

    def __call__(self, *args, **kwargs):  # stands in for the Bus class
        return self

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return None

    def subscribe(self, key, callback):
        for p in self.payloads:
            callback(key, p)

    def get(self, key, timeout_s=0.0):
        return []


def _maps(n: int, session: str = "srv1") -> list[bytes]:
    rng = np.random.default_rng(0)
    base = dataclasses.replace(fused_map(rng, m=50), session=session)
    return [codec.encode(dataclasses.replace(base, version=v, seg=base.seg + v)) for v in range(1, n + 1)]


def _run(monkeypatch, payloads, count, save=None) -> watch.FusedWatcher:
    made = []

    class Recording(watch.FusedWatcher):
        def __init__(self, *a, **k):
            super().__init__(*a, **k)
            made.append(self)

    monkeypatch.setattr("shared.bus.Bus", FakeBus(payloads))
    monkeypatch.setattr(subscribe, "FusedWatcher", Recording)
    args = argparse.Namespace(
        connect=["tcp/127.0.0.1:1"], bus_config=None, fleet="default", once=False, count=count, save=save
    )
    assert subscribe.run(args) == 0
    return made[0]


def test_row3_a_subscriber_left_running_keeps_a_bounded_history(monkeypatch, capsys):
    """3,000 updates (the operator's 3,437): every one printed, only the newest few kept."""
    w = _run(monkeypatch, _maps(3000), count=3000)
    out = capsys.readouterr().out
    assert len(w.updates) <= 16 and w.updates[-1].fused.version == 3000  # measured: all 3,000 kept
    assert out.count("put: v") == 3000 and w.received == 3000


def test_row4_save_replaces_the_file_at_once(monkeypatch, tmp_path, capsys):
    """``--save`` writes beside the file and renames over it: a reader that opened the path has
    the old file whole while the next one is written (in place, it would read the new one or an
    empty or cut one — 1,873 of 5,000 reads saw an empty GeoJSON)."""
    for name in ("map.geojson", "map.svg"):
        path = tmp_path / name
        _run(monkeypatch, _maps(1), count=1, save=str(path))
        with open(path) as reader:  # a program reading the map as the next one comes
            first = path.read_text()
            _run(monkeypatch, _maps(2), count=2, save=str(path))
            assert reader.read() == first, "written in place: a reader saw it change under it"
        text = path.read_text()
        assert text != first
        if name.endswith(".geojson"):
            assert json.loads(text)["type"] == "FeatureCollection"
        else:
            assert text.rstrip().endswith("</svg>")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["map.geojson", "map.svg"]  # no temp left
    capsys.readouterr()


def test_row5_a_forged_version_is_refused_and_the_real_ones_still_taken(monkeypatch, capsys):
    """On the plain profile anyone can put a fused map with the server's id and session: one at
    version 2**62 between real versions 1-5 and 6-10 is refused (counted), 6-10 are taken."""
    real = _maps(10)
    rng = np.random.default_rng(0)
    forged = dataclasses.replace(fused_map(rng, m=3), session="srv1", version=2**62)
    payloads = [*real[:5], codec.encode(forged), *real[5:]]
    w = _run(monkeypatch, payloads, count=6)  # (all are delivered before it counts)
    assert [u.fused.version for u in w.updates] == list(range(1, 11))[-len(w.updates) :]
    assert w.latest.version == 10 and w.implausible == 1
    out = capsys.readouterr().out
    assert "v4611686018427387904" not in out
    assert "warning: refused a fused map of srv with version 4611686018427387904" in out  # said so


@pytest.mark.parametrize("gap_s, jump, taken", [(0.0, 50, True), (0.0, 5000, False), (10.0, 5000, True)])
def test_a_version_jump_is_plausible_as_far_as_the_time_since_allows(gap_s, jump, taken, monkeypatch):
    """A server publishes at most MAX_VERSIONS_PER_S (its fusions are spaced): a jump of a few
    hundred is a subscriber that missed some; far more than the time since allows is forged."""
    now = [1000.0]
    monkeypatch.setattr(watch.time, "monotonic", lambda: now[0])
    w = watch.FusedWatcher(bus=None, keys=None)
    real = _maps(1)[0]
    w._on_payload(real, "put")
    now[0] += gap_s
    rng = np.random.default_rng(0)
    nxt = dataclasses.replace(fused_map(rng, m=3), session="srv1", version=1 + jump)
    w._on_payload(codec.encode(nxt), "put")
    assert (w.latest.version == 1 + jump) is taken and w.implausible == (0 if taken else 1)
