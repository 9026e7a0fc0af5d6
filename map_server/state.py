"""What the server remembers per robot, and its plain (JSON-able) form for snapshots."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from map_server.alignment import Alignment
from map_server.fusion import FusionConfig, RobotLayer, fuse_particles
from map_server.posegraph import RobotGraph
from shared.messages import PoseUpdate, RobotMap

if TYPE_CHECKING:
    from map_server.config import FleetConfig


def _unaligned(reason: str) -> Alignment:
    return Alignment("unaligned", np.zeros(3), np.zeros(3), reason=reason)


@dataclass
class RobotState:
    """One robot: its latest map (and cross-particle layer), pose, presence, alignment, and the
    bookkeeping of alignment attempts (robot-map and placed-map length at the last attempt, a
    candidate awaiting confirmation)."""

    robot: str
    order: int  # arrival order
    map: RobotMap | None = None
    layer: RobotLayer | None = None
    pose: PoseUpdate | None = None
    online: bool = True
    alignment: Alignment = field(default_factory=lambda: _unaligned("not attempted yet"))
    aligned_at_s: float | None = None  # server time (since the first message) of its first merge
    first_map_s: float | None = None  # server time of its first non-empty map (picks the reference)
    attempt_len_m: float | None = None
    attempt_placed_m: float = 0.0
    attempt_placed_key: str = ""  # which placed robots, how long, where (see schedule.placed_key)
    attempt_s: float = 0.0
    attempt_seq: int = -1  # the map's seq at the last attempt
    pending: Alignment | None = None
    pending_count: int = 0
    pending_s: float = 0.0  # server time of the first verdict of the pending place
    young_s: float | None = None  # server time of the last attempt made before the maps were
    # mature (policy.quiet), None once one is made on mature maps
    # the join claim (RobotMap.prior of a joined map) the fleet refuted: the free space seen
    # contradicted it, or the robot placed by it was undone or placed elsewhere since — it is
    # not verified again (the robot is matched as any robot); None while none was
    refuted_claim: list[float] | None = None
    lengths: list[tuple[float, float]] = field(default_factory=list)  # (server time, map length)
    graph: RobotGraph | None = None  # the map's pose graph (posegraph.RobotGraph), with the layer
    bent: RobotLayer | None = None  # the layer's rows in the global frame as the fleet's graph
    # moved them (None: the map is placed rigidly by its alignment's transform)
    bent_x: np.ndarray | None = None  # the keyframe poses (global) ``bent`` was moved with
    bent_of: RobotLayer | None = None  # the layer ``bent`` was made of

    def new_session(self) -> None:
        """The robot restarted: its map frame is a new one, nothing of the old alignment holds."""
        self.alignment = _unaligned("new session")
        self.layer, self.aligned_at_s, self.first_map_s = None, None, None
        self.graph = self.bent = self.bent_x = self.bent_of = None
        self.attempt_len_m, self.attempt_placed_m, self.attempt_placed_key = None, 0.0, ""
        self.attempt_seq = -1
        self.pending, self.pending_count = None, 0
        self.young_s = None
        self.refuted_claim = None
        self.lengths = []

    def record_length(self, now_s: float, keep_s: float) -> None:
        """Remember the layer's length now; forget what is older than ``keep_s`` but the newest."""
        self.lengths.append((now_s, self.layer.length_m))
        old = [i for i, (t, _) in enumerate(self.lengths) if t <= now_s - keep_s]
        if len(old) > 1:
            del self.lengths[: old[-1]]

    def mature(self, now_s: float, window_s: float, max_growth: float) -> bool:
        """Whether the map grew by at most ``max_growth`` (a share) over the last ``window_s``;
        a map not seen that long is not mature."""
        before = [length for t, length in self.lengths if t <= now_s - window_s]
        if not before or self.layer is None:
            return False
        return self.layer.length_m <= (1.0 + max_growth) * before[-1]

    def due(
        self,
        cfg: FleetConfig,
        placed_m: float,
        placed_key: str | Callable[[], str],
        now_s: float,
        urgent: bool = False,
    ) -> bool:
        """Whether an alignment attempt is worth it: never tried, the map changed length enough,
        or (while unaligned) the placed map grew enough, or its map or the placed map changed
        and the last attempt is ``retry_interval_s`` ago (a placed robot at once when ``urgent``: a
        robot just left)."""
        if self.grew(cfg):
            return True
        waited = now_s - self.attempt_s >= cfg.retry_interval_s
        if self.pending is not None:
            return waited  # a candidate awaits confirmation (never hurried: same evidence)
        changed = self.map.seq != self.attempt_seq
        if not changed and (waited or urgent):
            changed = (placed_key() if callable(placed_key) else placed_key) != self.attempt_placed_key
        if self.alignment.placed:  # refined against the others while the maps change (a prior
            return (waited or urgent) and changed  # robot, or an aligned one: where it is)
        if placed_m - self.attempt_placed_m >= cfg.retry_placed_growth_m:
            return True
        return waited and changed

    def grew(self, cfg: FleetConfig) -> bool:
        """Whether the map changed length enough since the last attempt for a full search (an
        aligned robot is otherwise only refined where it is)."""
        if self.attempt_len_m is None:
            return True
        grown = abs(self.layer.length_m - self.attempt_len_m)
        return grown >= max(cfg.retry_growth_m, cfg.retry_growth_share * self.attempt_len_m)

    def attempted(self, placed_m: float, placed_key: str, now_s: float) -> None:
        self.attempt_len_m, self.attempt_s, self.attempt_seq = self.layer.length_m, now_s, self.map.seq
        self.attempt_placed_m, self.attempt_placed_key = placed_m, placed_key

    def claim_refuted(self) -> bool:
        """Whether the map's join claim is one the fleet refuted (``refuted_claim``)."""
        c, m = self.refuted_claim, self.map
        return c is not None and m is not None and m.prior is not None and np.allclose(m.prior, c, atol=1e-9)

    def refute_claim(self) -> None:
        """The map's join claim does not hold: it is not verified again."""
        if self.map is not None and self.map.joined and self.map.prior is not None:
            self.refuted_claim = [float(v) for v in self.map.prior]

    def mark_placed(self, t_s: float) -> None:
        if self.aligned_at_s is None:
            self.aligned_at_s = max(0.0, float(t_s))

    # -- plain form ----------------------------------------------------------------------------

    def to_dict(self) -> dict:
        p = self.pending
        out = {k: getattr(self, k) for k in _SCALARS}
        out["alignment"] = alignment_to_dict(self.alignment)
        out["pending"] = None if p is None else alignment_to_dict(p)
        q = self.pose
        if q is not None:
            out["pose"] = dict(session=q.session, seq=q.seq, stamp_s=q.stamp_s, pose=_floats(q.pose))
        else:
            out["pose"] = None
        return out

    @classmethod
    def from_dict(cls, robot: str, d: dict, m: RobotMap | None) -> RobotState:
        q, p = d["pose"], d["pending"]
        pose = None
        if q is not None:
            pose = PoseUpdate(robot, q["session"], q["seq"], q["stamp_s"], np.array(q["pose"]))
        return cls(
            robot, map=m, alignment=alignment_from_dict(d["alignment"]), pose=pose,
            pending=None if p is None else alignment_from_dict(p),
            **{k: d.get(k, _ADDED[k]) if k in _ADDED else d[k] for k in _SCALARS},
        )  # fmt: skip


