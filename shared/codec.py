"""Wire codec: messages <-> msgpack bytes. The only module that imports msgpack.

A payload is one msgpack map ``{"schema": SCHEMA_VERSION, "kind": ..., <fields>}``. Arrays travel as raw
little-endian bytes with a fixed dtype per field (``WIRE_DTYPES``) beside the element counts they
are checked against, so a short or long buffer is an error, never a silent reshape. Decoding trusts
nothing: the size before unpacking, msgpack's own limits, the exact key set, python types, buffer
lengths, then the message's validation (shapes, finite values, ranges; ``shared/messages.py``).

Maps travel as chunks of at most ``MAX_CHUNK_ELEMENTS`` elements: :func:`robot_map_chunks`,
:func:`fused_map_chunks`, :class:`Assembler` and :class:`SeqFilter` live in ``shared/chunks.py``
(pure, no msgpack) and are re-exported here, so one import serves a sender or a receiver.
:func:`encode_stored_map` / :func:`decode_stored_map` are the same format for a whole robot map at
rest (the server's state), with the whole-map limits instead of the chunk limits.
"""

from __future__ import annotations

from dataclasses import dataclass

import msgpack
import numpy as np

from shared.chunks import (
    Assembler,
    ChunkRejected,
    SeqFilter,
    fused_map_chunks,
    join,
    robot_map_chunks,
    split,
    split_fused_map,
)
from shared.messages import (
    MAX_CHUNK_ELEMENTS,
    MAX_GRAPH_EDGES,
    MAX_KEYFRAMES,
    MAX_MAP_ELEMENTS,
    MAX_PARTICLES,
    MAX_ROBOTS,
    MAX_SCANS_POINTS,
    MAX_VERTICES,
    SCHEMA_VERSION,
    FreeSpace,
    FusedFree,
    FusedMap,
    Message,
    PoseUpdate,
    RobotMap,
    RobotPath,
    RobotStatus,
    WireFormatError,
)

MAX_MESSAGE_BYTES = 1 << 20  # 1 MiB; a full robot-map chunk is ~90 KB (zenoh drops big puts under load)
MAX_STORED_BYTES = 16 << 20  # a whole stored robot map: MAX_MAP_ELEMENTS × 44 bytes ≈ 5.8 MB
MAX_STR_BYTES = 256  # longest string on the wire: ids and extra keys are at most 64 characters
MAX_MAP_KEYS = 64  # largest msgpack map: the top level (~20 keys) or ``extra`` (32 entries)

__all__ = [
    "KINDS", "MAX_MESSAGE_BYTES", "WIRE_DTYPES", "Assembler", "ChunkRejected", "SeqFilter",
    "decode", "decode_stored_map", "encode", "encode_stored_map", "fused_map_chunks", "join",
    "robot_map_chunks", "split", "split_fused_map",
]  # fmt: skip

KINDS = {
    RobotMap: "robot_map", PoseUpdate: "pose", FusedMap: "fused_map", FreeSpace: "free_space",
    FusedFree: "fused_free", RobotPath: "robot_path",
}  # fmt: skip

# Fixed wire dtype of every array field, by field name (the same name has the same dtype everywhere).
WIRE_DTYPES = {
    "particle_weights": "<f8", "particle_poses": "<f8", "prior": "<f8", "prior_sigma": "<f8",
    "pose": "<f8", "transform": "<f8", "sigma": "<f8",
    "seg": "<f4", "trust": "<f4",  # float32: 8 µm at 100 m, 8 mm at the 100 km coordinate limit
    "element": "<i8", "members": "<u8", "hits": "<u4", "age": "<u4",
    # a robot's pose graph: keyframe ids (scan indices: 3 years of a 40 Hz laser) in uint32, poses
    # in float64 (the keyframes' are what the server optimizes from), information in float32
    # (seven digits of a weight)
    "kf_id": "<u4", "kf_stamp": "<f8", "kf_pose": "<f8", "edge_ids": "<u4", "edge_z": "<f8",
    "edge_info": "<f4", "anchor": "<u4", "local": "<f8",
    # keyframe scans: points in int16 centimetres in the keyframe's frame (±327 m)
    "scan_id": "<u4", "scan_count": "<u2", "scan_cm": "<i2",
    "support": "<u4", "prov_offsets": "<u4", "prov_robot": "<u2",
    # free space: a robot's views in centimetres around each view's pose (±327 m), the fused
    # polygons in float32 metres
    "view_pose": "<f4", "ring_offsets": "<u4", "ring_view": "<u4", "vertices_cm": "<i2", "wall_bits": "<u1",
    "ring_hole": "<u1", "vertices": "<f4", "walls": "<f4",
}  # fmt: skip

