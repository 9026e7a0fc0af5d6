"""Wire codec: round trips, chunk assembly, and every way a payload is refused (with the field named).

Tests build hostile payloads with msgpack directly: that is the point of a wire test.
"""

from __future__ import annotations

import dataclasses

import msgpack
import numpy as np
import pytest

from shared import codec
from shared.codec import Assembler, ChunkRejected, SeqFilter, decode, encode
from shared.messages import (
    MAX_CHUNK_ELEMENTS,
    SCHEMA_VERSION,
    FreeSpace,
    FusedFree,
    FusedMap,
    PoseUpdate,
    RobotMap,
    RobotStatus,
    WireFormatError,
)

F4 = dict(rtol=2e-7, atol=1e-6)  # float32 rounding of coordinates up to ~50 m


# -- samples (also used by test_codec_fuzz.py) ------------------------------------------------


def robot_map_fields(rng: np.random.Generator, n: int, k: int = 3, prior: bool = True) -> dict:
    """The keyword arguments of :func:`codec.robot_map_chunks` for a random map of ``n`` elements."""
    w = rng.random(k)
    w = 0.9 * w / w.sum()
    fields = dict(
        particle_weights=w, particle_poses=rng.uniform(-20, 20, (k, 3)), seg=rng.uniform(-50, 50, (n, 2, 2)),
        element=rng.permutation(n) * 3, members=rng.integers(1, 2**k, n), trust=rng.random(n),
        hits=rng.integers(0, 10_000, n), age=rng.integers(0, 100_000, n),
    )  # fmt: skip
    if prior:
        fields.update(prior=np.array([1.0, -2.0, 0.3]), prior_sigma=np.array([0.1, 0.1, 0.05]))
    return fields


def robot_map(rng: np.random.Generator, n: int = 10, k: int = 3, seq: int = 0, **over) -> RobotMap:
    """A single-chunk robot map."""
    fields = robot_map_fields(rng, n, k) | over
    return RobotMap(
        robot=fields.pop("robot", "r1"), session=fields.pop("session", "s1"), seq=seq,
        stamp_s=fields.pop("stamp_s", 12.5), chunk=0, n_chunks=1, **fields,
    )  # fmt: skip


def statuses() -> tuple[RobotStatus, ...]:
    return (
        RobotStatus("r1", "reference", True, "s1", 4, 120, np.zeros(3), np.zeros(3),
                    np.array([1.0, 2.0, 0.5]), 3.25, 0.0),
        RobotStatus("r2", "aligned", False, "s9", 7, 80, np.array([5.0, -1.0, 1.2]),
                    np.array([0.05, 0.05, 0.01]), None, 0.0, 17.5),
        RobotStatus("r3", "unaligned", True, "s3", 0, 0, np.zeros(3), np.full(3, 1e3)),
    )  # fmt: skip


def fused_map_fields(rng: np.random.Generator, m: int, n_robots: int = 3) -> dict:
    """The keyword arguments of :func:`codec.fused_map_chunks` for ``m`` segments, 1-3 robots each."""
    counts = rng.integers(1, n_robots + 1, m)
    prov = np.concatenate([rng.permutation(n_robots)[:c] for c in counts]) if m else np.zeros(0, int)
    return dict(
        server="srv", version=9, stamp_s=100.0, robots=statuses()[:n_robots],
        seg=rng.uniform(-50, 50, (m, 2, 2)), support=rng.integers(1, 50, m),
        prov_offsets=np.concatenate([[0], np.cumsum(counts)]), prov_robot=prov,
        extra={"fuse_s": 0.012, "n": 3},
    )  # fmt: skip


def fused_map(rng: np.random.Generator, m: int = 10, version: int = 9) -> FusedMap:
    f = fused_map_fields(rng, m) | {"version": version}
    return FusedMap(chunk=0, n_chunks=1, **f)


def pose_update(seq: int = 3, session: str = "s1", robot: str = "r1") -> PoseUpdate:
    return PoseUpdate(robot, session, seq, 4.5, np.array([1.5, -2.25, 3.0]))


