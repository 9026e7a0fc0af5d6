"""Cross-particle global map (report §5) and the refresh of the particles' maps from it.

Every element of every particle gets a weight (its trust — match quality, with a preference for
older and confirmed elements — times its particle's weight). Per column (one element identity
across particles, see particles.py) the global map takes the version with the highest weight
(report §5.2 ii: "the choice of which element to be selected from which particle's world map is
made based on the weights"). Then the particles' maps are refreshed from the global map for the
elements it is sure of and that are out of view (report §5.2 iii), so a particle that is good
now inherits what another particle mapped well earlier.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from robot_agent.slam.particles import ParticleSet
from robot_agent.slam.resampling import normalized_weights
from robot_agent.slam.update import TrustConfig, element_trust


@dataclass(frozen=True)
class ConsensusConfig:
    enabled: bool = True
    every: int = 10  # steps between global-map builds
    refresh: bool = True
    refresh_min_trust: float = 0.5  # only elements the global map is sure of ...
    refresh_min_support: float = 0.5  # ... that most of the particle weight agrees exists ...
    refresh_quiet_steps: int = 30  # ... and that nobody has seen for this long (out of view)
    # the trusted subset the agent publishes. Trust includes the match quality, a running mean of
    # exp(-cost/2) (a chi-square tail probability): about 0.5 for a true wall the model fits, lower
    # for one seen only from far away or through a door. Elements refreshed or relocalized on
    # keep the stricter trust of refresh_min_trust / relocalization.min_trust.
    publish_min_trust: float = 0.15
    publish_min_hits: int = 3


@dataclass(frozen=True)
class GlobalMap:
    """The consensus map: ``G`` elements (columns ``cols (G,)``), each the best particle version.

    ``seg (G,2,2)``, ``alpha/rho/facing (G,)``, ``moments (G,6)``, ``hits/born/last_seen (G,)``,
    ``trust (G,)`` the winning weight's element trust, ``support (G,)`` the share of particle
    weight whose map has the element, ``source (G,)`` the particle it was taken from.
    """

    step: int
    cols: np.ndarray
    seg: np.ndarray
    alpha: np.ndarray
    rho: np.ndarray
    facing: np.ndarray
    moments: np.ndarray
    hits: np.ndarray
    born: np.ndarray
    last_seen: np.ndarray
    trust: np.ndarray
    support: np.ndarray
    source: np.ndarray

    def __len__(self) -> int:
        return len(self.cols)

    def trusted(self, min_trust: float, min_hits: int) -> np.ndarray:
        """Mask ``(G,)`` of the elements worth publishing."""
        return (self.trust >= min_trust) & (self.hits >= min_hits)


def build_global_map(ps: ParticleSet, step: int, trust_cfg: TrustConfig, cfg: ConsensusConfig) -> GlobalMap:
    maps = ps.maps
    cols = maps.used_columns()
    w_particle = normalized_weights(ps.log_weights)  # (P,)
    trust = element_trust(maps.columns(cols), step, trust_cfg)  # (P,G)
    # only particles that hold the element compete (-1 never wins over a holder's score >= 0)
    score = np.where(maps.valid[:, cols], trust * w_particle[:, None], -1.0)
    src = np.argmax(score, axis=0)  # (G,) the particle whose version wins
    support = np.sum(np.where(maps.valid[:, cols], w_particle[:, None], 0.0), axis=0)
    g = np.arange(len(cols))

    def pick(a: np.ndarray) -> np.ndarray:
        return a[src, cols]

    return GlobalMap(
        step=step,
        cols=cols,
        seg=pick(maps.seg),
        alpha=pick(maps.alpha),
        rho=pick(maps.rho),
        facing=pick(maps.facing),
        moments=pick(maps.moments),
        hits=pick(maps.hits),
        born=pick(maps.born),
        last_seen=maps.last_seen[:, cols].max(axis=0),
        trust=trust[src, g],
        support=support,
        source=src,
    )


def refresh_particles(ps: ParticleSet, gm: GlobalMap, step: int, cfg: ConsensusConfig) -> int:
    """Overwrite the particles' versions of the sure, out-of-view elements by the global one
    (and give it to particles that lost it). Returns the number of columns refreshed."""
    if not cfg.refresh or len(gm) == 0:
        return 0
    sure = (
        (gm.trust >= cfg.refresh_min_trust)
        & (gm.support >= cfg.refresh_min_support)
        & (step - gm.last_seen >= cfg.refresh_quiet_steps)
    )
    c = gm.cols[sure]
    if len(c) == 0:
        return 0
    maps = ps.maps
    src = gm.source[sure]
    lacking = ~maps.valid[:, c]  # (P,K): particles that get the element anew take its history too
    for name in ("quality", "hits", "last_seen", "misses"):
        arr = getattr(maps, name)
        arr[:, c] = np.where(lacking, arr[src, c][None, :], arr[:, c])
    maps.valid[:, c] = True
    maps.seg[:, c] = gm.seg[sure]
    maps.alpha[:, c] = gm.alpha[sure]
    maps.rho[:, c] = gm.rho[sure]
    maps.facing[:, c] = gm.facing[sure]
    maps.moments[:, c] = gm.moments[sure]
    maps.hits[:, c] = np.maximum(maps.hits[:, c], gm.hits[sure])
    maps.born[:, c] = gm.born[sure]
    maps.misses[:, c] = np.minimum(maps.misses[:, c], maps.misses[src, c])
    return len(c)