# The exact key set of each map on the wire (besides "schema" and "kind" at the top level).
KEYS = {
    "robot_map": (
        "robot", "session", "seq", "stamp_s", "chunk", "n_chunks", "n_particles", "n_elements",
        "particle_weights", "particle_poses", "seg", "element", "members", "trust", "hits", "age",
        "prior", "prior_sigma", "n_keyframes", "n_edges", "kf_id", "kf_stamp", "kf_pose", "edge_ids",
        "edge_z", "edge_info", "anchor", "graph_seq", "joined", "n_scans", "n_scan_points", "scan_id",
        "scan_count", "scan_cm",
    ),
    "pose": ("robot", "session", "seq", "stamp_s", "pose", "status"),
    "fused_map": (
        "server", "version", "stamp_s", "chunk", "n_chunks", "robots", "n_segments", "n_prov",
        "seg", "support", "prov_offsets", "prov_robot", "extra", "session",
    ),
    "free_space": (
        "robot", "session", "seq", "stamp_s", "n_views", "n_rings", "n_vertices", "rings_from", "view_pose",
        "ring_offsets", "ring_view", "vertices_cm", "wall_bits",
    ),
    "fused_free": (
        "server", "session", "version", "map_version", "stamp_s", "tolerance_m", "n_rings", "n_vertices",
        "n_walls", "ring_offsets", "ring_hole", "vertices", "walls",
    ),
    "robot_path": (
        "server", "session", "version", "robot", "robot_session", "n_keyframes", "kf_stamp", "local", "pose",
    ),
    "robot_status": (
        "robot", "status", "online", "session", "map_seq", "n_elements", "transform", "sigma", "pose",
        "pose_stamp_s", "aligned_at_s",
    ),
}  # fmt: skip


# What schemas 2 to 6 carried: their messages are still decoded (6 had no keyframe scans; 5 no
# joined flag; 4 no robot graph; 3 no free space; 2 no pose status).
_GRAPH_KEYS = (
    "n_keyframes", "n_edges", "kf_id", "kf_stamp", "kf_pose", "edge_ids", "edge_z", "edge_info", "anchor",
    "graph_seq",
)  # fmt: skip
_SCAN_KEYS = ("n_scans", "n_scan_points", "scan_id", "scan_count", "scan_cm")
KEYS_SCHEMA_6 = dict(KEYS, robot_map=tuple(k for k in KEYS["robot_map"] if k not in _SCAN_KEYS))
KEYS_SCHEMA_5 = dict(KEYS_SCHEMA_6, robot_map=tuple(k for k in KEYS_SCHEMA_6["robot_map"] if k != "joined"))
KEYS_SCHEMA_4 = dict(
    {k: v for k, v in KEYS_SCHEMA_5.items() if k != "robot_path"},
    robot_map=tuple(k for k in KEYS_SCHEMA_5["robot_map"] if k not in _GRAPH_KEYS),
)
KEYS_SCHEMA_3 = {k: v for k, v in KEYS_SCHEMA_4.items() if k not in ("free_space", "fused_free")}
KEYS_SCHEMA_2 = dict(KEYS_SCHEMA_3, pose=tuple(k for k in KEYS["pose"] if k != "status"))
_KEYS_BY_SCHEMA = {
    2: KEYS_SCHEMA_2, 3: KEYS_SCHEMA_3, 4: KEYS_SCHEMA_4, 5: KEYS_SCHEMA_5, 6: KEYS_SCHEMA_6,
    SCHEMA_VERSION: KEYS,
}  # fmt: skip


