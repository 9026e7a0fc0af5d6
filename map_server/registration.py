"""Map-to-map registration kernels: overlap score, point-to-line refinement, contradictions.

Both maps are directed segment maps (facing = left normal of ``p0 → p1``). The placed (global)
map is sampled every ``step_m`` into points that carry their segment's line and facing, indexed
by a k-d tree once per alignment attempt; the robot map is sampled the same way. A robot sample
*lies on* the placed map at a pose when a placed sample within the gate has a facing within the
angle tolerance and the sample is within the perpendicular tolerance of that sample's line — so
the overlap score is the robot-map length lying on placed walls (shared/matching.py's
``overlap_scores``, to the sample step, at k-d tree cost instead of all pairs).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from shared.geometry import sample_segments, segment_directions, segment_lengths, transform_points, wrap_angle

NEIGHBOURS = 8  # placed samples examined per robot sample (the nearest within the gate)
OTHER_FACE_RAD = 0.75 * np.pi  # facings this far apart: the two faces of one thin wall
CROSS_CHUNK_PAIRS = 2_000_000  # robot × placed segment pairs tested at once for crossings


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
        facing = wrap_angle(segment_directions(seg) + 0.5 * np.pi)[owner]
        normal = np.stack([np.cos(facing), np.sin(facing)], axis=-1)
        offset = np.sum(normal * seg[owner, 0], axis=-1)
        return cls(pts, facing, normal, offset, length, owner)

    def __len__(self) -> int:
        return len(self.points)


class MapIndex:
    """The placed map's samples in a k-d tree, and its segments for the crossing test."""

    def __init__(self, seg: np.ndarray, step_m: float):
        self.seg = np.asarray(seg, float).reshape(-1, 2, 2)
        self.samples = Samples.of(self.seg, step_m)
        self.tree = cKDTree(self.samples.points) if len(self.samples) else None

    def match(
        self, pose: np.ndarray, robot: Samples, gate_m: float, angle_rad: float
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """For each robot sample moved by ``pose``: whether a facing-compatible placed sample is
        within ``gate_m`` (``ok (K,)``), the nearest such one (``idx (K,)``) and the signed
        distance to its line (``perp (K,)``)."""
        k = len(robot)
        if self.tree is None or k == 0:
            return np.zeros(k, bool), np.zeros(k, int), np.zeros(k)
        q = transform_points(pose, robot.points)
        _, j = self.tree.query(q, k=NEIGHBOURS, distance_upper_bound=gate_m)
        valid = j < len(self.samples)
        j = np.where(valid, j, 0)
        ps = self.samples
        dang = np.abs(wrap_angle(robot.facing[:, None] + pose[2] - ps.facing[j]))
        good = valid & (dang <= angle_rad)
        first = np.argmax(good, axis=1)
        idx = j[np.arange(k), first]
        perp = np.sum(ps.normal[idx] * q, axis=-1) - ps.offset[idx]
        return good.any(axis=1), idx, perp

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
        q = transform_points(pose, robot.points)
        _, j = self.tree.query(q, k=NEIGHBOURS, distance_upper_bound=max(conflict_m, perp_m))
        valid = j < len(self.samples)
        j = np.where(valid, j, 0)
        ps = self.samples
        dang = np.abs(wrap_angle(robot.facing[:, None] + pose[2] - ps.facing[j]))
        perp = np.abs(np.sum(ps.normal[j] * q[:, None, :], axis=-1) - ps.offset[j])
        dist = np.hypot(*(q[:, None, :] - ps.points[j]).transpose(2, 0, 1))
        gate = np.hypot(perp_m, robot_step(robot))
        on = (valid & (dang <= angle_rad) & (perp <= perp_m) & (dist <= gate)).any(axis=1)
        near = (valid & (dang < OTHER_FACE_RAD)).any(axis=1)
        return on, near | on

    def opposed(self, pose: np.ndarray, robot: Samples, perp_m: float) -> float:
        """Robot-map length [m] on a placed wall's line but facing the other way (a wall seen from
        a side the placed map says is inside it): a contradiction."""
        if self.tree is None or len(robot) == 0:
            return 0.0
        q = transform_points(pose, robot.points)
        _, j = self.tree.query(q, k=NEIGHBOURS, distance_upper_bound=np.hypot(perp_m, robot_step(robot)))
        valid = j < len(self.samples)
        j = np.where(valid, j, 0)
        ps = self.samples
        dang = np.abs(wrap_angle(robot.facing[:, None] + pose[2] - ps.facing[j]))
        perp = np.abs(np.sum(ps.normal[j] * q[:, None, :], axis=-1) - ps.offset[j])
        bad = (valid & (dang >= OTHER_FACE_RAD) & (perp <= perp_m)).any(axis=1)
        return float(robot.length[bad].sum())

    def crossings(self, moved: np.ndarray, margin_m: float, min_angle_rad: float) -> np.ndarray:
        """Mask ``(R,)`` of robot segments (already moved into the global frame) that cross a placed
        segment: both cut more than ``margin_m`` from their ends at more than ``min_angle_rad``
        — two walls cannot pass through each other."""
        r, p = len(moved), len(self.seg)
        out = np.zeros(r, bool)
        if r == 0 or p == 0:
            return out
        rows = max(1, CROSS_CHUNK_PAIRS // p)
        b0, e = self.seg[:, 0], self.seg[:, 1] - self.seg[:, 0]
        lb = np.maximum(segment_lengths(self.seg), 1e-12)
        for s in range(0, r, rows):
            a0 = moved[s : s + rows, 0][:, None]
            d = (moved[s : s + rows, 1] - moved[s : s + rows, 0])[:, None]
            la = np.maximum(segment_lengths(moved[s : s + rows]), 1e-12)[:, None]
            denom = d[..., 0] * e[None, :, 1] - d[..., 1] * e[None, :, 0]
            w = b0[None] - a0
            with np.errstate(divide="ignore", invalid="ignore"):
                sa = (w[..., 0] * e[None, :, 1] - w[..., 1] * e[None, :, 0]) / denom  # along robot seg
                sb = (w[..., 0] * d[..., 1] - w[..., 1] * d[..., 0]) / denom  # along placed seg
            steep = np.abs(denom) >= np.sin(min_angle_rad) * la * lb[None]
            inside = (sa * la >= margin_m) & ((1 - sa) * la >= margin_m)
            inside &= (sb * lb[None] >= margin_m) & ((1 - sb) * lb[None] >= margin_m)
            out[s : s + rows] = np.any(steep & inside, axis=1)
        return out


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