def free_space_and_fused_free() -> list:
    """A robot's free space (two views, three rings) and a fused one (a polygon with a hole)."""
    sq = np.array([[0.0, 0.0], [2.0, 0.0], [2.0, 2.0], [0.0, 2.0]])
    free = FreeSpace(
        "r1", "s1", 2, 4.0, np.array([[1.0, 2.0, 0.5], [3.0, 1.0, -1.0]]), np.array([0, 4, 8, 12]),
        np.array([0, 1, 1]), np.concatenate([sq, sq + 0.5, sq * 0.5]), np.array([1, 1, 0, 0] * 3, bool),
    )  # fmt: skip
    fused = FusedFree("srv", "abc123", 5, 9, 3.0, 0.02, np.array([0, 4, 8]), np.array([0, 1]),
                      np.concatenate([sq * 3, sq + 1.0]), np.array([[[0.0, 0.0], [1.0, 0.0]]]))  # fmt: skip
    return [free, fused]


def samples() -> list[bytes]:
    """One valid payload of each kind (small), for mutation."""
    rng = np.random.default_rng(7)
    return [encode(pose_update()), encode(robot_map(rng, n=6)), encode(fused_map(rng, m=5)),
            *map(encode, free_space_and_fused_free())]  # fmt: skip


def unpacked(data: bytes) -> dict:
    return msgpack.unpackb(data, raw=False)


def repack(data: bytes, **changes) -> bytes:
    """``data`` with top-level fields replaced; a value of ``...`` deletes the field."""
    fields = unpacked(data)
    for k, v in changes.items():
        if v is ...:
            del fields[k]
        else:
            fields[k] = v
    return msgpack.packb(fields, use_bin_type=True)


def assert_robot_maps_equal(a: RobotMap, b: RobotMap) -> None:
    for f in ("robot", "session", "seq", "stamp_s", "chunk", "n_chunks"):
        assert getattr(a, f) == getattr(b, f), f
    for f in (
        "particle_weights",
        "particle_poses",
        "element",
        "members",
        "hits",
        "age",
        "prior",
        "prior_sigma",
    ):
        np.testing.assert_array_equal(getattr(a, f), getattr(b, f), err_msg=f)  # f8 and integers: exact
    np.testing.assert_allclose(a.seg, b.seg, **F4)
    np.testing.assert_allclose(a.trust, b.trust, **F4)


def rejects(data: object, match: str, expect: type | None = None) -> None:
    with pytest.raises(WireFormatError, match=match) as info:
        decode(data, expect)
    assert codec.UNEXPECTED not in str(info.value)


# -- round trips ------------------------------------------------------------------------------


@pytest.mark.parametrize("with_prior", [True, False])
def test_robot_map_round_trip(with_prior):
    rng = np.random.default_rng(0)
    msg = robot_map(rng, n=50, k=5, seq=17, **({} if with_prior else {"prior": None, "prior_sigma": None}))
    out = decode(encode(msg), expect=RobotMap)
    assert isinstance(out, RobotMap)
    assert_robot_maps_equal(out, msg)
    assert (out.prior is None) == (not with_prior)


def test_a_joined_robots_claim_round_trips_and_older_schemas_read_as_not_joined():
    """Schema 6: ``joined`` says the prior is where the robot found itself in the fused map (agent
    --join). A schema-5 sender has no such field: its maps read as not joined; a joined map
    without its prior is refused."""
    rng = np.random.default_rng(3)
    msg = dataclasses.replace(robot_map(rng, n=8), joined=True)
    out = decode(encode(msg), expect=RobotMap)
    assert out.joined and np.array_equal(out.prior, msg.prior)
    assert not decode(encode(robot_map(rng, n=8)), expect=RobotMap).joined
    scans = dict.fromkeys(("n_scans", "n_scan_points", "scan_id", "scan_count", "scan_cm"), ...)
    old = decode(repack(encode(msg), joined=..., **scans, schema=5), expect=RobotMap)
    assert not old.joined and np.array_equal(old.prior, msg.prior)
    rejects(repack(encode(msg), **scans, schema=5), "'joined': unknown field of robot_map")
    rejects(repack(encode(msg), joined=1), "joined: expected a bool, got int")
    rejects(repack(encode(msg), prior=None, prior_sigma=None), "joined: needs the prior")
    with pytest.raises(WireFormatError, match="joined: needs the prior"):
        dataclasses.replace(msg, prior=None, prior_sigma=None)