@dataclass(frozen=True)
class _Limits:
    what: str
    elements: int  # per message
    bytes: int  # per payload


_WIRE = _Limits("message", MAX_CHUNK_ELEMENTS, MAX_MESSAGE_BYTES)
_STORED = _Limits("stored map", MAX_MAP_ELEMENTS, MAX_STORED_BYTES)

# Message text that marks an exception the decoder did not expect: a codec bug (the fuzz tests look for it).
UNEXPECTED = "unexpected decoder error"


# -- encode -----------------------------------------------------------------------------------


def encode(msg: Message) -> bytes:
    """``msg`` as msgpack bytes; refuses (WireFormatError) a chunk over ``MAX_CHUNK_ELEMENTS``."""
    return _encode(msg, _WIRE)


def encode_stored_map(msg: RobotMap) -> bytes:
    """A whole robot map (up to ``MAX_MAP_ELEMENTS``) as bytes for storage at rest, never for the bus."""
    if not isinstance(msg, RobotMap):
        raise TypeError(f"encode_stored_map: expected a RobotMap, got {type(msg).__name__}")
    return _encode(msg, _STORED)


def _encode(msg: Message, limits: _Limits) -> bytes:
    kind = KINDS.get(type(msg))
    if kind is None:
        raise TypeError(f"encode: expected one of {[k.__name__ for k in KINDS]}, got {type(msg).__name__}")
    if kind in ("robot_map", "fused_map") and len(msg.seg) > limits.elements:
        raise WireFormatError(f"seg: {len(msg.seg)} elements in one {limits.what}, at most {limits.elements}")
    fields = {"schema": SCHEMA_VERSION, "kind": kind, **_ENCODERS[kind](msg)}
    data = msgpack.packb(fields, use_bin_type=True)
    if len(data) > limits.bytes:
        raise WireFormatError(f"payload: {len(data)} bytes, at most {limits.bytes} in one {limits.what}")
    return data


def _wire(name: str, value: np.ndarray | None) -> bytes | None:
    if value is None:
        return None
    dtype = np.dtype(WIRE_DTYPES[name])
    arr = np.asarray(value)
    if dtype.kind in "iu" and arr.size:
        info = np.iinfo(dtype)
        if arr.min() < info.min or arr.max() > info.max:
            raise WireFormatError(
                f"{name}: values [{arr.min()}, {arr.max()}] do not fit the wire dtype {dtype}"
            )
    return arr.astype(dtype, copy=False).tobytes()


def _arrays(obj: object, *names: str) -> dict:
    return {name: _wire(name, getattr(obj, name)) for name in names}


def _encode_robot_map(m: RobotMap) -> dict:
    return {
        "robot": m.robot, "session": m.session, "seq": int(m.seq), "stamp_s": float(m.stamp_s),
        "chunk": int(m.chunk), "n_chunks": int(m.n_chunks),
        "n_particles": m.n_particles, "n_elements": len(m.seg),
        **_arrays(m, "particle_weights", "particle_poses", "seg", "element", "members", "trust", "hits",
                  "age", "prior", "prior_sigma", "kf_id", "kf_stamp", "kf_pose", "edge_ids", "edge_z",
                  "edge_info", "anchor"),
        "n_keyframes": 0 if m.kf_id is None else len(m.kf_id),
        "graph_seq": None if m.graph_seq is None else int(m.graph_seq),
        "n_edges": 0 if m.edge_ids is None else len(m.edge_ids),
        "joined": bool(m.joined),
        **_arrays(m, "scan_id", "scan_count"),
        "scan_cm": None if m.scan_xy is None else _wire("scan_cm", np.rint(np.asarray(m.scan_xy) * 100.0)),
        "n_scans": 0 if m.scan_id is None else len(m.scan_id),
        "n_scan_points": 0 if m.scan_xy is None else len(m.scan_xy),
    }  # fmt: skip


