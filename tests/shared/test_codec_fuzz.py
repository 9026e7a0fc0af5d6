"""Property tests: whatever bytes arrive, decode returns a valid message or raises WireFormatError.

A decoded message is always valid (its constructor validated it) and always encodes again; the
codec's defensive catch-all (``codec.UNEXPECTED``) must never fire. Budget: ~12,800 inputs, ~15 s.
"""

from __future__ import annotations

import math
import re

import msgpack
import numpy as np
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st

from shared import codec
from shared.messages import MAX_CHUNK_ELEMENTS, FusedMap, PoseUpdate, RobotMap, WireFormatError
from tests.shared.test_codec import robot_map, samples, unpacked

SAMPLES = samples()
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
    assert isinstance(msg, RobotMap | PoseUpdate | FusedMap)
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
