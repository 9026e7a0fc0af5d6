"""A fused-map subscriber: the latest fused map (query at start, then every update) and a history
of updates (what `fleet-slam subscribe` prints and what the demo measures) — the newest
``history`` of them, for a subscriber that lives for days."""

from __future__ import annotations

import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

from shared import codec
from shared.keys import Keys
from shared.messages import FusedMap, RobotPath, WireFormatError

# a server publishes a new version per fusion, its fusions spaced (--min-gap, 0.05 s by default):
# a version further ahead of the last one taken than this allows for the time since is not its
MAX_VERSIONS_PER_S = 1000.0
VERSION_SLACK = 64


@dataclass(frozen=True)
class Update:
    wall_s: float  # time.monotonic() at arrival
    fused: FusedMap
    via: str  # "query" or "put"


class FusedWatcher:
    def __init__(
        self,
        bus,
        keys: Keys,
        on_update: Callable[[Update], None] | None = None,
        history: int | None = None,
        on_refused: Callable[[str], None] | None = None,
    ):
        """``history``: the updates kept (the newest; ``None``: all — a run with an end);
        ``on_refused(text)``: a fused map refused as implausible, said why."""
        self.bus, self.keys, self.on_update, self.on_refused = bus, keys, on_update, on_refused
        self._lock = threading.Lock()
        self._assembler = codec.Assembler()
        self.latest: FusedMap | None = None
        self.updates: deque[Update] = deque(maxlen=history)
        self.received = 0  # updates taken in, all of them
        self.implausible = 0  # fused maps refused: a version jump no server could have made
        self._last: tuple[str, str, int, float] | None = None  # server, session, version, when
        self.rejected = 0
        self.changed = threading.Condition(self._lock)

    def start(self, query_timeout_s: float = 2.0) -> FusedMap | None:
        """Subscribe, then take the current fused map by query (so a late subscriber starts with
        the map at once); returns it (``None`` when the server has none yet)."""
        self.bus.subscribe(self.keys.fused, lambda k, p: self._on_payload(p, "put"))
        return self.fetch(query_timeout_s)

    def fetch(self, timeout_s: float = 2.0) -> FusedMap | None:
        for _key, payload in self.bus.get(self.keys.fused, timeout_s=timeout_s):
            self._on_payload(payload, "query")
        return self.latest

    def _on_payload(self, payload: bytes, via: str) -> None:
        try:
            msg = codec.decode(payload, expect=FusedMap)
        except WireFormatError:
            with self._lock:
                self.rejected += 1
            return
        with self._lock:
            now = time.monotonic()
            last = self._last
            if last is not None and (msg.server, msg.session) == last[:2]:
                allowed = last[2] + VERSION_SLACK + MAX_VERSIONS_PER_S * (now - last[3])
                if msg.version > allowed:  # forged (the plain profile lets anyone put it)
                    self.implausible += 1
                    said = (
                        f"refused a fused map of {msg.server} with version {msg.version}: at most "
                        f"{int(allowed)} could follow version {last[2]} by now (forged?); "
                        f"{self.implausible} refused so far"
                    )
                    n = self.implausible
                    if self.on_refused is not None and (n in (1, 10, 100, 1000) or n % 10000 == 0):
                        self.on_refused(said)  # the first, then ever more rarely
                    return
            try:  # refuses stale versions too: e.g. the query answer after a newer put
                done = self._assembler.add(msg)
            except WireFormatError:
                return
            if done is None:
                return
            self._last = (done.server, done.session, done.version, now)
            self.latest = done
            upd = Update(time.monotonic(), done, via)
            self.updates.append(upd)
            self.received += 1
            self.changed.notify_all()
        if self.on_update is not None:
            self.on_update(upd)

    def wait_for(self, done: Callable[[FusedMap], bool], timeout_s: float) -> FusedMap | None:
        """Wait until the latest map satisfies ``done`` (or ``timeout_s`` passed); the latest map."""
        end = time.monotonic() + timeout_s
        with self._lock:
            while not (self.latest is not None and done(self.latest)):
                left = end - time.monotonic()
                if left <= 0:
                    break
                self.changed.wait(min(1.0, left))
            return self.latest

    def wait_quiet(self, quiet_s: float, timeout_s: float) -> FusedMap | None:
        """Wait until no update arrived for ``quiet_s`` and the latest map does not say the
        server's fleet graph is being matched anew (``extra["graph_rebuilding"]``: the maps keep
        the last whole bend meanwhile, and nothing new is published until it is whole), or until
        ``timeout_s`` passed; the latest map."""
        end = time.monotonic() + timeout_s
        with self._lock:
            while time.monotonic() < end:
                last = self.updates[-1].wall_s if self.updates else 0.0
                rebuilding = self.latest is not None and self.latest.extra.get("graph_rebuilding", 0.0) > 0.0
                if time.monotonic() - last >= quiet_s and not rebuilding:
                    break
                self.changed.wait(min(quiet_s, max(0.0, end - time.monotonic())))
            return self.latest


def fetch_paths(bus, keys, timeout_s: float = 2.0) -> dict[str, RobotPath]:
    """Where the server's fleet graph puts each placed robot's keyframes (robot -> RobotPath);
    replies that do not decode are skipped."""
    out = {}
    for _key, payload in bus.get(keys.all_paths, timeout_s=timeout_s):
        try:
            p = codec.decode(payload, expect=RobotPath)
        except WireFormatError:
            continue
        out[p.robot] = p
    return out
