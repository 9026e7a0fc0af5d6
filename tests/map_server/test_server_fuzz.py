"""The map server's door under hostile input, without zenoh: thousands of bad messages interleaved
with two legitimate robots' maps, poses and presence, fed to :class:`MapServer` callbacks.

Hostile here means malformed, invalid, stale, duplicated or mismatched — never a well-formed
impersonation (a new session of a legitimate robot is its restart; an unknown robot on its own key
is a new robot: both are the access-control item's business). Each example checks: every hostile
message is refused and counted (``rejected`` grows by exactly their number), each reason is logged
once as a warning with its text, and the server's state is as if they never came — the same fused
map after every tick (a deterministic clock), the same fleet snapshot, the same messages received.
Budget: ~6,000 hostile messages in 150 examples, ~10 s; derandomized.
"""

from __future__ import annotations

import dataclasses
import functools
import itertools
import logging
import math

import msgpack
import numpy as np
import pytest
from hypothesis import HealthCheck, Phase, event, given, settings
from hypothesis import strategies as st

from map_server.server import MapServer
from shared import codec
from shared.geometry import apply_segments, inverse
from shared.keys import Keys
from shared.messages import MAX_ROBOTS, PoseUpdate, RobotMap, WireFormatError
from tests.shared.test_codec import fused_map

pytestmark = pytest.mark.timeout(300)

FUZZ = dict(
    deadline=None, suppress_health_check=[HealthCheck.too_slow], derandomize=True,
    phases=[Phase.explicit, Phase.generate, Phase.shrink],  # no "explain": minutes on these examples
)  # fmt: skip
KEYS = Keys()
ROBOTS = ("robot1", "robot2")
PRIORS = {"robot1": np.zeros(3), "robot2": np.array([2.0, 1.0, 0.1])}
GHOSTS = ("ghost1", "ghost2")  # robots nobody runs
FOREIGN_KEYS = (  # not a robot key of this fleet (zenoh would not deliver them; the callback must cope)
    "fleet/default/robots/robot1/map/extra",
    "fleet/other/robots/robot1/map",
    "fleet/default/robots/bad id/map",
    "fleet/default/robot/robot1/pose",
    "fleet/default/robots//pose",
    "",
    "fleet/default/map/fused",
)
HOSTILE_VALUES = [
    None,
    True,
    -1,
    2**64 - 1,
    2**63,
    math.nan,
    math.inf,
    -math.inf,
    1e308,
    "x",
    b"",
    b"\x00" * 7,
    [],
    {},
]
BAD_SCHEMAS = [0, 2, 99, -1, 2**40, "1", 1.0, True, None]


class FakeBus:
    def __init__(self):
        self.puts = []

    def put(self, key, payload, reliable=True):
        self.puts.append((key, payload))

    def get(self, key_expr, timeout_s=2.0):  # the server pulls a robot's map when it comes online
        return []


# -- the legitimate fleet: two robots mapping one room, robot1 restarts half-way ----------------


def walls(n: int) -> np.ndarray:
    """The first ``n`` pieces (0.9 m each, 1 m apart) of an 8 m x 6 m room's walls, global frame."""
    corners = [(0, 0), (8, 0), (8, 6), (0, 6), (0, 0)]
    seg = []
    for (x0, y0), (x1, y1) in itertools.pairwise(corners):
        d = np.array([x1 - x0, y1 - y0], float)
        length = np.linalg.norm(d)
        for t in np.arange(0.0, length, 1.0):
            a = np.array([x0, y0]) + d / length * t
            seg.append([a, a + d / length * 0.9])
    return np.array(seg[:n])


