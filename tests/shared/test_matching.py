"""Pose hypotheses from segment pairs and overlap scoring (report §6)."""

import dataclasses

import numpy as np
import pytest

from robot_agent.sim.lidar import cast_rays
from robot_agent.slam.extraction import extract_segments
from shared import matching
from shared.geometry import apply_segments, inverse, wrap_angle
from shared.matching import MatchingConfig, cluster_poses, overlap_scores, pose_hypotheses
from tests.rooms import ANGLES, L_FACING, L_ROOM, TRUE_POSE


def scan_segments(walls, pose, noise_m=0.01, seed=0):
    """Segments (robot frame) extracted from a simulated 360° scan, and their facing."""
    ranges = cast_rays(pose[None, :2], (pose[2] + ANGLES)[None], walls, 30.0)[0]
    ranges = ranges + np.random.default_rng(seed).normal(0.0, noise_m, ranges.shape)
    segs = extract_segments(ranges, ANGLES)
    return segs.endpoints, wrap_angle(segs.alpha + np.pi)


def test_wall_facings_point_into_the_free_space():
    # the inside point (0, 0) is on every room wall's facing side; the box faces point outward
    mid = L_ROOM.mean(axis=1)
    normal = np.c_[np.cos(L_FACING), np.sin(L_FACING)]
    assert np.all(np.sum((np.array([0.0, 0.0]) - mid[:6]) * normal[:6], axis=1) > 0)
    assert np.all(np.sum((mid[6:] - np.array([5.0, -2.0])) * normal[6:], axis=1) > 0)


def test_recovers_the_pose_in_an_l_room_with_a_box():
    ends, facing = scan_segments(L_ROOM, TRUE_POSE)
    assert len(ends) >= 6
    cfg = MatchingConfig()
    hyp = pose_hypotheses(ends, facing, L_ROOM, L_FACING, cfg)
    assert hyp.shape[1] == 3 and len(hyp) > 1
    scores = overlap_scores(hyp, ends, facing, L_ROOM, L_FACING, cfg)
    best = hyp[np.argmax(scores)]
    assert np.hypot(*(best[:2] - TRUE_POSE[:2])) < 0.01
    assert abs(wrap_angle(best[2] - TRUE_POSE[2])) < np.radians(0.1)
    # at the best pose nearly the whole scan lies on the map; the runner-up cluster explains far less
    total = np.hypot(*(ends[:, 1] - ends[:, 0]).T).sum()
    assert scores.max() > 0.97 * total
    far = np.hypot(*(hyp[:, :2] - TRUE_POSE[:2]).T) > 0.3
    assert scores[far].max() < 0.6 * scores.max()


def test_exact_segments_give_the_exact_pose():
    # the visible room walls themselves, moved into the robot frame: noise-free, the pose is exact
    walls = [0, 2, 4, 5, 8, 9]
    ends = apply_segments(inverse(TRUE_POSE), L_ROOM[walls])
    facing = wrap_angle(L_FACING[walls] - TRUE_POSE[2])
    hyp = pose_hypotheses(ends, facing, L_ROOM, L_FACING, MatchingConfig())
    err = np.abs(np.c_[hyp[:, :2] - TRUE_POSE[:2], wrap_angle(hyp[:, 2] - TRUE_POSE[2])])
    assert np.min(err.max(axis=1)) < 1e-9


CORRIDOR = np.array([[(0.0, 0.0), (20.0, 0.0)], [(20.0, 2.0), (0.0, 2.0)]])
CORRIDOR_FACING = np.array([np.pi / 2, -np.pi / 2])


def test_corridor_is_degenerate():
    pose = np.array([5.0, 1.0, 0.3])
    seen = np.array([[(2.0, 0.0), (9.0, 0.0)], [(9.0, 2.0), (2.0, 2.0)]])  # range-limited view
    ends = apply_segments(inverse(pose), seen)
    facing = wrap_angle(CORRIDOR_FACING - pose[2])
    cfg = MatchingConfig()
    assert len(pose_hypotheses(ends, facing, CORRIDOR, CORRIDOR_FACING, cfg)) == 0
    # the score cannot tell positions along the corridor apart
    along = pose + np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [-1.5, 0.0, 0.0]])
    scores = overlap_scores(along, ends, facing, CORRIDOR, CORRIDOR_FACING, cfg)
    np.testing.assert_allclose(scores, 14.0, atol=1e-9)
    # ... but it can across it
    assert (
        overlap_scores(pose[None] + [0.0, 0.3, 0.0], ends, facing, CORRIDOR, CORRIDOR_FACING, cfg)[0] == 0.0
    )


