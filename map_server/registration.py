"""Map-to-map registration kernels: overlap score, point-to-line refinement, contradictions.

Both maps are directed segment maps (facing = left normal of ``p0 → p1``). The placed (global)
map is sampled every ``step_m`` into points that carry their segment's line and facing, indexed
in a :class:`shared.kernels.NearIndex` once per alignment attempt (a cell grid searched by a
compiled kernel, else a k-d tree: the same answer); the robot map is sampled the same way. A robot sample
*lies on* the placed map at a pose when a placed sample within the gate has a facing within the
angle tolerance and the sample is within the perpendicular tolerance of that sample's line — so
the overlap score is the robot-map length lying on placed walls (shared/matching.py's
``overlap_scores``, to the sample step, at the index's cost instead of all pairs).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from map_server.fusion import box_pairs
from shared.geometry import sample_segments, segment_directions, segment_lengths, transform_points, wrap_angle
from shared.kernels import Lines, NearIndex

NEIGHBOURS = 8  # placed samples examined per robot sample (the nearest within the gate)
OTHER_FACE_RAD = 0.75 * np.pi  # facings this far apart: the two faces of one thin wall
CROSS_CHUNK_PAIRS = 2_000_000  # robot × placed segment pairs tested at once for crossings
INDEX_CELL_M = 0.3  # the placed samples' grid (compiled index): the usual query bound, 0.15-0.3 m


@dataclass(frozen=True, eq=False)
class Samples:
    """Points ``(K,2)`` every ``step`` along segments, each with its segment's facing ``(K,)``
    [rad], unit facing normal ``(K,2)``, line offset ``c (K,)`` (``normal·p = c`` on the line),
    the length it stands for ``(K,)`` and its segment ``owner (K,)``."""

    points: np.ndarray
    facing: np.ndarray
    normal: np.ndarray
    offset: np.ndarray
    length: np.ndarray
    owner: np.ndarray

    @classmethod
    def of(cls, seg: np.ndarray, step_m: float) -> Samples:
        seg = np.asarray(seg, float).reshape(-1, 2, 2)
        if len(seg) == 0:
            z = np.zeros(0)
            return cls(np.zeros((0, 2)), z, np.zeros((0, 2)), z, z, np.zeros(0, int))
        pts, owner, length = sample_segments(seg, step_m)
        facing = wrap_angle(segment_directions(seg) + 0.5 * np.pi)  # per segment, then per sample
        normal = np.stack([np.cos(facing), np.sin(facing)], axis=-1)
        offset = np.sum(normal * seg[:, 0], axis=-1)
        return cls(pts, facing[owner], normal[owner], offset[owner], length, owner)

    def __len__(self) -> int:
        return len(self.points)


class OutsideIndex(Exception):
    """A query reached beyond the region a cropped :class:`MapIndex` answers exactly for."""


class MapIndex:
    """The placed map's samples indexed for nearest-sample queries (``compiled``: a cell grid and
    a compiled search, else a k-d tree; the same answer), and its segments for the crossing test.

    ``inner (lo (2,), hi (2,))``: the index holds a crop of the placed map — every segment whose
    bounding box meets the inner box grown by ``reach`` — and answers like the whole map for query
    points inside the inner box, as long as no query looks farther than ``reach``; a query point
    outside raises :class:`OutsideIndex` (the caller asks the whole map instead)."""

    def __init__(
        self,
        seg: np.ndarray,
        step_m: float,
        inner: tuple[np.ndarray, np.ndarray] | None = None,
        compiled: bool = True,
    ):
        self.seg = np.asarray(seg, float).reshape(-1, 2, 2)
        self.samples = Samples.of(self.seg, step_m)
        ps = self.samples
        lines = Lines(ps.facing, ps.normal[:, 0], ps.normal[:, 1], ps.offset)
        self.tree = NearIndex(ps.points, INDEX_CELL_M, lines, compiled) if len(ps) else None
        self.inner = inner
        self.box = np.concatenate([self.seg.min(axis=1), self.seg.max(axis=1)], axis=1)  # (P,4)
        self._last: tuple | None = None  # the last _near() (robot, pose, bound, answer)

    def _near(self, pose: np.ndarray, robot: Samples, bound: float) -> tuple:
        """The nearest placed samples (at most NEIGHBOURS) within ``bound`` of ``robot``'s samples
        at ``pose``: ``valid (K,N)``, indices ``j (K,N)`` (N where not valid), distances ``d``,
        facing difference ``dang`` and distance to their lines ``perp`` (K,N). The nearest within
        a smaller bound are the nearest within a larger one that lie within it, so the last query
        (strict scoring, then the contradiction checks at the same pose) serves the next ones with
        a bound no larger. :class:`OutsideIndex` when a sample lies outside a crop's inner box."""
        last = self._last
        if last is not None and last[0] is robot and bound <= last[2] and np.array_equal(last[1], pose):
            valid, j, d, dang, perp = last[3]
            return (valid if bound == last[2] else valid & (d <= bound)), j, d, dang, perp
        near = self._query(pose, robot, bound)
        answer = near.j < len(self.samples), near.j, near.d, near.dang, np.abs(near.perp)
        self._last = (robot, np.array(pose, float), bound, answer)
        return answer

    def match(
        self, pose: np.ndarray, robot: Samples, gate_m: float, angle_rad: float
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """For each robot sample moved by ``pose``: whether a facing-compatible placed sample is
        within ``gate_m`` (``ok (K,)``) among its NEIGHBOURS nearest, the nearest such one
        (``idx (K,)``; else the nearest, else 0) and the signed distance to its line (``perp``)."""
        k = len(robot)
        if self.tree is None or k == 0:
            return np.zeros(k, bool), np.zeros(k, int), np.zeros(k)
        near = self._query(pose, robot, gate_m)
        good = (near.j < len(self.samples)) & (near.dang <= angle_rad)
        first = np.argmax(good, axis=1)
        rows = np.arange(k)
        idx = near.j[rows, first]
        return _any_row(good), np.where(idx < len(self.samples), idx, 0), near.perp[rows, first]

    def _query(self, pose: np.ndarray, robot: Samples, bound: float):
        """The index's answer (shared.kernels.Near) for ``robot``'s samples moved by ``pose``:
        their NEIGHBOURS nearest within ``bound``, with the facing differences and line distances;
        :class:`OutsideIndex` when a sample lies outside a crop's inner box."""
        q = transform_points(pose, robot.points)
        near = self.tree.query(q, NEIGHBOURS, bound, robot.facing + pose[2], self.inner)
        if near.outside:
            raise OutsideIndex
        return near

    def _inside(self, q: np.ndarray) -> None:
        if self.inner is None or len(q) == 0:
            return
        lo, hi = self.inner
        if (q.min(axis=0) < lo).any() or (q.max(axis=0) > hi).any():
            raise OutsideIndex

    def overlap(self, pose: np.ndarray, robot: Samples, perp_m: float, angle_rad: float) -> float:
        """Robot-map length [m] lying on the placed map at ``pose``."""
        ok, _, perp = self.match(pose, robot, float(np.hypot(perp_m, robot_step(robot))), angle_rad)
        return float(robot.length[ok & (np.abs(perp) <= perp_m)].sum())

    def evidence(
        self, pose: np.ndarray, robot: Samples, perp_m: float, angle_rad: float, conflict_m: float
    ) -> tuple[np.ndarray, np.ndarray]:
        """Masks ``(K,)`` of the robot samples that, at ``pose``, lie on the placed map (``on``)
        and that have a placed wall (not its other face) within ``conflict_m`` (``near``):
        ``near & ~on`` is where the placed robots mapped and this robot sees something else."""
        k = len(robot)
        if self.tree is None or k == 0:
            return np.zeros(k, bool), np.zeros(k, bool)
        valid, _, dist, dang, perp = self._near(pose, robot, max(conflict_m, perp_m))
        gate = np.hypot(perp_m, robot_step(robot))
        on = _any_row(valid & (dang <= angle_rad) & (perp <= perp_m) & (dist <= gate))
        near = _any_row(valid & (dang < OTHER_FACE_RAD))
        return on, near | on

    def opposed(self, pose: np.ndarray, robot: Samples, perp_m: float) -> float:
        """Robot-map length [m] on a placed wall's line but facing the other way (a wall seen from
        a side the placed map says is inside it): a contradiction. Not where the placed map has
        that wall's face this robot sees as well: a thin wall both sides of which were seen (a
        partition between a room and a corridor, both entered; MIT-CSAIL) is not a contradiction."""
        if self.tree is None or len(robot) == 0:
            return 0.0
        valid, _, _, dang, perp = self._near(pose, robot, float(np.hypot(perp_m, robot_step(robot))))
        line = valid & (perp <= perp_m)
        bad = _any_row(line & (dang >= OTHER_FACE_RAD)) & ~_any_row(line & (dang < OTHER_FACE_RAD))
        return float(robot.length[bad].sum())

    def crossings(self, moved: np.ndarray, margin_m: float, min_angle_rad: float) -> np.ndarray:
        """Mask ``(R,)`` of robot segments (already moved into the global frame) that cross a placed
        segment: both cut more than ``margin_m`` from their ends at more than ``min_angle_rad``
        — two walls cannot pass through each other."""
        r, p = len(moved), len(self.seg)
        self._inside(moved.reshape(-1, 2))
        out = np.zeros(r, bool)
        if r == 0 or p == 0:
            return out
        # only segments whose boxes meet can cross
        ia, jb = box_pairs(np.concatenate([moved.min(axis=1), moved.max(axis=1)], axis=1), self.box)
        for s in range(0, len(ia), CROSS_CHUNK_PAIRS):
            a, b = ia[s : s + CROSS_CHUNK_PAIRS], jb[s : s + CROSS_CHUNK_PAIRS]
            a0, d = moved[a, 0], moved[a, 1] - moved[a, 0]
            b0, e = self.seg[b, 0], self.seg[b, 1] - self.seg[b, 0]
            la = np.maximum(segment_lengths(moved[a]), 1e-12)
            lb = np.maximum(segment_lengths(self.seg[b]), 1e-12)
            denom = d[:, 0] * e[:, 1] - d[:, 1] * e[:, 0]
            w = b0 - a0
            with np.errstate(divide="ignore", invalid="ignore"):
                sa = (w[:, 0] * e[:, 1] - w[:, 1] * e[:, 0]) / denom  # along robot seg
                sb = (w[:, 0] * d[:, 1] - w[:, 1] * d[:, 0]) / denom  # along placed seg
            steep = np.abs(denom) >= np.sin(min_angle_rad) * la * lb
            inside = (sa * la >= margin_m) & ((1 - sa) * la >= margin_m)
            inside &= (sb * lb >= margin_m) & ((1 - sb) * lb >= margin_m)
            out[a[steep & inside]] = True
        return out


def _any_row(mask: np.ndarray) -> np.ndarray:
    """``mask.any(axis=1)`` for a boolean ``(K, 8)`` mask: each row read as one 64-bit word."""
    if mask.ndim == 2 and mask.shape[1] == 8 and mask.dtype == bool:
        return np.ascontiguousarray(mask).view(np.uint64)[:, 0] != 0
    return mask.any(axis=1)


def robot_step(robot: Samples) -> float:
    """Half the largest sample spacing: the along-line slack of a sample-to-sample match."""
    return 0.5 * float(robot.length.max(initial=0.0))


@dataclass(frozen=True)
class Refined:
    pose: np.ndarray  # (3,)
    info: np.ndarray  # (3,3) information matrix of the pose (point noise, correlation accounted)
    matched_m: float  # robot length matched in the last iteration


def refine(
    index: MapIndex,
    robot: Samples,
    pose: np.ndarray,
    stages: tuple[tuple[float, float], ...],
    point_sigma_m: float,
    correlation_m: float,
    prior: np.ndarray | None = None,
    prior_info: np.ndarray | None = None,
) -> Refined:
    """Gauss-Newton on point-to-line distances: robot samples to the lines of their nearest
    facing-compatible placed samples, one iteration per ``(gate_m, angle_rad)`` stage (the gates
    shrink), Huber-weighted (threshold ``point_sigma_m``). With ``prior`` / ``prior_info (3,3)``
    a Gaussian prior term (MAP estimate). Samples closer than ``correlation_m`` along a wall are
    not independent, so each counts ``step / correlation_m`` in the information."""
    pose = np.asarray(pose, float).copy()
    h = np.zeros((3, 3))
    matched = 0.0
    for gate_m, angle_rad in stages:
        ok, idx, perp = index.match(pose, robot, gate_m, angle_rad)
        ok &= np.abs(perp) <= gate_m
        if ok.sum() < 3:
            break
        n = index.samples.normal[idx[ok]]
        p = robot.points[ok]
        c, s = np.cos(pose[2]), np.sin(pose[2])
        dr = np.stack([-s * p[:, 0] - c * p[:, 1], c * p[:, 0] - s * p[:, 1]], axis=-1)  # dR/dθ p
        jac = np.column_stack([n[:, 0], n[:, 1], np.sum(n * dr, axis=-1)])
        e = perp[ok]
        huber = np.minimum(1.0, point_sigma_m / np.maximum(np.abs(e), 1e-12))
        wgt = huber * robot.length[ok] / correlation_m / point_sigma_m**2
        h = jac.T @ (wgt[:, None] * jac)
        g = jac.T @ (wgt * e)
        if prior is not None and prior_info is not None:
            dp = pose - prior
            dp[2] = wrap_angle(dp[2])
            h = h + prior_info
            g = g + prior_info @ dp
        try:
            delta = -np.linalg.solve(h + 1e-9 * np.eye(3), g)
        except np.linalg.LinAlgError:
            break
        pose = pose + delta
        pose[2] = float(wrap_angle(pose[2]))
        matched = float(robot.length[ok].sum())
    return Refined(pose, h, matched)
