"""A robot moved without odometry seeing it — picked up and carried, pushed while its wheels
stood, a log cut and spliced (issue 24: "a teleport").

The filter cannot notice it by itself: it aligns the scan to the map near where odometry puts
the robot, and in a building of alike corridors it finds a fit there and maps the new place over
the old one. Consecutive scans notice: moved by odometry's increment, a scan lies on the one
before it (Intel, the whole log: 30 % of the points at least, every scan). When two scans in a
row disagree with the last one that agreed, the filter doubts (:class:`Doubt`): it stops changing
its map, keeps tracking against the map as it was, and looks for the scan in the whole map
(:func:`robot_agent.slam.relocalize.relocalize_global`). Found twice, consistently, far from the
estimate: the robot was moved, and every particle moves there. Not found within ``doubt_m`` of
driving: when the estimate fitted the map where the doubt began, odometry erred and the filter
was right (ACES and MIT-CSAIL have such stretches); when it did not, the robot is somewhere the
map does not know and the filter gives up (:attr:`FastSLAM.lost`): the agent starts a new
session.

Not noticed: a robot moved to where the scan looks as it did, at odometry's pose (Intel's scan
700 carried to where scan 100 was: 0.58 of the points agree) — the filter maps on there.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from robot_agent.slam import kernels
from shared.geometry import apply_points, relative_one


@dataclass(frozen=True)
class KidnapConfig:
    enabled: bool = True
    points: int = 100  # scan points compared, spread over the scan
    tol_m: float = 0.1  # a point lies on the other scan within this ...
    tol_per_m: float = 0.05  # ... plus this per metre of its range (odometry's heading lags)
    compiled: bool = True  # the nearest-point search by the compiled kernel (kernels.py) when built
    min_overlap: float = 0.3  # a scan agrees with the reference when this share of it lies on it
    suspect_scans: int = 2  # this many scans in a row that disagree: doubt
    doubt_m: float = 3.0  # driving in doubt (odometry) before deciding without a relocalization ...
    doubt_scans: int = 150  # ... or this many scans (a robot that stands)
    far_m: float = 1.0  # a relocalization this far (or turning this much) from the estimate ...
    far_rad: float = np.radians(20.0)  # ... is a kidnapping (closer: tracking's business)
    pair_gap_m: float = 3.0  # map segments this far apart make a corner for the whole-map search
    explain_share: float = 0.7  # ... and a place found must explain this share of the scan's
    # segment length (Intel's own place: all of it; an alike corridor of another building: 0.38)
    fit_m: float = 0.1  # the estimate's fit: the share of the scan's points within this of the map
    lost_fit: float = 0.4  # below this at each of the doubt's first ``first_steps`` steps, and
    first_steps: int = 3  # nowhere found since: lost (MIT-CSAIL's odometry errs where the estimate
    # fits 0.5-0.6 and then drives on out of the map; Intel's scans carried into ACES fit 0.2)


def thin(points: np.ndarray, n: int) -> np.ndarray:
    """At most ``n`` of ``points (N,2)``, spread evenly over the scan's order."""
    if len(points) <= n:
        return points
    return points[np.linspace(0, len(points) - 1, n).astype(int)]


def overlap(
    ref_points: np.ndarray,
    ref_odometry: np.ndarray,
    points: np.ndarray,
    odometry: np.ndarray,
    cfg: KidnapConfig,
) -> float:
    """Share of ``points (N,2)`` (robot frame) on ``ref_points`` once moved by odometry's
    increment from the reference scan; 1 when either has too few points to judge (a blind laser
    is another fault, :mod:`robot_agent.health`)."""
    if len(ref_points) < 10 or len(points) < 10:
        return 1.0
    q = apply_points(relative_one(ref_odometry, odometry), points)
    r = np.hypot(points[:, 0], points[:, 1])
    tol = cfg.tol_m + cfg.tol_per_m * r
    if cfg.compiled and kernels.AVAILABLE and tol.max() > 0:  # a point farther than every tolerance: inf
        d = kernels.nearest_within(ref_points, q, float(tol.max()))
    else:
        d, _ = cKDTree(ref_points).query(q)
    return float(np.mean(d < tol))


@dataclass
class Doubt:
    """Scans disagreed with the last agreeing one from ``scan`` (trajectory index) on."""

    scan: int
    odometer_m: float  # the filter's odometer when it began
    scans: int = 0
    fits: list = field(default_factory=list)  # the estimate's fit at each processed step
    pending: object = None  # a relocalization found once (relocalize.Pending)