def test_corridor_from_a_simulated_scan_gives_no_hypothesis():
    ends, facing = scan_segments(CORRIDOR, np.array([5.0, 1.0, 0.3]))
    assert len(ends) >= 2
    assert len(pose_hypotheses(ends, facing, CORRIDOR, CORRIDOR_FACING, MatchingConfig())) == 0


MAP_SEG = np.array([[(0.0, 0.0), (4.0, 0.0)], [(3.5, 0.0), (6.0, 0.0)]])
MAP_FACING = np.array([np.pi / 2, np.pi / 2])


@pytest.mark.parametrize(
    ("seg", "facing", "maps", "expected"),
    [
        ([(3.0, 0.0), (5.0, 0.0)], np.pi / 2, [0], 1.0),  # half of it on the map segment
        ([(5.0, 0.0), (3.0, 0.0)], np.pi / 2, [0], 1.0),  # endpoint order does not matter
        ([(3.0, 0.1), (5.0, 0.1)], np.pi / 2, [0], 1.0),  # 0.1 m off: within score_perp_m
        ([(3.0, 0.2), (5.0, 0.2)], np.pi / 2, [0], 0.0),  # 0.2 m off: not
        ([(3.0, 0.0), (5.0, 0.0)], -np.pi / 2, [0], 0.0),  # the other face
        ([(3.0, 0.0), (5.0, 0.0)], np.pi / 2 + 0.1, [0], 0.0),  # 5.7° off in facing
        ([(3.0, 0.0), (5.0, 0.0)], np.pi / 2, [0, 1], 1.5),  # best map segment counts, once
        ([(4.5, 0.0), (5.0, 0.0)], np.pi / 2, [0], 0.0),  # beyond the end
    ],
)
def test_overlap_score_hand_made(seg, facing, maps, expected):
    s = overlap_scores(
        np.zeros((1, 3)),
        np.array([seg], float),
        np.array([facing]),
        MAP_SEG[maps],
        MAP_FACING[maps],
        MatchingConfig(),
    )
    assert s[0] == pytest.approx(expected, abs=1e-9)


def test_overlap_score_moves_the_scan_by_the_pose():
    # an observed segment 1 m ahead of the robot, seen facing back; the robot at (2, -1) facing +y
    seg = np.array([[(1.0, -1.0), (1.0, 1.0)]])
    pose = np.array([[2.0, -1.0, np.pi / 2]])  # moves it onto y = 0, x in [1, 3], facing -y
    s = overlap_scores(pose, seg, np.array([np.pi]), MAP_SEG[:1], np.array([-np.pi / 2]), MatchingConfig())
    assert s[0] == pytest.approx(2.0, abs=1e-9)


def test_overlap_scores_chunked_equals_unchunked(monkeypatch):
    ends, facing = scan_segments(L_ROOM, TRUE_POSE)
    poses = TRUE_POSE + np.random.default_rng(2).normal(0.0, [0.1, 0.1, 0.03], (37, 3))
    whole = overlap_scores(poses, ends, facing, L_ROOM, L_FACING, MatchingConfig())
    monkeypatch.setattr(matching, "SCORE_CHUNK_ELEMENTS", 3 * len(ends) * len(L_ROOM))
    chunked = overlap_scores(poses, ends, facing, L_ROOM, L_FACING, MatchingConfig())
    np.testing.assert_allclose(chunked, whole)
    assert np.ptp(whole) > 1.0  # the poses do score differently


