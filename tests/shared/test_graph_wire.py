"""A robot map's pose graph on the wire (schema 5): keyframes, edges with their information, each
element's keyframe; chunk 0 carries the graph, every chunk its rows' anchors; schema-4 maps are
still read; a bad graph is refused naming the field. The server's answer of where the fleet's
graph puts a robot (RobotPath)."""

import msgpack
import numpy as np
import pytest

from shared import codec
from shared.geometry import compose, inverse
from shared.messages import RobotMap, RobotPath, WireFormatError, info_matrices, info_upper


def graph_map(n: int = 5000, k: int = 40, seq: int = 1) -> RobotMap:
    rng = np.random.default_rng(1)
    seg = rng.uniform(-20, 20, (n, 2, 2))
    kf_id = np.arange(0, 10 * k, 10, dtype=np.int64)
    a = np.r_[np.arange(k - 1), [0, 1]]  # the chain and two loops
    b = np.r_[np.arange(1, k), [k - 1, k - 2]]
    info = np.zeros((len(a), 3, 3))
    info[:, [0, 1, 2], [0, 1, 2]] = [2500.0, 2500.0, 3000.0]
    info[:, 0, 1] = info[:, 1, 0] = 100.0
    return RobotMap(
        "r1", "s1", seq, 12.5, 0, 1, np.ones(1), np.zeros((1, 3)), seg, np.arange(n, dtype=np.int64),
        np.ones(n, np.int64), np.full(n, 0.9), np.full(n, 3, np.int64), np.full(n, 7, np.int64),
        kf_id=kf_id, kf_stamp=np.linspace(0.0, 12.0, k), kf_pose=rng.normal(0, 3, (k, 3)),
        edge_ids=np.column_stack([kf_id[a], kf_id[b]]), edge_z=rng.normal(0, 0.5, (len(a), 3)),
        edge_info=info_upper(info), anchor=rng.choice(kf_id, n), graph_seq=seq,
    )  # fmt: skip


def test_the_graph_round_trips_and_chunk_0_alone_carries_it():
    m = graph_map()
    chunks = codec.split(m)
    assert len(chunks) == 3
    assert chunks[0].has_graph and not chunks[1].has_graph and not chunks[2].has_graph
    assert sum(len(c.anchor) for c in chunks) == len(m.seg)  # every chunk: its rows' anchors
    back = codec.join([codec.decode(codec.encode(c)) for c in chunks])
    for name in ("kf_id", "kf_stamp", "kf_pose", "edge_ids", "edge_z", "anchor"):
        np.testing.assert_array_equal(getattr(back, name), getattr(m, name))
    # information travels as float32: seven digits
    np.testing.assert_allclose(info_matrices(back.edge_info), info_matrices(m.edge_info), rtol=1e-6)
    np.testing.assert_allclose(back.seg, m.seg, atol=1e-5)


def test_a_schema_4_map_is_read_without_a_graph():
    """Agents of the build before send schema 4 (no graph fields): read as a map that moves rigidly."""
    m = graph_map(n=10)
    plain = RobotMap(*(getattr(m, f) for f in ("robot", "session", "seq", "stamp_s", "chunk", "n_chunks",
                                                "particle_weights", "particle_poses", "seg", "element",
                                                "members", "trust", "hits", "age")))  # fmt: skip
    fields = msgpack.unpackb(codec.encode(plain), raw=False)
    for name in ("n_keyframes", "n_edges", "kf_id", "kf_stamp", "kf_pose", "edge_ids", "edge_z", "edge_info",
                 "anchor", "graph_seq", "joined", "n_scans", "n_scan_points", "scan_id", "scan_count",
                 "scan_cm"):  # fmt: skip
        del fields[name]
    old = codec.decode(msgpack.packb(dict(fields, schema=4), use_bin_type=True))
    assert not old.has_graph and old.anchor is None and len(old.seg) == 10
    with pytest.raises(WireFormatError, match="n_keyframes: missing field of robot_map"):
        codec.decode(msgpack.packb(dict(fields, schema=5), use_bin_type=True))


