"""Maps as bounded chunks and back: split a snapshot, assemble it on the receiving side.

A map travels as chunks of at most ``MAX_CHUNK_ELEMENTS`` elements, each a valid message carrying
the snapshot's small header (``shared/messages.py``). :class:`Assembler` puts a snapshot back
together and refuses stale, duplicated or inconsistent chunks; :class:`SeqFilter` refuses stale
pose updates. Pure: no I/O, no msgpack (that is ``shared/codec.py``, which re-exports this API).
"""

from __future__ import annotations

import dataclasses
import itertools
import threading
from collections import Counter, OrderedDict, deque

import numpy as np

from shared.messages import (
    GRAPH_FIELDS,
    MAX_CHUNK_ELEMENTS,
    MAX_CHUNKS,
    MAX_ROBOTS,
    SCAN_FIELDS,
    FusedMap,
    Message,
    RobotMap,
    RobotStatus,
    WireFormatError,
    check_int,
)

MAX_SENDERS = MAX_ROBOTS * 4  # senders an Assembler / SeqFilter remembers (least recently heard go first)
MAX_RETIRED_SESSIONS = 8  # replaced sessions remembered per sender, so their late messages are refused
# RobotMap arrays with one row per element (sliced by split, concatenated by join)
PER_ELEMENT = ("seg", "element", "members", "trust", "hits", "age", "anchor")


def _rows(value: np.ndarray | None, a: int, b: int) -> np.ndarray | None:
    return None if value is None else value[a:b]


