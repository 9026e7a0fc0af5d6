"""The laser's health as an agent sees it: unusable readings counted per scan, and a robot whose
laser goes mostly blind noticed.

A reading is *unusable* when it is not a number (NaN), infinite, negative, or absurdly far
(beyond ``ABSURD_RANGE_FACTOR`` times the laser's range limit: readings at or a little past the
limit are the laser's "no return", which logs hold by the thousand and which are not faults).
The filter drops unusable readings whatever happens here; this is what tells the operator.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field

import numpy as np

ABSURD_RANGE_FACTOR = 10.0
BLIND_WINDOW = 50  # scans: the laser is mostly blind when, over the last this many, ...
BLIND_SHARE = 0.5  # ... more than this share of the readings were unusable
KINDS = ("nan", "inf", "negative", "absurd")


def unusable_readings(ranges_m: np.ndarray, range_max_m: float) -> dict[str, int]:
    """How many readings of ``ranges_m`` are unusable, by kind (:data:`KINDS`)."""
    r = np.asarray(ranges_m, dtype=float)
    nan = np.isnan(r)
    inf = np.isinf(r)
    finite = ~(nan | inf)
    limit = ABSURD_RANGE_FACTOR * range_max_m if np.isfinite(range_max_m) else np.inf
    with np.errstate(invalid="ignore"):
        negative = finite & (r < 0)
        absurd = finite & (r > limit)
    return {
        "nan": int(nan.sum()),
        "inf": int(inf.sum()),
        "negative": int(negative.sum()),
        "absurd": int(absurd.sum()),
    }


@dataclass
class LaserHealth:
    """Counts over the run (``scans_with_unusable``, ``unusable``, ``readings``, ``by_kind``), the
    last scan's (``last_unusable``, ``last_readings``), and whether the laser is mostly blind now
    (``blind``: over the last BLIND_WINDOW scans more than BLIND_SHARE of the readings unusable)."""

    scans: int = 0
    readings: int = 0
    unusable: int = 0
    scans_with_unusable: int = 0
    by_kind: dict = field(default_factory=lambda: dict.fromkeys(KINDS, 0))
    last_unusable: int = 0
    last_readings: int = 0
    blind: bool = False
    blind_spells: int = 0  # times the laser went mostly blind
    _window: deque = field(default_factory=lambda: deque(maxlen=BLIND_WINDOW))  # (bad, readings)
    _window_bad: int = 0  # the window's sums, kept as it slides
    _window_seen: int = 0

    def add(self, ranges_m: np.ndarray, range_max_m: float) -> None:
        kinds = unusable_readings(ranges_m, range_max_m)
        bad, n = sum(kinds.values()), int(np.size(ranges_m))
        self.scans += 1
        self.readings += n
        self.unusable += bad
        self.scans_with_unusable += bad > 0
        for k, v in kinds.items():
            self.by_kind[k] += v
        self.last_unusable, self.last_readings = bad, n
        if len(self._window) == BLIND_WINDOW:
            out_bad, out_seen = self._window[0]
            self._window_bad -= out_bad
            self._window_seen -= out_seen
        self._window.append((bad, n))
        self._window_bad += bad
        self._window_seen += n
        full = len(self._window) == BLIND_WINDOW
        blind = full and self._window_bad > BLIND_SHARE * max(self._window_seen, 1)
        if blind and not self.blind:
            self.blind_spells += 1
        self.blind = blind

    @property
    def recent_share(self) -> float:
        """The share of unusable readings over the last BLIND_WINDOW scans."""
        return self._window_bad / self._window_seen if self._window_seen else 0.0

    def status(self) -> dict[str, float]:
        """Named numbers for a status report: the last scan's and the run's."""
        return {
            "laser_unusable_last": float(self.last_unusable),
            "laser_readings_last": float(self.last_readings),
            "laser_unusable_share_recent": self.recent_share,
            "laser_unusable_total": float(self.unusable),
            "laser_scans_with_unusable": float(self.scans_with_unusable),
            "laser_blind": float(self.blind),
        }
