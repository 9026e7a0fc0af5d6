"""Property tests: whatever bytes arrive, decode returns a valid message or raises WireFormatError.

A decoded message is always valid (its constructor validated it) and always encodes again; the
codec's defensive catch-all (``codec.UNEXPECTED``) must never fire. On the receiving side, streams
of duplicated, reordered, stale and inconsistent chunks and poses go through ``Assembler`` and
``SeqFilter``, and random keys through ``Keys.robot_of`` (the server's robot-id-vs-key check is
fuzzed in ``tests/map_server/test_server_fuzz.py``). Budget: ~14,600 inputs, ~15 s.
``tests/fuzz/fuzz_decoders.py`` is the longer, coverage-guided run (atheris).
"""

from __future__ import annotations

import functools
import itertools
import math
import re
import warnings
from collections import Counter

import msgpack
import numpy as np
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st

from shared import codec
from shared.keys import Keys
from shared.messages import (
    ID_PATTERN,
    MAX_CHUNK_ELEMENTS,
    FreeSpace,
    FusedFree,
    FusedMap,
    PoseUpdate,
    RobotMap,
    RobotPath,
    WireFormatError,
)
from tests.shared.test_codec import robot_map, robot_map_fields, samples, unpacked
from tests.shared.test_graph_wire import graph_map, robot_path

# one of each kind, and a robot map with a pose graph (schema 5)
SAMPLES = [*samples(), codec.encode(graph_map(n=6, k=5)), codec.encode(robot_path())]
STORED = codec.encode_stored_map(robot_map(np.random.default_rng(3), n=MAX_CHUNK_ELEMENTS + 5, k=4))
FAST = dict(deadline=None, suppress_health_check=[HealthCheck.too_slow], database=None)


FIELD_NAMES = {"payload", "schema", "kind", "prior", *(k for keys in codec.KEYS.values() for k in keys)}


def names_a_field(text: str) -> bool:
    """The error text starts with a field name (``seg: ...``, ``robots[2].pose: ...``, ``extra[k]: ...``)
    or with an unknown key, quoted."""
    head = text.split(": ")[0]
    if head.startswith(("'", '"', "b'", 'b"')):
        return True
    head = re.sub(r"^robots\[\d+\]\.?", "", head) or "robots"
    return head.split("[")[0].split(" ")[0] in FIELD_NAMES


def check(data: object) -> None:
    """The property: a message that survives a round trip, or a WireFormatError that is not a bug."""
    try:
        msg = codec.decode(data)
    except WireFormatError as e:
        assert codec.UNEXPECTED not in str(e), str(e)
        assert names_a_field(str(e)), str(e)
        event("refused: " + str(e).split(":")[0])
        return
    event("decoded")
    assert isinstance(msg, RobotMap | PoseUpdate | FusedMap | FreeSpace | FusedFree | RobotPath)
    assert isinstance(codec.decode(codec.encode(msg)), type(msg))


hostile_scalars = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(min_value=-(2**63), max_value=2**64 - 1),
    st.sampled_from([0, 1, -1, 3, 2**31, 2**32, 2**63 - 1, 2**63, 2**64 - 1, MAX_CHUNK_ELEMENTS + 1]),
    st.floats(allow_nan=True, allow_infinity=True),
    st.sampled_from([math.nan, math.inf, -math.inf, -0.0, 1e308]),
    st.text(max_size=80),
    st.binary(max_size=200),
)
hostile_values = st.recursive(
    hostile_scalars,
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=12), inner, max_size=4),
    max_leaves=5,
)


@settings(max_examples=3000, **FAST)
@given(st.binary(max_size=600))
def test_random_bytes(data):
    check(data)


@settings(max_examples=1500, **FAST)
@given(hostile_values)
def test_random_msgpack_values(obj):
    check(msgpack.packb(obj, use_bin_type=True))


