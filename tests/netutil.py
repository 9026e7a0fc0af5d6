"""Loopback networking helpers for tests: free ports, waiting for a condition."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

from fleet_slam.procs import free_port  # the one implementation (tests import it from here too)

POLL_S = 0.01


def loopback_endpoint(port: int | None = None) -> str:
    """A zenoh TCP endpoint on 127.0.0.1 (a free port unless one is given)."""
    return f"tcp/127.0.0.1:{free_port() if port is None else port}"


def start_router_and_server(group, endpoint: str, state, startup_s: float = 30.0) -> tuple:
    """A zenoh router on ``endpoint`` and a map server on ``state`` in ``group``, each waited for
    until it says it is up; ``(router, server)``."""
    from fleet_slam.procs import python_module

    router = group.start("router", python_module("shared.bus", "router", "--listen", endpoint))
    assert router.wait_for("listening", startup_s), router.output()
    server = group.start("server", python_module("map_server", "--connect", endpoint, "--state", state))
    assert server.wait_for("running", startup_s), server.output()
    return router, server


def wait_for(condition: Callable[[], bool], timeout_s: float = 5.0) -> bool:
    """Poll ``condition`` until it is true or ``timeout_s`` passed; its last value."""
    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > deadline:
            return condition()
        time.sleep(POLL_S)
    return True


def wait_while_progressing(
    progress: Callable[[], object], done: Callable[[], bool], stall_s: float, limit_s: float
) -> bool:
    """Poll until ``done()``; give up when ``progress()`` has not changed for ``stall_s`` or
    ``limit_s`` passed in all. For work whose pace depends on the machine's load (a server
    working through a backlog): a slow machine gets more time, a stuck one fails as soon."""
    start = last_change = time.monotonic()
    last = progress()
    while not done():
        now = time.monotonic()
        value = progress()
        if value != last:
            last, last_change = value, now
        if now - last_change > stall_s or now - start > limit_s:
            return done()
        time.sleep(POLL_S)
    return True


class Inbox:
    """Thread-safe record of callback calls (zenoh callbacks run on their own threads)."""

    def __init__(self):
        self.lock = threading.Lock()
        self.items: list = []

    def __call__(self, *args):
        with self.lock:
            self.items.append(args)

    def snapshot(self) -> list:
        with self.lock:
            return list(self.items)

    def __len__(self) -> int:
        with self.lock:
            return len(self.items)

    def has(self, item) -> bool:
        with self.lock:
            return item in self.items

    def states(self, key: str) -> list[bool]:
        """The liveliness states reported for ``key``, in order."""
        with self.lock:
            return [alive for k, alive in self.items if k == key]
