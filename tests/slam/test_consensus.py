"""Cross-particle global map (report §5): per-column choice, support, and refresh of the particles."""

import numpy as np
import pytest

from robot_agent.slam.consensus import ConsensusConfig, build_global_map, refresh_particles
from robot_agent.slam.particles import ParticleSet
from robot_agent.slam.update import TrustConfig, element_trust
from tests.maps import put_element as maps_put

STEP = 100
WEIGHTS = np.array([0.8, 0.1, 0.1])  # particle 0 much heavier
DOWN, LEFT = -np.pi / 2, np.pi


def put_element(maps, row, col, a, b, facing, *, born=0, last_seen=0, hits=10, quality=0.9):
    points = np.linspace(a, b, 21)
    fields = {"born": born, "last_seen": last_seen, "hits": hits, "quality": quality}
    maps_put(maps, col, points, facing, row, ends=[a, b], **fields)


def particle_set():
    """Column 0: all three hold a version (y = 2.0, 2.1, 2.2), equally trusted, all quiet.
    Column 1: particles 0 and 2 (quiet, sure). Column 2: only particle 1.
    Column 3: particles 0 and 2, but seen 5 steps ago (in view)."""
    ps = ParticleSet.create(3)
    ps.maps.misses[:] = 0.0
    ps.log_weights = np.log(WEIGHTS)
    m = ps.maps
    for p, y in enumerate([2.0, 2.1, 2.2]):
        put_element(m, p, 0, (0.0, y), (3.0, y), DOWN, last_seen=50)
    for p in (0, 2):
        put_element(m, p, 1, (5.0, 0.0), (5.0, 3.0), LEFT, last_seen=40)
        put_element(m, p, 3, (0.0, 6.0), (4.0, 6.0), DOWN, last_seen=STEP - 5)
    put_element(m, 1, 2, (-2.0, 1.0), (-2.0, 3.0), 0.0, last_seen=60)
    return ps


def test_global_map_takes_the_heavy_particles_version_of_a_shared_column():
    ps = particle_set()
    gm = build_global_map(ps, STEP, TrustConfig(), ConsensusConfig())
    np.testing.assert_array_equal(gm.cols, [0, 1, 2, 3])
    assert len(gm) == 4
    assert gm.source[0] == 0
    assert gm.rho[0] == pytest.approx(2.0)
    np.testing.assert_allclose(gm.seg[0], [[0.0, 2.0], [3.0, 2.0]])
    np.testing.assert_allclose(gm.moments[0], ps.maps.moments[0, 0])
    trust = element_trust(ps.maps, STEP, TrustConfig())
    assert gm.trust[0] == pytest.approx(trust[0, 0])
    assert gm.source[2] == 1  # the only holder wins however light it is
    assert gm.source[1] == 0 and gm.source[3] == 0  # equal trust: the heavier particle


def test_element_trust_beats_particle_weight_when_much_larger():
    ps = particle_set()
    ps.maps.quality[0, 0] = 0.05  # particle 0's version is poor: 0.8 × 0.05 < 0.1 × 0.9
    gm = build_global_map(ps, STEP, TrustConfig(), ConsensusConfig())
    assert gm.source[0] in (1, 2)
    assert gm.rho[0] == pytest.approx([2.1, 2.2][gm.source[0] - 1])


def test_support_is_the_weight_share_of_the_holders():
    gm = build_global_map(particle_set(), STEP, TrustConfig(), ConsensusConfig())
    np.testing.assert_allclose(gm.support, [1.0, 0.9, 0.1, 0.9], atol=1e-12)
    # log-weights need not be normalized
    ps = particle_set()
    ps.log_weights = ps.log_weights + 17.0
    np.testing.assert_allclose(
        build_global_map(ps, STEP, TrustConfig(), ConsensusConfig()).support, [1.0, 0.9, 0.1, 0.9], atol=1e-12
    )


def test_global_last_seen_is_the_latest_of_any_particle():
    ps = particle_set()
    ps.maps.last_seen[2, 0] = 77
    gm = build_global_map(ps, STEP, TrustConfig(), ConsensusConfig())
    assert gm.last_seen[0] == 77
    assert gm.last_seen[3] == STEP - 5