@settings(max_examples=1000, **FAST)
@given(st.integers(0, len(SAMPLES) - 1), st.data())
def test_fields_dropped_added_or_kind_swapped(i, data):
    fields = unpacked(SAMPLES[i])
    for key in data.draw(st.lists(st.sampled_from(sorted(fields)), max_size=3)):
        fields.pop(key, None)
    for key in data.draw(st.lists(st.text(max_size=12), max_size=2)):
        fields[key] = data.draw(hostile_scalars)
    if data.draw(st.booleans()):
        fields["kind"] = data.draw(st.sampled_from(["pose", "robot_map", "fused_map", "robot_status"]))
    check(msgpack.packb(fields, use_bin_type=True))


@settings(max_examples=1500, **FAST)
@given(st.integers(0, len(SAMPLES) - 1), st.data())
def test_truncated_or_extended(i, data):
    raw = SAMPLES[i]
    cut = data.draw(st.integers(0, len(raw)))
    tail = data.draw(st.binary(max_size=8))
    check(raw[:cut] + tail)


@settings(max_examples=2000, **FAST)
@given(st.integers(0, len(SAMPLES) - 1), st.data())
def test_flipped_bytes(i, data):
    raw = bytearray(SAMPLES[i])
    for _ in range(data.draw(st.integers(1, 4))):
        raw[data.draw(st.integers(0, len(raw) - 1))] ^= data.draw(st.integers(1, 255))
    check(bytes(raw))


@settings(max_examples=2000, **FAST)
@given(st.integers(0, len(SAMPLES) - 1), st.data(), hostile_values)
def test_a_field_replaced_by_a_hostile_value(i, data, value):
    fields = unpacked(SAMPLES[i])
    target = fields
    if fields["kind"] == "fused_map" and data.draw(st.booleans()):
        target = fields["robots"][data.draw(st.integers(0, len(fields["robots"]) - 1))]
    key = data.draw(st.sampled_from(sorted(target)))
    target[key] = value
    check(msgpack.packb(fields, use_bin_type=True))


@settings(max_examples=1000, **FAST)
@given(st.integers(0, len(SAMPLES) - 1), st.data())
def test_array_values_injected(i, data):
    fields = unpacked(SAMPLES[i])
    arrays = sorted(k for k, v in fields.items() if isinstance(v, bytes) and v)
    name = data.draw(st.sampled_from(arrays))
    arr = np.frombuffer(fields[name], codec.WIRE_DTYPES[name]).copy()
    j = data.draw(st.integers(0, arr.size - 1))
    if arr.dtype.kind == "f":
        arr[j] = data.draw(st.sampled_from([np.nan, np.inf, -np.inf, 1e30, -1e-30, 2.0, -0.5]))
    else:
        info = np.iinfo(arr.dtype)
        arr[j] = data.draw(st.integers(int(info.min), int(info.max)))
    fields[name] = arr.tobytes()
    check(msgpack.packb(fields, use_bin_type=True))


@settings(max_examples=500, **FAST)
@given(st.data())
def test_stored_maps_flipped_or_truncated(data):
    raw = bytearray(STORED)
    for _ in range(data.draw(st.integers(0, 3))):
        raw[data.draw(st.integers(0, len(raw) - 1))] ^= data.draw(st.integers(1, 255))
    raw = raw[: data.draw(st.integers(0, len(raw)))]
    try:
        msg = codec.decode_stored_map(bytes(raw))
    except WireFormatError as e:
        assert codec.UNEXPECTED not in str(e) and names_a_field(str(e)), str(e)
        return
    assert isinstance(codec.decode_stored_map(codec.encode_stored_map(msg)), RobotMap)


@settings(max_examples=300, **FAST)
@given(st.integers(0, 2**32 - 1), st.integers(0, 300), st.integers(1, 63), st.booleans())
def test_valid_maps_round_trip_and_assemble(seed, n, k, prior):
    rng = np.random.default_rng(seed)
    over = {} if prior else {"prior": None, "prior_sigma": None}
    msg = robot_map(rng, n=n, k=k, **over)
    chunks = codec.split(msg, max_elements=64)
    asm = codec.Assembler()
    out = [asm.add(codec.decode(codec.encode(c), expect=RobotMap)) for c in rng.permutation(chunks)]
    whole = out[-1]
    assert all(o is None for o in out[:-1])
    np.testing.assert_array_equal(whole.members, msg.members)
    np.testing.assert_array_equal(whole.particle_poses, msg.particle_poses)
    np.testing.assert_allclose(whole.seg, msg.seg.astype(np.float32))


