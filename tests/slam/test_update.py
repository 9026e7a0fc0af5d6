"""Map update (report §4.2): merge from moments, new columns, negative evidence, trust, cleaning."""

import numpy as np
import pytest

from robot_agent.slam.association import Association, observe
from robot_agent.slam.lines import fit_lines, line_covariance, moments_of, project_to_line
from robot_agent.slam.particles import SegmentMaps
from robot_agent.slam.update import (
    CleaningConfig,
    TrustConfig,
    UpdateConfig,
    add_new,
    apply_misses,
    clean,
    element_trust,
    merge_matches,
    visibility,
)
from shared.geometry import wrap_angle
from tests.maps import put_element as maps_put

DOWN, UP, LEFT = -np.pi / 2, np.pi / 2, np.pi


def put_element(maps, col, points, facing, rows=slice(None), *, born=0, hits=5, quality=0.5, misses=0.0):
    """An element fitted to ``points (K,2)``, its extent their projection on the line."""
    fields = {"born": born, "last_seen": born, "hits": hits, "quality": quality, "misses": misses}
    maps_put(maps, col, points, facing, rows, **fields)


def hline(x0, x1, y, n):
    return np.c_[np.linspace(x0, x1, n), np.full(n, y)]


def observe_points(point_sets, poses):
    """Observations of robot-frame point sets, moved into the map frame by each particle's pose."""
    moments = np.array([moments_of(p) for p in point_sets])
    alpha, _, s2 = fit_lines(moments)
    ends = []
    for p in point_sets:
        t, _ = project_to_line(p, *fit_lines(moments_of(p))[:2])
        ends.append([p[np.argmin(t)], p[np.argmax(t)]])
    cov = line_covariance(moments, alpha, np.maximum(s2, 0.02**2))
    return observe(np.asarray(poses, float), moments, np.array(ends), wrap_angle(alpha + np.pi), cov, 0.02)


def assoc_of(index, cost=0.5):
    index = np.asarray(index)
    matched = index >= 0
    return Association(
        index=index,
        cost=np.where(matched, cost, np.inf),
        d_angle=np.where(matched, 0.0, np.inf),
        d_perp=np.where(matched, 0.0, np.inf),
    )


# --- merge_matches ---------------------------------------------------------------------------

# left half-wall: 30 points on y = 2.00, x in [-2, -0.2] (mean x -1.1); right half: 20 points on
# y = 2.05, x in [0.2, 3.1] (mean x 1.65). Together the centroid is (0, 2.02): 30·2.00 + 20·2.05 / 50
LEFT_HALF = hline(-2.0, -0.2, 2.0, 30)
RIGHT_HALF = hline(0.2, 3.1, 2.05, 20)


