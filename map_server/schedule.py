"""Which placed maps are near which, and what a robot's alignment attempt was made against: the
bookkeeping by which the rounds decide that an attempt is due again (placing.py; state.RobotState.due).
A placed robot is refined again only when the maps near it changed, so its key names those maps
— their lengths and places — and nothing farther away."""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from map_server.state import RobotState


def global_box(bounds: np.ndarray, transforms: np.ndarray) -> np.ndarray:
    """Boxes ``(N,4)`` (x0, y0, x1, y1) in the global frame around map-frame boxes ``bounds (N,4)``
    moved by ``transforms (N,3)``."""
    corners = bounds[:, [[0, 1], [2, 1], [2, 3], [0, 3]]]  # (N,4,2)
    c, s = np.cos(transforms[:, 2])[:, None], np.sin(transforms[:, 2])[:, None]
    x = c * corners[..., 0] - s * corners[..., 1] + transforms[:, 0, None]
    y = s * corners[..., 0] + c * corners[..., 1] + transforms[:, 1, None]
    return np.column_stack([x.min(axis=1), y.min(axis=1), x.max(axis=1), y.max(axis=1)])


class Around:
    """Which placed maps (robots and retired pieces) are near which, from their global boxes at the
    start of a round (computed once, when first needed): a box grown by ``margin_m`` meets the
    other's box."""

    def __init__(self, items: list, margin_m: float):
        self.items, self.margin_m = items, margin_m
        self._row = {id(x): i for i, x in enumerate(items)}
        self._meet: np.ndarray | None = None

    def near(self, r: RobotState) -> list | None:
        """The maps near placed robot ``r`` (itself included), or None if it is not one of them."""
        i = self._row.get(id(r))
        if i is None:
            return None
        if self._meet is None:
            bounds = np.array([x.layer.bounds for x in self.items])
            box = global_box(bounds, np.array([x.alignment.transform for x in self.items]))
            grown = box + np.array([-1.0, -1.0, 1.0, 1.0]) * self.margin_m
            self._meet = (grown[:, None, 0] <= box[None, :, 2]) & (grown[:, None, 2] >= box[None, :, 0])
            self._meet &= (grown[:, None, 1] <= box[None, :, 3]) & (grown[:, None, 3] >= box[None, :, 1])
        return [self.items[j] for j in np.flatnonzero(self._meet[i])]


class PlacedKey:
    """What robot ``r`` is aligned against, as a string that changes when that changes (lazily:
    most checks do not need it): the placed maps — robots and retired pieces — with their lengths
    and places; for a placed robot only those near it (:class:`Around`): a map far away does not
    change where the robot fits; for an unplaced one also where the fleet's graph bent them (to
    the centimetre: its first and newest keyframe)."""

    def __init__(self, r: RobotState, against: Callable[[], list], around: Around, entries: dict):
        self.r, self.against, self.around, self.entries = r, against, around, entries
        self._text: str | None = None

    def __call__(self) -> str:
        if self._text is None:
            near = self.around.near(self.r) if self.r.alignment.placed else None
            if near is not None:  # the maps near it at the start of the round but itself
                near = [p for p in near if p is not self.r]
            against = self.against() if near is None else near
            self._text = placed_key(against, self.entries)
            if not self.r.alignment.placed:  # where the fleet's graph bent them too: an unplaced
                # robot is searched against the bent maps when the rigid ones give no place
                self._text += "".join(
                    f"~{p.robot}:" + ":".join(f"{v:.2f}" for v in p.bent_x[[0, -1]].ravel())
                    for p in against
                    if getattr(p, "bent", None) is not None
                )
        return self._text


def placed_key(placed: list, entries: dict | None = None) -> str:
    """Which maps are placed, how long they are and where. ``entries``: a cache of each map's
    part, per robot or retired piece (its layer and alignment are replaced on a change, never
    modified, so the part is formatted again only then)."""
    out = []
    for r in placed:
        k = (r.robot, getattr(r, "session", None))
        hit = entries.get(k) if entries is not None else None
        if hit is None or hit[0] is not r.layer or hit[1] is not r.alignment:
            text = f"{r.robot}:{r.layer.length_m:.3f}:" + ":".join(f"{v:.5f}" for v in r.alignment.transform)
            hit = (r.layer, r.alignment, text)
            if entries is not None:
                entries[k] = hit
        out.append(hit[2])
    return ";".join(out)