def test_refresh_copies_sure_quiet_elements_and_leaves_recent_ones_alone():
    ps = particle_set()
    cfg = ConsensusConfig()
    gm = build_global_map(ps, STEP, TrustConfig(), cfg)
    assert gm.trust[1] >= cfg.refresh_min_trust and gm.support[1] >= cfg.refresh_min_support
    before = {k: v.copy() for k, v in ps.maps.arrays().items()}
    n = refresh_particles(ps, gm, STEP, cfg)
    # column 0 (quiet, support 1) and 1 (quiet, support 0.9); not 2 (support 0.1), not 3 (recent)
    assert n == 2
    m = ps.maps
    assert m.valid[1, 1]  # particle 1 lacked column 1: it has it now, the global version
    np.testing.assert_allclose(m.seg[1, 1], gm.seg[1])
    assert (m.alpha[1, 1], m.rho[1, 1], m.facing[1, 1]) == (gm.alpha[1], gm.rho[1], gm.facing[1])
    np.testing.assert_allclose(m.moments[1, 1], gm.moments[1])
    assert m.hits[1, 1] == gm.hits[1] and m.born[1, 1] == gm.born[1]
    # column 0: everyone now holds particle 0's version
    np.testing.assert_allclose(m.rho[:, 0], 2.0)
    # column 3 is recently seen: particle 1 still lacks it, the others keep theirs
    assert not m.valid[1, 3]
    for k in ("seg", "moments", "alpha", "rho"):
        np.testing.assert_array_equal(getattr(m, k)[:, 3], before[k][:, 3], err_msg=k)
    # column 2 (only particle 1, light) is not pushed to the others
    np.testing.assert_array_equal(m.valid[:, 2], [False, True, False])


def test_refresh_disabled_or_not_quiet_does_nothing():
    ps = particle_set()
    gm = build_global_map(ps, STEP, TrustConfig(), ConsensusConfig())
    assert refresh_particles(ps, gm, STEP, ConsensusConfig(refresh=False)) == 0
    assert refresh_particles(ps, gm, 60, ConsensusConfig()) == 0  # 60 - 50 < 30 steps quiet
    assert not ps.maps.valid[1, 1]


def test_refreshed_element_is_as_trusted_in_the_particle_that_lacked_it():
    ps = particle_set()
    cfg = ConsensusConfig()
    gm = build_global_map(ps, STEP, TrustConfig(), cfg)
    refresh_particles(ps, gm, STEP, cfg)
    trust = element_trust(ps.maps, STEP, TrustConfig())
    assert trust[1, 1] == pytest.approx(gm.trust[1], rel=1e-6)


def test_global_version_comes_from_a_particle_that_holds_it():
    ps = particle_set()
    ps.log_weights = np.array([0.0, 0.0, -2000.0])  # particle 2's weight underflows to 0
    ps.maps.valid[:, 1] = [False, False, True]  # particle 0's column 1 holds stale data now
    gm = build_global_map(ps, STEP, TrustConfig(), ConsensusConfig())
    assert gm.source[1] == 2
    assert gm.trust[1] > 0.0


def test_published_subset_keeps_a_confirmed_wall_of_average_match_quality():
    """Match quality is a chi-square tail probability, about 0.5 for a wall the model fits; a
    well-confirmed element with that quality and some misses is published; one with too few hits
    or seen through again and again is not."""
    ps = ParticleSet.create(1)
    ps.log_weights = np.zeros(1)
    m = ps.maps
    put_element(m, 0, 0, (0.0, 2.0), (3.0, 2.0), DOWN, hits=40, quality=0.45)
    m.misses[0, 0] = 1.5
    put_element(m, 0, 1, (5.0, 0.0), (5.0, 3.0), LEFT, hits=2, quality=0.9)  # too few hits
    put_element(m, 0, 2, (0.0, 6.0), (4.0, 6.0), DOWN, hits=40, quality=0.45)
    m.misses[0, 2] = 2.9  # seen through again and again: about to be cleaned away
    cfg = ConsensusConfig()
    gm = build_global_map(ps, STEP, TrustConfig(), cfg)
    published = gm.trusted(cfg.publish_min_trust, cfg.publish_min_hits)
    np.testing.assert_array_equal(published, [True, False, False])