def test_merge_refits_from_summed_moments_and_extends_to_the_union():
    maps = SegmentMaps.empty(2, 3)
    put_element(maps, 0, LEFT_HALF, DOWN, hits=5, quality=0.5, misses=2.0)
    before = {k: v.copy() for k, v in maps.arrays().items()}
    obs = observe_points([RIGHT_HALF], np.zeros((2, 3)))
    merge_matches(maps, obs, assoc_of([[0], [-1]], cost=0.5), step=7, cfg=UpdateConfig())

    np.testing.assert_allclose(maps.moments[0, 0], moments_of(LEFT_HALF) + moments_of(RIGHT_HALF))
    # the point-weighted mean offset, not the mean of the two offsets (2.025); the line tilts by
    # ~0.015 rad, which changes rho at the centroid x = 0 only by 2.02 (1 - cos) ≈ 2e-4
    assert maps.rho[0, 0] == pytest.approx(2.02, abs=5e-4)
    assert abs(wrap_angle(maps.alpha[0, 0] - np.pi / 2)) < 0.02
    # the TLS line passes through the centroid of all points
    c = np.vstack([LEFT_HALF, RIGHT_HALF]).mean(axis=0)
    np.testing.assert_allclose(c, [0.0, 2.02], atol=1e-12)
    _, off = project_to_line(c, maps.alpha[0, 0], maps.rho[0, 0])
    assert off == pytest.approx(0.0, abs=1e-12)
    # extent: from the old element's far end to the observation's far end, on the new line
    t_seg, d_seg = project_to_line(maps.seg[0, 0], maps.alpha[0, 0], maps.rho[0, 0])
    t_ref, _ = project_to_line(np.array([[-2.0, 2.0], [3.1, 2.05]]), maps.alpha[0, 0], maps.rho[0, 0])
    np.testing.assert_allclose(np.sort(t_seg), np.sort(t_ref), atol=1e-12)
    np.testing.assert_allclose(d_seg, 0.0, atol=1e-12)
    # bookkeeping: one more hit, seen now, misses halved, quality EMA toward exp(-cost / 2)
    assert maps.hits[0, 0] == 6 and maps.last_seen[0, 0] == 7
    assert maps.misses[0, 0] == pytest.approx(1.0)
    assert maps.quality[0, 0] == pytest.approx(0.5 + 0.2 * (np.exp(-0.25) - 0.5), rel=1e-6)
    # particle 1 did not match: untouched
    for k, v in maps.arrays().items():
        np.testing.assert_array_equal(v[1], before[k][1], err_msg=k)


def test_merge_turns_the_facing_with_the_refitted_line_and_keeps_its_side():
    """The facing is compared in association and weights: left at a tilted first view, it would
    charge that tilt to every later match of the element."""
    tilted = np.c_[np.linspace(0.0, 1.0, 11), 2.0 + 0.05 * np.linspace(0.0, 1.0, 11)]  # 2.9 deg off
    for facing, normal in ((DOWN, DOWN), (UP, UP)):  # either side of the wall
        maps = SegmentMaps.empty(1, 1)
        put_element(maps, 0, tilted, facing + np.arctan(0.05))
        obs = observe_points([hline(-4.0, 4.0, 2.0, 161)], np.zeros((1, 3)))
        merge_matches(maps, obs, assoc_of([[0]]), step=1, cfg=UpdateConfig())
        line_normal = maps.alpha[0, 0] if np.cos(maps.alpha[0, 0] - normal) > 0 else maps.alpha[0, 0] + np.pi
        assert abs(wrap_angle(maps.alpha[0, 0] - np.pi / 2)) < np.radians(0.3)  # refitted: nearly level
        assert wrap_angle(maps.facing[0, 0] - line_normal) == pytest.approx(0.0, abs=1e-12)
        assert abs(wrap_angle(maps.facing[0, 0] - normal)) < np.radians(0.3)


def test_two_observations_merged_into_one_element_in_one_call():
    middle, left, right = hline(0.0, 2.0, 2.0, 21), hline(-1.5, -0.3, 2.0, 13), hline(2.4, 4.0, 2.0, 17)
    maps = SegmentMaps.empty(1, 2)
    put_element(maps, 1, middle, DOWN, hits=3)
    obs = observe_points([left, right], np.zeros((1, 3)))
    merge_matches(maps, obs, assoc_of([[1, 1]]), step=3, cfg=UpdateConfig())
    assert maps.hits[0, 1] == 5
    np.testing.assert_allclose(maps.moments[0, 1], moments_of(np.vstack([middle, left, right])))
    assert maps.rho[0, 1] == pytest.approx(2.0, abs=1e-12)
    np.testing.assert_allclose(np.sort(maps.seg[0, 1, :, 0]), [-1.5, 4.0], atol=1e-12)
    np.testing.assert_allclose(maps.seg[0, 1, :, 1], 2.0, atol=1e-12)
    assert not maps.valid[0, 0]


