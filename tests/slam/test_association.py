"""ML association (report §4.2): the right element among decoys, gates, pair terms, likelihood cap."""

import numpy as np
import pytest

from robot_agent.slam.association import (
    Association,
    AssociationConfig,
    associate,
    match_log_likelihood,
    observe,
    pair_terms,
)
from robot_agent.slam.particles import SegmentMaps
from shared.geometry import wrap_angle
from tests.maps import put_element as maps_put
from tests.maps import seen_from, wall_points

POINTS_PER_M = 20
POINT_SIGMA_M = 0.02
TRUE_POSE = np.array([1.0, 0.5, 0.3])
# particle poses: the truth, a pure translation (hand-computable offsets), a small rotation too
PARTICLE_OFFSETS = np.array([[0.0, 0.0, 0.0], [0.02, -0.01, 0.0], [-0.015, 0.02, 0.01]])


def scan_from_map(segments_map, pose):
    """Robot-frame ``moments (O,6), ends (O,2,2), facing (O,), cov (O,2,2)`` of walls given in the
    map frame, seen from ``pose`` (tests/maps.py)."""
    return seen_from(segments_map, pose, POINT_SIGMA_M, POINTS_PER_M)


def put_element(maps, col, a, b, facing, rows=slice(None)):
    maps_put(maps, col, wall_points(a, b, POINTS_PER_M), facing, rows, ends=[a, b], hits=5)


def _rotated(a, b, angle, centre):
    c, s = np.cos(angle), np.sin(angle)
    rot = np.array([[c, -s], [s, c]])
    return [tuple(rot @ (np.asarray(p, float) - centre) + centre) for p in (a, b)]


# Observed walls (map frame): W0 on y = 3 seen from below, W1 on x = 6 seen from the left.
W0 = ((1.0, 3.0), (3.0, 3.0))
W1 = ((6.0, 0.0), (6.0, 2.5))
DOWN, LEFT, UP = -np.pi / 2, np.pi, np.pi / 2
TRUE_W0, TRUE_W1, CLOSE_DECOY = 3, 5, 6


def room_with_decoys(n_particles=3):
    maps = SegmentMaps.empty(n_particles, 8)
    put_element(maps, 0, (3.6, 3.0), (6.0, 3.0), DOWN)  # same line, 0.6 m gap along it
    put_element(maps, 1, (1.0, 3.5), (3.0, 3.5), DOWN)  # parallel, 0.5 m behind
    put_element(maps, 2, (1.0, 3.1), (3.0, 3.1), UP)  # the other face of a 0.1 m thin wall
    put_element(maps, TRUE_W0, (0.5, 3.0), (3.4, 3.0), DOWN)
    a, b = _rotated(*W0, np.radians(20.0), np.array([2.0, 3.0]))
    put_element(maps, 4, a, b, DOWN + np.radians(20.0))  # rotated 20° about W0's centre
    put_element(maps, TRUE_W1, (6.0, -0.5), (6.0, 3.0), LEFT)
    put_element(maps, CLOSE_DECOY, (1.0, 2.88), (3.0, 2.88), DOWN)  # inside the gates, but farther
    return maps


def observations(offsets=PARTICLE_OFFSETS):
    poses = TRUE_POSE + offsets
    m, ends, facing, cov = scan_from_map([W0, W1], TRUE_POSE)
    return observe(poses, m, ends, facing, cov, POINT_SIGMA_M)


def test_observe_moves_the_scan_into_each_particles_frame():
    obs = observations()
    assert obs.alpha.shape == (3, 2) and obs.ends.shape == (3, 2, 2, 2)
    # particle 0 is at the truth: the walls come back where they are
    np.testing.assert_allclose(obs.ends[0, 0], np.array(W0), atol=1e-9)
    np.testing.assert_allclose(obs.centroid[0], [[2.0, 3.0], [6.0, 1.25]], atol=1e-9)
    np.testing.assert_allclose(wrap_angle(obs.facing[0] - [DOWN, LEFT]), 0.0, atol=1e-9)
    np.testing.assert_allclose(obs.alpha[0], [np.pi / 2, 0.0], atol=1e-9)
    np.testing.assert_allclose(obs.rho[0], [3.0, 6.0], atol=1e-9)
    # particle 1 is the truth shifted by (0.02, -0.01): so are its observations
    np.testing.assert_allclose(
        obs.ends[1] - obs.ends[0], np.broadcast_to([0.02, -0.01], (2, 2, 2)), atol=1e-9
    )
    n = obs.n_points
    np.testing.assert_allclose(obs.var_perp, POINT_SIGMA_M**2 / n)