@dataclass(frozen=True, eq=False)
class RetiredPiece:
    """The last map of a robot's replaced session (the agent restarted), kept in the fused map
    where it was placed: its own frame died with the session, so its transform is frozen (but for
    the common motion of a prior frame, Fleet._hold_prior_gauge)."""

    robot: str
    session: str
    map: RobotMap
    layer: RobotLayer
    alignment: Alignment
    retired_s: float  # server time (since the first message) it was replaced

    @property
    def blob(self) -> str:
        return retired_blob(self.robot, self.session)

    def to_dict(self) -> dict:
        a = alignment_to_dict(self.alignment)
        return dict(session=self.session, retired_s=self.retired_s, alignment=a)

    @classmethod
    def from_dict(cls, robot: str, d: dict, maps: dict[str, RobotMap], fusion: FusionConfig) -> RetiredPiece:
        """The piece of :meth:`to_dict`, its map taken from a snapshot's ``maps`` by its blob name."""
        m = maps[retired_blob(robot, d["session"])]
        a = alignment_from_dict(d["alignment"])
        return cls(robot, d["session"], m, fuse_particles(m, fusion), a, float(d["retired_s"]))


def retired_blob(robot: str, session: str) -> str:
    """A retired piece's map name in a snapshot (``~`` is never part of a robot id)."""
    return f"{robot}~{session}"


# the plain fields of RobotState that a snapshot keeps as they are
_SCALARS = (
    "order", "online", "aligned_at_s", "first_map_s", "attempt_len_m", "attempt_placed_m",
    "attempt_placed_key", "attempt_s", "attempt_seq",
    "pending_count", "pending_s", "young_s", "refuted_claim",
)  # fmt: skip
_ADDED = {
    "attempt_seq": -1,
    "pending_s": 0.0,
    "young_s": None,
    "refuted_claim": None,
}  # fields newer than some snapshots: their value when missing


def _floats(a: np.ndarray) -> list[float]:
    return [float(v) for v in np.asarray(a).reshape(-1)]


def alignment_to_dict(a: Alignment) -> dict:
    return dict(
        status=a.status, transform=_floats(a.transform), sigma=_floats(a.sigma), score_m=float(a.score_m),
        inlier_share=float(a.inlier_share), rival_ratio=float(a.rival_ratio), reason=a.reason,
        contradicted_m=None if a.contradicted_m is None else float(a.contradicted_m),
        seen_m2=float(a.seen_m2),
    )  # fmt: skip


def alignment_from_dict(d: dict) -> Alignment:
    return Alignment(
        d["status"], np.array(d["transform"], float), np.array(d["sigma"], float), float(d["score_m"]),
        float(d["inlier_share"]), float(d["rival_ratio"]), str(d["reason"]),
        d.get("contradicted_m"), float(d.get("seen_m2", 0.0)),
    )  # fmt: skip