def test_merge_of_a_contained_observation_keeps_the_extent():
    maps = SegmentMaps.empty(1, 1)
    put_element(maps, 0, hline(0.0, 4.0, 2.0, 41), DOWN)
    obs = observe_points([hline(1.0, 2.5, 2.0, 16)], np.zeros((1, 3)))
    merge_matches(maps, obs, assoc_of([[0]]), step=1, cfg=UpdateConfig())
    np.testing.assert_allclose(np.sort(maps.seg[0, 0, :, 0]), [0.0, 4.0], atol=1e-12)
    np.testing.assert_allclose(maps.seg[0, 0, :, 1], 2.0, atol=1e-12)


def test_merge_fades_old_evidence_past_max_points():
    maps = SegmentMaps.empty(1, 1)
    put_element(maps, 0, LEFT_HALF, DOWN)
    obs = observe_points([RIGHT_HALF], np.zeros((1, 3)))
    merge_matches(maps, obs, assoc_of([[0]]), step=1, cfg=UpdateConfig(max_points=25.0))
    full = moments_of(np.vstack([LEFT_HALF, RIGHT_HALF]))
    np.testing.assert_allclose(maps.moments[0, 0], full * 25.0 / 50.0, atol=1e-9)  # same centroid and shape
    assert maps.rho[0, 0] == pytest.approx(fit_lines(full)[1], abs=1e-12)


# --- add_new -----------------------------------------------------------------------------------


def test_add_new_uses_one_column_per_observation_shared_by_the_particles_that_missed_it():
    poses = np.array([[0.0, 0.0, 0.0], [0.05, 0.0, 0.0], [0.0, -0.03, 0.02]])
    obs = observe_points([hline(0, 2, 2.0, 21), hline(3, 5, 1.0, 21), hline(-3, -1, 3.0, 21)], poses)
    maps = SegmentMaps.empty(3, 4)
    put_element(maps, 0, hline(0, 2, 2.0, 21), DOWN, rows=0)
    put_element(maps, 2, hline(0, 2, 2.0, 21), DOWN, rows=1)  # columns 1 and 3 are free
    before = {k: v.copy() for k, v in maps.arrays().items()}
    # obs 0 matched everywhere; obs 1 only in particle 1; obs 2 nowhere
    assoc = assoc_of([[0, -1, -1], [2, 2, -1], [0, -1, -1]])
    cols = add_new(maps, obs, assoc, step=9, cfg=UpdateConfig())
    np.testing.assert_array_equal(cols, [1, 3])
    np.testing.assert_array_equal(maps.valid[:, 1], [True, False, True])
    np.testing.assert_array_equal(maps.valid[:, 3], [True, True, True])
    for p, c, o in [(0, 1, 1), (2, 1, 1), (0, 3, 2), (1, 3, 2), (2, 3, 2)]:
        np.testing.assert_allclose(maps.moments[p, c], obs.moments[p, o])  # each particle's own frame
        np.testing.assert_allclose(maps.seg[p, c], obs.ends[p, o])
        assert maps.alpha[p, c] == obs.alpha[p, o] and maps.rho[p, c] == obs.rho[p, o]
        assert maps.facing[p, c] == obs.facing[p, o]
        assert (maps.hits[p, c], maps.born[p, c], maps.last_seen[p, c]) == (1, 9, 9)
        assert maps.misses[p, c] == 0.0
        assert maps.quality[p, c] == pytest.approx(UpdateConfig().initial_quality)
    assert not np.allclose(maps.moments[0, 3], maps.moments[2, 3])  # particles differ
    for k in ("valid", "moments", "seg", "hits"):  # the old columns are untouched
        np.testing.assert_array_equal(getattr(maps, k)[:, [0, 2]], before[k][:, [0, 2]], err_msg=k)


