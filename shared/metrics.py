"""The numbers the project is judged on — one implementation for replay, demo and benchmarks.

- Relations error (Kümmerle et al., "On measuring the accuracy of SLAM algorithms",
  Autonomous Robots 27(4), 2009): for each relation ``(t1, t2, dx, dy, dyaw)`` compare the
  estimated relative motion ``inv(P(t1)) * P(t2)`` with the reference; translational error
  ``sqrt(ex² + ey²)`` [m], rotational ``|e_yaw|`` [deg]; mean ± population std.
- ATE: RMSE of positions against ground truth, after a rigid SE(2) alignment (Horn/Umeyama
  without scale) unless the frames are known to agree.
- Map precision / completeness of a segment map against true walls (see :func:`map_quality`).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from shared import geometry
from shared.geometry import compose, inverse, relative, wrap_angle

# Kümmerle's evaluator takes the pose nearest each relation time; further than this from any
# pose it shifts the nearest pose by the odometry motion in between.
NEAREST_POSE_MAX_DT_S = 0.1


class MetricsInputError(ValueError):
    """A relations file, trajectory or map given to a metric is malformed."""


@dataclass(frozen=True)
class Relations:
    """Reference relations: ``t1_s (R,)``, ``t2_s (R,)``, ``delta (R,3)`` = (dx, dy, dyaw)."""

    t1_s: np.ndarray
    t2_s: np.ndarray
    delta: np.ndarray

    def __len__(self) -> int:
        return len(self.t1_s)

    def until(self, t_max_s: float) -> Relations:
        """The relations that end by ``t_max_s`` (a run over part of a log scores only those)."""
        keep = self.t2_s <= t_max_s
        return Relations(self.t1_s[keep], self.t2_s[keep], self.delta[keep])


@dataclass(frozen=True)
class RelationsError:
    trans_m: np.ndarray  # (R,) per-relation translational error
    rot_deg: np.ndarray  # (R,) per-relation rotational error

    @property
    def n(self) -> int:
        return len(self.trans_m)

    def summary(self) -> dict[str, float]:
        return {
            "n": self.n,
            "trans_mean_m": float(self.trans_m.mean()),
            "trans_std_m": float(self.trans_m.std()),
            "trans_max_m": float(self.trans_m.max()),
            "rot_mean_deg": float(self.rot_deg.mean()),
            "rot_std_deg": float(self.rot_deg.std()),
            "rot_max_deg": float(self.rot_deg.max()),
        }

    def __str__(self) -> str:
        s = self.summary()
        return (
            f"n={s['n']}  trans {s['trans_mean_m']:.3f} ± {s['trans_std_m']:.3f} m "
            f"(max {s['trans_max_m']:.3f})  rot {s['rot_mean_deg']:.2f} ± {s['rot_std_deg']:.2f}° "
            f"(max {s['rot_max_deg']:.1f})"
        )


# --- files ----------------------------------------------------------------------------------


def read_relations(path: str | Path) -> Relations:
    """Read ``t1 t2 dx dy dz droll dpitch dyaw`` lines (Kümmerle format; ``#`` comments)."""
    rows = []
    with open(path) as fh:
        for lineno, line in enumerate(fh, 1):
            parts = line.split()
            if not parts or parts[0].startswith("#"):
                continue
            if len(parts) != 8:
                raise MetricsInputError(
                    f"{path}:{lineno}: relation needs 8 fields (t1 t2 dx dy dz droll dpitch dyaw),"
                    f" got {len(parts)}"
                )
            try:
                vals = [float(v) for v in parts]
            except ValueError as exc:
                raise MetricsInputError(f"{path}:{lineno}: {exc}") from None
            if not np.all(np.isfinite(vals)):
                raise MetricsInputError(f"{path}:{lineno}: non-finite value in relation")
            rows.append((vals[0], vals[1], vals[2], vals[3], vals[7]))
    if not rows:
        raise MetricsInputError(f"{path}: no relations")
    a = np.array(rows)
    return Relations(a[:, 0], a[:, 1], a[:, 2:5])


def write_relations(path: str | Path, rel: Relations) -> None:
    with open(path, "w") as fh:
        for t1, t2, (dx, dy, dyaw) in zip(rel.t1_s, rel.t2_s, rel.delta, strict=True):
            fh.write(f"{t1:.6f} {t2:.6f} {dx:.6f} {dy:.6f} 0.000000 0.000000 0.000000 {dyaw:.6f}\n")


def read_poses(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Read ``timestamp x y theta`` lines → ``stamps_s (N,)``, ``poses (N,3)``."""
    try:
        a = np.loadtxt(path, ndmin=2, comments="#")
    except ValueError as exc:
        raise MetricsInputError(f"{path}: {exc}") from None
    if a.shape[1] != 4:
        raise MetricsInputError(f"{path}: expected 4 columns (timestamp x y theta), got {a.shape[1]}")
    if not np.all(np.isfinite(a)):
        raise MetricsInputError(f"{path}: non-finite values")
    return a[:, 0], a[:, 1:4]


def write_poses(path: str | Path, stamps_s: np.ndarray, poses: np.ndarray) -> None:
    np.savetxt(path, np.column_stack([stamps_s, poses]), fmt=["%.6f", "%.6f", "%.6f", "%.6f"])


def write_tum(path: str | Path, stamps_s: np.ndarray, poses: np.ndarray) -> None:
    """TUM format: ``timestamp tx ty tz qx qy qz qw`` (planar: z = 0, rotation about z)."""
    half = 0.5 * poses[:, 2]
    z = np.zeros(len(poses))
    rows = np.column_stack([stamps_s, poses[:, 0], poses[:, 1], z, z, z, np.sin(half), np.cos(half)])
    np.savetxt(path, rows, fmt="%.6f")


# --- relations error ------------------------------------------------------------------------


def _nearest_index(stamps_s: np.ndarray, t_s: np.ndarray) -> np.ndarray:
    """Index of the stamp nearest each ``t_s`` (``stamps_s`` sorted)."""
    i = np.clip(np.searchsorted(stamps_s, t_s), 1, len(stamps_s) - 1)
    left_closer = np.abs(t_s - stamps_s[i - 1]) <= np.abs(stamps_s[i] - t_s)
    return np.where(left_closer, i - 1, i)


def poses_at(
    stamps_s: np.ndarray,
    poses: np.ndarray,
    t_s: np.ndarray,
    odom_stamps_s: np.ndarray | None = None,
    odom_poses: np.ndarray | None = None,
    max_dt_s: float = NEAREST_POSE_MAX_DT_S,
) -> np.ndarray:
    """Estimated poses at times ``t_s``: the nearest pose, shifted by odometry if it is far."""
    order = np.argsort(stamps_s, kind="stable")
    stamps_s, poses = np.asarray(stamps_s)[order], np.asarray(poses)[order]
    if len(stamps_s) < 2:
        raise MetricsInputError("a trajectory needs at least 2 poses")
    j = _nearest_index(stamps_s, t_s)
    out = poses[j].copy()
    far = np.abs(stamps_s[j] - t_s) > max_dt_s
    if odom_stamps_s is not None and odom_poses is not None and np.any(far) and len(odom_stamps_s) > 1:
        o = np.argsort(odom_stamps_s, kind="stable")
        ot, op = np.asarray(odom_stamps_s)[o], np.asarray(odom_poses)[o]
        a = _nearest_index(ot, stamps_s[j[far]])
        b = _nearest_index(ot, t_s[far])
        out[far] = compose(poses[j[far]], relative(op[a], op[b]))
    return out


def relations_error(
    stamps_s: np.ndarray,
    poses: np.ndarray,
    relations: Relations,
    odom_stamps_s: np.ndarray | None = None,
    odom_poses: np.ndarray | None = None,
) -> RelationsError:
    """Kümmerle relations error of a trajectory ``poses (N,3)`` stamped ``stamps_s (N,)``."""
    poses = np.asarray(poses, dtype=float)
    if poses.ndim != 2 or poses.shape[1] != 3 or len(poses) != len(stamps_s):
        raise MetricsInputError(f"poses must be (N,3) matching stamps (N,), got {poses.shape}")
    if not np.all(np.isfinite(poses)):
        raise MetricsInputError("poses contain non-finite values")
    p1 = poses_at(stamps_s, poses, relations.t1_s, odom_stamps_s, odom_poses)
    p2 = poses_at(stamps_s, poses, relations.t2_s, odom_stamps_s, odom_poses)
    est = relative(p1, p2)
    err = est - relations.delta
    trans = np.hypot(err[:, 0], err[:, 1])
    rot = np.degrees(np.abs(wrap_angle(err[:, 2])))
    return RelationsError(trans, rot)


def make_relations(
    stamps_s: np.ndarray,
    truth: np.ndarray,
    rng: np.random.Generator,
    n_short: int | None = None,
    n_long: int | None = None,
    revisit_radius_m: float = 2.0,
    revisit_min_dt_s: float = 30.0,
    n_revisit: int | None = None,
) -> Relations:
    """Reference relations from a true trajectory, spanning short and long spans.

    Short: a pose and one 1–20 scans later (local consistency, like Kümmerle's). Long: random
    pairs anywhere in the run. Revisit: pairs that are near in space but far in time (loop
    closures — what drift breaks first).
    """
    n = len(stamps_s)
    n_short = n // 2 if n_short is None else n_short
    n_long = n // 4 if n_long is None else n_long
    n_revisit = n // 4 if n_revisit is None else n_revisit
    i_s = rng.integers(0, n - 1, n_short)
    j_s = np.minimum(i_s + rng.integers(1, 21, n_short), n - 1)
    i_l, j_l = rng.integers(0, n, n_long), rng.integers(0, n, n_long)
    # revisits: candidate pairs sampled, kept if close in space and apart in time
    cand_i, cand_j = rng.integers(0, n, 40 * max(n_revisit, 1)), rng.integers(0, n, 40 * max(n_revisit, 1))
    d = np.hypot(*(truth[cand_i, :2] - truth[cand_j, :2]).T)
    keep = (d < revisit_radius_m) & (np.abs(stamps_s[cand_i] - stamps_s[cand_j]) > revisit_min_dt_s)
    i_r, j_r = cand_i[keep][:n_revisit], cand_j[keep][:n_revisit]
    i = np.concatenate([i_s, i_l, i_r])
    j = np.concatenate([j_s, j_l, j_r])
    lo, hi = np.minimum(i, j), np.maximum(i, j)
    keep = lo != hi
    lo, hi = lo[keep], hi[keep]
    return Relations(stamps_s[lo], stamps_s[hi], relative(truth[lo], truth[hi]))


# --- ATE ------------------------------------------------------------------------------------


def align_se2(source_xy: np.ndarray, target_xy: np.ndarray) -> np.ndarray:
    """Rigid SE(2) transform (3,) minimising ``sum |T(source) - target|²`` (Umeyama, no scale)."""
    ms, mt = source_xy.mean(axis=0), target_xy.mean(axis=0)
    s, t = source_xy - ms, target_xy - mt
    # 2-D closed form: angle of the cross-covariance
    num = np.sum(s[:, 0] * t[:, 1] - s[:, 1] * t[:, 0])
    den = np.sum(s[:, 0] * t[:, 0] + s[:, 1] * t[:, 1])
    th = np.arctan2(num, den)
    c, sn = np.cos(th), np.sin(th)
    tx = mt[0] - (c * ms[0] - sn * ms[1])
    ty = mt[1] - (sn * ms[0] + c * ms[1])
    return np.array([tx, ty, th])


@dataclass(frozen=True)
class ATE:
    rmse_m: float
    mean_m: float
    max_m: float
    alignment: np.ndarray  # (3,) estimate frame → truth frame
    errors_m: np.ndarray  # (N,)

    def summary(self) -> dict[str, float]:
        return {"rmse_m": self.rmse_m, "mean_m": self.mean_m, "max_m": self.max_m}


def ate(
    est_stamps_s: np.ndarray,
    est_poses: np.ndarray,
    true_stamps_s: np.ndarray,
    true_poses: np.ndarray,
    align: bool = True,
) -> ATE:
    """Absolute trajectory error of positions; estimates matched to the nearest true stamp."""
    if len(est_poses) == 0:
        raise MetricsInputError("empty estimated trajectory")
    order = np.argsort(true_stamps_s, kind="stable")
    ts, tp = np.asarray(true_stamps_s)[order], np.asarray(true_poses)[order]
    j = _nearest_index(ts, np.asarray(est_stamps_s))
    target = tp[j, :2]
    est = np.asarray(est_poses, dtype=float)
    t = align_se2(est[:, :2], target) if align else np.zeros(3)
    moved = compose(t, est)[:, :2]
    e = np.hypot(*(moved - target).T)
    return ATE(float(np.sqrt(np.mean(e**2))), float(e.mean()), float(e.max()), t, e)


def transform_error(estimated: np.ndarray, true: np.ndarray) -> tuple[float, float]:
    """Translation [m] and rotation [deg] error between two transforms ``(3,)``."""
    d = compose(inverse(true), estimated)
    return float(np.hypot(d[0], d[1])), float(np.degrees(abs(wrap_angle(d[2]))))


# --- map quality ----------------------------------------------------------------------------

MAP_TOL_M = 0.10
MAP_ANGLE_TOL_RAD = np.radians(5.0)
SAMPLE_STEP_M = 0.05
_CHUNK_PAIRS = 2_000_000


def sample_segments(segments: np.ndarray, step_m: float = SAMPLE_STEP_M) -> tuple[np.ndarray, ...]:
    """:func:`shared.geometry.sample_segments`, by default at the map-quality step."""
    return geometry.sample_segments(segments, step_m)


def nearest_segment(
    points: np.ndarray,
    segments: np.ndarray,
    point_dirs: np.ndarray | None = None,
    angle_tol_rad: float | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Distance ``(K,)`` and index ``(K,)`` of the nearest segment to each point, chunked.

    With ``point_dirs (K,)`` [rad] and ``angle_tol_rad``, only segments whose direction is within
    the tolerance of the point's (either way round) count; distance inf and index -1 where none
    does. At a corner the nearest wall is often the perpendicular one while a parallel one lies
    within tolerance too: judging by the nearest alone calls such a point uncovered."""
    seg = np.asarray(segments, dtype=float).reshape(-1, 2, 2)
    k = len(points)
    if len(seg) == 0:
        return np.full(k, np.inf), np.full(k, -1)
    a, ab = seg[:, 0], seg[:, 1] - seg[:, 0]
    l2 = np.maximum(np.sum(ab * ab, axis=1), 1e-12)
    sdir = np.arctan2(ab[:, 1], ab[:, 0])
    pdir = None if point_dirs is None else np.asarray(point_dirs, dtype=float)
    dist, idx = np.empty(k), np.empty(k, dtype=int)
    step = max(1, _CHUNK_PAIRS // len(seg))
    for s in range(0, k, step):
        p = points[s : s + step, None, :]
        t = np.clip(np.sum((p - a) * ab, axis=2) / l2, 0.0, 1.0)
        d = np.linalg.norm(p - (a + t[..., None] * ab), axis=2)
        if pdir is not None:
            da = np.abs(wrap_angle(pdir[s : s + step, None] - sdir))
            d[np.minimum(da, np.pi - da) > angle_tol_rad] = np.inf
        idx[s : s + step] = d.argmin(axis=1)
        dist[s : s + step] = d[np.arange(len(d)), idx[s : s + step]]
    idx[~np.isfinite(dist)] = -1
    return dist, idx


@dataclass(frozen=True)
class MapQuality:
    precision: float  # share of mapped length within tol (distance and angle) of a true wall
    completeness: float  # share of seen true wall length covered by the map
    mapped_length_m: float
    seen_wall_length_m: float

    def summary(self) -> dict[str, float]:
        return dict(self.__dict__)


def map_quality(
    map_segments: np.ndarray,
    walls: np.ndarray,
    seen_points: np.ndarray | None = None,
    tol_m: float = MAP_TOL_M,
    angle_tol_rad: float = MAP_ANGLE_TOL_RAD,
) -> MapQuality:
    """Precision and completeness of a segment map against true walls.

    precision: share of mapped length whose samples lie within ``tol_m`` of a true wall whose
    direction is within ``angle_tol_rad``. completeness: share of true wall length *seen by a
    sensor* (wall samples within ``tol_m`` of a noise-free laser hit ``seen_points (H,2)``;
    all walls if None) that has a mapped sample within ``tol_m`` and ``angle_tol_rad``. Any wall
    (segment) within both tolerances counts, not only the nearest: near a corner the nearest is
    often the perpendicular one (until session 10 only the nearest was judged, which called
    0.1-0.3 % of the office's seen walls uncovered and 1 % of its mapped length imprecise).
    """
    from scipy.spatial import cKDTree

    m = np.asarray(map_segments, dtype=float).reshape(-1, 2, 2)
    w = np.asarray(walls, dtype=float).reshape(-1, 2, 2)
    m = m[np.hypot(*(m[:, 1] - m[:, 0]).T) > 1e-9]
    w = w[np.hypot(*(w[:, 1] - w[:, 0]).T) > 1e-9]
    mdir = np.arctan2(*(m[:, 1] - m[:, 0])[:, ::-1].T)
    wdir = np.arctan2(*(w[:, 1] - w[:, 0])[:, ::-1].T)

    mapped_length = float(np.hypot(*(m[:, 1] - m[:, 0]).T).sum())
    if len(m):
        mp, mo, mlen = sample_segments(m)
        d, _ = nearest_segment(mp, w, mdir[mo], angle_tol_rad)
        precision = float(mlen[d <= tol_m].sum() / mlen.sum())
    else:
        precision = 0.0
    wp, wo, wlen = sample_segments(w)
    if seen_points is not None:
        seen = cKDTree(np.asarray(seen_points, dtype=float).reshape(-1, 2))
        dseen, _ = seen.query(wp, distance_upper_bound=tol_m)
        keep = np.isfinite(dseen)
        wp, wo, wlen = wp[keep], wo[keep], wlen[keep]
    seen_length = float(wlen.sum())
    if len(m) and len(wp):
        d, _ = nearest_segment(wp, m, wdir[wo], angle_tol_rad)
        completeness = float(wlen[d <= tol_m].sum() / wlen.sum())
    else:
        completeness = 0.0
    return MapQuality(precision, completeness, mapped_length, seen_length)