def test_pose_round_trip_is_exact():
    msg = PoseUpdate("robot-7", "a1b2", 2**40, 1e6 + 0.125, np.array([1e5, -1e-9, np.pi]))
    out = decode(encode(msg), expect=PoseUpdate)
    assert (out.robot, out.session, out.seq, out.stamp_s) == ("robot-7", "a1b2", 2**40, 1e6 + 0.125)
    np.testing.assert_array_equal(out.pose, msg.pose)


def test_fused_map_round_trip():
    msg = fused_map(np.random.default_rng(1), m=40)
    out = decode(encode(msg), expect=FusedMap)
    assert (out.server, out.version, out.stamp_s, out.extra) == ("srv", 9, 100.0, {"fuse_s": 0.012, "n": 3.0})
    np.testing.assert_allclose(out.seg, msg.seg, **F4)
    for f in ("support", "prov_offsets", "prov_robot"):
        np.testing.assert_array_equal(getattr(out, f), getattr(msg, f), err_msg=f)
    assert [out.provenance(i) for i in range(40)] == [msg.provenance(i) for i in range(40)]
    for a, b in zip(out.robots, msg.robots, strict=True):
        for f in dataclasses.fields(RobotStatus):
            x, y = getattr(a, f.name), getattr(b, f.name)
            if isinstance(y, np.ndarray):
                np.testing.assert_array_equal(x, y, err_msg=f.name)
            else:
                assert x == y, f.name
    assert out.robots[1].pose is None and out.robots[2].aligned_at_s is None


def test_reencoding_a_decoded_message_gives_the_same_bytes():
    for data in samples():
        assert encode(decode(data)) == data


def test_payload_layout_and_size():
    """1,000 elements, 3 particles: 44 bytes per element (f4 seg 16, i8 element, u8 members, f4 trust,
    u4 hits, u4 age) plus a small header."""
    msg = robot_map(np.random.default_rng(2), n=1000, k=3)
    data = encode(msg)
    fields = unpacked(data)
    assert set(fields) == {"schema", "kind", *codec.KEYS["robot_map"]}
    assert fields["schema"] == SCHEMA_VERSION and fields["kind"] == "robot_map"
    assert len(fields["seg"]) == 1000 * 16 and len(fields["hits"]) == 1000 * 4
    assert 44_000 < len(data) < 44_600
    np.testing.assert_array_equal(np.frombuffer(fields["element"], "<i8"), msg.element)


def test_empty_maps_are_one_chunk():
    rng = np.random.default_rng(3)
    (rm,) = codec.robot_map_chunks("r1", "s1", 0, 0.0, **robot_map_fields(rng, 0))
    (fm,) = codec.fused_map_chunks(**fused_map_fields(rng, 0))
    for msg in (rm, fm):
        out = decode(encode(msg))
        assert (out.chunk, out.n_chunks, len(out.seg)) == (0, 1, 0)
    assert decode(encode(fm)).prov_offsets.tolist() == [0]


# -- chunking and assembly --------------------------------------------------------------------


def test_5000_element_map_goes_as_3_chunks_and_assembles_to_the_original():
    rng = np.random.default_rng(4)
    fields = robot_map_fields(rng, 5000)
    chunks = codec.robot_map_chunks("r1", "s1", 5, 2.0, **fields)
    assert [(c.chunk, c.n_chunks, len(c.seg)) for c in chunks] == [(0, 3, 1666), (1, 3, 1667), (2, 3, 1667)]
    assert all(len(encode(c)) < codec.MAX_MESSAGE_BYTES for c in chunks)
    asm = Assembler()
    got = [asm.add(decode(encode(c))) for c in (chunks[2], chunks[0], chunks[1])]  # any order
    assert got[:2] == [None, None]
    whole = RobotMap("r1", "s1", 5, 2.0, 0, 1, **fields)
    assert_robot_maps_equal(got[2], whole)
    assert not asm.rejected


def test_fused_provenance_survives_chunking():
    rng = np.random.default_rng(5)
    fields = fused_map_fields(rng, 5000)
    whole = FusedMap(chunk=0, n_chunks=1, **fields)
    chunks = codec.fused_map_chunks(**fields)
    assert len(chunks) == 3
    assert all(c.prov_offsets[0] == 0 for c in chunks)
    first = [c.provenance(i) for c in chunks for i in range(len(c.seg))]
    assert first == [whole.provenance(i) for i in range(5000)]
    out = None
    asm = Assembler()
    for c in chunks:
        out = asm.add(decode(encode(c)))
    np.testing.assert_array_equal(out.prov_offsets, whole.prov_offsets)
    np.testing.assert_array_equal(out.prov_robot, whole.prov_robot)
    np.testing.assert_array_equal(out.support, whole.support)
    np.testing.assert_allclose(out.seg, whole.seg, **F4)