def test_add_new_grows_the_capacity_and_keeps_the_old_columns():
    obs = observe_points(
        [hline(0, 2, 2.0, 21), hline(3, 5, 1.0, 21), hline(-3, -1, 3.0, 21)], np.zeros((2, 3))
    )
    maps = SegmentMaps.empty(2, 2)
    put_element(maps, 0, hline(0, 2, 5.0, 21), DOWN)
    put_element(maps, 1, hline(0, 2, 6.0, 21), DOWN)
    old = maps.seg[:, :2].copy()
    cols = add_new(maps, obs, assoc_of(np.full((2, 3), -1)), step=1, cfg=UpdateConfig())
    np.testing.assert_array_equal(cols, [2, 3, 4])
    assert maps.capacity >= 5 and maps.valid.shape == maps.seg.shape[:2] == maps.hits.shape
    np.testing.assert_array_equal(maps.seg[:, :2], old)
    assert maps.valid[:, :5].all() and not maps.valid[:, 5:].any()


def test_add_new_with_everything_matched_adds_nothing():
    obs = observe_points([hline(0, 2, 2.0, 21)], np.zeros((2, 3)))
    maps = SegmentMaps.empty(2, 2)
    cols = add_new(maps, obs, assoc_of([[0], [1]]), step=1, cfg=UpdateConfig())
    assert len(cols) == 0 and not maps.valid.any()


# --- visibility --------------------------------------------------------------------------------

ANGLES = np.radians(np.linspace(-90.0, 90.0, 181))
LASER_UP = np.array([0.0, 0.0, np.pi / 2])  # at the origin looking along +y


def scan_of_wall_at(y):
    """Laser ranges to the infinite wall ``y`` (world), from LASER_UP; 30 m beyond ±80°."""
    with np.errstate(divide="ignore"):
        r = y / np.cos(ANGLES)
    return np.where(np.abs(ANGLES) < np.radians(80), r, 30.0)


def test_visibility_sees_through_nearer_elements_not_occluded_ones():
    ranges = scan_of_wall_at(5.0)  # the laser sees a wall 5 m ahead
    maps = SegmentMaps.empty(3, 3)
    put_element(maps, 0, hline(-1, 1, 3.0, 21), DOWN, rows=0)  # nearer: the beams went through it
    put_element(maps, 0, hline(-1, 1, 6.0, 21), DOWN, rows=1)  # farther: occluded by the 5 m wall
    put_element(maps, 0, hline(-1, 1, 5.0, 21), DOWN, rows=2)  # the wall the laser sees
    # particle 0 also has a grazing element nearly along the beams (incidence > 65°) ...
    put_element(maps, 1, np.c_[np.linspace(0.2, 0.4, 21), np.linspace(1.0, 4.0, 21)], LEFT, rows=0)
    # ... and one behind the laser, outside the field of view
    put_element(maps, 2, hline(-1, 1, -3.0, 21), UP, rows=0)
    # particle 1 holds a nearer element too, but not valid (removed): no evidence
    put_element(maps, 2, hline(-1, 1, 3.0, 21), DOWN, rows=1)
    maps.valid[1, 2] = False
    through, in_view = visibility(maps, np.tile(LASER_UP, (3, 1)), ranges, ANGLES, 20.0, UpdateConfig())
    np.testing.assert_array_equal(through, [[3, 0, 0], [0, 0, 0], [0, 0, 0]])
    np.testing.assert_array_equal(
        in_view, [[False, False, False], [False, False, False], [True, False, False]]
    )


def test_visibility_depends_on_each_particles_laser_pose():
    ranges = scan_of_wall_at(5.0)
    maps = SegmentMaps.empty(2, 1)
    put_element(maps, 0, hline(-1, 1, 5.0, 21), DOWN)
    # particle 1 is 2 m farther back: the same element is 7 m away and the beams end 2 m short
    poses = np.array([LASER_UP, LASER_UP - np.array([0.0, 2.0, 0.0])])
    through, in_view = visibility(maps, poses, ranges, ANGLES, 20.0, UpdateConfig())
    np.testing.assert_array_equal(through[:, 0], [0, 0])
    np.testing.assert_array_equal(in_view[:, 0], [True, False])
    # 2 m closer instead: the element is 3 m away and the beams pass it
    through, _ = visibility(
        maps, np.array([LASER_UP, LASER_UP + np.array([0.0, 2.0, 0.0])]), ranges, ANGLES, 20.0, UpdateConfig()
    )
    np.testing.assert_array_equal(through[:, 0], [0, 3])


