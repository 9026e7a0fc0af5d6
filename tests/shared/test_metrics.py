"""Metrics on hand-made trajectories and maps, where the right answer is known."""

import numpy as np
import pytest

from shared import geometry as g
from shared import metrics as m


def straight_line(n=101, dt=0.2, v=0.5):
    t = 1000.0 + dt * np.arange(n)
    poses = np.column_stack([v * dt * np.arange(n), np.zeros(n), np.zeros(n)])
    return t, poses


def test_relations_error_zero_for_truth_and_hand_computed_offset():
    t, truth = straight_line()
    rel = m.Relations(t[[0, 10, 50]], t[[5, 60, 100]], g.relative(truth[[0, 10, 50]], truth[[5, 60, 100]]))
    err = m.relations_error(t, truth, rel)
    assert err.trans_m.max() == pytest.approx(0.0, abs=1e-12)
    assert err.rot_deg.max() == pytest.approx(0.0, abs=1e-12)
    # estimate that drives 10 % too far: error of a relation = 10 % of its length
    est = truth.copy()
    est[:, 0] *= 1.1
    err = m.relations_error(t, est, rel)
    lengths = truth[[5, 60, 100], 0] - truth[[0, 10, 50], 0]
    np.testing.assert_allclose(err.trans_m, 0.1 * lengths, atol=1e-12)
    s = err.summary()
    assert s["trans_mean_m"] == pytest.approx(np.mean(0.1 * lengths))
    assert s["trans_std_m"] == pytest.approx(np.std(0.1 * lengths))


def test_relations_error_rotation_and_nearest_pose():
    t, truth = straight_line()
    est = truth.copy()
    est[60:, 2] = np.radians(3.0)  # a 3° heading error from scan 60 on
    rel = m.Relations(np.array([t[0] + 0.04]), np.array([t[70] - 0.03]), g.relative(truth[[0]], truth[[70]]))
    err = m.relations_error(t, est, rel)  # nearest poses: 0 and 70
    assert err.rot_deg[0] == pytest.approx(3.0, abs=1e-9)


def test_relations_odometry_shift_when_pose_far_in_time():
    t, truth = straight_line()
    keep = np.arange(0, 101, 10)  # sparse estimate: one pose every 2 s
    rel = m.Relations(np.array([t[3]]), np.array([t[47]]), g.relative(truth[[3]], truth[[47]]))
    without = m.relations_error(t[keep], truth[keep], rel)
    with_odom = m.relations_error(t[keep], truth[keep], rel, t, truth)
    assert without.trans_m[0] > 0.1
    assert with_odom.trans_m[0] == pytest.approx(0.0, abs=1e-9)


def test_relations_file_round_trip_and_errors(tmp_path):
    t, truth = straight_line()
    rel = m.make_relations(t, truth, np.random.default_rng(0))
    p = tmp_path / "a.relations"
    m.write_relations(p, rel)
    back = m.read_relations(p)
    np.testing.assert_allclose(back.t1_s, rel.t1_s, atol=1e-6)
    np.testing.assert_allclose(back.delta, rel.delta, atol=1e-6)
    bad = tmp_path / "bad.relations"
    bad.write_text("1 2 3 4 5 6 7 8\n1 2 x 4 5 6 7 8\n")
    with pytest.raises(m.MetricsInputError, match=r"bad.relations:2"):
        m.read_relations(bad)
    bad.write_text("1 2 3\n")
    with pytest.raises(m.MetricsInputError, match="8 fields"):
        m.read_relations(bad)