def test_split_limits():
    rng = np.random.default_rng(6)
    chunks = codec.split(robot_map(rng, n=100), max_elements=30)
    assert [len(c.seg) for c in chunks] == [25, 25, 25, 25]
    with pytest.raises(WireFormatError, match="seg: 100 elements need 100 chunks"):
        codec.split(robot_map(rng, n=100), max_elements=1)
    with pytest.raises(WireFormatError, match="max_elements"):
        codec.split(robot_map(rng, n=10), max_elements=MAX_CHUNK_ELEMENTS + 1)
    with pytest.raises(WireFormatError, match="n_chunks"):
        codec.split(chunks[0])


def two_chunks(seq: int = 0, session: str = "s1", **over) -> list[RobotMap]:
    fields = robot_map_fields(np.random.default_rng(seq), 10) | over
    return codec.robot_map_chunks("r1", session, seq, 1.0 + seq, **fields, max_elements=5)


def test_stale_chunks_are_refused():
    asm = Assembler()
    old, new = two_chunks(3), two_chunks(4)
    assert asm.add(new[0]) is None
    with pytest.raises(ChunkRejected, match="seq: stale chunk 1 of r1 seq 3, 4 is pending"):
        asm.add(old[1])
    assert asm.add(new[1]) is not None
    with pytest.raises(ChunkRejected, match=r"seq: stale .* 4 already assembled"):
        asm.add(old[0])
    with pytest.raises(ChunkRejected, match="seq: stale"):
        asm.add(new[0])  # the completed snapshot again
    assert asm.rejected == {"stale": 3}


def test_a_newer_snapshot_abandons_the_pending_one():
    asm = Assembler()
    a, b = two_chunks(1), two_chunks(2)
    assert asm.add(a[0]) is None
    assert asm.add(b[1]) is None
    with pytest.raises(ChunkRejected, match="seq"):
        asm.add(a[1])
    whole = asm.add(b[0])
    assert whole.seq == 2 and len(whole.seg) == 10
    assert asm.dropped["incomplete"] == 1


def test_duplicate_chunk_is_refused():
    asm = Assembler()
    a = two_chunks(1)
    asm.add(a[0])
    with pytest.raises(ChunkRejected, match="chunk: duplicate chunk 0 of r1 seq 1"):
        asm.add(a[0])
    assert asm.rejected == {"duplicate": 1}
    assert asm.add(a[1]).seq == 1


@pytest.mark.parametrize(
    "field, value",
    [
        ("stamp_s", 99.0),
        ("particle_poses", np.zeros((3, 3))),
        ("particle_weights", np.full(3, 0.1)),
        ("prior", np.array([9.0, 9.0, 0.0])),
        ("prior_sigma", np.ones(3)),
    ],
)
def test_chunk_disagreeing_with_its_snapshot_header_is_refused(field, value):
    asm = Assembler()
    a = two_chunks(1)
    asm.add(a[0])
    with pytest.raises(ChunkRejected, match=f"{field}: chunk 1 of r1 seq 1 disagrees"):
        asm.add(dataclasses.replace(a[1], **{field: value}))
    assert asm.rejected == {"header": 1}


def test_chunk_count_disagreement_is_refused():
    asm = Assembler()
    a = two_chunks(1)
    asm.add(a[0])
    three = codec.robot_map_chunks("r1", "s1", 1, 2.0, **robot_map_fields(np.random.default_rng(1), 10),
                                   max_elements=4)  # fmt: skip
    with pytest.raises(ChunkRejected, match="n_chunks"):
        asm.add(three[1])


def test_fused_chunks_must_share_the_robot_table_and_extra():
    rng = np.random.default_rng(8)
    chunks = codec.fused_map_chunks(**fused_map_fields(rng, 20), max_elements=10)
    asm = Assembler()
    asm.add(chunks[0])
    moved = dataclasses.replace(statuses()[0], transform=np.array([0.0, 0.0, 0.1]))
    with pytest.raises(ChunkRejected, match="robots"):
        asm.add(dataclasses.replace(chunks[1], robots=(moved, *statuses()[1:])))
    with pytest.raises(ChunkRejected, match="extra"):
        asm.add(dataclasses.replace(chunks[1], extra={"fuse_s": 1.0}))
    assert asm.add(chunks[1]).version == 9
    with pytest.raises(ChunkRejected, match="version: stale"):
        asm.add(chunks[0])