def test_each_particle_picks_the_true_element_among_decoys():
    obs = observations()
    cfg = AssociationConfig()
    assoc = associate(obs, room_with_decoys(), cfg)
    np.testing.assert_array_equal(assoc.index, [[TRUE_W0, TRUE_W1]] * 3)
    assert np.all(assoc.matched)
    # pure translation (0.02, -0.01): offsets from y = 3 and x = 6 are -0.01 and +0.02
    np.testing.assert_allclose(assoc.d_perp[0], [0.0, 0.0], atol=1e-9)
    np.testing.assert_allclose(assoc.d_perp[1], [-0.01, 0.02], atol=1e-9)
    np.testing.assert_allclose(assoc.d_angle[:2], 0.0, atol=1e-9)
    assert assoc.d_angle[2] == pytest.approx([0.01, 0.01], abs=1e-9)
    var_p = obs.var_perp + cfg.sigma_perp_m**2
    np.testing.assert_allclose(assoc.cost[1], np.array([0.01, 0.02]) ** 2 / var_p, rtol=1e-6)


@pytest.mark.parametrize("decoy", [0, 1, 2, 4], ids=["far-gap", "parallel-0.5m", "other-face", "rot-20deg"])
def test_each_decoy_alone_is_outside_the_gates(decoy):
    maps = room_with_decoys()
    keep = np.zeros(maps.capacity, bool)
    keep[decoy] = True
    maps.valid &= keep[None, :]
    assoc = associate(observations(), maps, AssociationConfig())
    np.testing.assert_array_equal(assoc.index, -1)
    assert np.all(np.isinf(assoc.cost)) and not np.any(assoc.matched)


def test_decoy_inside_the_gates_wins_only_when_the_true_element_is_missing():
    maps = room_with_decoys()
    maps.valid[1, TRUE_W0] = False  # particle 1 never mapped W0's true element
    assoc = associate(observations(), maps, AssociationConfig())
    np.testing.assert_array_equal(
        assoc.index, [[TRUE_W0, TRUE_W1], [CLOSE_DECOY, TRUE_W1], [TRUE_W0, TRUE_W1]]
    )
    # particle 1's W0 lies at y = 2.99, the decoy at y = 2.88 with normal +y: offset +0.11
    assert assoc.d_perp[1, 0] == pytest.approx(0.11, abs=1e-9)


def test_unmatched_when_every_element_is_outside_the_gates():
    maps = room_with_decoys()
    maps.valid[:, [TRUE_W0, TRUE_W1, CLOSE_DECOY]] = False
    assoc = associate(observations(), maps, AssociationConfig())
    np.testing.assert_array_equal(assoc.index, -1)
    assert np.all(np.isinf(assoc.cost))
    # gates 2.5× wider (uncertain pose) admit the 0.6 m gap (< 0.75) and the parallel wall 0.5 m
    # behind (< 0.625); the gap costs (0.6 / 0.3)² = 4, the offset 0.5² / 0.05² ≈ 100: the gap wins
    wide = associate(observations(), maps, AssociationConfig(), gate_scale=2.5)
    np.testing.assert_array_equal(wide.index[:, 0], 0)
    assert wide.cost[0, 0] == pytest.approx(4.0, rel=1e-6)
    maps.valid[:, [0, 4]] = False  # (30° admits the 20°-rotated one as well)
    wide = associate(observations(), maps, AssociationConfig(), gate_scale=2.5)
    np.testing.assert_array_equal(wide.index[:, 0], 1)
    assert wide.d_perp[0, 0] == pytest.approx(-0.5, abs=1e-9)


