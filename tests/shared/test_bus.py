"""shared/bus.py in one process: a router Bus on a free loopback port and client Buses around it."""

from __future__ import annotations

import json
import logging
import threading
import time

import pytest

from shared.bus import Bus, BusConfig, BusError, run_router, zenoh_config
from tests.netutil import Inbox, free_port, loopback_endpoint, wait_for


@pytest.fixture
def endpoint():
    return loopback_endpoint()


@pytest.fixture
def router(endpoint):
    with Bus(BusConfig(mode="router", connect=(), listen=(endpoint,))) as bus:
        yield bus


@pytest.fixture
def clients(router, endpoint):
    """Two clients of ``router``: (publisher, subscriber)."""
    with Bus(BusConfig(connect=(endpoint,))) as a, Bus(BusConfig(connect=(endpoint,))) as b:
        yield a, b


def wait_routed(pub: Bus, inbox: Inbox, key: str) -> None:
    """Put probes on ``key`` until one arrives: the subscription has reached the router."""

    def probe() -> bool:
        pub.put(key, b"probe")
        return len(inbox) > 0

    assert wait_for(probe), f"no subscription for {key} reached the router"


def config_json(cfg: BusConfig, path: str):
    return json.loads(zenoh_config(cfg).get_json(path))


# -- configuration ---------------------------------------------------------------------------------


def test_client_config_is_loopback_only_without_multicast():
    cfg = BusConfig(connect=("tcp/127.0.0.1:7999",), lease_s=2.5, retry_ms=150)
    assert config_json(cfg, "mode") == "client"
    assert config_json(cfg, "scouting/multicast/enabled") is False
    assert config_json(cfg, "connect/endpoints") == ["tcp/127.0.0.1:7999"]
    assert config_json(cfg, "listen/endpoints") == []  # not zenoh's tcp/[::]:0
    assert config_json(cfg, "connect/timeout_ms") == -1  # wait for the router
    assert config_json(cfg, "connect/retry")["period_max_ms"] == 150
    assert config_json(cfg, "transport/link/tx/lease") == 2500
    assert config_json(cfg, "transport/shared_memory/enabled") is False
    text = str(zenoh_config(cfg))
    assert "[::]" not in text and "0.0.0.0" not in text


def test_router_config_listens_only_where_asked():
    cfg = BusConfig(mode="router", connect=(), listen=("tcp/127.0.0.1:7998",), connect_timeout_s=1.5)
    assert config_json(cfg, "listen/endpoints") == ["tcp/127.0.0.1:7998"]  # not zenoh's tcp/[::]:7447
    assert config_json(cfg, "connect/endpoints") == []
    assert config_json(cfg, "connect/timeout_ms") == 1500
    assert config_json(cfg, "scouting/multicast/enabled") is False
    assert "[::]" not in str(zenoh_config(cfg))


def test_endpoint_lists_become_tuples():
    cfg = BusConfig(connect=["tcp/127.0.0.1:7999"])
    assert cfg.connect == ("tcp/127.0.0.1:7999",)
    assert hash(cfg) == hash(BusConfig(connect=("tcp/127.0.0.1:7999",)))


def test_overrides_are_applied_last():
    cfg = BusConfig(overrides=(("transport/auth/usrpwd/user", '"robot1"'),))
    assert config_json(cfg, "transport/auth/usrpwd/user") == "robot1"
    with pytest.raises(BusError, match="no/such/key"):
        zenoh_config(BusConfig(overrides=(("no/such/key", "1"),)))


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"mode": "server"}, "mode"),
        ({"connect": ()}, "connect"),
        ({"connect": "tcp/127.0.0.1:7447"}, "connect"),
        ({"mode": "router", "listen": ()}, "listen"),
        ({"connect_timeout_s": 0}, "connect_timeout_s"),
        ({"retry_ms": 0}, "retry_ms"),
        ({"lease_s": -1.0}, "lease_s"),
    ],
)
def test_bad_config_names_the_field(kwargs, field):
    with pytest.raises(BusError, match=field):
        BusConfig(**kwargs)


def test_client_without_router_raises_after_timeout():
    with pytest.raises(BusError, match="cannot open"):
        Bus(BusConfig(connect=(loopback_endpoint(),), connect_timeout_s=0.3))


