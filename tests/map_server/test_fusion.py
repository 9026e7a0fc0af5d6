"""Cross-particle fusion of one robot's map and the merge of collinear segments across robots."""

import numpy as np
import pytest

from map_server.fusion import FusionConfig, collinear_pairs, fuse_particles, merge_segments
from shared.geometry import point_line_distance
from shared.messages import RobotMap

CFG = FusionConfig()


def robot_map(seg, element, members, trust, weights=(0.5, 0.3, 0.2)):
    n = len(seg)
    return RobotMap(
        "r1", "s1", 1, 1.0, 0, 1, np.array(weights), np.zeros((len(weights), 3)), np.array(seg, float),
        np.array(element, np.int64), np.array(members, np.int64), np.array(trust, float),
        np.full(n, 5, np.int64), np.full(n, 50, np.int64),
    )  # fmt: skip


WALL_A = [(0.0, 0.0), (4.0, 0.0)]
WALL_A2 = [(0.0, 0.05), (4.2, 0.05)]  # another version of the same element
WALL_B = [(5.0, 1.0), (5.0, 3.0)]


def test_the_version_of_highest_weight_times_trust_wins():
    # element 7: version 1 held by particles 0 and 1 (0.5 + 0.3) at trust 0.5 -> 0.40;
    # version 2 held by particle 2 (0.2) at trust 0.9 -> 0.18. Version 1 wins despite lower trust.
    m = robot_map([WALL_A, WALL_A2], [7, 7], [0b011, 0b100], [0.5, 0.9])
    layer = fuse_particles(m, CFG)
    assert len(layer) == 1
    np.testing.assert_array_equal(layer.seg[0], WALL_A)
    assert layer.support[0] == pytest.approx(1.0)  # every particle holds some version
    assert layer.weight[0] == pytest.approx(0.40)
    assert layer.trust[0] == 0.5
    # with particle 2 heavier the other version wins
    m = robot_map([WALL_A, WALL_A2], [7, 7], [0b011, 0b100], [0.5, 0.9], weights=(0.2, 0.1, 0.7))
    np.testing.assert_array_equal(fuse_particles(m, CFG).seg[0], WALL_A2)


def test_an_element_only_a_light_particle_holds_is_dropped():
    # element 3 only in particle 2 (0.2 of the 1.0 sent): support 0.2 < 0.5
    m = robot_map([WALL_A, WALL_B], [1, 3], [0b111, 0b100], [0.6, 0.9])
    layer = fuse_particles(m, CFG)
    np.testing.assert_array_equal(layer.element, [1])
    # support is a share of the weight *sent*: the same map with weights summing to 0.5
    m = robot_map([WALL_A, WALL_B], [1, 3], [0b111, 0b011], [0.6, 0.9], weights=(0.2, 0.1, 0.2))
    layer = fuse_particles(m, CFG)
    assert layer.support[list(layer.element).index(3)] == pytest.approx(0.6)


def test_untrusted_elements_are_dropped():
    m = robot_map([WALL_A, WALL_B], [1, 2], [0b111, 0b111], [0.6, 0.1])
    np.testing.assert_array_equal(fuse_particles(m, CFG).element, [1])


def test_empty_map():
    m = robot_map(np.zeros((0, 2, 2)), [], [], [])
    assert len(fuse_particles(m, CFG)) == 0


# --- across robots ---------------------------------------------------------------------------


def test_overlapping_collinear_pieces_of_two_robots_merge_into_the_union():
    seg = np.array([[(0.0, 0.0), (3.0, 0.0)], [(2.0, 0.0), (6.0, 0.0)]])
    out, support, off, prov = merge_segments(seg, np.ones(2), np.array([0, 1]), CFG)
    assert len(out) == 1
    np.testing.assert_array_equal(support, [2])
    np.testing.assert_array_equal(off, [0, 2])
    np.testing.assert_array_equal(prov, [0, 1])
    np.testing.assert_allclose(out[0], [[0.0, 0.0], [6.0, 0.0]], atol=1e-9)


def test_the_refit_is_total_least_squares_not_endpoint_averaging():
    # a 6 m piece and a 4 m piece inside it, 0.02 m aside: by symmetry the TLS line is level,
    # at the length-weighted mean offset 4 * 0.02 / 10; endpoint averaging would give 0.01
    seg = np.array([[(0.0, 0.0), (6.0, 0.0)], [(1.0, 0.02), (5.0, 0.02)]])
    out, *_ = merge_segments(seg, np.ones(2), np.array([0, 1]), CFG)
    np.testing.assert_allclose(out[0], [[0.0, 0.008], [6.0, 0.008]], atol=1e-9)


def test_weights_pull_the_refit_toward_the_stronger_member():
    seg = np.array([[(0.0, 0.0), (4.0, 0.0)], [(0.0, 0.08), (4.0, 0.08)]])
    out, *_ = merge_segments(seg, np.array([3.0, 1.0]), np.array([0, 1]), CFG)
    np.testing.assert_allclose(out[0, :, 1], [0.02, 0.02], atol=1e-9)