def _encode_pose(m: PoseUpdate) -> dict:
    return {"robot": m.robot, "session": m.session, "seq": int(m.seq), "stamp_s": float(m.stamp_s),
            **_arrays(m, "pose"), "status": {k: float(v) for k, v in m.status.items()}}  # fmt: skip


def _encode_status(r: RobotStatus) -> dict:
    return {
        "robot": r.robot, "status": r.status, "online": r.online, "session": r.session,
        "map_seq": int(r.map_seq), "n_elements": int(r.n_elements),
        **_arrays(r, "transform", "sigma", "pose"), "pose_stamp_s": float(r.pose_stamp_s),
        "aligned_at_s": None if r.aligned_at_s is None else float(r.aligned_at_s),
    }  # fmt: skip


def _encode_fused_map(m: FusedMap) -> dict:
    return {
        "server": m.server, "version": int(m.version), "stamp_s": float(m.stamp_s),
        "chunk": int(m.chunk), "n_chunks": int(m.n_chunks),
        "robots": [_encode_status(r) for r in m.robots],
        "n_segments": len(m.seg), "n_prov": len(m.prov_robot),
        **_arrays(m, "seg", "support", "prov_offsets", "prov_robot"),
        "extra": {k: float(v) for k, v in m.extra.items()}, "session": m.session,
    }  # fmt: skip


def _encode_free_space(m: FreeSpace) -> dict:
    return {
        "robot": m.robot, "session": m.session, "seq": int(m.seq), "stamp_s": float(m.stamp_s),
        "n_views": len(m.view_pose), "n_rings": len(m.ring_view), "n_vertices": len(m.vertices),
        "rings_from": int(m.rings_from), **_arrays(m, "view_pose", "ring_offsets", "ring_view"),
        "vertices_cm": _wire("vertices_cm", np.rint(m.vertices * 100.0)),
        "wall_bits": _wire("wall_bits", np.packbits(m.wall.astype(np.uint8))),
    }  # fmt: skip


def _encode_fused_free(m: FusedFree) -> dict:
    return {
        "server": m.server, "session": m.session, "version": int(m.version),
        "map_version": int(m.map_version), "stamp_s": float(m.stamp_s), "tolerance_m": float(m.tolerance_m),
        "n_rings": len(m.ring_hole), "n_vertices": len(m.vertices), "n_walls": len(m.walls),
        **_arrays(m, "ring_offsets", "ring_hole", "vertices", "walls"),
    }  # fmt: skip


def _encode_robot_path(m: RobotPath) -> dict:
    return {
        "server": m.server, "session": m.session, "version": int(m.version), "robot": m.robot,
        "robot_session": m.robot_session, "n_keyframes": len(m.kf_stamp),
        **_arrays(m, "kf_stamp", "local", "pose"),
    }  # fmt: skip


_ENCODERS = {
    "robot_map": _encode_robot_map, "pose": _encode_pose, "fused_map": _encode_fused_map,
    "free_space": _encode_free_space, "fused_free": _encode_fused_free, "robot_path": _encode_robot_path,
}  # fmt: skip


# -- decode -----------------------------------------------------------------------------------


def decode(data: bytes, expect: type | None = None) -> Message:
    """The message in ``data``; ``expect`` (a message class of ``KINDS``) refuses any other kind.

    Raises only :class:`WireFormatError`, whose text names the field and what is wrong.
    """
    if expect is not None and expect not in KINDS:
        names = [k.__name__ for k in KINDS]
        raise TypeError(f"decode: expect must be one of {names} or None, got {expect!r}")
    return _guarded(data, expect, _WIRE)


def decode_stored_map(data: bytes) -> RobotMap:
    """The whole robot map in bytes from :func:`encode_stored_map` (checked as strictly as the wire)."""
    return _guarded(data, RobotMap, _STORED)