def _dense_overlap_scores(poses, obs_ends, obs_facing, map_ends, map_facing, cfg):
    """Every (pose, observed, map) triple tested in full: the reference for the sparse kernel."""
    moved = apply_segments(poses, obs_ends)  # (H,O,2,2)
    facing = wrap_angle(obs_facing[None, :] + poses[:, 2:3])
    fm = np.stack([np.cos(map_facing), np.sin(map_facing)], axis=-1)
    dm = np.stack([-fm[:, 1], fm[:, 0]], axis=-1)
    a = map_ends[:, 0]
    rel = moved[:, :, None, :, :] - a[None, None, :, None, :]  # (H,O,M,2,2)
    perp = np.sum(rel * fm[None, None, :, None, :], axis=-1)
    t = np.sum(rel * dm[None, None, :, None, :], axis=-1)
    tm = np.sum((map_ends[:, 1] - a) * dm, axis=-1)
    t_lo = np.maximum(np.minimum(t[..., 0], t[..., 1]), np.minimum(0.0, tm))
    t_hi = np.minimum(np.maximum(t[..., 0], t[..., 1]), np.maximum(0.0, tm))
    overlap = t_hi - t_lo
    dang = np.abs(wrap_angle(facing[:, :, None] - map_facing[None, None, :]))
    ok = (np.max(np.abs(perp), axis=-1) <= cfg.score_perp_m) & (dang <= cfg.score_angle_rad)
    ok &= overlap > cfg.score_overlap_m
    return np.sum(np.max(np.where(ok, overlap, 0.0), axis=2), axis=1)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_overlap_scores_equal_the_dense_reference(seed):
    """The facing test first and the geometry only where it passes: the same scores as testing
    every triple, on a room's scan against the room and many unrelated walls, from poses near and
    far from the true one."""
    rng = np.random.default_rng(seed)
    ends, facing = scan_segments(L_ROOM, TRUE_POSE)
    centre = rng.uniform(-10.0, 10.0, (300, 2))
    turn = rng.uniform(-np.pi, np.pi, 300)
    half = rng.uniform(0.2, 3.0, 300)[:, None] * np.column_stack([np.cos(turn), np.sin(turn)])
    clutter = np.stack([centre - half, centre + half], axis=1)
    map_ends = np.concatenate([L_ROOM, clutter])
    map_facing = np.concatenate([L_FACING, wrap_angle(turn + np.pi / 2 * rng.choice([-1, 1], 300))])
    poses = np.vstack([TRUE_POSE + rng.normal(0.0, [0.05, 0.05, 0.03], (40, 3)), rng.uniform(-8, 8, (40, 3))])
    for cfg in (MatchingConfig(), MatchingConfig(score_overlap_m=0.3, score_angle_rad=np.radians(15))):
        got = overlap_scores(poses, ends, facing, map_ends, map_facing, cfg)
        want = _dense_overlap_scores(poses, ends, facing, map_ends, map_facing, cfg)
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-9)
        assert np.count_nonzero(want) > 40  # near the true pose and by chance elsewhere


def test_empty_inputs():
    cfg = MatchingConfig()
    assert overlap_scores(np.zeros((0, 3)), L_ROOM, L_FACING, L_ROOM, L_FACING, cfg).shape == (0,)
    np.testing.assert_array_equal(
        overlap_scores(np.zeros((2, 3)), L_ROOM[:0], L_FACING[:0], L_ROOM, L_FACING, cfg), [0.0, 0.0]
    )
    assert pose_hypotheses(L_ROOM[:1], L_FACING[:1], L_ROOM, L_FACING, cfg).shape == (0, 3)


def test_cluster_poses_keeps_the_best_of_each_cluster():
    poses = np.array([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 0.2]])
    scores = np.array([1.0, 3.0, 2.0, 0.5])
    keep = cluster_poses(poses, scores, 0.2, np.radians(3.0))
    # 0 is within 0.1 m and 0° of 1 (better): suppressed; 3 is 0.2 rad away in heading: its own cluster
    np.testing.assert_array_equal(keep, [1, 2, 3])


def test_a_t_junction_is_a_pair_when_gaps_run_to_the_segment():
    """A wall ending on another's middle (a T): 2.5 m from either end of it, 0 m from the wall.
    The endpoint gap misses the pair; ``gap_to_segment`` (the whole-map search of a robot that
    was carried) finds it."""
    ends = np.array([[[-5.0, 0.0], [5.0, 0.0]], [[0.0, 0.0], [0.0, 3.0]]])
    facing = np.array([np.pi / 2, 0.0])
    plain = MatchingConfig(max_pair_gap_m=1.5)
    assert len(matching._pairs(ends, facing, plain, 1.5)[0]) == 0
    to_segment = dataclasses.replace(plain, gap_to_segment=True)
    assert len(matching._pairs(ends, facing, to_segment, 1.5)[0]) == 1


@pytest.mark.parametrize("to_segment", [False, True])
def test_pairs_skip_far_apart_ones_without_losing_any(to_segment):
    """The centre-distance bound drops pairs before their gap is computed: the pairs are those
    of the gap computed for every pair (random walls, 3 seeds)."""
    for seed in range(3):
        rng = np.random.default_rng(seed)
        ends, facing = rng.uniform(0, 30, (300, 2, 2)), rng.uniform(-np.pi, np.pi, 300)
        cfg = MatchingConfig(max_pair_gap_m=3.0, gap_to_segment=to_segment)
        i, j = np.triu_indices(len(ends), 1)
        ok = np.abs(np.sin(matching.wrap_angle(facing[j] - facing[i]))) >= np.sin(cfg.min_pair_angle_rad)
        gap = matching._end_to_segment_gap if to_segment else matching._segment_gap
        want = np.flatnonzero(ok)[gap(ends[i[ok]], ends[j[ok]]) <= 3.0]
        a, b, _ = matching._pairs(ends, facing, cfg, 3.0)
        assert np.array_equal(a, i[want]) and np.array_equal(b, j[want])
        assert len(want) > 0
