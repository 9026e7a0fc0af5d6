"""Keyframe scans on the wire (schema 7): a map with a graph carries the thinned scans of some of
its keyframes (int16 centimetres in each keyframe's frame), chunk 0 only; schema-6 maps are read
without; bad scans are refused naming the field; the receiver keeps every keyframe's scan with
the map (RobotMap.with_scans_of)."""

import dataclasses

import msgpack
import numpy as np
import pytest

from shared import codec
from shared.messages import MAX_SCAN_POINTS, RobotMap, WireFormatError
from tests.shared.test_graph_wire import graph_map


def with_scans(m: RobotMap, ids: list[int], seed: int = 0) -> RobotMap:
    rng = np.random.default_rng(seed)
    pts = [rng.uniform(-30, 30, (int(n), 2)) for n in rng.integers(20, 64, len(ids))]
    return dataclasses.replace(
        m, scan_id=np.array(ids, np.int64), scan_count=np.array([len(p) for p in pts]),
        scan_xy=np.concatenate(pts),
    )  # fmt: skip


def test_scans_round_trip_in_centimetres_in_chunk_0():
    m = with_scans(graph_map(), [0, 30, 390])
    chunks = codec.split(m)
    assert chunks[0].has_scans and not any(c.has_scans for c in chunks[1:])
    back = codec.join([codec.decode(codec.encode(c)) for c in chunks])
    np.testing.assert_array_equal(back.scan_id, m.scan_id)
    np.testing.assert_array_equal(back.scan_count, m.scan_count)
    np.testing.assert_allclose(back.scan_xy, m.scan_xy, atol=0.005 + 1e-9)  # (half a centimetre)
    scans = back.scans()
    assert sorted(scans) == [0, 30, 390] and len(scans[30]) == m.scan_count[1]
    assert not graph_map().has_scans and graph_map().scans() == {}


def test_a_schema_6_map_is_read_without_scans():
    fields = msgpack.unpackb(codec.encode(graph_map(n=10)), raw=False)
    for name in ("n_scans", "n_scan_points", "scan_id", "scan_count", "scan_cm"):
        del fields[name]
    old = codec.decode(msgpack.packb(dict(fields, schema=6), use_bin_type=True))
    assert old.has_graph and not old.has_scans
    with pytest.raises(WireFormatError, match="n_scans: missing field of robot_map"):
        codec.decode(msgpack.packb(dict(fields, schema=7), use_bin_type=True))


@pytest.mark.parametrize(
    "change, match",
    [
        (lambda m: {"scan_id": m.scan_id + 1}, "scan_id: names a keyframe not in kf_id"),
        (lambda m: {"scan_id": m.scan_id[::-1].copy()}, "scan_id: must increase"),
        (lambda m: {"scan_count": m.scan_count + 1}, "scan_xy: expected shape"),
        (lambda m: {"scan_xy": None}, "scan_xy: missing"),
        (lambda m: {"scan_xy": m.scan_xy + 400.0}, "scan_xy"),
        (lambda m: {"scan_count": np.full(3, MAX_SCAN_POINTS + 1),
                    "scan_xy": np.zeros((3 * MAX_SCAN_POINTS + 3, 2))}, "scan_count"),
        (lambda m: dict.fromkeys(("kf_id", "kf_stamp", "kf_pose", "edge_ids", "edge_z", "edge_info")),
         "scan_id: keyframe scans need the graph"),
    ],
)  # fmt: skip
def test_bad_scans_are_refused_by_name(change, match):
    m = with_scans(graph_map(n=10), [0, 30, 390])
    fields = {f.name: getattr(m, f.name) for f in dataclasses.fields(m)} | change(m)
    if fields["kf_id"] is None:
        fields["anchor"] = fields["graph_seq"] = None
    with pytest.raises(WireFormatError, match=match):
        RobotMap(**fields)


def test_the_receiver_keeps_every_keyframes_scan_of_the_session():
    """A map carries the scans of its new keyframes (and a few old ones): what the receiver keeps
    is the whole — those it had of keyframes still in the graph, and the new ones; a keyframe gone
    from the graph takes its scan with it; another session's scans are not taken."""
    first = with_scans(graph_map(n=10, seq=1), [0, 10, 20], seed=1)
    second = with_scans(graph_map(n=10, seq=2), [20, 30], seed=2)
    kept = second.with_scans_of(first)
    assert kept.scan_id.tolist() == [0, 10, 20, 30]
    np.testing.assert_array_equal(kept.scans()[10], first.scans()[10])
    np.testing.assert_array_equal(kept.scans()[20], second.scans()[20])  # (the newer copy)
    fewer = dataclasses.replace(
        graph_map(n=10, seq=3), kf_id=np.arange(10, 400, 10), kf_stamp=np.linspace(0, 12, 39),
        kf_pose=np.zeros((39, 3)), edge_ids=np.array([[10, 20]]), edge_z=np.zeros((1, 3)),
        edge_info=np.array([[1.0, 0, 0, 1, 0, 1]]), anchor=np.full(10, 10),
    )  # fmt: skip
    assert fewer.with_scans_of(kept).scan_id.tolist() == [10, 20, 30]
    other = dataclasses.replace(second, session="s2")
    assert other.with_scans_of(first).scan_id.tolist() == [20, 30]
    assert second.with_scans_of(None) is second
    assert graph_map(n=10, seq=4).with_scans_of(kept).scan_id.tolist() == [0, 10, 20, 30]