def test_malformed_endpoint_is_refused_by_name():
    with pytest.raises(BusError, match="connect/endpoints"):
        Bus(BusConfig(connect=("127.0.0.1:7447",)))  # no protocol


def test_waiting_for_a_router_can_be_cancelled():
    cancel = threading.Event()
    timer = threading.Timer(0.2, cancel.set)
    timer.start()
    try:
        with pytest.raises(BusError, match="cancelled"):
            Bus(BusConfig(connect=(loopback_endpoint(),)), cancel=cancel)  # would wait forever
    finally:
        timer.cancel()


def test_router_on_a_taken_port_raises(router, endpoint):
    with pytest.raises(BusError, match="Address already in use"):
        Bus(BusConfig(mode="router", connect=(), listen=(endpoint,)))


# -- publish / subscribe ---------------------------------------------------------------------------


def test_put_subscribe_round_trip(clients):
    pub, sub = clients
    inbox, deleted = Inbox(), Inbox()
    sub.subscribe("rt/*", inbox, deleted)
    wait_routed(pub, inbox, "rt/probe")
    payload = bytes(range(256)) * 4
    pub.put("rt/data", payload)
    pub.delete("rt/data")
    assert wait_for(lambda: len(deleted) == 1)
    assert ("rt/data", payload) in inbox.snapshot()
    assert deleted.snapshot() == [("rt/data",)]


def test_subscription_only_sees_matching_keys(clients):
    pub, sub = clients
    inbox = Inbox()
    sub.subscribe("only/a/*", inbox)
    wait_routed(pub, inbox, "only/a/probe")
    pub.put("only/b/x", b"no")
    pub.put("only/a/x", b"yes")
    assert wait_for(lambda: ("only/a/x", b"yes") in inbox.snapshot())
    assert all(key.startswith("only/a/") for key, _ in inbox.snapshot())


def test_reliable_put_delivers_every_message_in_order(clients):
    pub, sub = clients
    n_messages, size = 200, 50_000
    inbox = Inbox()
    sub.subscribe("bulk/*", inbox)
    wait_routed(pub, inbox, "bulk/probe")
    for i in range(n_messages):
        pub.put("bulk/data", i.to_bytes(4, "big") + bytes(size - 4), reliable=True)
    assert wait_for(lambda: sum(k == "bulk/data" for k, _ in inbox.snapshot()) == n_messages, 20.0)
    data = [p for k, p in inbox.snapshot() if k == "bulk/data"]
    assert [int.from_bytes(p[:4], "big") for p in data] == list(range(n_messages))
    assert {len(p) for p in data} == {size}


def test_unsubscribed_handle_gets_nothing_more(clients):
    pub, sub = clients
    inbox = Inbox()
    handle = sub.subscribe("unsub/*", inbox)
    wait_routed(pub, inbox, "unsub/probe")
    handle.close()
    handle.close()  # idempotent
    seen = len(inbox)
    later = Inbox()  # a second subscriber proves that puts still flow
    sub.subscribe("unsub/*", later)
    wait_routed(pub, later, "unsub/probe")
    assert len(inbox) == seen


def test_close_waits_for_a_callback_being_delivered_and_none_comes_after(clients):
    """zenoh may still run a callback after ``undeclare`` returns (a CI run saw a closed
    subscription's inbox grow by one): closing waits for the callback under way, and samples
    that arrive later are not delivered."""
    pub, sub = clients
    started, got = threading.Event(), []

    def slow(key, payload):
        started.set()
        time.sleep(0.3)
        got.append(payload)

    handle = sub.subscribe("slow/*", slow)
    assert wait_for(lambda: pub.put("slow/probe", b"p") or started.is_set())
    handle.close()  # the first callback is asleep: the close waits for it
    n = len(got)
    pub.put("slow/probe", b"after")
    time.sleep(0.8)
    assert n >= 1 and len(got) == n and b"after" not in got


def test_callback_exception_does_not_kill_the_subscription(clients, caplog):
    pub, sub = clients
    inbox = Inbox()

    def fragile(key, payload):
        inbox(key, payload)
        if payload == b"boom":
            raise RuntimeError("callback bug")

    sub.subscribe("fragile/*", fragile)
    wait_routed(pub, inbox, "fragile/probe")
    with caplog.at_level(logging.ERROR, logger="fleet_slam.bus"):
        pub.put("fragile/x", b"boom")
        pub.put("fragile/x", b"after")
        assert wait_for(lambda: ("fragile/x", b"after") in inbox.snapshot())
    assert any("callback bug" in (r.exc_text or "") or r.exc_info for r in caplog.records)
    assert any(r.name == "fleet_slam.bus" and r.levelno == logging.ERROR for r in caplog.records)