def test_in_view_only_from_the_free_side_not_grazing_and_wide_enough_to_be_extracted():
    """An element missed while "in view" loses trust; it must really have been in view: the far
    face of a thin wall (0.15 m behind the seen face, inside the range margin), a wall along the
    beams at a grazing angle, and an element spanning fewer beams than a segment needs are not."""
    ranges = scan_of_wall_at(5.0)
    maps = SegmentMaps.empty(1, 5)
    put_element(maps, 0, hline(-1, 1, 5.0, 21), DOWN)  # the seen face: in view
    put_element(maps, 1, hline(-1, 1, 5.15, 21), UP)  # its back face, facing away from the laser
    put_element(maps, 2, hline(-1, 1, 5.15, 21), DOWN)  # the same place facing the laser: in view
    put_element(maps, 3, hline(0.0, 0.3, 5.0, 5), DOWN)  # 0.3 m at 5 m: about 3.4 beams of 1°
    put_element(maps, 4, np.c_[np.full(21, 0.3), np.linspace(4.9, 5.0, 21)], LEFT)  # along the beam
    _, in_view = visibility(maps, LASER_UP[None], ranges, ANGLES, 20.0, UpdateConfig())
    np.testing.assert_array_equal(in_view[0], [True, False, True, False, False])
    # with the span rule off the short element counts
    _, in_view = visibility(maps, LASER_UP[None], ranges, ANGLES, 20.0, UpdateConfig(min_view_beams=0))
    np.testing.assert_array_equal(in_view[0], [True, False, True, True, False])


def test_apply_misses_counts_strong_and_weak_evidence():
    maps = SegmentMaps.empty(1, 4)
    maps.valid[:] = True
    cfg = UpdateConfig()
    through = np.array([[3, 1, 0, 0]])
    in_view = np.array([[False, False, True, True]])
    matched = np.array([[False, False, False, True]])
    apply_misses(maps, through, in_view, matched, cfg)
    np.testing.assert_allclose(maps.misses[0], [cfg.through_miss, 0.0, cfg.unmatched_miss, 0.0])


# --- trust and cleaning --------------------------------------------------------------------------


def test_element_trust_hand_computed_and_monotone():
    cfg = TrustConfig()
    maps = SegmentMaps.empty(1, 6)
    maps.valid[:, :5] = True
    maps.quality[:] = 0.8
    maps.hits[0] = [5, 10, 5, 5, 5, 5]
    maps.born[0] = [51, 51, 1, 51, 51, 51]
    maps.misses[0] = [2.0, 2.0, 2.0, 4.0, 0.0, 0.0]
    w = element_trust(maps, step=100, cfg=cfg)[0]
    # hits 5 = hits_scale, age 49 (+1) = age_scale, misses 2 = miss_scale: each factor 1 - 1/e or 1/e
    assert w[0] == pytest.approx(0.8 * (1 - np.exp(-1)) ** 2 * np.exp(-1), rel=1e-6)
    assert w[1] > w[0]  # more hits
    assert w[2] > w[0]  # older
    assert w[3] < w[0]  # more misses
    assert w[3] == pytest.approx(w[0] * np.exp(-1), rel=1e-6)
    assert w[4] == pytest.approx(w[0] * np.e, rel=1e-6)
    assert w[5] == 0.0  # invalid
    assert np.all((w >= 0) & (w <= 1))


