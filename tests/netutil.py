"""Loopback networking helpers for tests: free ports, waiting for a condition."""

from __future__ import annotations

import socket
import threading
import time
from collections.abc import Callable

POLL_S = 0.01


def free_port() -> int:
    """A TCP port on 127.0.0.1 that was free a moment ago (bound to port 0, then released)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def loopback_endpoint(port: int | None = None) -> str:
    """A zenoh TCP endpoint on 127.0.0.1 (a free port unless one is given)."""
    return f"tcp/127.0.0.1:{free_port() if port is None else port}"


def wait_for(condition: Callable[[], bool], timeout_s: float = 5.0) -> bool:
    """Poll ``condition`` until it is true or ``timeout_s`` passed; its last value."""
    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > deadline:
            return condition()
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