def test_new_session_replaces_the_old_one_and_late_old_chunks_are_refused():
    asm = Assembler()
    assert asm.add(two_chunks(7)[0]) is None
    restarted = two_chunks(0, session="s2")
    assert asm.add(restarted[0]) is None  # seq 0 < 7 is fine: a new session
    assert asm.dropped["incomplete"] == 1
    with pytest.raises(ChunkRejected, match="session: stale session 's1' of r1"):
        asm.add(two_chunks(8)[0])
    assert asm.add(restarted[1]).session == "s2"
    assert asm.rejected == {"stale_session": 1}


def test_a_server_restarted_without_state_is_a_new_session_not_stale_versions():
    rng = np.random.default_rng(11)
    asm = Assembler()
    before = dataclasses.replace(fused_map(rng, version=40), session="run1")
    assert asm.add(decode(encode(before))) is not None
    again = dataclasses.replace(fused_map(rng, version=1), session="run2")  # versions from 1 again
    assert decode(encode(again)).session == "run2"
    assert asm.add(decode(encode(again))).version == 1
    with pytest.raises(ChunkRejected, match="stale session 'run1'"):
        asm.add(dataclasses.replace(before, version=41))  # a late map of the old process
    with pytest.raises(ChunkRejected, match="version: stale"):
        asm.add(dataclasses.replace(again, version=1))


def test_single_chunk_passes_through_but_obeys_the_rules():
    asm = Assembler()
    msg = robot_map(np.random.default_rng(9), seq=3)
    assert asm.add(msg) is msg
    with pytest.raises(ChunkRejected, match="seq: stale"):
        asm.add(msg)
    other = robot_map(np.random.default_rng(9), seq=3, robot="r2")
    assert asm.add(other) is other  # senders are independent


def test_robot_and_server_of_the_same_name_do_not_collide():
    asm = Assembler()
    rng = np.random.default_rng(10)
    assert asm.add(robot_map(rng, seq=50, robot="srv")) is not None
    assert asm.add(fused_map(rng, version=1)) is not None


def test_assembler_memory_is_bounded_by_senders():
    asm = Assembler(max_senders=2)
    rng = np.random.default_rng(11)
    for robot in ("a", "b", "c"):
        asm.add(robot_map(rng, seq=5, robot=robot))
    assert asm.dropped["evicted"] == 1
    assert asm.add(robot_map(rng, seq=5, robot="a")) is not None  # "a" was forgotten, not refused
    with pytest.raises(ChunkRejected):
        asm.add(robot_map(rng, seq=5, robot="c"))


def test_assembler_takes_only_maps():
    with pytest.raises(TypeError, match="PoseUpdate"):
        Assembler().add(pose_update())


def test_seq_filter():
    f = SeqFilter()
    assert f.accept(pose_update(1)) and f.accept(pose_update(5))
    assert not f.accept(pose_update(5)) and not f.accept(pose_update(4))
    assert f.accept(pose_update(0, robot="r2"))
    assert f.accept(pose_update(0, session="s2"))  # restarted
    assert not f.accept(pose_update(6, session="s1"))  # late message of the old session
    assert f.accept(pose_update(1, session="s2"))
    assert f.rejected == {"stale": 2, "stale_session": 1}


def test_seq_filter_check_raises_naming_the_field():
    f = SeqFilter()
    f.check(pose_update(3))
    with pytest.raises(ChunkRejected, match="seq: stale 2 of r1, 3 already seen"):
        f.check(pose_update(2))
    f.check(pose_update(0, session="s2"))
    with pytest.raises(ChunkRejected, match="session: stale session 's1'"):
        f.check(pose_update(4))
    assert f.rejected == {"stale": 1, "stale_session": 1}


def test_split_fused_map_takes_only_fused_maps():
    rng = np.random.default_rng(15)
    assert len(codec.split_fused_map(fused_map(rng, m=30), max_elements=10)) == 3
    with pytest.raises(TypeError, match="RobotMap"):
        codec.split_fused_map(robot_map(rng))