# -- query / reply ---------------------------------------------------------------------------------


def test_get_returns_the_queryable_answer(clients):
    client, server = clients
    asked = Inbox()

    def answer(key_expr):
        asked(key_expr)
        return [("maps/r1", b"map of r1"), ("maps/r2", b"map of r2"), ("elsewhere/x", b"disjoint")]

    server.serve("maps/*", answer)
    assert wait_for(lambda: len(client.get("maps/*", timeout_s=1.0)) > 0)
    replies = client.get("maps/*", timeout_s=1.0)
    # the disjoint key does not intersect the query: skipped (and logged), the others arrive
    assert sorted(replies) == [("maps/r1", b"map of r1"), ("maps/r2", b"map of r2")]
    assert asked.snapshot()[-1] == ("maps/*",)


def test_get_without_queryable_returns_nothing(clients):
    client, _ = clients
    assert client.get("nobody/home/*", timeout_s=0.3) == []


def test_get_with_a_silent_queryable_times_out_empty(clients):
    client, server = clients
    release = threading.Event()

    def answer_late(key_expr):
        release.wait(5.0)
        return [("slow/x", b"too late")]

    server.serve("slow/*", answer_late)
    try:
        assert client.get("slow/*", timeout_s=0.3) == []  # a timeout is not a reply
    finally:
        release.set()


# -- liveliness ------------------------------------------------------------------------------------


def test_liveliness_token_appears_and_disappears_on_close(router, endpoint):
    with Bus(BusConfig(connect=(endpoint,))) as watcher:
        early = Bus(BusConfig(connect=(endpoint,)))
        early.declare_alive("fleet/t/robots/r1/alive")
        changes = Inbox()
        watcher.watch_alive("fleet/t/robots/*/alive", changes)
        # history: the token declared before the watch is reported first
        assert wait_for(lambda: ("fleet/t/robots/r1/alive", True) in changes.snapshot())
        with Bus(BusConfig(connect=(endpoint,))) as late:
            token = late.declare_alive("fleet/t/robots/r2/alive")
            assert wait_for(lambda: ("fleet/t/robots/r2/alive", True) in changes.snapshot())
            token.close()
            assert wait_for(lambda: ("fleet/t/robots/r2/alive", False) in changes.snapshot())
        early.close()
        assert wait_for(lambda: ("fleet/t/robots/r1/alive", False) in changes.snapshot())
        assert changes.snapshot() == [
            ("fleet/t/robots/r1/alive", True),
            ("fleet/t/robots/r2/alive", True),
            ("fleet/t/robots/r2/alive", False),
            ("fleet/t/robots/r1/alive", False),
        ]


# -- lifecycle -------------------------------------------------------------------------------------


def test_close_is_idempotent_and_a_closed_bus_refuses_work(router, endpoint):
    bus = Bus(BusConfig(connect=(endpoint,)))
    handle = bus.subscribe("closed/*", Inbox())
    bus.close()
    bus.close()
    assert bus.closed and handle.closed
    for call in (
        lambda: bus.put("closed/x", b""),
        lambda: bus.get("closed/*"),
        lambda: bus.subscribe("closed/*", Inbox()),
        lambda: bus.declare_alive("closed/x"),
    ):
        with pytest.raises(BusError, match="closed"):
            call()


def test_run_router_serves_until_stopped():
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    stop, ready = threading.Event(), threading.Event()
    on_ready = {"on_ready": lambda _bus: ready.set()}
    thread = threading.Thread(target=run_router, args=((endpoint,), stop), kwargs=on_ready)
    thread.start()
    try:
        assert ready.wait(5.0)
        with Bus(BusConfig(connect=(endpoint,), connect_timeout_s=2.0)) as a:
            inbox = Inbox()
            a.subscribe("embedded/*", inbox)
            wait_routed(a, inbox, "embedded/probe")
    finally:
        stop.set()
        thread.join(5.0)
    assert not thread.is_alive()
