"""Crashes of every process of the fleet, as real processes on loopback (issue 5, item 2).

One fleet (router, map server on a state directory, two simulated agents with priors) takes, in
order: an agent killed with SIGKILL and restarted (a new session of the same robot), the router
killed and restarted, the map server killed at random moments four times in a row and restarted
on its state. After each the fused map still covers what it held before (nothing acknowledged is
lost), versions only increase, and the fleet goes on fusing. A damaged state directory makes
``fleet-slam server`` exit at once with an error naming the file, and leaves the state as it was.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
import time

import numpy as np
import pytest

from fleet_slam.procs import ProcGroup, python_module
from fleet_slam.watch import FusedWatcher
from map_server.server import MapServer
from map_server.store import Store
from shared import codec
from shared.bus import Bus, BusConfig
from shared.keys import Keys
from shared.messages import FusedMap, RobotMap
from shared.metrics import map_quality
from tests.netutil import loopback_endpoint, wait_for

pytestmark = pytest.mark.integration

STARTUP_S = 30.0
SETTLE_S = 30.0  # the fleet catching up after a fault
SIM_S = 600.0  # agents outlive the test; they are stopped by their handles
MIN_COVERAGE = 0.95  # share of the fused map's length before a fault still covered after it
PRIORS = ("9.0,4.5,0.0", "15.0,5.5,-1.5707963267948966")  # the office routes' true starts


def agent_argv(i: int, endpoint: str) -> list[str]:
    args = ["--robot", f"robot{i + 1}", "--world", "office", "--route", i, "--prior", PRIORS[i]]
    args += ["--duration", SIM_S, "--particles", 10, "--connect", endpoint]
    return python_module("robot_agent", *args)


def coverage(before: FusedMap, after: FusedMap) -> float:
    """Share of ``before``'s segment length that ``after`` covers (within 0.10 m and 5°)."""
    return map_quality(after.seg, before.seg).completeness if len(before.seg) else 1.0


def restored_from(state) -> FusedMap | None:
    """The fused map a server restarted on ``state`` begins with; raises if the state is damaged."""

    class NoBus:  # MapServer only touches the bus in start() and tick()
        pass

    return MapServer(NoBus(), Keys(), store=Store(state)).fleet.latest()


def both_merged(f: FusedMap | None, min_segments: int = 10) -> bool:
    return f is not None and len(f.seg) >= min_segments and sum(r.merged and r.online for r in f.robots) == 2