# -- the receiving side: duplicated, out-of-order, stale and inconsistent chunks ------------------


@functools.cache
def snapshot(robot: str, session: str, seq: int, n_chunks: int, variant: int = 0) -> tuple[bytes, ...]:
    """The encoded chunks of one robot-map snapshot; a ``variant`` has the same identity (robot,
    session, seq) but another header (``stamp_s``), as a forged or corrupted sender would make."""
    rng = np.random.default_rng([hash((robot, session)) % 2**32, seq, n_chunks])
    fields = robot_map_fields(rng, 3 * n_chunks) | {"prior": None, "prior_sigma": None}
    chunks = codec.robot_map_chunks(robot, session, seq, 1.0 + seq + 0.5 * variant, **fields, max_elements=3)
    assert len(chunks) == n_chunks
    return tuple(codec.encode(c) for c in chunks)


SESSIONS = ("s1", "s2", "s3")  # in the order a robot uses them (restarts)
sent_chunk = st.tuples(
    st.sampled_from(["r1", "r2"]),
    st.integers(0, 2),
    st.integers(0, 4),
    st.integers(1, 3),
    st.integers(0, 1),
    st.integers(0, 2),
)  # robot, session index, seq, n_chunks, variant, chunk index (clipped to n_chunks)


@settings(max_examples=500, **FAST)
@given(st.lists(sent_chunk, max_size=40), st.permutations(range(4)), st.data())
def test_assembler_under_duplicated_reordered_and_stale_chunks(stream, final_order, data):
    """Whatever arrives: every chunk is taken or refused with a counted reason; a map comes out only
    whole, as one snapshot was sent (never chunks of two variants mixed), newer than the last one
    of its session, never from a session already replaced; a message seen before is always
    refused; and after all that, a restarted robot's snapshot still comes out."""
    asm = codec.Assembler()
    seen: set[bytes] = set()
    refused: Counter = Counter()
    out: list[RobotMap] = []
    for robot, s, seq, n_chunks, variant, i in stream:
        session = SESSIONS[s]
        if data.draw(st.booleans()):  # mostly the sessions in order, sometimes a late old one
            session = SESSIONS[
                max(s, max((SESSIONS.index(m.session) for m in out if m.robot == robot), default=0))
            ]
        payload = snapshot(robot, session, seq, n_chunks, variant)[min(i, n_chunks - 1)]
        again = payload in seen
        seen.add(payload)
        try:
            whole = asm.add(codec.decode(payload, expect=RobotMap))
        except codec.ChunkRejected as e:
            assert e.reason in {"stale", "duplicate", "header", "stale_session"}, e
            assert str(e).split(":")[0] in {"seq", "chunk", "session", "stamp_s", "n_chunks"}, str(e)
            refused[e.reason] += 1
            event(f"refused: {e.reason}")
            continue
        assert not again, "a message seen before was taken"
        if whole is not None:
            out.append(whole)
    assert asm.rejected == refused
    for m in out:  # whole, and exactly one sent snapshot
        variants = [snapshot(m.robot, m.session, m.seq, len(m.seg) // 3, v) for v in (0, 1)]
        joined = [codec.join([codec.decode(c) for c in chunks]) for chunks in variants]
        assert any(codec.encode(m) == codec.encode(j) for j in joined)
    for robot in ("r1", "r2"):  # per session increasing; a session left is never back
        mine = [(m.session, m.seq) for m in out if m.robot == robot]
        for (sa, a), (sb, b) in itertools.pairwise(mine):
            assert sb != sa or b > a, mine
        sessions = [s for s, _ in mine]
        left = [s for i, s in enumerate(sessions) if s not in sessions[i + 1 :]]
        assert sessions == sorted(sessions, key=left.index), mine
    # liveness: the robot restarted (a session never seen): its snapshot, chunks in any order, comes out
    final = snapshot("r1", "s4", 9, 4)
    results = [asm.add(codec.decode(final[j])) for j in final_order]
    assert all(r is None for r in results[:-1]) and results[-1].seq == 9 and len(results[-1].seg) == 12


pose_sent = st.tuples(st.sampled_from(["r1", "r2"]), st.integers(0, 2), st.integers(0, 6))


@settings(max_examples=500, **FAST)
@given(st.lists(pose_sent, max_size=40))
def test_seq_filter_under_duplicated_and_reordered_poses(stream):
    """A pose is taken exactly when it is newer than every pose taken from its robot's session and
    its session was not replaced; everything else is refused and counted."""
    f = codec.SeqFilter()
    newest: dict[tuple[str, str], int] = {}
    current: dict[str, str] = {}
    retired: dict[str, set] = {"r1": set(), "r2": set()}
    refused = Counter()
    for robot, s, seq in stream:
        session = SESSIONS[s]
        msg = codec.decode(codec.encode(PoseUpdate(robot, session, seq, 1.0, np.zeros(3))), expect=PoseUpdate)
        fresh = session not in retired[robot] and seq > newest.get((robot, session), -1)
        try:
            f.check(msg)
        except codec.ChunkRejected as e:
            assert not fresh, f"refused a fresh pose: {e}"
            refused[e.reason] += 1
            event(f"refused: {e.reason}")
            continue
        assert fresh, f"took a stale pose {robot} {session} {seq}"
        if current.get(robot, session) != session:
            retired[robot].add(current[robot])
            newest.pop((robot, current[robot]), None)
        current[robot], newest[(robot, session)] = session, seq
    assert f.rejected == refused


@settings(max_examples=500, **FAST)
@given(
    st.one_of(
        st.text(max_size=60),
        st.tuples(
            st.sampled_from(["fleet/default", "fleet/other", "fleet", "", "fleet/default/x"]),
            st.sampled_from(["robots", "robot", "Robots", ""]),
            st.one_of(
                st.sampled_from(["r1", "robot_2", "a-b", "", "*", "**", "a b", "é"]), st.text(max_size=70)
            ),
            st.sampled_from(["map", "pose", "alive", "", "map/x"]),
        ).map("/".join),
    )
)
def test_robot_of_a_key(key):
    """A key names a robot only as ``fleet/<fleet>/robots/<id>/<leaf>`` with a valid id; anything
    else is a WireFormatError quoting the key."""
    keys = Keys()
    parts = key.split("/")
    valid = (
        len(parts) == 5
        and parts[:3] == ["fleet", "default", "robots"]
        and ID_PATTERN.match(parts[3]) is not None
    )
    try:
        robot = keys.robot_of(key)
    except WireFormatError as e:
        assert not valid and str(e).startswith("key: "), (key, str(e))
        return
    assert valid and robot == parts[3] and keys.robot_of(keys.robot_map(robot)) == robot


# any float32 word, and often one with the exponent all ones: infinities, quiet and signalling NaNs
float32_bits = st.one_of(
    st.integers(0, 2**32 - 1), st.integers(0x7F800000, 0x7FFFFFFF), st.integers(0xFF800000, 0xFFFFFFFF)
)


@settings(max_examples=300, **FAST)
@given(st.sampled_from(["seg", "trust"]), st.lists(float32_bits, min_size=1, max_size=6), st.data())
def test_any_float32_bit_pattern_with_warnings_as_errors(name, words, data):
    """Any float32 bits in a map's float32 arrays (signalling NaNs too): taken or refused naming the
    array, and numpy says nothing (a RuntimeWarning made an error by a strict host would have
    escaped as the codec's catch-all)."""
    fields = unpacked(SAMPLES[1])
    arr = np.frombuffer(fields[name], "<u4").copy()
    for w in words:
        arr[data.draw(st.integers(0, arr.size - 1))] = w
    fields[name] = arr.tobytes()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        try:
            codec.decode(msgpack.packb(fields, use_bin_type=True), expect=RobotMap)
        except WireFormatError as e:
            assert str(e).startswith(f"{name}: "), str(e)
