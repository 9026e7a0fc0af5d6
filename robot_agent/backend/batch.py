"""The pose-graph back end over a whole trajectory, and the map rebuilt along its result.

One implementation for every robot that has its scans: ``replay`` at the end of a log, a log
piece's agent, a simulated agent at the end of its run (the pure graph and matching live in
:mod:`robot_agent.slam.backend`, :mod:`~robot_agent.slam.posegraph`,
:mod:`~shared.scanmatch`).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from robot_agent.slam.backend import run_backend
from robot_agent.slam.extraction import scan_points
from robot_agent.slam.fastslam import FastSLAM, SlamConfig
from robot_agent.sources import LaserLog
from shared.geometry import apply_points, compose, inverse
from shared.metrics import align_se2


def correct_trajectory(
    log: LaserLog,
    first: int,
    stamps: np.ndarray,
    poses: np.ndarray,
    cfg: SlamConfig,
    hints: list[tuple[int, np.ndarray]] | None = None,
    jumps: np.ndarray | None = None,
    gauge: str = "fit",
) -> tuple[np.ndarray, dict | None]:
    """The back end (pose graph) over ``poses (S,3)``, the trajectory of scans ``first ..
    first + S - 1`` of ``log``: the corrected poses and the back end's statistics (``poses`` and
    ``None`` when it is disabled).

    ``gauge``: ``"fit"`` puts the corrected trajectory where it fits ``poses`` best (it then
    agrees with the filter's map, drawn along ``poses``); ``"start"`` keeps its first pose at
    ``poses[0]`` — the map frame stays the robot's start frame, for a map rebuilt along the
    corrected path (:func:`remap`) that a server places against a start prior or other robots."""
    if gauge not in ("fit", "start"):
        raise ValueError(f"gauge must be 'fit' or 'start', got {gauge!r}")
    if not cfg.backend.enabled or len(poses) < 2:
        return poses, None

    def points(i: int) -> np.ndarray:
        return scan_points_robot(log, first + i, cfg)

    odometry = log.odometry[first : first + len(poses)]
    corrected, stats = run_backend(stamps, poses, odometry, points, cfg.backend, hints, jumps)
    if gauge == "start":
        return compose(compose(poses[0], inverse(corrected[0])), corrected), stats
    # the pose graph holds the first pose fixed, an arbitrary gauge: the map (built along the
    # filter's trajectory) is in the frame that fits the filter's trajectory best, so that is where
    # the corrected trajectory is put (relative motions, what relations score, are unchanged)
    gauge = align_se2(corrected[:, :2], poses[:, :2])
    return compose(gauge, corrected), stats


def scan_points_robot(log: LaserLog, i: int, cfg: SlamConfig) -> np.ndarray:
    """Scan ``i``'s points ``(N,2)`` in the robot frame (its valid beams, laser mount applied)."""
    scan = log.scan(i)
    xy = scan_points(scan.ranges_m, scan.angles_rad, cfg.extraction, scan.range_max_m)
    return apply_points(scan.laser_offset, xy)


def remap(log: LaserLog, first: int, poses: np.ndarray, cfg: SlamConfig) -> FastSLAM:
    """A one-particle filter whose map is built along ``poses (S,3)``, the known poses of scans
    ``first .. first + S - 1`` of ``log`` (e.g. the back end's corrected trajectory): the same
    extraction, association, update and cleaning, no sampling and no relocalization. Its map and
    those poses agree, which the filter's map (drawn along the uncorrected path) does not."""
    known = replace(cfg, particles=1, relocalization=replace(cfg.relocalization, enabled=False))
    slam = FastSLAM(known, np.random.default_rng(0))
    for i in range(len(poses)):
        feed(slam, log, first + i, poses[i])
    return slam


def feed(slam: FastSLAM, log: LaserLog, i: int, pose: np.ndarray | None = None) -> None:
    """Scan ``i`` of ``log`` to ``slam`` (with its own beams: the geometry may change from scan to
    scan); ``pose``: its known pose (mapping along a given path)."""
    scan = log.scan(i)
    slam.step(
        scan.stamp_s, scan.odometry, scan.ranges_m, scan.angles_rad, scan.laser_offset, scan.range_max_m, pose
    )