def map_chunks(robot: str, session: str, seq: int, n: int, n_chunks: int) -> list[bytes]:
    seg = apply_segments(inverse(PRIORS[robot]), walls(n))  # in the robot's map frame
    k = len(seg)
    chunks = codec.robot_map_chunks(
        robot, session, seq, 1.0 + seq, np.array([0.9]), np.zeros((1, 3)), seg, np.arange(k),
        np.ones(k, np.int64), np.full(k, 0.8), np.full(k, 10 + seq), np.full(k, 50 + seq),
        prior=PRIORS[robot], prior_sigma=np.array([0.05, 0.05, 0.02]), max_elements=-(-k // n_chunks),
    )  # fmt: skip
    assert len(chunks) == n_chunks
    return [codec.encode(c) for c in chunks]


def pose(robot: str, session: str, seq: int) -> bytes:
    return codec.encode(PoseUpdate(robot, session, seq, 1.0 + 0.2 * seq, np.array([0.1 * seq, 1.0, 0.2])))


def legit_schedule() -> list[tuple]:
    """Events: ("map"|"pose", robot, key, payload), ("alive", robot, key, bool), ("tick", t)."""
    ev: list[tuple] = [("alive", r, KEYS.robot_alive(r), True) for r in ROBOTS]

    def maps(robot, session, seq, n, n_chunks, only=None):
        for i, p in enumerate(map_chunks(robot, session, seq, n, n_chunks)):
            if only is None or i in only:
                ev.append(("map", robot, KEYS.robot_map(robot), p))

    def poses(robot, session, seq):
        ev.append(("pose", robot, KEYS.robot_pose(robot), pose(robot, session, seq)))

    maps("robot1", "s1", 0, 10, 2), poses("robot1", "s1", 0), poses("robot2", "t1", 0)
    ev.append(("tick", 1.0))
    maps("robot2", "t1", 0, 12, 3), poses("robot1", "s1", 1)
    ev.append(("tick", 2.0))
    (
        maps("robot1", "s1", 1, 16, 2, only=[0]),
        poses("robot2", "t1", 1),
        maps("robot1", "s1", 1, 16, 2, only=[1]),
    )
    ev.append(("tick", 3.0))
    maps("robot1", "s2", 0, 8, 2), poses("robot1", "s2", 0)  # robot1 restarted: a new session
    ev.append(("tick", 4.0))
    maps("robot2", "t1", 1, 20, 1), poses("robot2", "t1", 2), poses("robot1", "s2", 1)
    ev.append(("alive", "robot2", KEYS.robot_alive("robot2"), False))
    ev.append(("tick", 5.0))
    maps("robot1", "s2", 1, 14, 2)
    ev.append(("tick", 6.0))
    return ev


SCHEDULE = legit_schedule()
LEGIT = [e for e in SCHEDULE if e[0] in ("map", "pose")]
FUSED_BYTES = codec.encode(fused_map(np.random.default_rng(1), m=5))


def run(server: MapServer, events: list[tuple]) -> list:
    """Feed ``events`` (legit and hostile) to ``server`` on a deterministic clock; the fused map
    (as comparable content) after every tick."""
    clock = [0.0]
    server.now_s = lambda: clock[0]
    out = []
    for e in events:
        if e[0] == "map":
            server.on_map(e[2], e[3])
        elif e[0] == "pose":
            server.on_pose(e[2], e[3])
        elif e[0] == "alive":
            server.on_presence(e[2], e[3])
        else:
            clock[0] = e[1]
            out.append(content(server.tick()))
    return out


def content(fused) -> tuple | None:
    """What a fused map says about the fleet (not the server's own health figures)."""
    if fused is None:
        return None
    robots = tuple(
        tuple(v.tobytes() if isinstance(v, np.ndarray) else v for v in dataclasses.astuple(r))
        for r in fused.robots
    )
    arrays = tuple(getattr(fused, f).tobytes() for f in ("seg", "support", "prov_offsets", "prov_robot"))
    extra = {k: v for k, v in fused.extra.items() if not k.startswith("server_")}
    return fused.version, fused.stamp_s, robots, arrays, extra


@functools.cache
def baseline() -> tuple[list, dict, dict]:
    server = MapServer(FakeBus(), KEYS)
    fused = run(server, SCHEDULE)
    assert not server.rejected, server.reasons  # the legitimate fleet alone: nothing refused
    assert sum(f is not None for f in fused) >= 4 and fused[-1] is not None
    return fused, server.fleet.snapshot()[0], dict(server.received)


# -- hostile messages, each made to be refused given what was delivered before it -----------------


@dataclasses.dataclass
class History:
    """The legitimate messages delivered before a point of the schedule."""

    maps: list  # (robot, payload, message) in delivery order
    poses: list

    @staticmethod
    def at(i: int) -> History:
        h = History([], [])
        for e in SCHEDULE[:i]:
            if e[0] == "map":
                h.maps.append((e[1], e[3], codec.decode(e[3])))
            elif e[0] == "pose":
                h.poses.append((e[1], e[3], codec.decode(e[3])))
        return h


HISTORY = [History.at(i) for i in range(len(SCHEDULE) + 1)]


def refused_by_codec(payload: bytes) -> bool:
    try:
        codec.decode(payload)
    except WireFormatError:
        return True
    return False


def channel_key(data, robot: str | None = None) -> tuple[str, str]:
    robot = robot or data.draw(st.sampled_from(ROBOTS + GHOSTS))
    what = data.draw(st.sampled_from(["map", "pose"]))
    return what, KEYS.robot_map(robot) if what == "map" else KEYS.robot_pose(robot)


def own(entry_robot: str, msg) -> tuple[str, str]:
    if isinstance(msg, RobotMap):
        return "map", KEYS.robot_map(entry_robot)
    return "pose", KEYS.robot_pose(entry_robot)


def hostile(data, i: int) -> tuple | None:
    """One hostile event to deliver before schedule position ``i`` (None: this draw made none)."""
    h = HISTORY[i]
    delivered = h.maps + h.poses
    kind = data.draw(
        st.sampled_from(
            ["garbage", "truncated", "flipped", "field", "schema", "kind", "mismatch", "foreign", "presence"]
            + ["replay", "altered", "older"] * bool(delivered)
        )
    )
    event(f"hostile: {kind}")
    payload = data.draw(st.sampled_from([e[3] for e in LEGIT]))
    msg = codec.decode(payload)
    if kind == "garbage":
        junk = data.draw(
            st.one_of(
                st.binary(max_size=64),
                st.sampled_from([b"", b"\xc1", b"\x80", b"\x90", msgpack.packb({}), msgpack.packb([1, 2])]),
                st.dictionaries(st.text(max_size=8), st.sampled_from(HOSTILE_VALUES), max_size=4).map(
                    msgpack.packb
                ),
            )
        )
        return (*channel_key(data), junk)
    if kind == "truncated":
        return (*own(msg.robot, msg), payload[: data.draw(st.integers(0, len(payload) - 1))])
    if kind == "flipped":
        raw = bytearray(payload)
        for _ in range(data.draw(st.integers(1, 3))):
            raw[data.draw(st.integers(0, len(raw) - 1))] ^= data.draw(st.integers(1, 255))
        return (*own(msg.robot, msg), bytes(raw)) if refused_by_codec(bytes(raw)) else None
    if kind in ("field", "schema"):
        fields = msgpack.unpackb(payload)
        if kind == "schema":
            fields["schema"] = data.draw(st.sampled_from(BAD_SCHEMAS))
        else:
            fields[data.draw(st.sampled_from(sorted(fields)))] = data.draw(st.sampled_from(HOSTILE_VALUES))
        bad = msgpack.packb(fields)
        return (*own(msg.robot, msg), bad) if refused_by_codec(bad) else None
    if kind == "kind":  # a pose on a map key, a map on a pose key, a fused map on either
        what, _ = own(msg.robot, msg)
        other = KEYS.robot_pose(msg.robot) if what == "map" else KEYS.robot_map(msg.robot)
        if data.draw(st.booleans()):
            return (*channel_key(data, msg.robot), FUSED_BYTES)
        return ("pose" if what == "map" else "map", other, payload)
    if kind == "mismatch":  # a valid message on another robot's key
        robot = data.draw(st.sampled_from([r for r in ROBOTS + GHOSTS if r != msg.robot]))
        return (*own(robot, msg), payload)
    if kind == "foreign":
        return (own(msg.robot, msg)[0], data.draw(st.sampled_from(FOREIGN_KEYS)), payload)
    if kind == "presence":
        return ("alive", None, data.draw(st.sampled_from(FOREIGN_KEYS)), data.draw(st.booleans()))
    robot, payload, msg = data.draw(st.sampled_from(delivered))
    if kind == "replay":  # the same bytes again
        return (*own(robot, msg), payload)
    if kind == "altered":  # same identity (robot, session, seq, chunk), other content
        if isinstance(msg, RobotMap):
            change = data.draw(st.sampled_from(["seg", "stamp_s"]))
            msg = dataclasses.replace(
                msg, **{change: msg.seg + 0.5 if change == "seg" else msg.stamp_s + 1.0}
            )
        else:
            msg = dataclasses.replace(msg, pose=msg.pose + 1.0)
        return (*own(robot, msg), codec.encode(msg))
    # older: a seq below the newest delivered of its session (stale, or older than the one pending)
    same = [
        m.seq
        for r, _, m in (h.maps if isinstance(msg, RobotMap) else h.poses)
        if r == robot and m.session == msg.session
    ]
    if max(same) == 0:
        return None
    msg = dataclasses.replace(msg, seq=data.draw(st.integers(0, max(same) - 1)))
    return (*own(robot, msg), codec.encode(msg))


@functools.cache
def incomplete(n: int) -> bytes:
    """A ghost's chunk 1 of a 3-chunk map whose other chunks never come (seq ``n``: each abandons
    the last): taken and held, never a map — not refused, and no state change either."""
    return map_chunks_for("ghost1", n)[1]


def map_chunks_for(robot: str, seq: int) -> list[bytes]:
    rm = codec.robot_map_chunks(
        robot, "g", seq, 1.0, np.array([1.0]), np.zeros((1, 3)), walls(6), np.arange(6), np.ones(6, np.int64),
        np.full(6, 0.5), np.full(6, 1), np.full(6, 1), max_elements=2,
    )  # fmt: skip
    return [codec.encode(c) for c in rm]


class Records(logging.Handler):
    def __init__(self):
        super().__init__(logging.DEBUG)
        self.records: list[logging.LogRecord] = []

    def emit(self, record):
        self.records.append(record)


@settings(max_examples=150, **FUZZ)
@given(st.data())
def test_hostile_messages_are_refused_counted_logged_and_change_nothing(data):
    want_fused, want_snapshot, want_received = baseline()
    events: list[tuple] = []
    n_hostile = n_incomplete = 0
    for i, e in enumerate(SCHEDULE):
        for _ in range(data.draw(st.integers(0, 4))):
            if data.draw(st.integers(0, 19)) == 0:
                events.append(("map", "ghost1", KEYS.robot_map("ghost1"), incomplete(n_incomplete)))
                n_incomplete += 1
                continue
            h = hostile(data, i)
            if h is not None:
                events.append((h[0], None, *h[2:]) if h[0] == "alive" else (h[0], None, h[1], h[2]))
                n_hostile += 1
        events.append(e)
    logger = logging.getLogger("fleet_slam.server")
    records = Records()
    logger.addHandler(records)
    try:
        server = MapServer(FakeBus(), KEYS)
        fused = run(server, events)
    finally:
        logger.removeHandler(records)
    event(f"hostile messages: {n_hostile // 20 * 20}+")

    # every hostile message refused and counted, under a reason; the legitimate ones all taken
    assert sum(server.rejected.values()) == n_hostile, (n_hostile, server.reasons)
    assert sum(server.reasons.values()) == n_hostile
    received = dict(want_received)
    received["map_chunk"] = received.get("map_chunk", 0) + n_incomplete
    assert dict(server.received) == received
    # each reason logged once as a warning, with the message's text
    warnings = [r.getMessage() for r in records.records if r.levelno == logging.WARNING]
    warnings = [w for w in warnings if w.startswith("rejected ") and "so far" not in w]
    assert len(warnings) == len(server.reasons), (warnings, server.reasons)
    assert all("(further ones counted)" in w for w in warnings)
    # and nothing changed: the same fused map after every tick, the same fleet state
    assert fused == want_fused
    assert server.fleet.snapshot()[0] == want_snapshot


def test_the_fuzz_can_fail():
    """The comparison sees a changed state: one more legitimate-looking map (a new seq) changes it."""
    want_fused, _, _ = baseline()
    extra = ("map", "robot1", KEYS.robot_map("robot1"), map_chunks("robot1", "s2", 5, 30, 1)[0])
    events = [*SCHEDULE[:-1], extra, SCHEDULE[-1]]
    assert run(MapServer(FakeBus(), KEYS), events) != want_fused


@settings(max_examples=300, **FUZZ)
@given(st.sampled_from(ROBOTS + GHOSTS + ("r-1", "A_b")), st.sampled_from(ROBOTS + GHOSTS + ("r-1", "A_b")))
def test_a_robot_id_must_match_its_key(in_message, in_key):
    """A valid message is taken on its own robot's key only; elsewhere it is refused, named."""
    server = MapServer(FakeBus(), KEYS)
    server.on_pose(KEYS.robot_pose(in_key), codec.encode(PoseUpdate(in_message, "s", 0, 1.0, np.zeros(3))))
    server.on_map(KEYS.robot_map(in_key), map_chunks_for(in_message, 0)[0])
    if in_message == in_key:
        assert not server.rejected and server.received == {"pose": 1, "map_chunk": 1}
    else:
        assert server.rejected == {"pose": 1, "map": 1} and not server.received
        with pytest.raises(WireFormatError, match=f"{in_message!r} published on the key of {in_key!r}"):
            server._decode(
                KEYS.robot_pose(in_key),
                codec.encode(PoseUpdate(in_message, "s", 0, 1.0, np.zeros(3))),
                PoseUpdate,
            )


def test_each_kind_of_refusal_has_its_own_reason():
    server = MapServer(FakeBus(), KEYS)
    server.on_pose(KEYS.robot_pose("robot2"), pose("robot1", "s1", 0))  # robot1 on robot2's key
    server.on_pose("fleet/other/robots/robot1/pose", pose("robot1", "s1", 0))  # not this fleet's key
    assert len(server.reasons) == 2 and not any(r.endswith(": malformed") for r in server.reasons), (
        server.reasons
    )


def test_a_flood_of_unknown_robots_does_not_stop_the_server():
    server = MapServer(FakeBus(), KEYS)
    server.now_s = lambda: 1.0
    for e in SCHEDULE[:4]:
        run(server, [e])
    before = len(server._robot_ids)  # admitted so far (some still queued)
    for i in range(300):  # well-formed, each on its own key: new robots, refused once the fleet is full
        ghost = f"ghost{i}"
        server.on_pose(KEYS.robot_pose(ghost), codec.encode(PoseUpdate(ghost, "g", 0, 1.0, np.zeros(3))))
    server.tick()  # used to raise in every tick: more robots than a fused map may hold
    assert len(server.fleet.robots) == MAX_ROBOTS
    assert server.reasons == {"pose: robot": 300 - (MAX_ROBOTS - before)}, server.reasons
    known = sorted(server.fleet.robots)[0]  # a robot the fleet knows still gets through
    server.on_pose(KEYS.robot_pose(known), codec.encode(PoseUpdate(known, "z", 0, 2.0, np.zeros(3))))
    assert server.received["pose"] >= 1 and sum(server.rejected.values()) == 300 - (MAX_ROBOTS - before)
