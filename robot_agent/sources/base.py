"""The one interface every scan source offers: a stream of :class:`Scan` records."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from typing import Protocol

import numpy as np


@dataclass(frozen=True)
class Scan:
    """One laser scan with the odometry read at the same time.

    ``ranges_m`` (B,) and ``angles_rad`` (B,) are in the laser frame; a reading ``>=
    range_max_m`` (or non-finite) means "no return". ``odometry`` (3,) is the robot pose
    ``(x, y, theta)`` integrated by wheel odometry in its own odometry frame; ``laser_offset``
    (3,) is the laser pose in the robot frame.
    """

    stamp_s: float
    ranges_m: np.ndarray
    angles_rad: np.ndarray
    odometry: np.ndarray
    laser_offset: np.ndarray
    range_max_m: float


class ScanSource(Protocol):
    """Anything that yields scans in time order (log replay, live simulator)."""

    def scans(self) -> Iterator[Scan]: ...