def _guarded(data: bytes, expect: type | None, limits: _Limits) -> Message:
    try:
        return _decode(data, expect, limits)
    except WireFormatError:
        raise
    except Exception as e:  # defensive: hostile bytes must never raise anything else
        raise WireFormatError(f"payload: {UNEXPECTED} {type(e).__name__}: {e}") from e


def _decode(data: bytes, expect: type | None, limits: _Limits) -> Message:
    if not isinstance(data, bytes | bytearray | memoryview):
        raise WireFormatError(f"payload: expected bytes, got {type(data).__name__}")
    size = memoryview(data).nbytes
    if size > limits.bytes:
        raise WireFormatError(f"payload: {size} bytes, at most {limits.bytes} in one {limits.what}")
    if isinstance(data, memoryview):
        data = data.tobytes()  # any layout or item format: the bytes as they are
    try:
        obj = msgpack.unpackb(
            data, raw=False, strict_map_key=True, max_bin_len=limits.bytes, max_str_len=MAX_STR_BYTES,
            max_array_len=MAX_ROBOTS, max_map_len=MAX_MAP_KEYS, max_ext_len=0,
        )  # fmt: skip
    except (ValueError, TypeError, OverflowError, msgpack.UnpackException) as e:
        raise WireFormatError(f"payload: malformed msgpack ({type(e).__name__}: {e})") from None
    if not isinstance(obj, dict):
        raise WireFormatError(f"payload: expected a msgpack map at the top level, got {type(obj).__name__}")
    fields = dict(obj)
    if "schema" not in fields:
        raise WireFormatError("schema: missing")
    schema = fields.pop("schema")
    if isinstance(schema, bool) or not isinstance(schema, int) or schema not in _KEYS_BY_SCHEMA:
        raise WireFormatError(
            f"schema: unknown schema version {schema!r:.40}, this build speaks {SCHEMA_VERSION} "
            f"(and reads {', '.join(map(str, sorted(_KEYS_BY_SCHEMA)))})"
        )
    if "kind" not in fields:
        raise WireFormatError("kind: missing")
    kind = fields.pop("kind")
    if not isinstance(kind, str) or kind not in _DECODERS:
        raise WireFormatError(f"kind: unknown kind {kind!r:.40}, expected one of {tuple(_DECODERS)}")
    if expect is not None and kind != KINDS[expect]:
        raise WireFormatError(f"kind: expected {KINDS[expect]}, got {kind}")
    if kind not in _KEYS_BY_SCHEMA[schema]:
        raise WireFormatError(f"kind: {kind} does not exist in schema {schema}")
    return _DECODERS[kind](_Reader(kind, fields, limits=limits, keys=_KEYS_BY_SCHEMA[schema][kind]))


class _Reader:
    """Typed access to one msgpack map whose key set must be exactly ``keys`` (default
    ``KEYS[kind]``, this schema's)."""

    def __init__(
        self,
        kind: str,
        fields: dict,
        where: str = "",
        limits: _Limits | None = None,
        keys: tuple | None = None,
    ):
        self.fields, self.where, self.limits = fields, where, limits
        keys = KEYS[kind] if keys is None else keys
        missing = [k for k in keys if k not in fields]
        unknown = [k for k in fields if k not in keys]
        if missing:
            raise WireFormatError(f"{where}{missing[0]}: missing field of {kind}")
        if unknown:
            raise WireFormatError(f"{where}{unknown[0]!r:.80}: unknown field of {kind}")

    def _get(self, name: str, types: tuple[type, ...], what: str, optional: bool = False):
        value = self.fields[name]
        if value is None and optional:
            return None
        if isinstance(value, bool) is not (bool in types) or not isinstance(value, types):
            raise WireFormatError(f"{self.where}{name}: expected {what}, got {type(value).__name__}")
        return value

    def integer(self, name: str) -> int:
        return self._get(name, (int,), "an integer")

    def number(self, name: str, optional: bool = False) -> float | None:
        return self._get(name, (int, float), "a number", optional)

    def text(self, name: str) -> str:
        return self._get(name, (str,), "a string")

    def flag(self, name: str) -> bool:
        return self._get(name, (bool,), "a bool")

    def items(self, name: str) -> list:
        return self._get(name, (list,), "a list")

    def mapping(self, name: str) -> dict:
        return self._get(name, (dict,), "a map")

    def count(self, name: str, hi: int) -> int:
        n = self.integer(name)
        if not 0 <= n <= hi:
            raise WireFormatError(f"{self.where}{name}: {n} out of range [0, {hi}]")
        return n

    def array(self, name: str, shape: tuple[int, ...], optional: bool = False) -> np.ndarray | None:
        buf = self._get(name, (bytes,), "bytes", optional)
        if buf is None:
            return None
        dtype = np.dtype(WIRE_DTYPES[name])
        want = int(np.prod(shape)) * dtype.itemsize
        if len(buf) != want:
            raise WireFormatError(
                f"{self.where}{name}: {len(buf)} bytes, expected {want} (shape {shape} of {dtype.str})"
            )
        return np.frombuffer(buf, dtype).reshape(shape)