def test_the_two_faces_of_a_thin_wall_stay_apart():
    # a 0.05 m wall seen from both sides: same line within tolerance, opposite facing
    seg = np.array([[(0.0, 0.0), (4.0, 0.0)], [(4.0, 0.05), (0.0, 0.05)]])
    out, support, _, _ = merge_segments(seg, np.ones(2), np.array([0, 1]), CFG)
    assert len(out) == 2
    np.testing.assert_array_equal(support, [1, 1])


def test_far_apart_collinear_pieces_stay_apart_and_touching_ones_merge():
    seg = np.array(
        [
            [(0.0, 0.0), (2.0, 0.0)],
            [(3.0, 0.0), (5.0, 0.0)],  # 1 m gap: a door, not one wall
            [(5.2, 0.0), (7.0, 0.0)],  # 0.2 m gap: the same wall
        ]
    )
    out, support, off, prov = merge_segments(seg, np.ones(3), np.array([0, 0, 1]), CFG)
    assert len(out) == 2
    order = np.argsort(out[:, 0, 0])
    np.testing.assert_allclose(out[order[0]], seg[0], atol=1e-9)
    np.testing.assert_allclose(out[order[1]], [[3.0, 0.0], [7.0, 0.0]], atol=1e-9)
    np.testing.assert_array_equal(support[order], [1, 2])
    i = order[1]
    np.testing.assert_array_equal(prov[off[i] : off[i + 1]], [0, 1])


def test_parallel_offset_and_angled_segments_do_not_merge():
    seg = np.array(
        [
            [(0.0, 0.0), (4.0, 0.0)],
            [(0.0, 0.3), (4.0, 0.3)],  # 0.3 m beside it
            [(0.0, 0.0), (4.0, 4.0 * np.tan(np.radians(10.0)))],  # 10 degrees off
        ]
    )
    assert len(collinear_pairs(seg, CFG)[0]) == 0
    out, *_ = merge_segments(seg, np.ones(3), np.zeros(3, np.int64), CFG)
    assert len(out) == 3


def test_a_bent_chain_splits_off_the_outliers():
    # 1 m pieces turning 4 degrees each: neighbours pass the pair test, the chain bends 28 degrees
    heading = np.radians(4.0) * np.arange(8)
    pts = np.vstack([[0.0, 0.0], np.cumsum(np.c_[np.cos(heading), np.sin(heading)], axis=0)])
    seg = np.stack([pts[:-1], pts[1:]], axis=1)
    assert len(collinear_pairs(seg, CFG)[0]) >= 7  # chained
    out, support, _, _ = merge_segments(seg, np.ones(len(seg)), np.zeros(len(seg), np.int64), CFG)
    assert support.sum() == len(seg)
    assert len(out) >= 2  # not one 8 m segment through all of them
    # every output segment stays within the outlier tolerance of its members
    mid = 0.5 * (seg[:, 0] + seg[:, 1])
    d = np.min(np.abs(point_line_distance(mid[:, None], out[None])), axis=1)
    assert d.max() <= CFG.outlier_perp_m


def test_merge_is_vectorized_over_many_segments():
    rng = np.random.default_rng(0)
    a = rng.uniform(0, 100, (3000, 2))
    ang = rng.uniform(-np.pi, np.pi, 3000)
    seg = np.stack([a, a + 2.0 * np.c_[np.cos(ang), np.sin(ang)]], axis=1)
    _, support, off, prov = merge_segments(seg, np.ones(3000), rng.integers(0, 3, 3000), CFG)
    assert support.sum() == 3000
    assert off[-1] == len(prov)


@pytest.mark.parametrize("chunk", [7, 1_000_000])
def test_candidate_pairs_sweep_equals_all_pairs(monkeypatch, chunk):
    """The x-sweep finds exactly the box-overlap pairs of the all-pairs test, in the same order,
    whatever the chunk size."""
    from map_server import fusion

    rng = np.random.default_rng(3)
    a = rng.uniform(0.0, 40.0, (800, 2))
    seg = np.stack([a, a + rng.normal(0.0, 2.0, (800, 2))], axis=1)
    lo, hi = seg.min(axis=1) - 0.4, seg.max(axis=1) + 0.4
    hit = np.all((lo[:, None] <= hi[None]) & (lo[None] <= hi[:, None]), axis=-1)
    bi, bj = np.nonzero(np.triu(hit, 1))
    monkeypatch.setattr(fusion, "PAIR_CHUNK_ELEMENTS", chunk)
    i, j = fusion._candidate_pairs(seg, 0.4)
    assert len(bi) > 1000
    np.testing.assert_array_equal(i, bi)
    np.testing.assert_array_equal(j, bj)