def replaced(m: RobotMap, **fields) -> dict:
    names = [f for f in RobotMap.__dataclass_fields__]
    return {**{f: getattr(m, f) for f in names}, **fields}


@pytest.mark.parametrize(
    "change, match",
    [
        (lambda m: {"edge_ids": np.where(m.edge_ids == 390, 391, m.edge_ids)}, "edge_ids: an edge names"),
        (lambda m: {"edge_ids": np.repeat(m.edge_ids[:, :1], 2, axis=1)}, "edge_ids: an edge joins"),
        (lambda m: {"anchor": np.full(len(m.seg), 5)}, "anchor: names a keyframe not in kf_id"),
        (lambda m: {"anchor": None}, "anchor: required with a graph"),
        (lambda m: {"graph_seq": None}, "graph_seq: required with a graph"),
        (lambda m: {"graph_seq": m.seq + 1}, "graph_seq: 2 out of range"),
        (lambda m: {"kf_id": m.kf_id[::-1].copy()}, "kf_id: must increase"),
        (lambda m: {"edge_z": None}, "edge_z: missing"),
        (lambda m: {"chunk": 1, "n_chunks": 2}, "kf_id: only chunk 0 carries the graph"),
        (lambda m: {"edge_info": -m.edge_info}, "edge_info: not positive semi-definite"),
        (lambda m: {"kf_pose": np.full((len(m.kf_id), 3), np.nan)}, "kf_pose: contains NaN"),
    ],
)  # fmt: skip
def test_a_bad_graph_is_refused_naming_the_field(change, match):
    m = graph_map(n=20)
    with pytest.raises(WireFormatError, match=match):
        RobotMap(**replaced(m, **change(m)))


def robot_path() -> RobotPath:
    local = np.array([[0.0, 0.0, 0.0], [2.0, 0.0, 0.0], [4.0, 0.0, 0.5]])
    moved = np.array([[1.0, 1.0, 0.0], [3.0, 1.2, 0.1], [5.0, 1.0, 0.6]])
    stamps = np.array([0.0, 2.0, 1.0])  # (out of order: a log's clock may step back)
    return RobotPath("srv", "s9", 7, "r1", "s1", stamps, local, moved)


def test_a_robot_path_moves_a_robots_poses_with_its_keyframes():
    """RobotPath.apply: each pose moves with the last keyframe at or before its time (a log's
    clock that steps back is taken in time order); the message round-trips."""
    local = np.array([[0.0, 0.0, 0.0], [2.0, 0.0, 0.0], [4.0, 0.0, 0.5]])
    moved = np.array([[1.0, 1.0, 0.0], [3.0, 1.2, 0.1], [5.0, 1.0, 0.6]])
    p = RobotPath(
        "srv", "s9", 7, "r1", "s1", np.array([0.0, 2.0, 1.0]), local, moved
    )  # (stamps out of order)
    back = codec.decode(codec.encode(p), expect=RobotPath)
    poses = np.array([[0.5, 0.0, 0.0], [2.5, 0.0, 0.0], [4.5, 0.1, 0.5]])
    out = back.apply(np.array([0.5, 1.5, 2.5]), poses)
    # 0.5 s: keyframe 0; 1.5 s: the keyframe stamped 1.0 (the third); 2.5 s: the one stamped 2.0
    for i, k in enumerate([0, 2, 1]):
        np.testing.assert_allclose(
            out[i], compose(compose(moved[k], inverse(local[k])), poses[i]), atol=1e-12
        )
    with pytest.raises(WireFormatError, match="local: expected shape"):
        RobotPath("srv", "", 1, "r1", "s1", np.zeros(2), np.zeros((3, 3)), np.zeros((2, 3)))