def split(msg: RobotMap | FusedMap, max_elements: int = MAX_CHUNK_ELEMENTS) -> list[RobotMap | FusedMap]:
    """A whole map (``n_chunks=1``) as chunks of at most ``max_elements``, sizes within one of
    each other, provenance offsets rebased to 0 in each chunk. An empty map is one empty chunk."""
    check_int("max_elements", max_elements, 1, MAX_CHUNK_ELEMENTS)
    if msg.n_chunks != 1:
        raise WireFormatError(f"n_chunks: split takes a whole map (n_chunks=1), got {msg.n_chunks}")
    n = len(msg.seg)
    n_chunks = max(1, -(-n // max_elements))
    if n_chunks > MAX_CHUNKS:
        raise WireFormatError(
            f"seg: {n} elements need {n_chunks} chunks of {max_elements}, at most {MAX_CHUNKS}"
        )
    bounds = [i * n // n_chunks for i in range(n_chunks + 1)]
    return [_slice(msg, i, n_chunks, a, b) for i, (a, b) in enumerate(itertools.pairwise(bounds))]


def split_fused_map(msg: FusedMap, max_elements: int = MAX_CHUNK_ELEMENTS) -> list[FusedMap]:
    """:func:`split` for a fused map (the server's side)."""
    if not isinstance(msg, FusedMap):
        raise TypeError(f"split_fused_map: expected a FusedMap, got {type(msg).__name__}")
    return split(msg, max_elements)


def _slice(msg: RobotMap | FusedMap, i: int, n_chunks: int, a: int, b: int) -> RobotMap | FusedMap:
    if isinstance(msg, RobotMap):
        per_element = {f: _rows(getattr(msg, f), a, b) for f in PER_ELEMENT}
        if i > 0:  # the graph travels in chunk 0 only
            per_element.update(dict.fromkeys(GRAPH_FIELDS + SCAN_FIELDS))
        return dataclasses.replace(msg, chunk=i, n_chunks=n_chunks, **per_element)
    pa, pb = msg.prov_offsets[a], msg.prov_offsets[b]
    return dataclasses.replace(
        msg, chunk=i, n_chunks=n_chunks, seg=msg.seg[a:b], support=msg.support[a:b],
        prov_offsets=msg.prov_offsets[a : b + 1] - pa, prov_robot=msg.prov_robot[pa:pb],
    )  # fmt: skip


def robot_map_chunks(
    robot: str, session: str, seq: int, stamp_s: float,
    particle_weights: np.ndarray, particle_poses: np.ndarray,
    seg: np.ndarray, element: np.ndarray, members: np.ndarray, trust: np.ndarray, hits: np.ndarray,
    age: np.ndarray, prior: np.ndarray | None = None, prior_sigma: np.ndarray | None = None,
    max_elements: int = MAX_CHUNK_ELEMENTS, **graph: np.ndarray | None,
) -> list[RobotMap]:  # fmt: skip
    """One robot map snapshot as validated chunks (fields as in :class:`RobotMap`; ``graph``:
    its graph fields and ``anchor``)."""
    whole = RobotMap(
        robot, session, seq, stamp_s, 0, 1, particle_weights, particle_poses, seg, element, members, trust,
        hits, age, prior, prior_sigma, **graph,
    )  # fmt: skip
    return split(whole, max_elements)


def fused_map_chunks(
    server: str, version: int, stamp_s: float, robots: tuple[RobotStatus, ...] | list[RobotStatus],
    seg: np.ndarray, support: np.ndarray, prov_offsets: np.ndarray, prov_robot: np.ndarray,
    extra: dict | None = None, max_elements: int = MAX_CHUNK_ELEMENTS, session: str = "",
) -> list[FusedMap]:  # fmt: skip
    """One fused map snapshot as validated chunks (fields as in :class:`FusedMap`)."""
    robots, extra = tuple(robots), dict(extra or {})
    whole = FusedMap(
        server, version, stamp_s, 0, 1, robots, seg, support, prov_offsets, prov_robot, extra, session
    )
    return split(whole, max_elements)


def join(parts: list[RobotMap | FusedMap]) -> RobotMap | FusedMap:
    """The whole map (``chunk=0, n_chunks=1``) from all chunks of one snapshot, in chunk order."""
    first = parts[0]
    if len(parts) == 1 and first.n_chunks == 1:
        return first

    def cat(name: str) -> np.ndarray | None:
        arrays = [getattr(p, name) for p in parts]
        if any(v is None for v in arrays):
            if not all(v is None for v in arrays):
                raise WireFormatError(f"{name}: some chunks carry it, some do not")
            return None
        return np.concatenate(arrays)

    if isinstance(first, RobotMap):
        per_element = {f: cat(f) for f in PER_ELEMENT}
        return dataclasses.replace(first, chunk=0, n_chunks=1, **per_element)
    base = np.cumsum([0] + [p.prov_offsets[-1] for p in parts[:-1]])
    offsets = np.concatenate([[0]] + [p.prov_offsets[1:] + b for p, b in zip(parts, base, strict=True)])
    return dataclasses.replace(
        first, chunk=0, n_chunks=1, seg=cat("seg"), support=cat("support"), prov_offsets=offsets,
        prov_robot=cat("prov_robot"),
    )  # fmt: skip


# -- receiving: stale, duplicate and inconsistent messages ------------------------------------


class ChunkRejected(WireFormatError):
    """A well-formed message refused by an :class:`Assembler` or :class:`SeqFilter`; ``reason`` is
    the key it is counted under in their ``rejected`` counter."""

    def __init__(self, reason: str, text: str):
        super().__init__(text)
        self.reason = reason


@dataclasses.dataclass
class _Sender:
    session: str
    retired: deque = dataclasses.field(default_factory=lambda: deque(maxlen=MAX_RETIRED_SESSIONS))
    last: int = -1  # newest seq assembled (Assembler) or accepted (SeqFilter) in this session
    pending: _Pending | None = None


@dataclasses.dataclass
class _Pending:
    seq: int
    header: dict
    parts: dict  # chunk index -> message


class _Senders:
    """Per-sender state that follows sessions (a new session = the sender restarted, its seq restarts);
    at most ``max_senders``, the least recently heard forgotten first."""

    def __init__(self, max_senders: int, dropped: Counter):
        self.max_senders, self.dropped = max_senders, dropped
        self._by_key: OrderedDict[tuple, _Sender] = OrderedDict()

    def get(self, key: tuple, session: str) -> _Sender:
        s = self._by_key.get(key)
        if s is None:
            if len(self._by_key) >= self.max_senders:
                self._by_key.popitem(last=False)
                self.dropped["evicted"] += 1
            s = self._by_key[key] = _Sender(session)
        elif session != s.session:
            if session in s.retired:
                raise ChunkRejected(
                    "stale_session", f"session: stale session {session!r} of {key[1]}, now {s.session!r}"
                )
            if s.pending is not None:
                self.dropped["incomplete"] += 1
            s.retired.append(s.session)
            s.session, s.last, s.pending = session, -1, None
        self._by_key.move_to_end(key)
        return s


def _identity(msg: Message) -> tuple[tuple, str, int, str]:
    """(sender key, session, snapshot number, the snapshot number's field name)."""
    if isinstance(msg, FusedMap):
        return ("FusedMap", msg.server), msg.session, msg.version, "version"
    return (type(msg).__name__, msg.robot), msg.session, msg.seq, "seq"


def _header(msg: RobotMap | FusedMap) -> dict:
    """What every chunk of one snapshot must repeat identically (arrays compared as bytes)."""
    header = {"stamp_s": msg.stamp_s, "n_chunks": msg.n_chunks}
    if isinstance(msg, RobotMap):
        for name in ("particle_weights", "particle_poses", "prior", "prior_sigma"):
            header[name] = _comparable(getattr(msg, name))
        header["graph_seq"] = msg.graph_seq
        header["joined"] = msg.joined
    else:
        header["robots"] = [
            tuple(_comparable(getattr(r, f.name)) for f in dataclasses.fields(r)) for r in msg.robots
        ]
        header["extra"] = msg.extra
    return header


def _comparable(value: object) -> object:
    return value.tobytes() if isinstance(value, np.ndarray) else value


class Assembler:
    """Collects map chunks (RobotMap and FusedMap) per sender and returns each snapshot when whole.

    Per sender (robot id, or server id) only the newest snapshot is pending: an older chunk is
    refused, a newer one abandons the pending snapshot. Thread-safe (zenoh callbacks run concurrently).
    """

    def __init__(self, max_senders: int = MAX_SENDERS):
        self.rejected: Counter = Counter()  # refused chunks by reason
        self.dropped: Counter = Counter()  # "incomplete" snapshots abandoned, "evicted" senders
        self._senders = _Senders(max_senders, self.dropped)
        self._lock = threading.Lock()

    def add(self, msg: RobotMap | FusedMap) -> RobotMap | FusedMap | None:
        """The whole map once ``msg`` completes its snapshot, else None; raises :class:`ChunkRejected`
        (a WireFormatError) for a stale, duplicated or inconsistent chunk."""
        if not isinstance(msg, RobotMap | FusedMap):
            raise TypeError(f"Assembler.add: expected RobotMap or FusedMap, got {type(msg).__name__}")
        with self._lock:
            try:
                return self._add(msg)
            except ChunkRejected as e:
                self.rejected[e.reason] += 1
                raise

    def _add(self, msg: RobotMap | FusedMap) -> RobotMap | FusedMap | None:
        key, session, seq, seq_name = _identity(msg)
        s = self._senders.get(key, session)
        what = f"chunk {msg.chunk} of {key[1]} {seq_name} {seq}"
        if seq <= s.last:
            raise ChunkRejected("stale", f"{seq_name}: stale {what}, {s.last} already assembled")
        p = s.pending
        if p is not None and seq < p.seq:
            raise ChunkRejected("stale", f"{seq_name}: stale {what}, {p.seq} is pending")
        header = _header(msg)
        if p is None or seq > p.seq:
            if p is not None:
                self.dropped["incomplete"] += 1
            p = s.pending = _Pending(seq, header, {})
        else:
            differs = [name for name, value in header.items() if value != p.header[name]]
            if differs:
                raise ChunkRejected("header", f"{differs[0]}: {what} disagrees with its earlier chunks")
            if msg.chunk in p.parts:
                raise ChunkRejected("duplicate", f"chunk: duplicate {what}")
        p.parts[msg.chunk] = msg
        if len(p.parts) < msg.n_chunks:
            return None
        s.pending, s.last = None, seq
        return join([p.parts[i] for i in range(msg.n_chunks)])


class SeqFilter:
    """Accepts a robot's messages (e.g. PoseUpdate) only with increasing ``seq`` within a session;
    a new session starts afresh, a late message of a replaced session is refused. Thread-safe."""

    def __init__(self, max_senders: int = MAX_SENDERS):
        self.rejected: Counter = Counter()
        self.dropped: Counter = Counter()
        self._senders = _Senders(max_senders, self.dropped)
        self._lock = threading.Lock()

    def check(self, msg: Message) -> None:
        """Raises :class:`ChunkRejected` unless ``msg`` is newer than every message passed before
        from its robot's session."""
        key, session, seq, seq_name = _identity(msg)
        with self._lock:
            try:
                s = self._senders.get(key, session)
                if seq <= s.last:
                    raise ChunkRejected(
                        "stale", f"{seq_name}: stale {seq} of {key[1]}, {s.last} already seen"
                    )
            except ChunkRejected as e:
                self.rejected[e.reason] += 1
                raise
            s.last = seq

    def accept(self, msg: Message) -> bool:
        """:meth:`check` as a boolean."""
        try:
            self.check(msg)
        except ChunkRejected:
            return False
        return True