def _cleaning_map():
    maps = SegmentMaps.empty(1, 9)
    put_element(maps, 0, hline(0, 2, -6.0, 21), UP, misses=3.0)  # missed too often
    put_element(maps, 1, np.c_[np.full(21, 8.0), np.linspace(0, 2, 21)], LEFT, misses=2.9)  # just below
    put_element(maps, 2, hline(0, 0.1, -8.0, 5), UP)  # 0.1 m: too short
    put_element(maps, 3, hline(10, 12, 0.0, 21), DOWN, born=30, hits=1)  # a one-off, 70 steps old
    # collinear and overlapping: column 4 (born 40) goes into column 5 (born 5, the older)
    put_element(maps, 4, hline(2.0, 5.0, 2.02, 31), DOWN, born=40, hits=3)
    put_element(maps, 5, hline(0.0, 3.0, 2.0, 31), DOWN, born=5, hits=4)
    # collinear across a 0.5 m doorway: stay two
    put_element(maps, 6, hline(0.0, 2.0, -3.0, 21), UP, born=5)
    put_element(maps, 7, hline(2.5, 4.0, -3.0, 16), UP, born=20)
    # the other face of column 5's wall (0.05 m thick): never merged with it
    put_element(maps, 8, hline(0.0, 3.0, 2.05, 31), UP, born=6)
    return maps


def test_clean_removes_bad_elements_and_merges_redundant_ones_into_the_older():
    maps = _cleaning_map()
    m4, m5 = maps.moments[0, 4].copy(), maps.moments[0, 5].copy()
    clean(maps, step=100, cfg=CleaningConfig())
    np.testing.assert_array_equal(maps.valid[0], [False, True, False, False, False, True, True, True, True])
    np.testing.assert_allclose(maps.moments[0, 5], m4 + m5)
    assert maps.hits[0, 5] == 7 and maps.born[0, 5] == 5
    alpha, rho, _ = fit_lines(m4 + m5)
    assert maps.alpha[0, 5] == pytest.approx(alpha) and maps.rho[0, 5] == pytest.approx(rho)
    # union extent [0, 5] along the refitted line
    t, d = project_to_line(maps.seg[0, 5], maps.alpha[0, 5], maps.rho[0, 5])
    t_ref, _ = project_to_line(np.array([[0.0, 2.0], [5.0, 2.02]]), alpha, rho)
    np.testing.assert_allclose(np.sort(t), np.sort(t_ref), atol=1e-9)
    np.testing.assert_allclose(d, 0.0, atol=1e-12)
    assert maps.last_seen[0, 5] == 40
    # the doorway pair and the other face are as they were
    np.testing.assert_allclose(maps.seg[0, 6, :, 0], [0.0, 2.0])
    np.testing.assert_allclose(maps.seg[0, 7, :, 0], [2.5, 4.0])
    assert maps.hits[0, 8] == 5


def test_clean_redundancy_only_for_recent_columns():
    maps = _cleaning_map()
    clean(maps, step=100, cfg=CleaningConfig(), recent=np.array([1, 6]))  # neither is redundant
    assert maps.valid[0, 4] and maps.valid[0, 5]
    assert not maps.valid[0, 0]  # bad elements go regardless
    clean(maps, step=100, cfg=CleaningConfig(), recent=np.array([4]))
    assert not maps.valid[0, 4] and maps.valid[0, 5]


def test_clean_merges_a_stale_younger_duplicate_into_a_recently_extended_older_element():
    maps = SegmentMaps.empty(1, 2)
    put_element(maps, 0, hline(0.0, 3.0, 2.0, 31), DOWN, born=5, hits=4)  # old, just extended
    put_element(maps, 1, hline(2.0, 5.0, 2.02, 31), DOWN, born=40, hits=3)  # younger, not touched
    clean(maps, step=100, cfg=CleaningConfig(), recent=np.array([0]))  # a pair with a recent column
    np.testing.assert_array_equal(maps.valid[0], [True, False])
