"""The map server's state, pure: robot maps and poses in, alignments and the fused map out.

Time is passed in (``now_s``, the server's clock); nothing here does I/O.

Global frame: if a robot's map carries a start-pose prior when the first robot is placed, the
priors define the global frame: every prior robot is placed by its prior and refined, within its
sigma, against the others as they move (so the maps settle on their consensus), and after each
round the whole placed set is moved by the rigid motion that balances the prior robots against
their priors (``prior_gauge``: one robot at a time fixes the robots relative to each other, not
where the set is); robots without a prior are matched against them. Otherwise the first robot to
publish a non-empty map becomes the *reference* (identity transform) and the others are matched
against the fused map of the robots already placed (never including themselves). Priors that
arrive after a reference was chosen are in a frame nobody placed, so those robots are matched like
the others.

Matching is conservative at the fleet level too (alignment.py verifies one attempt):

- an unplaced robot is only tried once its map and every placed robot's map are *mature* (grown
  by at most ``mature_growth`` over ``mature_window_s``): partial maps of a symmetric or
  repetitive building match their mirror image as well as the truth or better (office, 60-90 s:
  the half-turned placement scored up to 1.7x the truth, with exact maps too);
- of the unplaced robots that match in one round only the most decisive (highest rival ratio)
  is taken; the others are tried again against the grown placed map;
- a new place (a first alignment or a revision) counts after ``confirmations`` attempts in a row
  agree on it.

Attempts are repeated only when a robot's map grew enough, the map it is matched against changed,
or a candidate awaits confirmation; a placed robot (by prior or by matching) is refined where it
is whenever its map or the placed map changed, every ``retry_interval_s`` or at once when a robot
leaves (its agent published its final map, rebuilt by its back end, just before).
:meth:`Fleet.fuse` then merges the placed robots' cross-particle maps (fusion.py); the version
increases only when the content (segments, provenance, robot statuses — not the poses) changed.

A robot that restarts comes back as a new *session* in a new map frame. What the fused map held
of its old session is not dropped: the old session's last map becomes a *retired piece*, kept in
the fused map where it was placed (its transform frozen but for the prior frame's common motion,
its segments credited to the robot) and in the snapshot. The new session starts unaligned and is
placed like any robot — by its prior, or by matching against the fused map, which holds its own
old piece: a robot that re-maps the same place aligns to it. At most ``max_retired`` pieces are
kept per robot, the oldest dropped (logged); an old session that was never placed had nothing in
the fused map and is dropped (logged).
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass, field

import numpy as np

from map_server.alignment import (
    Alignment,
    AlignmentConfig,
    estimate_alignment,
    floored_prior_sigma,
    prior_gauge,
)
from map_server.candidates import mean_displacement
from map_server.fusion import FusionConfig, fuse_particles, merge_segments
from map_server.state import RetiredPiece, RobotState
from shared.geometry import apply_segments, compose, wrap_angle
from shared.messages import FusedMap, PoseUpdate, RobotMap, RobotStatus

log = logging.getLogger("fleet_slam.fleet")


@dataclass(frozen=True)
class FleetConfig:
    fusion: FusionConfig = field(default_factory=FusionConfig)
    alignment: AlignmentConfig = field(default_factory=AlignmentConfig)
    retry_growth_m: float = 5.0  # re-attempt a robot's alignment when its map grew by this much ...
    retry_growth_share: float = 0.05  # ... or by this share of its length (whichever is larger)
    retry_placed_growth_m: float = 10.0  # an unaligned robot is retried when the placed map grew so
    retry_interval_s: float = 10.0  # ... or when anything changed (or a candidate waits) this long ago
    confirmations: int = 2  # consecutive attempts that must agree on a new place
    same_place_m: float = 0.3  # two verdicts agree when they move the robot map this little (mean)
    # maturity (module docstring). Office, 3 robots, 10 seeds, 180 s: no wrong merge with 0.2-0.3
    # (placed at 125-170 s), one with 0.4; warehouse: maps never mature below 0.15
    mature_window_s: float = 30.0
    mature_growth: float = 0.25
    # retired pieces (module docstring) kept per robot: a robot that keeps restarting re-maps the
    # same places, so the oldest piece is mostly covered by the newer ones; bounds memory and state
    max_retired: int = 3
    # when a robot leaves, placed robots are refined against each other in rounds until no frame
    # moves by more than these (one round is one Gauss-Seidel sweep: office, 3 robots, the final
    # maps: 3.3 cm / 0.19° left after one sweep, converged in 5), at most ``settle_rounds``
    settle_rounds: int = 8
    settle_m: float = 1e-3
    settle_rad: float = 1e-4


class Fleet:
    def __init__(self, cfg: FleetConfig, server_id: str):
        self.cfg, self.server_id = cfg, server_id
        self.robots: dict[str, RobotState] = {}
        self.retired: dict[str, list[RetiredPiece]] = {}  # per robot, oldest first
        self.reference: str | None = None
        self.frame: str | None = None  # "prior" or "reference", fixed when the first robot is placed
        self.version = 0
        self.epoch_s: float | None = None  # server time of the first message
        self._latest: FusedMap | None = None
        self._content: tuple | None = None
        self._arrivals = 0
        self._left = False  # a robot left since the last fusion: settle (not persisted)

    # -- inputs ------------------------------------------------------------------------------

    def _robot(self, robot: str, now_s: float | None) -> RobotState:
        if self.epoch_s is None and now_s is not None:
            self.epoch_s = now_s
        if robot not in self.robots:
            self.robots[robot] = RobotState(robot, order=self._arrivals)
            self._arrivals += 1
        return self.robots[robot]

    def put_map(self, m: RobotMap, now_s: float) -> None:
        """An assembled map (chunk 0 of 1). A new session replaces the old map and its alignment
        (the old map, if placed, lives on as a retired piece); an older or repeated ``seq`` of the
        current session is ignored."""
        r = self._robot(m.robot, now_s)
        if r.map is not None and m.session == r.map.session and m.seq <= r.map.seq:
            return
        if any(p.session == m.session for p in self.retired.get(m.robot, ())):
            return  # a late map of a replaced session (e.g. pulled from the state after a restart)
        if r.map is not None and m.session != r.map.session:
            self._retire(r, now_s)
            r.new_session()
            if self.reference == m.robot:
                self.reference = None  # its old frame lives on only through the robots placed in it
        r.map, r.layer = m, None
        if r.first_map_s is None and len(m.seg):
            r.first_map_s = now_s

    def _retire(self, r: RobotState, now_s: float) -> None:
        """Keep the replaced session's map in the fused map where it was placed (bounded)."""
        if not r.alignment.placed:
            if r.map is not None and len(r.map.seg):
                log.info("%s: session %s replaced unplaced; its map is dropped", r.robot, r.map.session)
            return
        layer = r.layer if r.layer is not None else fuse_particles(r.map, self.cfg.fusion)
        if len(layer) == 0:
            return
        t = now_s - (self.epoch_s if self.epoch_s is not None else now_s)
        pieces = self.retired.setdefault(r.robot, [])
        pieces.append(RetiredPiece(r.robot, r.map.session, r.map, layer, r.alignment, max(0.0, t)))
        while len(pieces) > self.cfg.max_retired:
            old = pieces.pop(0)
            log.info(
                "%s: more than %d retired sessions; the oldest (%s, %d segments) is dropped",
                r.robot, self.cfg.max_retired, old.session, len(old.layer),
            )  # fmt: skip

    def _pieces(self) -> list[RetiredPiece]:
        return [p for name in sorted(self.retired) for p in self.retired[name]]

    def put_pose(self, p: PoseUpdate, now_s: float) -> None:
        r = self._robot(p.robot, now_s)
        if r.pose is None or p.session != r.pose.session or p.seq > r.pose.seq:
            r.pose = p

    def set_online(self, robot: str, online: bool) -> None:
        """Presence. A robot leaving has published its final map (an agent at the end of its run
        publishes the map rebuilt by its back end last): every placed robot is refined against
        the maps as they are now, without waiting for ``retry_interval_s``."""
        r = self._robot(robot, None)
        self._left |= r.online and not online
        r.online = bool(online)

    # -- fusion ------------------------------------------------------------------------------

    def fuse(self, now_s: float) -> FusedMap | None:
        """Recompute alignments where warranted, then the fused map; ``None`` if nothing changed."""
        if self.epoch_s is None:
            self.epoch_s = now_s
        for r in self.robots.values():
            if r.map is not None and r.layer is None:
                r.layer = fuse_particles(r.map, self.cfg.fusion)
                r.record_length(now_s, self.cfg.mature_window_s)
        self._choose_frame(now_s)
        while self._align_round(now_s):
            pass
        if self._left:
            self._left = False
            self._settle(now_s)
        if self.frame == "prior":
            self._hold_prior_gauge()
        return self._publish(now_s)

    def _settle(self, now_s: float) -> None:
        """Refinement rounds of every placed robot against the others until the frames stop
        moving (a robot left: the maps are final, and one round leaves each robot refined
        against where the others were before theirs)."""
        c = self.cfg
        for _ in range(c.settle_rounds):
            placed = self._placed()
            if not placed:
                return
            before = np.array([r.alignment.transform for r in placed])
            while self._align_round(now_s, urgent=True):
                pass
            d = np.array([r.alignment.transform for r in placed]) - before
            still_m = np.hypot(d[:, 0], d[:, 1]).max() <= c.settle_m
            if still_m and np.abs(wrap_angle(d[:, 2])).max() <= c.settle_rad:
                return

    def latest(self) -> FusedMap | None:
        return self._latest

    def placements(self) -> dict[tuple[str, str], np.ndarray]:
        """Where each placed map is: ``(robot, session) -> transform (3,)`` (its map frame in
        the global frame), for the robots' current sessions and the retired pieces."""
        out = {(r.robot, r.map.session): r.alignment.transform for r in self._placed() if r.map is not None}
        for p in self._pieces():
            out[(p.robot, p.session)] = p.alignment.transform
        return out

    def sessions(self) -> set[tuple[str, str]]:
        """Every (robot, session) whose map the fleet keeps, placed or not."""
        out = {(r.robot, r.map.session) for r in self.robots.values() if r.map is not None}
        return out | {(p.robot, p.session) for p in self._pieces()}

    def _placed(self) -> list[RobotState]:
        return [r for r in self._ordered() if r.alignment.placed and r.layer is not None]

    def _ordered(self) -> list[RobotState]:
        return sorted(self.robots.values(), key=lambda r: r.order)

    def _choose_frame(self, now_s: float) -> None:
        with_map = [r for r in self._ordered() if r.layer is not None and len(r.layer)]
        if self.frame is None and with_map:
            self.frame = "prior" if any(r.map.prior is not None for r in with_map) else "reference"
        if self.frame != "reference" or self._placed() or self.retired or not with_map:
            return  # priors define the frame (_align_round places them), or it is defined already
        first = min(with_map, key=lambda r: (r.first_map_s, r.order))
        self.reference = first.robot
        first.alignment = Alignment("reference", np.zeros(3), np.zeros(3), reason="first non-empty map")
        first.mark_placed(now_s - self.epoch_s)

    def _global_segments(self, exclude: str) -> np.ndarray:
        """The fused map of the placed robots except ``exclude``, with every retired piece (its
        own too): what a robot is aligned to."""
        seg, w, owner = self._stack([r for r in self._placed() if r.robot != exclude] + self._pieces())
        return merge_segments(seg, w, owner, self.cfg.fusion)[0]

    def _stack(self, placed: list) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Placed robots' (or retired pieces') layers in the global frame, weights, owner index."""
        seg = [apply_segments(r.alignment.transform, r.layer.seg) for r in placed]
        w = [r.layer.weight for r in placed]
        owner = [np.full(len(r.layer), i) for i, r in enumerate(placed)]
        if not seg:
            return np.zeros((0, 2, 2)), np.zeros(0), np.zeros(0, np.int64)
        return np.concatenate(seg), np.concatenate(w), np.concatenate(owner)

    def _align_round(self, now_s: float, urgent: bool = False) -> bool:
        """One pass over the robots that deserve an attempt; True if a robot got placed.

        Of the unplaced robots that matched, only the most decisive one (highest rival ratio)
        is taken this round; the others are tried again against the grown placed map — a robot
        matched against more of the fleet has fewer mirror images to fall for."""
        fresh: list[tuple[RobotState, Alignment, float, str]] = []
        for r in self._ordered():
            if r.layer is None or r.alignment.status == "reference":
                continue
            prior = r.map.prior if self.frame == "prior" else None
            others = [p for p in self._placed() if p.robot != r.robot]
            against = others + self._pieces()
            placed_m = sum(p.layer.length_m for p in against)
            key = _placed_key(against)
            if not r.due(self.cfg, placed_m, key, now_s, urgent):
                continue
            if prior is None and not r.alignment.placed and not self._mature([r, *others], now_s):
                if r.alignment.score_m == 0.0:  # no candidate to report yet: say why
                    r.alignment = Alignment("unaligned", np.zeros(3), np.zeros(3), reason=self._waiting)
                continue  # not even attempted: a young map's match is not evidence yet
            current = r.alignment if r.alignment.status == "aligned" else None
            sigma = r.map.prior_sigma if prior is not None else None
            a = estimate_alignment(
                r.layer.seg, self._global_segments(r.robot), self.cfg.alignment, prior, sigma, current,
                search=current is None or r.grew(self.cfg),
            )  # fmt: skip
            if not r.alignment.placed or a.status != r.alignment.status:  # why a robot is (not) placed
                log.info("%s: attempt at %.1f s: %s (%s)", r.robot, now_s, a.status, a.reason)
            if a.status == "aligned" and not r.alignment.placed:
                fresh.append((r, a, placed_m, key))
                continue
            r.attempted(placed_m, key, now_s)
            if a.status == "aligned" and current is not None and self._moved(r, current, a):
                a = self._confirm(r, a, current)  # a revision: not before it is confirmed
            else:
                r.pending, r.pending_count = None, 0
            was_placed = r.alignment.placed
            r.alignment = a
            if a.placed and not was_placed:
                r.mark_placed(now_s - self.epoch_s)
        if not fresh:
            return False
        for f in fresh:
            f[0].attempted(f[2], f[3], now_s)
        r, a = max(fresh, key=lambda f: f[1].rival_ratio)[:2]
        r.alignment = self._confirm(r, a, None)
        if r.alignment.placed:
            r.mark_placed(now_s - self.epoch_s)
            return True
        return False

    def _hold_prior_gauge(self) -> None:
        """Move every placed frame (robots and retired pieces) by the common rigid motion that
        balances the prior-placed ones against their priors (alignment.prior_gauge): each prior
        robot is refined against the others, which fixes where they are relative to each other
        but not where the whole set is. A motion below a millimetre is left alone."""
        placed = self._placed() + self._pieces()
        held = [x for x in placed if x.alignment.status == "prior" and x.map.prior is not None]
        if not held:
            return
        t = np.array([x.alignment.transform for x in held])
        g = prior_gauge(
            t, np.array([x.map.prior for x in held]),
            floored_prior_sigma([x.map.prior_sigma for x in held], self.cfg.alignment),
        )  # fmt: skip
        moved = np.linalg.norm(compose(g, t)[:, :2] - t[:, :2], axis=1).max()
        if moved < 1e-3 and abs(g[2]) < 1e-4:
            return
        for r in placed:
            a = dataclasses.replace(r.alignment, transform=compose(g, r.alignment.transform))
            if isinstance(r, RetiredPiece):
                pieces = self.retired[r.robot]
                pieces[pieces.index(r)] = dataclasses.replace(r, alignment=a)
            else:
                r.alignment = a

    @property
    def _waiting(self) -> str:
        c = self.cfg
        return f"waiting for mature maps (grown by at most {c.mature_growth:.0%} in {c.mature_window_s:g} s)"

    def _mature(self, robots: list[RobotState], now_s: float) -> bool:
        c = self.cfg
        return all(r.mature(now_s, c.mature_window_s, c.mature_growth) for r in robots)

    def _moved(self, r: RobotState, a: Alignment, b: Alignment) -> bool:
        """Whether ``a`` and ``b`` put the robot's map at different places."""
        pts = 0.5 * (r.layer.seg[:, 0] + r.layer.seg[:, 1])
        return mean_displacement(a.transform, b.transform, pts) > self.cfg.same_place_m

    def _confirm(self, r: RobotState, a: Alignment, current: Alignment | None) -> Alignment:
        """A new alignment (or a revision) counts once ``confirmations`` attempts in a row put the
        robot at the same place; until then the robot stays unaligned (or where it was)."""
        same = r.pending is not None and not self._moved(r, r.pending, a)
        r.pending_count = r.pending_count + 1 if same else 1
        r.pending = a
        if r.pending_count >= self.cfg.confirmations:
            r.pending, r.pending_count = None, 0
            return a
        why = f"awaiting confirmation ({r.pending_count}/{self.cfg.confirmations}) of {a.reason}"
        if current is not None:
            c = current
            return Alignment("aligned", c.transform, c.sigma, c.score_m, c.inlier_share, c.rival_ratio, why)
        return Alignment("unaligned", a.transform, a.sigma, a.score_m, a.inlier_share, a.rival_ratio, why)

    # -- output --------------------------------------------------------------------------------

    def _status(self, r: RobotState) -> RobotStatus | None:
        session = r.map.session if r.map is not None else (r.pose.session if r.pose is not None else None)
        if session is None:
            return None
        a = r.alignment
        transform = a.transform if a.placed else np.zeros(3)
        sigma = a.sigma if a.placed else np.zeros(3)
        local, stamp = None, 0.0
        if r.pose is not None and r.pose.session == session:
            local, stamp = r.pose.pose, r.pose.stamp_s
        elif r.map is not None:
            local, stamp = r.map.particle_poses[int(np.argmax(r.map.particle_weights))], r.map.stamp_s
        pose = compose(transform, local) if a.placed and local is not None else None
        return RobotStatus(
            r.robot, a.status, r.online, session, r.map.seq if r.map is not None else 0,
            len(r.layer) if r.layer is not None else 0, transform, sigma, pose, stamp, r.aligned_at_s,
        )  # fmt: skip

    def _build(self) -> tuple[tuple, tuple, dict]:
        """The fused content: robot table, merged arrays, and the key that says if it changed."""
        table = [s for s in (self._status(r) for _, r in sorted(self.robots.items())) if s is not None]
        row = {s.robot: i for i, s in enumerate(table)}
        robots, pieces = sorted(self._placed(), key=lambda r: r.robot), self._pieces()
        placed = robots + pieces
        seg, w, owner = self._stack(placed)
        to_row = np.array([row[r.robot] for r in placed], np.int64)
        fseg, support, off, prov = merge_segments(
            seg, w, to_row[owner] if len(owner) else owner, self.cfg.fusion
        )
        arrays = (fseg, support, off, prov)
        key = tuple(a.tobytes() for a in arrays) + tuple(
            (s.robot, s.status, s.online, s.session, s.map_seq, s.n_elements, s.transform.tobytes(),
             s.sigma.tobytes(), s.aligned_at_s)
            for s in table
        )  # fmt: skip
        extra = {
            "robots_merged": float(len(robots)), "segments_in": float(len(seg)),
            "retired_pieces": float(len(pieces)),
        }  # fmt: skip
        return tuple(table), arrays, {"key": key, "extra": extra}

    def _publish(self, now_s: float) -> FusedMap | None:
        built = self._build()
        if not built[0] or built[2]["key"] == self._content:
            return None
        self.version += 1
        return self._keep(built, now_s)

    def _keep(self, built: tuple, stamp_s: float) -> FusedMap:
        """Make ``built`` (from :meth:`_build`) the latest fused map, at the current version."""
        table, (seg, support, off, prov), info = built
        self._content = info["key"]
        self._latest = FusedMap(
            self.server_id,
            self.version,
            max(0.0, stamp_s),
            0,
            1,
            table,
            seg,
            support,
            off,
            prov,
            info["extra"],
        )
        return self._latest

    # -- persistence ---------------------------------------------------------------------------

    def snapshot(self) -> tuple[dict, dict[str, RobotMap]]:
        """Everything needed to resume: a JSON-able dict and the latest map of every robot."""
        meta = dict(
            version=self.version, epoch_s=self.epoch_s, reference=self.reference, frame=self.frame,
            arrivals=self._arrivals, stamp_s=None if self._latest is None else self._latest.stamp_s,
            robots={name: r.to_dict() for name, r in self.robots.items()},
            retired={name: [p.to_dict() for p in pieces] for name, pieces in self.retired.items()},
        )  # fmt: skip
        maps = {name: r.map for name, r in self.robots.items() if r.map is not None}
        maps.update((p.blob, p.map) for p in self._pieces())
        return meta, maps

    @classmethod
    def restore(cls, meta: dict, maps: dict[str, RobotMap], cfg: FleetConfig, server_id: str) -> Fleet:
        """A fleet that fuses to the same map, same version (no alignment is re-attempted until
        a map changes). ``maps`` holds the robots' maps and the retired pieces' (see snapshot)."""
        f = cls(cfg, server_id)
        f.version, f.epoch_s, f.reference = int(meta["version"]), meta["epoch_s"], meta["reference"]
        f.frame, f._arrivals = meta["frame"], int(meta["arrivals"])
        for name, d in meta["robots"].items():
            r = f.robots[name] = RobotState.from_dict(name, d, maps.get(name))
            if r.map is not None:
                r.layer = fuse_particles(r.map, cfg.fusion)
        for name, pieces in meta.get("retired", {}).items():
            f.retired[name] = [RetiredPiece.from_dict(name, d, maps, cfg.fusion) for d in pieces]
        built = f._build()
        if built[0] and meta["stamp_s"] is not None:
            f._keep(built, meta["stamp_s"])
        return f


def _placed_key(placed: list[RobotState]) -> str:
    """Which robots are placed, how long their maps are and where: changes when the map a robot
    is aligned against changes."""
    return ";".join(
        f"{r.robot}:{r.layer.length_m:.3f}:" + ":".join(f"{v:.5f}" for v in r.alignment.transform)
        for r in placed
    )