@pytest.fixture(scope="module")
def fleet(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("crash")
    endpoint = loopback_endpoint()
    procs = {}
    with ProcGroup(tmp / "logs") as group:

        def start(name: str, argv: list[str], ready: str):
            p = procs[name] = group.start(name, argv)
            assert p.wait_for(ready, STARTUP_S), p.output()[-3000:]
            return p

        start("router", python_module("shared.bus", "router", "--listen", endpoint), "listening")
        server_argv = python_module("map_server", "--connect", endpoint, "--state", tmp / "state")
        start("server", server_argv, "running")
        for i in range(2):
            start(f"robot{i + 1}", agent_argv(i, endpoint), "connected")
        with Bus(BusConfig(connect=(endpoint,))) as bus:
            watcher = FusedWatcher(bus, Keys())
            watcher.start(query_timeout_s=2.0)
            assert wait_for(lambda: both_merged(watcher.fetch(0.5), 40), STARTUP_S + 30.0)
            yield {
                "group": group, "procs": procs, "start": start, "endpoint": endpoint, "tmp": tmp,
                "state": tmp / "state", "server_argv": server_argv, "watcher": watcher, "bus": bus,
            }  # fmt: skip
    assert all(not p.running for p in group.procs)  # every process stopped by its handle
    for p in procs.values():  # one log per name: restarts append to it
        assert "Traceback" not in p.output(), p.output()[-3000:]


def updates_since(watcher: FusedWatcher, n: int) -> list[FusedMap]:
    return [u.fused for u in list(watcher.updates)[n:]]


def has_every_latest_map(fleet) -> bool:
    """Whether the fused map holds, for every robot, the map its agent publishes now (or newer)."""
    w = fleet["watcher"]
    for robot in ("robot1", "robot2"):
        replies = fleet["bus"].get(Keys().robot_map(robot), timeout_s=2.0)  # the agent's queryable
        seqs = [codec.decode(p, expect=RobotMap).seq for _, p in replies]
        if not seqs:
            return False
        seq = max(seqs)
        if not wait_for(lambda r=robot, q=seq: w.latest.robot(r).map_seq >= q, SETTLE_S):
            return False
    return True


def versions_increase(watcher: FusedWatcher) -> bool:
    v = [u.fused.version for u in list(watcher.updates)]
    return v == sorted(set(v))


def test_an_agent_killed_and_restarted_loses_nothing(fleet):
    w = fleet["watcher"]
    before = w.latest
    old = before.robot("robot2").session
    n = len(w.updates)
    fleet["procs"]["robot2"].kill()
    assert wait_for(lambda: not w.latest.robot("robot2").online, SETTLE_S)
    fleet["start"]("robot2", agent_argv(1, fleet["endpoint"]), "connected")  # same log, new session

    def back() -> bool:
        s = w.latest.robot("robot2")
        return s.session != old and s.status == "prior" and s.online and s.n_elements > 0

    assert wait_for(back, SETTLE_S)
    after = w.latest
    assert after.extra["retired_pieces"] >= 1.0  # the old session's map, kept where it was
    seen = updates_since(w, n)
    worst = min(coverage(before, f) for f in seen)
    assert worst >= MIN_COVERAGE, f"at some update only {worst:.3f} of the map before the kill was left"
    assert versions_increase(w)
    # the new session re-maps the same route: it merges into its old piece rather than doubling it
    assert wait_for(lambda: w.latest.robot("robot2").n_elements >= 20, SETTLE_S)
    assert credited(w.latest, "robot2") <= 1.5 * credited(before, "robot2")  # measured 29 -> 29


def credited(f: FusedMap, robot: str) -> int:
    """How many fused segments name ``robot`` in their provenance."""
    return sum(robot in f.provenance(i) for i in range(len(f.seg)))


def test_the_router_killed_and_restarted_the_fleet_goes_on(fleet):
    w = fleet["watcher"]
    assert wait_for(lambda: both_merged(w.latest), SETTLE_S)
    before = w.latest
    fleet["procs"]["router"].kill()
    time.sleep(1.0)  # an outage: puts are dropped, every token looks gone
    router = python_module("shared.bus", "router", "--listen", fleet["endpoint"])
    fleet["start"]("router", router, "listening")  # the same endpoint

    def caught_up() -> bool:
        f = w.latest
        return f.version > before.version and both_merged(f)

    assert wait_for(caught_up, SETTLE_S)  # every client reconnected by itself
    assert has_every_latest_map(fleet)  # what was put during the outage is caught up on
    assert coverage(before, w.latest) >= MIN_COVERAGE
    assert versions_increase(w)
    assert all(p.running for name, p in fleet["procs"].items() if name != "router")


def test_the_server_killed_at_random_moments_keeps_everything_it_published(fleet):
    """Kill -9 four times, 0.2-2.5 s after it is up (it persists before every publication, so
    kills land during writes too): each time the state loads and holds at least what was seen."""
    w = fleet["watcher"]
    assert wait_for(lambda: both_merged(w.latest), SETTLE_S)
    first = w.latest
    rng = np.random.default_rng(5)
    for _ in range(4):
        time.sleep(float(rng.uniform(0.2, 2.5)))
        seen = w.latest
        fleet["procs"]["server"].kill()
        restored = restored_from(fleet["state"])  # a half-written state would raise here
        assert restored is not None and restored.version >= seen.version  # persisted before published
        if restored.version == seen.version:
            assert np.allclose(restored.seg, seen.seg, atol=1e-4)  # the wire carries float32
        assert coverage(seen, restored) >= MIN_COVERAGE
        fleet["start"]("server", fleet["server_argv"], "running")
    v = w.latest.version
    assert wait_for(lambda: w.latest.version > v and both_merged(w.latest), SETTLE_S)
    assert has_every_latest_map(fleet)
    assert coverage(first, w.latest) >= MIN_COVERAGE
    assert versions_increase(w)


@pytest.mark.parametrize("damage", ["flip a byte of the index", "truncate the index", "flip a byte of a blob",
                                    "delete a blob"])  # fmt: skip
def test_a_damaged_state_is_reported_and_not_loaded(damage, tmp_path):
    """At once, before connecting: no router listens on the endpoint it is given."""
    state = tmp_path / "state"
    server = MapServer(_Sink(), Keys(), store=Store(state))
    seg = np.array([[[0, 0], [8, 0]], [[8, 0], [8, 6]], [[8, 6], [0, 6]]], float)
    for c in codec.robot_map_chunks(
        "robot1", "s1", 1, 1.0, np.ones(1), np.zeros((1, 3)), seg, np.arange(3), np.ones(3, np.int64),
        np.full(3, 0.8), np.full(3, 10), np.full(3, 50), prior=np.zeros(3), prior_sigma=np.full(3, 0.05),
    ):  # fmt: skip
        server.on_map(Keys().robot_map("robot1"), codec.encode(c))
    assert server.tick() is not None
    index = state / "state.json"
    (blob,) = (state / "blobs").glob("*.bin")
    if damage == "flip a byte of the index":
        data = bytearray(index.read_bytes())
        i = data.index(b'"version":') + len(b'"version":')
        data[i] = ord("7") if data[i] != ord("7") else ord("8")
        index.write_bytes(bytes(data))
        bad, why = index, "checksum mismatch"
    elif damage == "truncate the index":
        index.write_bytes(index.read_bytes()[:100])
        bad, why = index, "not valid JSON"
    elif damage == "flip a byte of a blob":
        data = bytearray(blob.read_bytes())
        data[len(data) // 2] ^= 0xFF
        blob.write_bytes(bytes(data))
        bad, why = blob, "checksum mismatch"
    else:
        blob.unlink()
        bad, why = blob, "missing"
    copy = tmp_path / "copy"
    shutil.copytree(state, copy)
    argv = [sys.executable, "-m", "fleet_slam.cli", "server", "--connect", loopback_endpoint()]
    argv += ["--state", state]
    done = subprocess.run(list(map(str, argv)), capture_output=True, text=True, timeout=STARTUP_S / 2)
    assert done.returncode == 2, done.stdout + done.stderr
    assert "fleet-slam server: error:" in done.stderr and str(bad) in done.stderr and why in done.stderr
    assert "running" not in done.stdout  # it never started, on an empty state or otherwise
    for path in copy.rglob("*"):  # and the damaged state is left as it was, for a human to look at
        assert path.is_dir() or path.read_bytes() == (state / path.relative_to(copy)).read_bytes()


class _Sink:
    def put(self, key, payload, reliable=True):
        pass
