"""Wire messages (frozen dataclasses) with a schema version — the contract between agents and server.

Every message validates itself on construction (``__post_init__``): shapes, dtypes, finite values,
ranges and size limits. ``shared/codec.py`` turns bytes into these objects, so a decoded message is
a valid message; a bad one raises :class:`WireFormatError` naming the field and what is wrong.

Frames: a robot's map and poses are in its own *map frame* (where its filter started, the origin);
the fused map and ``RobotStatus.transform`` / ``pose`` are in the *global frame*.
``transform`` maps the robot's map frame into the global frame (``global = transform ∘ local``).

Large maps travel as bounded chunks (``chunk`` of ``n_chunks``, at most ``MAX_CHUNK_ELEMENTS``
elements each — the codec refuses to encode or decode a bigger chunk), every chunk carrying the
small header; the receiver assembles a map when all chunks of one ``(session, seq)`` are in. An
assembled map is the same dataclass with ``chunk=0, n_chunks=1`` and up to ``MAX_MAP_ELEMENTS``.

Segments are directed: the sensor saw the wall from the *left* of ``p0 → p1``, i.e. the facing
normal (pointing back to where the wall was seen from) is ``direction(p1 - p0)`` rotated by +90°.
Map matching relies on it so that the two faces of a thin wall never match.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field, replace

import numpy as np

SCHEMA_VERSION = 7  # 2: FusedMap.session; 3: PoseUpdate.status; 4: free space; 5: RobotMap keyframes
# and graph; 6: RobotMap.joined; 7: RobotMap keyframe scans (2 to 6 still read: codec)

MAX_CHUNK_ELEMENTS = 2048  # elements (segments) per chunk: ~64 KB per message
MAX_CHUNKS = 64  # chunks per map
MAX_MAP_ELEMENTS = MAX_CHUNKS * MAX_CHUNK_ELEMENTS  # 131,072 elements in an assembled map
MAX_PARTICLES = 63  # top particles per robot map (the membership mask is a non-negative int64)
MAX_ROBOTS = 256  # robots in one fused map
MAX_ID_LENGTH = 64
MAX_COORD_M = 1.0e5  # |x|, |y| of any point or pose: 100 km
ID_PATTERN = re.compile(r"^[A-Za-z0-9_\-]{1,64}$")  # robot ids are key-expression chunks

ALIGNMENT_STATUSES = ("reference", "prior", "aligned", "unaligned")

MAX_KEYFRAMES = 4096  # keyframes of one robot's pose graph in a map message
MAX_GRAPH_EDGES = 2 * MAX_KEYFRAMES  # its edges (chain, loops, carried over): a full graph ~0.7 MB
MAX_SCAN_POINTS = 256  # points of one keyframe's scan in a map message (an agent sends 64)
MAX_SCANS_POINTS = 1 << 17  # keyframe scan points in one map message (512 kB of int16 pairs)
MAX_SCAN_REACH_M = 327.0  # a keyframe's scan points travel as int16 centimetres in its frame
MAX_VIEWS = 4096  # free-space views (keyframes) in one robot's FreeSpace
MAX_RINGS = 16384  # polygon rings in one free-space message
MAX_VERTICES = 131072  # polygon vertices in one free-space message (robot: 512 kB of int16 pairs)
MAX_VIEW_REACH_M = 327.0  # a view's vertices travel as int16 centimetres around the view's pose


class WireFormatError(ValueError):
    """A message that is not a valid fleet-slam message; the text says which field and why."""


# -- validation helpers -----------------------------------------------------------------------


def check_id(name: str, value: object) -> str:
    if not isinstance(value, str) or not ID_PATTERN.match(value):
        raise WireFormatError(
            f"{name}: expected 1-{MAX_ID_LENGTH} characters of [A-Za-z0-9_-], got {value!r:.80}"
        )
    return value


def check_int(name: str, value: object, lo: int = 0, hi: int = 2**63 - 1) -> int:
    if isinstance(value, bool) or not isinstance(value, int | np.integer):
        raise WireFormatError(f"{name}: expected an integer, got {type(value).__name__}")
    if not lo <= int(value) <= hi:
        raise WireFormatError(f"{name}: {value} out of range [{lo}, {hi}]")
    return int(value)


def check_float(name: str, value: object, lo: float = -math.inf, hi: float = math.inf) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float | np.floating | np.integer):
        raise WireFormatError(f"{name}: expected a number, got {type(value).__name__}")
    v = float(value)
    if not math.isfinite(v):
        raise WireFormatError(f"{name}: not finite ({v})")
    if not lo <= v <= hi:
        raise WireFormatError(f"{name}: {v} out of range [{lo}, {hi}]")
    return v


def check_array(
    name: str,
    value: object,
    shape: tuple[int | None, ...],
    kind: str = "f",
    lo: float = -math.inf,
    hi: float = math.inf,
) -> np.ndarray:
    """``value`` as an array of ``shape`` (``None`` = any length) and dtype kind ``f`` (float64) or
    ``i`` (int64), every value finite and in ``[lo, hi]``; raises naming ``name`` otherwise."""
    if not isinstance(value, np.ndarray):
        raise WireFormatError(f"{name}: expected an array, got {type(value).__name__}")
    bad = value.ndim != len(shape) or any(
        s is not None and s != d for s, d in zip(shape, value.shape, strict=True)
    )
    if bad:
        want = "(" + ", ".join("N" if s is None else str(s) for s in shape) + ")"
        raise WireFormatError(f"{name}: expected shape {want}, got {value.shape}")
    if kind == "f":
        if value.dtype.kind not in "fiu":
            raise WireFormatError(f"{name}: expected numbers, got dtype {value.dtype}")
        with np.errstate(invalid="ignore"):  # a signalling NaN warns on the cast: refused just below
            arr = value.astype(np.float64, copy=False)
        if not np.all(np.isfinite(arr)):
            raise WireFormatError(f"{name}: contains NaN or inf")
    else:
        if value.dtype.kind not in "iu":
            raise WireFormatError(f"{name}: expected integers, got dtype {value.dtype}")
        arr = value.astype(np.int64, copy=False)
    if arr.size and (arr.min() < lo or arr.max() > hi):
        raise WireFormatError(f"{name}: values out of range [{lo}, {hi}] (min {arr.min()}, max {arr.max()})")
    return arr


def _freeze(obj: object, **arrays: np.ndarray) -> None:
    for k, v in arrays.items():
        v = np.array(v, copy=True)
        v.setflags(write=False)
        object.__setattr__(obj, k, v)


def _pose(name: str, value: object) -> np.ndarray:
    arr = check_array(name, value, (3,), lo=-MAX_COORD_M, hi=MAX_COORD_M)
    return arr


# -- messages ---------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class RobotMap:
    """One chunk of a robot's trusted segment map: the top particles' trusted elements.

    Elements shared by several top particles are sent once; ``members`` is a bitmask over the
    ``K`` particles (bit k set: particle k's map has this element version).

    - ``particle_weights (K,)`` normalized weights of the top particles (sum ≤ 1: the rest is
      the weight of the particles not sent), ``particle_poses (K,3)`` their current poses;
    - ``seg (N,2,2)`` endpoints [m] in the robot's map frame, ``element (N,)`` element identity
      (the same id in several particles = one landmark seen by each), ``members (N,)``,
      ``trust (N,)`` in [0, 1] (match quality × age × confirmation, report §5), ``hits (N,)``
      observations merged, ``age (N,)`` filter steps since the element was born;
    - ``prior (3,)`` the robot's map frame in the global frame when known (a start-pose prior),
      with ``prior_sigma (3,)`` [m, m, rad]; ``None`` when the server must estimate it;
      ``joined`` (schema 6): the prior is where the robot found itself in the fused map
      (``fleet-slam agent --join``, robot_agent/join.py), in the fused map's frame — a claim the
      server checks against the fused map and places the robot by, not a frame-defining prior;
    - the robot's pose graph as its back end last solved it (schema 5; ``None`` from a robot
      without one, whose map moves rigidly): keyframes ``kf_id (K,)`` (increasing identities),
      ``kf_stamp (K,)`` [s], ``kf_pose (K,3)`` in the map frame; edges ``edge_ids (E,2)`` (keyframe
      ids a, b) measuring ``edge_z (E,3)`` (b's pose in a's frame) with information
      ``edge_info (E,6)`` (upper triangle: xx, xy, xθ, yy, yθ, θθ); ``anchor (N,)`` the keyframe
      each element moves with; ``graph_seq`` the ``seq`` of the map that carried that graph: this
      one (the graph fields given), or an earlier one of the session whose graph is unchanged
      (the fields left out: the receiver has it). Only chunk 0 carries the graph; every chunk
      carries its rows' anchors.
    - keyframe scans (schema 7; ``None`` from a robot that sends none): ``scan_id (M,)`` keyframes
      of this graph (a subset of ``kf_id``, increasing) whose scan points this map carries,
      ``scan_count (M,)`` points each, ``scan_xy (P,2)`` the points [m] in that keyframe's frame
      (a thinned scan: the fleet graph matches robots' keyframes on them, map_server/posegraph.py).
      A keyframe's scan never changes: an agent sends it once in a session and its queryable's
      whole map carries all; the receiver keeps them (:meth:`with_scans_of`).
    """

    robot: str
    session: str
    seq: int
    stamp_s: float
    chunk: int
    n_chunks: int
    particle_weights: np.ndarray
    particle_poses: np.ndarray
    seg: np.ndarray
    element: np.ndarray
    members: np.ndarray
    trust: np.ndarray
    hits: np.ndarray
    age: np.ndarray
    prior: np.ndarray | None = None
    prior_sigma: np.ndarray | None = None
    kf_id: np.ndarray | None = None
    kf_stamp: np.ndarray | None = None
    kf_pose: np.ndarray | None = None
    edge_ids: np.ndarray | None = None
    edge_z: np.ndarray | None = None
    edge_info: np.ndarray | None = None
    anchor: np.ndarray | None = None
    graph_seq: int | None = None
    joined: bool = False
    scan_id: np.ndarray | None = None
    scan_count: np.ndarray | None = None
    scan_xy: np.ndarray | None = None

    def __post_init__(self) -> None:
        check_id("robot", self.robot)
        check_id("session", self.session)
        check_int("seq", self.seq)
        check_float("stamp_s", self.stamp_s, lo=0.0)
        n_chunks = check_int("n_chunks", self.n_chunks, 1, MAX_CHUNKS)
        check_int("chunk", self.chunk, 0, n_chunks - 1)
        w = check_array("particle_weights", self.particle_weights, (None,), lo=0.0, hi=1.0)
        k = len(w)
        if not 1 <= k <= MAX_PARTICLES:
            raise WireFormatError(f"particle_weights: {k} particles, expected 1..{MAX_PARTICLES}")
        if w.sum() > 1.0 + 1e-6:
            raise WireFormatError(f"particle_weights: sum {w.sum():.6f} exceeds 1")
        poses = check_array("particle_poses", self.particle_poses, (k, 3), lo=-MAX_COORD_M, hi=MAX_COORD_M)
        seg = check_array("seg", self.seg, (None, 2, 2), lo=-MAX_COORD_M, hi=MAX_COORD_M)
        n = len(seg)
        if n > MAX_MAP_ELEMENTS:
            raise WireFormatError(f"seg: {n} elements, at most {MAX_MAP_ELEMENTS}")
        element = check_array("element", self.element, (n,), "i", 0, 2**62)
        members = check_array("members", self.members, (n,), "i", 1, 2**k - 1)
        trust = check_array("trust", self.trust, (n,), lo=0.0, hi=1.0)
        hits = check_array("hits", self.hits, (n,), "i", 0, 2**40)
        age = check_array("age", self.age, (n,), "i", 0, 2**40)
        arrays = dict(
            particle_weights=w, particle_poses=poses, seg=seg, element=element,
            members=members, trust=trust, hits=hits, age=age,
        )  # fmt: skip
        if (self.prior is None) != (self.prior_sigma is None):
            raise WireFormatError("prior and prior_sigma: give both or neither")
        if not isinstance(self.joined, bool):
            raise WireFormatError(f"joined: expected a bool, got {type(self.joined).__name__}")
        if self.joined and self.prior is None:
            raise WireFormatError("joined: needs the prior (where the robot found itself in the fused map)")
        if self.prior is not None:
            arrays["prior"] = _pose("prior", self.prior)
            arrays["prior_sigma"] = check_array("prior_sigma", self.prior_sigma, (3,), lo=0.0, hi=MAX_COORD_M)
        arrays.update(self._graph(n))
        _freeze(self, **arrays)

    def _graph(self, n: int) -> dict:
        if self.graph_seq is not None:
            check_int("graph_seq", self.graph_seq, 0, self.seq)
        given = [getattr(self, f) is not None for f in GRAPH_FIELDS]
        if any(given) and not all(given):
            missing = GRAPH_FIELDS[given.index(False)]
            raise WireFormatError(f"{missing}: missing (the graph's fields come together)")
        out = {}
        if all(given) and self.graph_seq is None:
            raise WireFormatError("graph_seq: required with a graph (the seq of the map that carried it)")
        if all(given):
            if self.chunk != 0:
                raise WireFormatError("kf_id: only chunk 0 carries the graph")
            ids = check_array("kf_id", self.kf_id, (None,), "i", 0, 2**62)
            k = len(ids)
            if not 1 <= k <= MAX_KEYFRAMES:
                raise WireFormatError(f"kf_id: {k} keyframes, expected 1..{MAX_KEYFRAMES}")
            if np.any(np.diff(ids) <= 0):
                raise WireFormatError("kf_id: must increase")
            out["kf_id"] = ids
            out["kf_stamp"] = check_array("kf_stamp", self.kf_stamp, (k,), lo=0.0)
            out["kf_pose"] = check_array("kf_pose", self.kf_pose, (k, 3), lo=-MAX_COORD_M, hi=MAX_COORD_M)
            e = check_array("edge_ids", self.edge_ids, (None, 2), "i", 0, 2**62)
            if len(e) > MAX_GRAPH_EDGES:
                raise WireFormatError(f"edge_ids: {len(e)} edges, at most {MAX_GRAPH_EDGES}")
            if not np.isin(e, ids).all():
                raise WireFormatError("edge_ids: an edge names a keyframe not in kf_id")
            if np.any(e[:, 0] == e[:, 1]):
                raise WireFormatError("edge_ids: an edge joins a keyframe to itself")
            out["edge_ids"] = e
            out["edge_z"] = check_array("edge_z", self.edge_z, (len(e), 3), lo=-MAX_COORD_M, hi=MAX_COORD_M)
            info = check_array("edge_info", self.edge_info, (len(e), 6), lo=-1e12, hi=1e12)
            if len(info) and np.linalg.eigvalsh(info_matrices(info)).min(axis=1).min() < -1e-6 * max(
                1.0, float(np.abs(info).max())
            ):
                raise WireFormatError("edge_info: not positive semi-definite")
            out["edge_info"] = info
        if self.anchor is not None:
            anchor = check_array("anchor", self.anchor, (n,), "i", 0, 2**62)
            if all(given) and not np.isin(anchor, out["kf_id"]).all():
                raise WireFormatError("anchor: names a keyframe not in kf_id")
            out["anchor"] = anchor
        elif self.graph_seq is not None and n:
            raise WireFormatError("anchor: required with a graph (the keyframe of every element)")
        if self.anchor is not None and self.graph_seq is None:
            raise WireFormatError("graph_seq: required with anchors (the map whose graph they name)")
        out.update(self._scans(out.get("kf_id")))
        return out

    def _scans(self, kf_id: np.ndarray | None) -> dict:
        given = [getattr(self, f) is not None for f in SCAN_FIELDS]
        if not any(given):
            return {}
        if not all(given):
            missing = SCAN_FIELDS[given.index(False)]
            raise WireFormatError(f"{missing}: missing (the scans' fields come together)")
        if kf_id is None:
            raise WireFormatError("scan_id: keyframe scans need the graph (kf_id) beside them")
        ids = check_array("scan_id", self.scan_id, (None,), "i", 0, 2**62)
        if np.any(np.diff(ids) <= 0):
            raise WireFormatError("scan_id: must increase")
        if not np.isin(ids, kf_id).all():
            raise WireFormatError("scan_id: names a keyframe not in kf_id")
        count = check_array("scan_count", self.scan_count, (len(ids),), "i", 0, MAX_SCAN_POINTS)
        total = int(count.sum())
        if total > MAX_SCANS_POINTS:
            raise WireFormatError(f"scan_xy: {total} points, at most {MAX_SCANS_POINTS}")
        xy = check_array("scan_xy", self.scan_xy, (total, 2), lo=-MAX_SCAN_REACH_M, hi=MAX_SCAN_REACH_M)
        return dict(scan_id=ids, scan_count=count, scan_xy=xy)

    @property
    def has_scans(self) -> bool:
        return self.scan_id is not None

    def scans(self) -> dict[int, np.ndarray]:
        """Keyframe id -> its scan points ``(n,2)`` (empty without scans)."""
        if self.scan_id is None:
            return {}
        parts = np.split(self.scan_xy, np.cumsum(self.scan_count)[:-1])
        return dict(zip(self.scan_id.tolist(), parts, strict=True))

    def with_scans_of(self, before: RobotMap | None) -> RobotMap:
        """This map with the scans of ``before`` (an earlier map of its session) added for the
        keyframes of its graph that it carries none of: what the receiver keeps, the whole."""
        if self.kf_id is None or before is None or before.session != self.session or not before.has_scans:
            return self
        if not self.has_scans and np.isin(before.scan_id, self.kf_id).all():  # (the same graph's, as a
            # rule: a map whose graph went out before, filled in by the receiver — no copy)
            return replace(self, scan_id=before.scan_id, scan_count=before.scan_count, scan_xy=before.scan_xy)
        got = before.scans() | self.scans()
        ids = np.array(sorted(got), np.int64)
        ids = ids[np.isin(ids, self.kf_id)]
        if self.has_scans and len(ids) == len(self.scan_id):
            return self
        pts = [got[int(i)] for i in ids]
        xy = np.concatenate(pts) if pts else np.zeros((0, 2))
        count = np.array([len(p) for p in pts], np.int64)
        return replace(self, scan_id=ids, scan_count=count, scan_xy=xy)

    @property
    def n_particles(self) -> int:
        return len(self.particle_weights)

    @property
    def has_graph(self) -> bool:
        return self.kf_id is not None


GRAPH_FIELDS = ("kf_id", "kf_stamp", "kf_pose", "edge_ids", "edge_z", "edge_info")
SCAN_FIELDS = ("scan_id", "scan_count", "scan_xy")
_UPPER = ([0, 0, 0, 1, 1, 2], [0, 1, 2, 1, 2, 2])


def info_matrices(upper: np.ndarray) -> np.ndarray:
    """Symmetric ``(E,3,3)`` from upper triangles ``(E,6)`` (xx, xy, xθ, yy, yθ, θθ)."""
    upper = np.asarray(upper, float)
    out = np.zeros((len(upper), 3, 3))
    out[:, _UPPER[0], _UPPER[1]] = upper
    out[:, _UPPER[1], _UPPER[0]] = upper
    return out


def info_upper(info: np.ndarray) -> np.ndarray:
    """Upper triangles ``(E,6)`` of symmetric ``(E,3,3)`` (averaged with the transpose)."""
    info = np.asarray(info, float)
    sym = 0.5 * (info + np.swapaxes(info, 1, 2))
    return sym[:, _UPPER[0], _UPPER[1]]


def check_named_numbers(name: str, value: object) -> dict:
    """Up to 32 named finite numbers (names of at most 64 characters)."""
    if not isinstance(value, dict) or len(value) > 32:
        raise WireFormatError(f"{name}: expected a dict of at most 32 entries")
    for k, v in value.items():
        if not isinstance(k, str) or len(k) > MAX_ID_LENGTH:
            raise WireFormatError(f"{name}: bad key {k!r:.40}")
        check_float(f"{name}[{k}]", v)
    return value


@dataclass(frozen=True, eq=False)
class PoseUpdate:
    """A robot's current pose ``(3,)`` in its own map frame (sent often, small), and its
    ``status``: up to 32 named numbers on the robot's health (the laser's unusable readings,
    ``robot_agent/health.py``; empty from a schema-2 sender)."""

    robot: str
    session: str
    seq: int
    stamp_s: float
    pose: np.ndarray
    status: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        check_id("robot", self.robot)
        check_id("session", self.session)
        check_int("seq", self.seq)
        check_float("stamp_s", self.stamp_s, lo=0.0)
        check_named_numbers("status", self.status)
        _freeze(self, pose=_pose("pose", self.pose))


@dataclass(frozen=True, eq=False)
class RobotStatus:
    """One robot as the server sees it.

    ``status``: ``reference`` (its map frame defines the global frame), ``prior`` (placed by a
    start-pose prior), ``aligned`` (placed by map matching), ``unaligned`` (not merged).
    ``transform (3,)`` its map frame in the global frame with ``sigma (3,)`` [m, m, rad];
    ``pose (3,)`` its latest pose in the global frame (``None`` if unaligned or never heard).
    ``aligned_at_s`` server time (seconds since the server's first message) of its first merge.
    """

    robot: str
    status: str
    online: bool
    session: str
    map_seq: int
    n_elements: int
    transform: np.ndarray
    sigma: np.ndarray
    pose: np.ndarray | None = None
    pose_stamp_s: float = 0.0
    aligned_at_s: float | None = None

    def __post_init__(self) -> None:
        check_id("robot", self.robot)
        if self.status not in ALIGNMENT_STATUSES:
            raise WireFormatError(f"status: {self.status!r:.40} is not one of {ALIGNMENT_STATUSES}")
        if not isinstance(self.online, bool):
            raise WireFormatError(f"online: expected a bool, got {type(self.online).__name__}")
        check_id("session", self.session)
        check_int("map_seq", self.map_seq)
        check_int("n_elements", self.n_elements, 0, MAX_MAP_ELEMENTS)
        check_float("pose_stamp_s", self.pose_stamp_s, lo=0.0)
        if self.aligned_at_s is not None:
            check_float("aligned_at_s", self.aligned_at_s, lo=0.0)
        arrays = {
            "transform": _pose("transform", self.transform),
            "sigma": check_array("sigma", self.sigma, (3,), lo=0.0, hi=MAX_COORD_M),
        }
        if self.pose is not None:
            arrays["pose"] = _pose("pose", self.pose)
        _freeze(self, **arrays)

    @property
    def merged(self) -> bool:
        return self.status != "unaligned"


@dataclass(frozen=True, eq=False)
class FusedMap:
    """One chunk of the fused map (global frame).

    ``seg (M,2,2)`` segments, ``support (M,)`` how many robot-map elements were merged into each,
    provenance as CSR: the robots (indices into ``robots``) that contributed to segment ``i`` are
    ``prov_robot[prov_offsets[i]:prov_offsets[i+1]]``. ``robots`` (every chunk carries the full
    table) and ``version`` (increases with every change) identify the snapshot. ``session`` names
    the server process that made it (new at every start): a server restarted without its state
    counts versions from 1 again, and receivers take a new session as a restart, not as stale
    versions ("" only for maps never sent, e.g. the persisted copy).
    """

    server: str
    version: int
    stamp_s: float
    chunk: int
    n_chunks: int
    robots: tuple[RobotStatus, ...]
    seg: np.ndarray
    support: np.ndarray
    prov_offsets: np.ndarray
    prov_robot: np.ndarray
    extra: dict = field(default_factory=dict)  # up to 32 named numbers (e.g. fusion time)
    session: str = ""

    def __post_init__(self) -> None:
        check_id("server", self.server)
        if self.session != "":
            check_id("session", self.session)
        check_int("version", self.version)
        check_float("stamp_s", self.stamp_s, lo=0.0)
        n_chunks = check_int("n_chunks", self.n_chunks, 1, MAX_CHUNKS)
        check_int("chunk", self.chunk, 0, n_chunks - 1)
        if not isinstance(self.robots, tuple) or not all(isinstance(r, RobotStatus) for r in self.robots):
            raise WireFormatError("robots: expected a tuple of RobotStatus")
        if len(self.robots) > MAX_ROBOTS:
            raise WireFormatError(f"robots: {len(self.robots)} robots, at most {MAX_ROBOTS}")
        names = [r.robot for r in self.robots]
        if len(set(names)) != len(names):
            raise WireFormatError("robots: duplicate robot ids")
        seg = check_array("seg", self.seg, (None, 2, 2), lo=-MAX_COORD_M, hi=MAX_COORD_M)
        m = len(seg)
        if m > MAX_MAP_ELEMENTS:
            raise WireFormatError(f"seg: {m} segments, at most {MAX_MAP_ELEMENTS}")
        support = check_array("support", self.support, (m,), "i", 1, 2**40)
        offsets = check_array("prov_offsets", self.prov_offsets, (m + 1,), "i", 0, m * MAX_ROBOTS)
        if offsets[0] != 0 or np.any(np.diff(offsets) < 1):
            raise WireFormatError("prov_offsets: must start at 0 and increase (every segment has a robot)")
        if m and not self.robots:
            raise WireFormatError("prov_robot: segments but the robot table is empty")
        n_prov = (int(offsets[-1]),)
        prov = check_array("prov_robot", self.prov_robot, n_prov, "i", 0, max(len(self.robots) - 1, 0))
        check_named_numbers("extra", self.extra)
        _freeze(self, seg=seg, support=support, prov_offsets=offsets, prov_robot=prov)

    def provenance(self, i: int) -> list[str]:
        a, b = self.prov_offsets[i], self.prov_offsets[i + 1]
        return [self.robots[j].robot for j in self.prov_robot[a:b]]

    def robot(self, robot_id: str) -> RobotStatus | None:
        return next((r for r in self.robots if r.robot == robot_id), None)


def ring_subset(offsets: np.ndarray, keep: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The rings ``keep (R,)`` (a mask) of rings laid out by ``offsets (R+1,)``: the indices of
    their vertices and their own offsets."""
    lengths = np.diff(offsets)[keep]
    starts = np.asarray(offsets)[:-1][keep]
    new = np.concatenate([[0], np.cumsum(lengths)]).astype(np.int64)
    take = np.repeat(starts - new[:-1], lengths) + np.arange(new[-1])
    return take, new


def _rings(name: str, offsets: object, n_vertices: int) -> np.ndarray:
    """Ring offsets ``(R+1,)`` into ``n_vertices`` vertices: from 0 to all, each ring ≥ 3 vertices."""
    off = check_array(name, offsets, (None,), "i", 0, n_vertices)
    if len(off) < 1 or len(off) - 1 > MAX_RINGS:
        raise WireFormatError(f"{name}: {len(off) - 1} rings, expected 0..{MAX_RINGS}")
    if off[0] != 0 or off[-1] != n_vertices or np.any(np.diff(off) < 3):
        raise WireFormatError(f"{name}: must run from 0 to {n_vertices} with at least 3 vertices a ring")
    return off


@dataclass(frozen=True, eq=False)
class FreeSpace:
    """The space a robot's laser saw free, per *view* (a keyframe: a scan kept because it saw free
    space no earlier view had), in the robot's map frame (``robot_agent/freespace.py``).

    ``view_pose (V,3)`` each view's robot pose as the agent's latest correction puts it (the
    anchor: a correction of the path moves the view's polygon with it); ``ring_offsets (R+1,)``
    and ``ring_view (R,)``: ring ``i`` is ``vertices[ring_offsets[i]:ring_offsets[i+1]]`` (an
    open ring, at least 3 vertices, in the frame of view ``ring_view[i]``: metres, within
    ``MAX_VIEW_REACH_M``; the wire carries centimetres). A view's rings are disjoint polygons
    without holes: free space seen from one place, up to the hits. ``wall (P,)`` is 1 where the
    edge from that vertex to the next of its ring runs along hits — a wall seen — and 0 where it
    runs along a beam or the no-return reach (the wire packs it into bits).

    ``rings_from``: the rings are those of views ``rings_from`` on (every view's pose is always
    there). 0: the whole free space. Above 0: the views before it are as the message of ``seq - 1``
    of the same session had them — a view's polygon never changes, so an agent sends each once and
    then only the poses (:meth:`merged_onto` puts the two together; a receiver that missed one asks
    the agent's queryable, which answers with the whole).
    """

    robot: str
    session: str
    seq: int
    stamp_s: float
    view_pose: np.ndarray
    ring_offsets: np.ndarray
    ring_view: np.ndarray
    vertices: np.ndarray
    wall: np.ndarray
    rings_from: int = 0

    def __post_init__(self) -> None:
        check_id("robot", self.robot)
        check_id("session", self.session)
        check_int("seq", self.seq)
        check_float("stamp_s", self.stamp_s, lo=0.0)
        poses = check_array("view_pose", self.view_pose, (None, 3), lo=-MAX_COORD_M, hi=MAX_COORD_M)
        if len(poses) > MAX_VIEWS:
            raise WireFormatError(f"view_pose: {len(poses)} views, at most {MAX_VIEWS}")
        v = check_array("vertices", self.vertices, (None, 2), lo=-MAX_VIEW_REACH_M, hi=MAX_VIEW_REACH_M)
        if len(v) > MAX_VERTICES:
            raise WireFormatError(f"vertices: {len(v)} vertices, at most {MAX_VERTICES}")
        off = _rings("ring_offsets", self.ring_offsets, len(v))
        first = check_int("rings_from", self.rings_from, 0, len(poses))
        view = check_array("ring_view", self.ring_view, (len(off) - 1,), "i", first, max(len(poses) - 1, 0))
        if len(view) and not len(poses):
            raise WireFormatError("ring_view: rings but no views")
        wall = check_array("wall", np.asarray(self.wall).astype(np.int64), (len(v),), "i", 0, 1)
        _freeze(self, view_pose=poses, ring_offsets=off, ring_view=view, vertices=v, wall=wall.astype(bool))

    def merged_onto(self, before: FreeSpace) -> FreeSpace | None:
        """The whole free space this message and ``before`` (the same session's ``seq - 1``, or a
        whole one of that seq) make: ``before``'s rings of the views before ``rings_from``, this
        one's of the rest, this one's poses. ``None`` if ``before`` is not that message."""
        if self.rings_from == 0:
            return self
        if (before.robot, before.session, before.seq) != (self.robot, self.session, self.seq - 1):
            return None
        if before.rings_from != 0 or len(before.view_pose) < self.rings_from:
            return None
        keep = before.ring_view < self.rings_from
        take, offsets = ring_subset(before.ring_offsets, keep)
        return FreeSpace(
            self.robot, self.session, self.seq, self.stamp_s, self.view_pose,
            np.concatenate([offsets, offsets[-1] + self.ring_offsets[1:]]),
            np.concatenate([before.ring_view[keep], self.ring_view]),
            np.concatenate([before.vertices[take], self.vertices]),
            np.concatenate([before.wall[take], self.wall]),
        )  # fmt: skip

    def rings(self) -> list[tuple[int, np.ndarray, np.ndarray]]:
        """``(view, vertices (n,2), wall (n,))`` of every ring, in the view's frame."""
        o = self.ring_offsets
        return [(int(self.ring_view[i]), self.vertices[o[i] : o[i + 1]], self.wall[o[i] : o[i + 1]])
                for i in range(len(o) - 1)]  # fmt: skip


@dataclass(frozen=True, eq=False)
class FusedFree:
    """The fleet's free space in the global frame: the union of every placed robot's views, kept
    off the walls they saw (``map_server/freespace.py``). Polygons as rings: ring ``i`` is
    ``vertices[ring_offsets[i]:ring_offsets[i+1]]``; ``ring_hole[i]`` is 0 for a polygon's outer
    ring and 1 for a hole of the last outer ring before it. ``walls (K,2,2)``: walls the robots'
    lasers saw that the fused segment map does not hold (short or seldom seen ones), for an
    occupancy grid. ``map_version`` is the fused map's version whose placements it used;
    ``tolerance_m`` how far its simplification may move a boundary. ``session`` as in
    :class:`FusedMap`."""

    server: str
    session: str
    version: int
    map_version: int
    stamp_s: float
    tolerance_m: float
    ring_offsets: np.ndarray
    ring_hole: np.ndarray
    vertices: np.ndarray
    walls: np.ndarray

    def __post_init__(self) -> None:
        check_id("server", self.server)
        if self.session != "":
            check_id("session", self.session)
        check_int("version", self.version)
        check_int("map_version", self.map_version)
        check_float("stamp_s", self.stamp_s, lo=0.0)
        check_float("tolerance_m", self.tolerance_m, lo=0.0, hi=100.0)
        v = check_array("vertices", self.vertices, (None, 2), lo=-MAX_COORD_M, hi=MAX_COORD_M)
        if len(v) > MAX_VERTICES:
            raise WireFormatError(f"vertices: {len(v)} vertices, at most {MAX_VERTICES}")
        off = _rings("ring_offsets", self.ring_offsets, len(v))
        hole = check_array("ring_hole", self.ring_hole, (len(off) - 1,), "i", 0, 1)
        if len(hole) and hole[0] != 0:
            raise WireFormatError("ring_hole: the first ring must be an outer ring")
        walls = check_array("walls", self.walls, (None, 2, 2), lo=-MAX_COORD_M, hi=MAX_COORD_M)
        if len(walls) > MAX_MAP_ELEMENTS:
            raise WireFormatError(f"walls: {len(walls)} segments, at most {MAX_MAP_ELEMENTS}")
        _freeze(self, ring_offsets=off, ring_hole=hole, vertices=v, walls=walls)

    def polygons(self) -> list[tuple[np.ndarray, list[np.ndarray]]]:
        """``(outer (n,2), [hole (m,2), ...])`` of every polygon."""
        out: list[tuple[np.ndarray, list[np.ndarray]]] = []
        o = self.ring_offsets
        for i in range(len(o) - 1):
            ring = self.vertices[o[i] : o[i + 1]]
            if self.ring_hole[i]:
                out[-1][1].append(ring)
            else:
                out.append((ring, []))
        return out


@dataclass(frozen=True, eq=False)
class RobotPath:
    """Where the fleet's pose graph puts one robot's keyframes (the server answers it on query):
    ``server`` and its ``session``, the fused map ``version`` it goes with, ``robot`` and its map's
    ``robot_session``; keyframes ``kf_stamp (K,)`` [s], their poses in the robot's map frame
    ``local (K,3)`` and in the global frame ``pose (K,3)``. A robot placed as a whole: one keyframe
    at its map frame's origin (stamp 0) at its transform. Any pose ``p`` of the robot at time
    ``t``: ``pose[k] ∘ local[k]⁻¹ ∘ p``, ``k`` the last keyframe at or before ``t`` (the first
    before it): :meth:`apply`."""

    server: str
    session: str
    version: int
    robot: str
    robot_session: str
    kf_stamp: np.ndarray
    local: np.ndarray
    pose: np.ndarray

    def __post_init__(self) -> None:
        check_id("server", self.server)
        if self.session != "":
            check_id("session", self.session)
        check_int("version", self.version)
        check_id("robot", self.robot)
        check_id("robot_session", self.robot_session)
        t = check_array("kf_stamp", self.kf_stamp, (None,), lo=0.0)
        if not 1 <= len(t) <= MAX_KEYFRAMES:
            raise WireFormatError(f"kf_stamp: {len(t)} keyframes, expected 1..{MAX_KEYFRAMES}")
        k = len(t)
        local = check_array("local", self.local, (k, 3), lo=-MAX_COORD_M, hi=MAX_COORD_M)
        pose = check_array("pose", self.pose, (k, 3), lo=-MAX_COORD_M, hi=MAX_COORD_M)
        _freeze(self, kf_stamp=t, local=local, pose=pose)

    def apply(self, stamps_s: np.ndarray, poses: np.ndarray) -> np.ndarray:
        """The robot's poses ``(S,3)`` at ``stamps_s (S,)`` in its map frame, in the global frame."""
        from shared.geometry import compose, inverse  # (geometry imports nothing of this module)

        order = np.argsort(self.kf_stamp, kind="stable")  # (a log's clock may step back)
        at = np.searchsorted(self.kf_stamp[order], np.asarray(stamps_s), side="right") - 1
        k = order[np.maximum(at, 0)]
        return compose(compose(self.pose[k], inverse(self.local[k])), np.asarray(poses, float))


Message = RobotMap | PoseUpdate | FusedMap | FreeSpace | FusedFree | RobotPath