def test_make_relations_span_short_long_and_revisits():
    # a square loop driven twice: revisits exist
    n = 800
    s = np.linspace(0, 2 * 40.0, n) % 40.0
    side = (s // 10).astype(int)
    u = s % 10
    xy = np.select(
        [side[:, None] == 0, side[:, None] == 1, side[:, None] == 2],
        [
            np.column_stack([u, 0 * u]),
            np.column_stack([10 + 0 * u, u]),
            np.column_stack([10 - u, 10 + 0 * u]),
        ],
        np.column_stack([0 * u, 10 - u]),
    )
    truth = np.column_stack([xy, np.zeros(n)])
    t = np.arange(n) * 0.5
    rel = m.make_relations(t, truth, np.random.default_rng(1))
    span = rel.t2_s - rel.t1_s
    assert np.all(span > 0)
    assert span.min() <= 1.0 and span.max() > 0.5 * t[-1]
    lo = np.searchsorted(t, rel.t1_s)
    hi = np.searchsorted(t, rel.t2_s)
    close = np.hypot(*(truth[lo, :2] - truth[hi, :2]).T) < 2.0
    assert np.sum(close & (span > 30)) >= 50  # loop-closure relations


def test_ate_alignment_and_known_offset():
    t, truth = straight_line()
    truth[:, 1] = np.sin(truth[:, 0])  # not a straight line, so rotation is observable
    tf = np.array([3.0, -2.0, 0.7])
    est = g.compose(g.inverse(tf), truth)  # same path in another frame
    res = m.ate(t, est, t, truth)
    assert res.rmse_m == pytest.approx(0.0, abs=1e-9)
    np.testing.assert_allclose(res.alignment, tf, atol=1e-9)
    shifted = truth.copy()
    shifted[:, 1] += 0.2
    assert m.ate(t, shifted, t, truth, align=False).rmse_m == pytest.approx(0.2)


def test_transform_error():
    e_t, e_r = m.transform_error(np.array([1.0, 0.0, 0.02]), np.array([1.0, 0.05, 0.0]))
    assert e_r == pytest.approx(np.degrees(0.02))
    assert 0.04 < e_t < 0.06


def test_map_quality_hand_made():
    walls = np.array([[[0, 0], [10, 0]], [[10, 0], [10, 5]]], dtype=float)
    perfect = walls.copy()
    q = m.map_quality(perfect, walls)
    assert q.precision == pytest.approx(1.0) and q.completeness == pytest.approx(1.0)
    # half the first wall mapped, plus a 5 m phantom wall: precision 5/10, completeness 5/15
    half = np.array([[[0, 0.02], [5, 0.02]], [[3, 3], [8, 3]]], dtype=float)
    q = m.map_quality(half, walls)
    assert q.precision == pytest.approx(0.5, abs=0.01)
    assert q.completeness == pytest.approx(5 / 15, abs=0.01)
    # right place, wrong angle (10°): not precise
    tilted = np.array([[[0, 0], [0.5, 0.5 * np.tan(np.radians(10))]]])
    assert m.map_quality(tilted, walls).precision < 0.05
    # completeness only counts what a sensor saw
    seen = np.column_stack([np.linspace(0, 10, 200), np.zeros(200)])
    q = m.map_quality(walls[:1], walls, seen_points=seen)
    assert q.completeness == pytest.approx(1.0, abs=0.01)
    assert q.seen_wall_length_m == pytest.approx(10.0, abs=0.2)


def test_map_quality_judges_against_any_wall_within_tolerance_not_only_the_nearest():
    """An inside corner mapped 0.06 m off both walls, each mapped wall running on to the true
    corner: the last 0.12 m of each true wall is nearer the other (perpendicular) mapped wall,
    yet covered by its own; the first 0.06 m of each mapped wall is nearer the perpendicular
    true wall, yet precise. Judged by the nearest alone: precision 0.975, completeness 0.95."""
    walls = np.array([[[0, 0], [2, 0]], [[0, 0], [0, 2]]], dtype=float)
    mapped = np.array([[[0, 0.06], [2, 0.06]], [[0.06, 0], [0.06, 2]]], dtype=float)
    q = m.map_quality(mapped, walls)
    assert q.precision == pytest.approx(1.0) and q.completeness == pytest.approx(1.0)
    d, j = m.nearest_segment(np.array([[0.02, 0.0]]), mapped)
    assert j[0] == 1 and d[0] == pytest.approx(0.04)  # without directions: the perpendicular one
    d, j = m.nearest_segment(np.array([[0.02, 0.0]]), mapped, np.array([0.0]), np.radians(5.0))
    assert j[0] == 0 and d[0] == pytest.approx(0.06)  # the parallel one, not the nearer (0.04 m)
    d, j = m.nearest_segment(np.array([[1.0, 1.0]]), walls[:1], np.array([np.pi / 2]), 0.1)
    assert j[0] == -1 and d[0] == np.inf  # nothing within the angle
    # a misdirected wall still does not cover (10° off)
    tilted = np.array([[[0, 0], [2, 2 * np.tan(np.radians(10))]]])
    assert m.map_quality(tilted, walls[:1]).completeness < 0.2


def test_poses_and_tum_files(tmp_path):
    t, truth = straight_line(5)
    m.write_poses(tmp_path / "p.txt", t, truth)
    _t2, p2 = m.read_poses(tmp_path / "p.txt")
    np.testing.assert_allclose(p2, truth, atol=1e-6)
    m.write_tum(tmp_path / "p.tum", t, truth)
    rows = np.loadtxt(tmp_path / "p.tum")
    assert rows.shape == (5, 8)
    np.testing.assert_allclose(rows[:, 7], 1.0)  # zero yaw → identity quaternion
    (tmp_path / "bad.txt").write_text("1 2 3\n")
    with pytest.raises(m.MetricsInputError, match="4 columns"):
        m.read_poses(tmp_path / "bad.txt")