def _decode_robot_map(r: _Reader) -> RobotMap:
    k = r.count("n_particles", MAX_PARTICLES)
    n = r.count("n_elements", r.limits.elements)
    return RobotMap(
        robot=r.text("robot"), session=r.text("session"), seq=r.integer("seq"), stamp_s=r.number("stamp_s"),
        chunk=r.integer("chunk"), n_chunks=r.integer("n_chunks"),
        particle_weights=r.array("particle_weights", (k,)), particle_poses=r.array("particle_poses", (k, 3)),
        seg=r.array("seg", (n, 2, 2)), element=r.array("element", (n,)), members=r.array("members", (n,)),
        trust=r.array("trust", (n,)), hits=r.array("hits", (n,)), age=r.array("age", (n,)),
        prior=r.array("prior", (3,), optional=True), prior_sigma=r.array("prior_sigma", (3,), optional=True),
        joined=r.flag("joined") if "joined" in r.fields else False,  # (schema 5 and before: none)
        **_decode_graph(r, n),
    )  # fmt: skip


def _decode_graph(r: _Reader, n: int) -> dict:
    """A robot map's graph fields (schema 5; none before)."""
    if "kf_id" not in r.fields:
        return {}
    k = r.count("n_keyframes", MAX_KEYFRAMES)
    e = r.count("n_edges", MAX_GRAPH_EDGES)
    shapes = dict(
        kf_id=(k,), kf_stamp=(k,), kf_pose=(k, 3), edge_ids=(e, 2), edge_z=(e, 3), edge_info=(e, 6),
        anchor=(n,),
    )  # fmt: skip
    out = {name: r.array(name, shape, optional=True) for name, shape in shapes.items()}
    seq = r.fields["graph_seq"]
    out["graph_seq"] = None if seq is None else r.integer("graph_seq")
    if "scan_id" in r.fields:  # (schema 6 and before: none)
        m = r.count("n_scans", MAX_KEYFRAMES)
        p = r.count("n_scan_points", MAX_SCANS_POINTS)
        out["scan_id"] = r.array("scan_id", (m,), optional=True)
        out["scan_count"] = r.array("scan_count", (m,), optional=True)
        cm = r.array("scan_cm", (p, 2), optional=True)
        out["scan_xy"] = None if cm is None else cm.astype(np.float64) / 100.0
    return out


def _decode_pose(r: _Reader) -> PoseUpdate:
    status = r.mapping("status") if "status" in r.fields else {}  # schema 2: none
    return PoseUpdate(robot=r.text("robot"), session=r.text("session"), seq=r.integer("seq"),
                      stamp_s=r.number("stamp_s"), pose=r.array("pose", (3,)), status=status)  # fmt: skip


