"""SE(2) identities over several batch shapes (jaxlie-style: one helper, many shapes)."""

import numpy as np
import pytest

from shared import geometry as g

BATCH_SHAPES = [(), (1,), (5,), (3, 4), (2, 1, 3)]


def random_poses(rng: np.random.Generator, shape: tuple[int, ...]) -> np.ndarray:
    xy = rng.uniform(-10, 10, (*shape, 2))
    th = rng.uniform(-np.pi, np.pi, (*shape, 1))
    return np.concatenate([xy, th], axis=-1)


def assert_pose_close(a, b, atol=1e-9):
    a, b = np.asarray(a), np.asarray(b)
    assert a.shape == b.shape
    np.testing.assert_allclose(a[..., :2], b[..., :2], atol=atol)
    np.testing.assert_allclose(g.wrap_angle(a[..., 2] - b[..., 2]), 0.0, atol=atol)


@pytest.mark.parametrize("shape", BATCH_SHAPES)
def test_compose_inverse_identity(shape):
    rng = np.random.default_rng(0)
    p = random_poses(rng, shape)
    assert_pose_close(g.compose(p, g.inverse(p)), g.identity(shape))
    assert_pose_close(g.compose(g.inverse(p), p), g.identity(shape))
    assert_pose_close(g.inverse(g.inverse(p)), p)


@pytest.mark.parametrize("shape", BATCH_SHAPES)
def test_compose_is_associative_and_matches_matrices(shape):
    rng = np.random.default_rng(1)
    a, b, c = (random_poses(rng, shape) for _ in range(3))
    assert_pose_close(g.compose(g.compose(a, b), c), g.compose(a, g.compose(b, c)))
    m = g.to_matrix(a) @ g.to_matrix(b)
    assert_pose_close(g.from_matrix(m), g.compose(a, b))
    assert_pose_close(g.from_matrix(g.to_matrix(a)), a)


@pytest.mark.parametrize("shape", BATCH_SHAPES)
def test_relative_round_trip(shape):
    rng = np.random.default_rng(2)
    a, b = random_poses(rng, shape), random_poses(rng, shape)
    assert_pose_close(g.compose(a, g.relative(a, b)), b)
    assert_pose_close(g.relative(a, a), g.identity(shape))


@pytest.mark.parametrize("shape", BATCH_SHAPES)
def test_points_and_segments_follow_composition(shape):
    rng = np.random.default_rng(3)
    a, b = random_poses(rng, shape), random_poses(rng, shape)
    pts = rng.uniform(-5, 5, (*shape, 7, 2))
    segs = rng.uniform(-5, 5, (*shape, 4, 2, 2))
    np.testing.assert_allclose(
        g.apply_points(a, g.apply_points(b, pts)), g.apply_points(g.compose(a, b), pts), atol=1e-9
    )
    np.testing.assert_allclose(g.apply_points(g.inverse(a), g.apply_points(a, pts)), pts, atol=1e-9)
    moved = g.apply_segments(a, segs)
    assert moved.shape == segs.shape
    # rigid motions keep lengths and rotate directions by theta
    np.testing.assert_allclose(g.segment_lengths(moved), g.segment_lengths(segs), atol=1e-9)
    dth = g.wrap_angle(g.segment_directions(moved) - g.segment_directions(segs) - a[..., None, 2])
    np.testing.assert_allclose(dth, 0.0, atol=1e-9)


def test_hand_computed_values():
    p = np.array([1.0, 2.0, np.pi / 2])
    np.testing.assert_allclose(g.transform_points(p, np.array([1.0, 0.0])), [1.0, 3.0], atol=1e-12)
    assert_pose_close(g.compose(p, [1.0, 0.0, np.pi / 2]), [1.0, 3.0, np.pi])
    assert_pose_close(g.inverse(p), [-2.0, 1.0, -np.pi / 2])


def test_broadcasting_one_pose_many_sets():
    rng = np.random.default_rng(4)
    poses = random_poses(rng, (6,))
    segs = rng.uniform(-1, 1, (9, 2, 2))
    out = g.apply_segments(poses, segs)  # one set of 9 segments seen from 6 poses
    assert out.shape == (6, 9, 2, 2)
    np.testing.assert_allclose(out[4], g.apply_segments(poses[4], segs), atol=1e-12)


def test_wrap_angle_range():
    a = np.linspace(-20, 20, 1001)
    w = g.wrap_angle(a)
    assert np.all(w >= -np.pi) and np.all(w < np.pi)
    np.testing.assert_allclose(np.sin(w), np.sin(a), atol=1e-12)
    np.testing.assert_allclose(np.cos(w), np.cos(a), atol=1e-12)


def test_distances_and_angles():
    seg = np.array([[0.0, 0.0], [2.0, 0.0]])
    pts = np.array([[1.0, 1.0], [3.0, 0.0], [-1.0, -1.0]])
    np.testing.assert_allclose(g.point_line_distance(pts, seg), [1.0, 0.0, -1.0])
    np.testing.assert_allclose(g.point_segment_distance(pts, seg), [1.0, 1.0, np.sqrt(2.0)])
    assert g.line_angle_diff(0.1, np.pi + 0.1) == pytest.approx(0.0, abs=1e-12)
    assert g.line_angle_diff(0.0, np.pi / 2) == pytest.approx(np.pi / 2)
    assert g.line_angle_diff(0.2, -0.1) == pytest.approx(0.3)


def test_sample_segments_hand_computed():
    # 1 m at step 0.3: four 0.25 m pieces, a point at each middle; a zero-length segment: one point
    seg = np.array([[[0.0, 0.0], [1.0, 0.0]], [[2.0, 2.0], [2.0, 2.0]]])
    pts, owner, length = g.sample_segments(seg, 0.3)
    np.testing.assert_allclose(pts, [[0.125, 0], [0.375, 0], [0.625, 0], [0.875, 0], [2, 2]])
    np.testing.assert_array_equal(owner, [0, 0, 0, 0, 1])
    np.testing.assert_allclose(length, [0.25, 0.25, 0.25, 0.25, 0.0])
    assert all(len(a) == 0 for a in g.sample_segments(np.zeros((0, 2, 2)), 0.3))
    # the pieces' ends instead: both endpoints and every cut
    pts, owner, length = g.sample_segments(seg, 0.3, ends=True)
    np.testing.assert_allclose(pts, [[0, 0], [0.25, 0], [0.5, 0], [0.75, 0], [1, 0], [2, 2], [2, 2]])
    np.testing.assert_array_equal(owner, [0, 0, 0, 0, 0, 1, 1])
    assert all(len(a) == 0 for a in g.sample_segments(np.zeros((0, 2, 2)), 0.3, ends=True))


def test_relative_one_is_relative_bit_for_bit():
    """The scalar fast path of one pose pair: the same numbers, not only close ones (the filter's
    odometry increments go through it, and a trajectory must not depend on which was used)."""
    rng = np.random.default_rng(11)
    for _ in range(2000):
        a = rng.uniform([-50, -50, -4], [50, 50, 4])
        b = a + rng.normal(0, [0.2, 0.2, 0.3])
        np.testing.assert_array_equal(g.relative_one(a, b), g.relative(a, b))
    turned = g.relative_one(np.zeros(3), np.array([1.0, 2.0, np.pi]))
    np.testing.assert_array_equal(turned, [1.0, 2.0, -np.pi])
