"""Correlative scan matching: the max pyramid, branch and bound against brute force, ICP."""

import numpy as np
import pytest
from scipy.spatial import cKDTree

from shared.geometry import apply_points, compose, inverse, relative
from shared.scanmatch import (
    branch_and_bound,
    icp,
    likelihood_field,
    max_pyramid,
    window_scores,
)

ROOMS = np.array(
    [
        [[0, 0], [8, 0]], [[8, 0], [8, 6]], [[8, 6], [0, 6]], [[0, 6], [0, 0]],
        [[3, 0], [3, 2.5]], [[5, 6], [5, 4]], [[5.5, 2], [7, 2]], [[1, 4], [2, 4]],
    ],
    float,
)  # fmt: skip


def wall_points(walls, rng, per_m=20):
    pts = [p + rng.uniform(0, 1, (int(np.hypot(*(q - p)) * per_m), 1)) * (q - p) for p, q in walls]
    return np.vstack(pts) + rng.normal(0, 0.01, (sum(len(p) for p in pts), 2))


def test_max_pyramid_holds_the_block_maximum():
    rng = np.random.default_rng(0)
    v = rng.random((13, 9))
    for k, level in enumerate(max_pyramid(v, 3)):
        b = 2**k
        for i, j in [(0, 0), (5, 3), (12, 8), (10, 7)]:
            assert level[i, j] == v[i : i + b, j : j + b].max()


@pytest.mark.parametrize("error", [(1.7, -2.3, 9.0), (-0.4, 0.9, -14.0), (2.9, 2.6, 3.0)])
def test_branch_and_bound_finds_the_brute_force_best(error):
    """A query 3.5 m and 14° off its place: branch and bound finds the pose brute force over the
    same grid finds, and scores it the same."""
    rng = np.random.default_rng(1)
    cloud = wall_points(ROOMS, rng)
    true = np.array([4.0, 3.0, 0.3])
    query = apply_points(inverse(true), wall_points(ROOMS, rng))[::7]
    fld = likelihood_field(cloud, 0.1, 0.08, 0.32)
    guess = compose(true, np.array([error[0], error[1], np.radians(error[2])]))
    step = np.radians(1.0)
    poses, scores = branch_and_bound(fld, query, guess, 3.5, np.radians(16.0), step, 0.3, 0.9, depth=4)
    brute, angles, offs = window_scores(fld, query, guess, 3.5, np.radians(16.0), 0.1, step)
    a, t = np.unravel_index(np.argmax(brute), brute.shape)
    assert scores[0] == pytest.approx(brute[a, t], rel=1e-5)
    np.testing.assert_allclose(poses[0, :2], guess[:2] + offs[t], atol=1e-9)
    assert poses[0, 2] == pytest.approx(angles[a])
    z = relative(true, poses[0])  # and that is the place the query came from
    assert np.hypot(z[0], z[1]) < 0.1 and abs(z[2]) < np.radians(1.0)
    # every pose it keeps scores within keep_ratio of the best; brute force finds no other
    assert np.all(scores >= 0.9 * scores[0] - 1e-6)
    assert len(scores) == np.sum(brute >= 0.9 * brute[a, t] - 1e-6)


def test_branch_and_bound_below_the_minimum_finds_nothing():
    rng = np.random.default_rng(2)
    fld = likelihood_field(wall_points(ROOMS, rng), 0.1, 0.08, 0.32)
    far = rng.uniform(30, 40, (80, 2))  # points nowhere near the cloud at any pose searched
    poses, scores = branch_and_bound(fld, far, np.zeros(3), 2.0, 0.2, 0.02, 0.3, 0.9, depth=3)
    assert len(poses) == 0 and len(scores) == 0


def test_icp_converges_from_a_near_pose():
    rng = np.random.default_rng(3)
    cloud = wall_points(ROOMS, rng)
    true = np.array([4.0, 3.0, 0.3])
    query = apply_points(inverse(true), wall_points(ROOMS, rng))
    x, share = icp(cKDTree(cloud), cloud, query, compose(true, np.array([0.08, -0.06, 0.03])), 10, 0.3, 0.05)
    assert np.hypot(*(x[:2] - true[:2])) < 0.01 and abs(x[2] - true[2]) < np.radians(0.2)
    assert share > 0.8  # both clouds are noisy samples 5 cm apart on average: not every point has a twin