def test_empty_map_gives_no_match():
    assoc = associate(observations(), SegmentMaps.empty(3, 0), AssociationConfig())
    assert assoc.index.shape == (3, 2)
    np.testing.assert_array_equal(assoc.index, -1)


def _one_observation_at_identity(n_particles=1):
    m, ends, facing, cov = scan_from_map([W0], np.zeros(3))  # robot at the origin: robot = map frame
    return observe(np.zeros((n_particles, 3)), m, ends, facing, cov, POINT_SIGMA_M)


@pytest.mark.parametrize(
    ("a", "b", "gap"),
    [
        ((2.0, 3.0), (5.0, 3.0), 0.0),  # overlapping
        ((1.5, 3.0), (2.5, 3.0), 0.0),  # contained
        ((3.0, 3.0), (4.0, 3.0), 0.0),  # touching
        ((3.7, 3.0), (5.0, 3.0), 0.7),  # disjoint, on the right
        ((5.0, 3.0), (3.7, 3.0), 0.7),  # same, endpoints reversed
        ((-2.0, 3.0), (0.25, 3.0), 0.75),  # disjoint, on the left
    ],
)
def test_pair_terms_gap_along_the_line(a, b, gap):
    obs = _one_observation_at_identity()  # x in [1, 3] on y = 3
    maps = SegmentMaps.empty(1, 1)
    put_element(maps, 0, a, b, DOWN)
    d_angle, d_perp, g = pair_terms(obs, maps)
    assert g.shape == (1, 1, 1)
    assert g[0, 0, 0] == pytest.approx(gap, abs=1e-9)
    assert d_angle[0, 0, 0] == pytest.approx(0.0, abs=1e-9)
    assert d_perp[0, 0, 0] == pytest.approx(0.0, abs=1e-9)


def test_pair_terms_signed_offset_and_facing_difference():
    obs = _one_observation_at_identity()
    maps = SegmentMaps.empty(1, 3)
    put_element(maps, 0, (1.0, 3.5), (3.0, 3.5), DOWN)  # normal +y, rho 3.5: centroid is 0.5 short
    put_element(maps, 1, (1.0, 2.6), (3.0, 2.6), DOWN)  # 0.4 beyond
    put_element(maps, 2, (1.0, 3.0), (3.0, 3.0), UP)  # other face
    d_angle, d_perp, gap = pair_terms(obs, maps)
    np.testing.assert_allclose(d_perp[0, 0], [-0.5, 0.4, 0.0], atol=1e-9)
    np.testing.assert_allclose(d_angle[0, 0], [0.0, 0.0, np.pi], atol=1e-9)
    np.testing.assert_allclose(gap[0, 0], 0.0, atol=1e-9)


def test_match_log_likelihood_is_gaussian_and_capped_below_by_log_p_new():
    cfg = AssociationConfig()
    obs3 = _one_observation_at_identity(3)
    # particle 0: good match; 1: matched but 0.3 m off; 2: unmatched
    assoc = Association(
        index=np.array([[0], [0], [-1]]),
        cost=np.array([[0.1], [40.0], [np.inf]]),
        d_angle=np.array([[0.01], [0.0], [np.inf]]),
        d_perp=np.array([[0.01], [0.3], [np.inf]]),
    )
    log_p_new = -4.0
    ll = match_log_likelihood(assoc, obs3, cfg, log_p_new)
    var_a = obs3.var_angle[0] + cfg.sigma_angle_rad**2
    var_p = obs3.var_perp[0] + cfg.sigma_perp_m**2
    assert ll.shape == (3, 1)
    assert ll[0, 0] == pytest.approx(-0.5 * (0.01**2 / var_a + 0.01**2 / var_p), rel=1e-9)
    assert -0.5 * 0.3**2 / var_p < log_p_new  # the raw Gaussian term would be far below the cap
    assert ll[1, 0] == log_p_new
    assert ll[2, 0] == log_p_new
    assert np.all(ll >= log_p_new)