def test_stored_maps_hold_a_whole_map():
    rng = np.random.default_rng(16)
    whole = robot_map(rng, n=5000, k=8)
    blob = codec.encode_stored_map(whole)
    assert_robot_maps_equal(codec.decode_stored_map(blob), whole)
    rejects(blob, "n_elements: 5000 out of range")  # never valid on the wire
    with pytest.raises(WireFormatError, match="kind: expected robot_map, got pose"):
        codec.decode_stored_map(samples()[0])
    with pytest.raises(WireFormatError, match=r"seg: .* bytes, expected"):
        codec.decode_stored_map(repack(blob, n_elements=4999))
    with pytest.raises(TypeError, match="PoseUpdate"):
        codec.encode_stored_map(pose_update())


# -- encode refusals --------------------------------------------------------------------------


def test_encode_refuses_an_oversized_chunk():
    msg = robot_map(np.random.default_rng(12), n=MAX_CHUNK_ELEMENTS + 1)  # a valid *assembled* map
    with pytest.raises(
        WireFormatError, match=f"seg: {MAX_CHUNK_ELEMENTS + 1} elements in one message, at most"
    ):
        encode(msg)


def test_encode_refuses_values_beyond_the_wire_dtype():
    msg = robot_map(np.random.default_rng(13), n=3, hits=np.array([1, 2**33, 3]))
    with pytest.raises(WireFormatError, match=r"hits: .* do not fit the wire dtype uint32"):
        encode(msg)


def test_encode_takes_only_messages():
    with pytest.raises(TypeError, match="RobotStatus"):
        encode(statuses()[0])


# -- decode refusals, each naming what is wrong -----------------------------------------------


def test_refuses_non_bytes_and_oversized_payloads(monkeypatch):
    rejects("hello", "payload: expected bytes, got str")
    rejects(None, "payload: expected bytes, got NoneType")
    assert decode(bytearray(samples()[0])).robot == "r1"
    assert decode(memoryview(samples()[0])).robot == "r1"

    def never(*a, **k):
        raise AssertionError("unpacked an oversized payload")

    monkeypatch.setattr(codec.msgpack, "unpackb", never)
    rejects(b"\x00" * (codec.MAX_MESSAGE_BYTES + 1), f"payload: {codec.MAX_MESSAGE_BYTES + 1} bytes, at most")


@pytest.mark.parametrize(
    "data",
    [
        b"",
        b"\xc1",  # never used
        b"\x92\x01",  # truncated array
        b"\x81\xa1a",  # truncated map
        b"\x80\x00",  # extra data
        b"\x91" * 5000 + b"\x00",  # nested too deep
        b"\xa2\xff\xfe",  # invalid utf-8
        b"\x81\x01\x02",  # int map key
        b"\xd4\x01\x00",  # ext type
        b"\xd6\xff\x00\x00\x00\x00",  # timestamp ext
        b"\xdb\x00\x00\x10\x00" + b"a" * 10,  # str longer than its limit (and than the data)
        b"\xdd\x00\x01\x00\x00",  # array longer than its limit
    ],
)
def test_refuses_malformed_msgpack(data):
    rejects(data, "payload: malformed msgpack")


@pytest.mark.parametrize("obj, what", [([1, 2], "list"), (3, "int"), (None, "NoneType"), (b"x", "bytes")])
def test_refuses_a_top_level_that_is_not_a_map(obj, what):
    rejects(msgpack.packb(obj), f"payload: expected a msgpack map at the top level, got {what}")


@pytest.mark.parametrize(
    "schema, match",
    [
        (8, "schema: unknown schema version 8, this build speaks 7 \\(and reads 2, 3, 4, 5, 6, 7\\)"),
        (1, "schema: unknown schema version 1, this build speaks 7"),
        (0, "schema: unknown schema version 0"),
        ("1", "schema: unknown schema version '1'"),
        (True, "schema: unknown schema version True"),
        (..., "schema: missing"),
    ],
)
def test_refuses_other_schema_versions(schema, match):
    rejects(repack(samples()[0], schema=schema), match)