def _decode_status(i: int, item: object) -> RobotStatus:
    where = f"robots[{i}]."
    if not isinstance(item, dict):
        raise WireFormatError(f"{where[:-1]}: expected a map, got {type(item).__name__}")
    r = _Reader("robot_status", item, where)
    try:
        return RobotStatus(
            robot=r.text("robot"), status=r.text("status"), online=r.flag("online"),
            session=r.text("session"), map_seq=r.integer("map_seq"), n_elements=r.integer("n_elements"),
            transform=r.array("transform", (3,)), sigma=r.array("sigma", (3,)),
            pose=r.array("pose", (3,), optional=True),
            pose_stamp_s=r.number("pose_stamp_s"), aligned_at_s=r.number("aligned_at_s", optional=True),
        )  # fmt: skip
    except WireFormatError as e:
        if str(e).startswith(where):
            raise
        raise WireFormatError(f"{where}{e}") from None


def _decode_fused_map(r: _Reader) -> FusedMap:
    m = r.count("n_segments", MAX_CHUNK_ELEMENTS)
    n_prov = r.count("n_prov", MAX_CHUNK_ELEMENTS * MAX_ROBOTS)
    robots = r.items("robots")
    return FusedMap(
        server=r.text("server"), version=r.integer("version"), stamp_s=r.number("stamp_s"),
        chunk=r.integer("chunk"), n_chunks=r.integer("n_chunks"),
        robots=tuple(_decode_status(i, item) for i, item in enumerate(robots)),
        seg=r.array("seg", (m, 2, 2)), support=r.array("support", (m,)),
        prov_offsets=r.array("prov_offsets", (m + 1,)), prov_robot=r.array("prov_robot", (n_prov,)),
        extra=r.mapping("extra"), session=r.text("session"),
    )  # fmt: skip


def _decode_free_space(r: _Reader) -> FreeSpace:
    v = r.count("n_views", MAX_VERTICES)
    n_rings = r.count("n_rings", MAX_VERTICES)
    p = r.count("n_vertices", MAX_VERTICES)
    return FreeSpace(
        robot=r.text("robot"), session=r.text("session"), seq=r.integer("seq"), stamp_s=r.number("stamp_s"),
        view_pose=r.array("view_pose", (v, 3)), ring_offsets=r.array("ring_offsets", (n_rings + 1,)),
        ring_view=r.array("ring_view", (n_rings,)),
        vertices=r.array("vertices_cm", (p, 2)).astype(np.float64) / 100.0,
        wall=np.unpackbits(r.array("wall_bits", ((p + 7) // 8,)), count=p),
        rings_from=r.integer("rings_from"),
    )  # fmt: skip


def _decode_fused_free(r: _Reader) -> FusedFree:
    n_rings = r.count("n_rings", MAX_VERTICES)
    p = r.count("n_vertices", MAX_VERTICES)
    return FusedFree(
        server=r.text("server"), session=r.text("session"), version=r.integer("version"),
        map_version=r.integer("map_version"), stamp_s=r.number("stamp_s"),
        tolerance_m=r.number("tolerance_m"), ring_offsets=r.array("ring_offsets", (n_rings + 1,)),
        ring_hole=r.array("ring_hole", (n_rings,)), vertices=r.array("vertices", (p, 2)),
        walls=r.array("walls", (r.count("n_walls", MAX_VERTICES), 2, 2)),
    )  # fmt: skip


def _decode_robot_path(r: _Reader) -> RobotPath:
    k = r.count("n_keyframes", MAX_KEYFRAMES)
    return RobotPath(
        server=r.text("server"), session=r.text("session"), version=r.integer("version"),
        robot=r.text("robot"), robot_session=r.text("robot_session"), kf_stamp=r.array("kf_stamp", (k,)),
        local=r.array("local", (k, 3)), pose=r.array("pose", (k, 3)),
    )  # fmt: skip


_DECODERS = {
    "robot_map": _decode_robot_map, "pose": _decode_pose, "fused_map": _decode_fused_map,
    "free_space": _decode_free_space, "fused_free": _decode_fused_free, "robot_path": _decode_robot_path,
}  # fmt: skip