def test_a_schema_2_pose_is_read_with_an_empty_status_and_a_status_travels_in_schema_3():
    """Agents of the build before send schema 2: their poses still decode (no status); the
    status of a schema-3 pose comes through; a schema-2 pose with a status field is refused
    (each schema has its exact key set), as is a status that is not named finite numbers."""
    pose = PoseUpdate("r1", "s1", 3, 10.0, np.array([1.0, 2.0, 0.5]), {"laser_unusable_last": 12.0})
    data = codec.encode(pose)
    back = codec.decode(data)
    assert back.status == {"laser_unusable_last": 12.0}
    fields = unpacked(data)
    del fields["status"]
    old = codec.decode(msgpack.packb(dict(fields, schema=2), use_bin_type=True))
    assert old.status == {} and np.array_equal(old.pose, pose.pose)
    rejects(repack(data, schema=2), "'status': unknown field of pose")
    rejects(repack(data, status={"x": float("nan")}), "status\\[x\\]")
    rejects(repack(data, status={str(i): 1.0 for i in range(33)}), "status: expected a dict of at most 32")


def test_refuses_unknown_kind_and_unexpected_kind():
    pose = samples()[0]
    rejects(repack(pose, kind="bogus"), "kind: unknown kind 'bogus'")
    rejects(repack(pose, kind=...), "kind: missing")
    rejects(repack(pose, kind=1), "kind: unknown kind 1")
    rejects(pose, "kind: expected robot_map, got pose", expect=RobotMap)
    rejects(samples()[2], "kind: expected pose, got fused_map", expect=PoseUpdate)
    with pytest.raises(TypeError, match="expect"):
        decode(pose, expect=RobotStatus)


@pytest.mark.parametrize("i", [0, 1, 2, 3, 4])
def test_refuses_missing_and_unknown_fields(i):
    data = samples()[i]
    kind = unpacked(data)["kind"]
    for name in codec.KEYS[kind]:
        rejects(repack(data, **{name: ...}), f"^{name}: missing field of {kind}")
    rejects(repack(data, colour="red"), "'colour': unknown field")


@pytest.mark.parametrize(
    "i, field, value, match",
    [
        (0, "seq", "5", "seq: expected an integer, got str"),
        (0, "seq", True, "seq: expected an integer, got bool"),
        (0, "seq", 1.0, "seq: expected an integer, got float"),
        (0, "seq", -1, r"seq: -1 out of range"),
        (0, "seq", 2**64 - 1, r"seq: .* out of range"),
        (0, "stamp_s", "now", "stamp_s: expected a number, got str"),
        (0, "stamp_s", False, "stamp_s: expected a number, got bool"),
        (0, "stamp_s", float("nan"), r"stamp_s: not finite"),
        (0, "stamp_s", -1.0, r"stamp_s: -1.0 out of range"),
        (0, "robot", 5, "robot: expected a string, got int"),
        (0, "robot", "a/b", "robot: expected 1-64 characters"),
        (0, "robot", "", "robot: expected 1-64 characters"),
        (0, "session", None, "session: expected a string, got NoneType"),
        (0, "pose", [1.0, 2.0, 3.0], "pose: expected bytes, got list"),
        (0, "pose", None, "pose: expected bytes, got NoneType"),
        (1, "chunk", 1, r"chunk: 1 out of range \[0, 0\]"),
        (1, "n_chunks", 0, "n_chunks: 0 out of range"),
        (1, "n_chunks", 65, "n_chunks: 65 out of range"),
        (1, "n_elements", -1, r"n_elements: -1 out of range \[0, 2048\]"),
        (1, "n_elements", 2**40, "n_elements: 1099511627776 out of range"),
        (1, "n_elements", MAX_CHUNK_ELEMENTS + 1, "n_elements: 2049 out of range"),
        (1, "n_elements", 7, r"seg: 96 bytes, expected 112 \(shape \(7, 2, 2\) of <f4\)"),
        (1, "n_particles", 0, r"particle_weights: 24 bytes, expected 0"),
        (1, "n_particles", "3", "n_particles: expected an integer"),
        (1, "prior", None, "prior and prior_sigma: give both or neither"),
        (1, "prior_sigma", b"\x00" * 23, "prior_sigma: 23 bytes, expected 24"),
        (2, "robots", {}, "robots: expected a list, got dict"),
        (2, "robots", [1], r"robots\[0\]: expected a map, got int"),
        (2, "extra", [], "extra: expected a map, got list"),
        (2, "extra", {"a": "b"}, r"extra\[a\]: expected a number"),
        (2, "extra", {"a": float("inf")}, r"extra\[a\]: not finite"),
        (2, "n_prov", 4, "prov_robot: .* bytes, expected 8"),
        (2, "n_segments", 6, r"seg: 80 bytes, expected 96"),
        (2, "version", -3, "version: -3 out of range"),
        (2, "server", "x" * 65, "server: expected 1-64 characters"),
    ],
)
def test_refuses_wrong_types_counts_and_values(i, field, value, match):
    rejects(repack(samples()[i], **{field: value}), match)


def with_array(data: bytes, field: str, fill) -> bytes:
    """``data`` with array ``field`` overwritten (same dtype and length) by ``fill(array)``."""
    buf = unpacked(data)[field]
    arr = np.frombuffer(buf, codec.WIRE_DTYPES[field]).copy()
    fill(arr)
    return repack(data, **{field: arr.tobytes()})


def set_at(i, value):
    def fill(a):
        a.flat[i] = value

    return fill


@pytest.mark.parametrize(
    "i, field, fill, match",
    [
        (0, "pose", set_at(2, np.nan), "pose: contains NaN or inf"),
        (0, "pose", set_at(0, 2e5), "pose: values out of range"),
        (1, "seg", set_at(5, np.inf), "seg: contains NaN or inf"),
        (1, "seg", set_at(0, -1e6), "seg: values out of range"),
        (1, "particle_poses", set_at(4, -np.inf), "particle_poses: contains NaN or inf"),
        (1, "particle_weights", set_at(0, -0.1), "particle_weights: values out of range"),
        (1, "particle_weights", set_at(slice(None), 0.5), "particle_weights: sum 1.500000 exceeds 1"),
        (1, "trust", set_at(1, 1.5), "trust: values out of range"),
        (1, "members", set_at(2, 0), "members: values out of range"),
        (1, "members", set_at(2, 8), "members: values out of range"),  # bit 3 of 3 particles
        (1, "members", set_at(2, 2**63), "members: values out of range"),
        (1, "element", set_at(0, -4), "element: values out of range"),
        (2, "prov_offsets", set_at(1, 0), "prov_offsets: must start at 0 and increase"),
        (2, "prov_offsets", set_at(0, 1), "prov_offsets: must start at 0 and increase"),
        (2, "prov_robot", set_at(0, 3), "prov_robot: values out of range"),
        (2, "support", set_at(0, 0), "support: values out of range"),
    ],
)
def test_refuses_bad_array_values(i, field, fill, match):
    rejects(with_array(samples()[i], field, fill), match)


def test_errors_inside_the_robot_table_name_the_entry():
    data = samples()[2]
    robots = unpacked(data)["robots"]
    robots[1]["transform"] = np.array([0.0, np.nan, 0.0]).tobytes()
    rejects(repack(data, robots=robots), r"robots\[1\]\.transform: contains NaN or inf")
    robots = unpacked(data)["robots"]
    robots[2]["online"] = 1
    rejects(repack(data, robots=robots), r"robots\[2\]\.online: expected a bool, got int")
    robots = unpacked(data)["robots"]
    robots[0]["status"] = "lost"
    rejects(repack(data, robots=robots), r"robots\[0\]\.status: 'lost' is not one of")
    robots = unpacked(data)["robots"]
    del robots[0]["sigma"]
    rejects(repack(data, robots=robots), r"robots\[0\]\.sigma: missing field of robot_status")
    robots = unpacked(data)["robots"]
    robots[1] = robots[0]
    rejects(repack(data, robots=robots), "robots: duplicate robot ids")


def test_a_chunk_over_the_limit_is_refused_on_decode():
    big = robot_map(np.random.default_rng(14), n=MAX_CHUNK_ELEMENTS + 1)
    fields = {"schema": SCHEMA_VERSION, "kind": "robot_map", **codec._encode_robot_map(big)}
    rejects(msgpack.packb(fields), "n_elements: 2049 out of range")


def test_unexpected_errors_still_leave_as_wire_format_errors(monkeypatch):
    def broken(_reader):
        raise KeyError("oops")

    monkeypatch.setitem(codec._DECODERS, "pose", broken)
    with pytest.raises(WireFormatError, match=f"payload: {codec.UNEXPECTED} KeyError"):
        decode(samples()[0])
