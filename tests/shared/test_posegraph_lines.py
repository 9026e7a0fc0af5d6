"""shared/posegraph.py's point-on-line ties: their Jacobians, and a pose fixed by walls alone."""

import numpy as np

from shared.geometry import compose, inverse, transform_points
from shared.posegraph import LineTies, line_residuals, optimize


def _ties(rng: np.random.Generator, n: int) -> LineTies:
    normal = rng.normal(size=(n, 2))
    normal /= np.linalg.norm(normal, axis=1)[:, None]
    return LineTies(
        rng.integers(0, 2, n), rng.integers(2, 4, n), rng.normal(size=(n, 2)), normal,
        rng.normal(size=n), np.ones(n), np.zeros(n),
    )  # fmt: skip


def test_line_tie_jacobians_match_finite_differences():
    rng = np.random.default_rng(3)
    x = rng.normal(size=(4, 3))
    t = _ties(rng, 7)
    r, ja, jb = line_residuals(x, t)
    eps = 1e-7
    for nodes, jac in ((t.a, ja), (t.b, jb)):
        numeric = np.zeros_like(jac)
        for i, node in enumerate(nodes):
            for j in range(3):
                moved = x.copy()
                moved[node, j] += eps
                numeric[i, j] = (line_residuals(moved, t)[0][i] - r[i]) / eps
        np.testing.assert_allclose(jac, numeric, atol=1e-5)


def _walls_seen(true_b: np.ndarray, true_a: np.ndarray) -> LineTies:
    """Three walls (two facing x, one facing y) in node a's frame; two points on each, in node b's."""
    normal = np.array([[1.0, 0.0], [1.0, 0.0], [0.0, 1.0]])
    offset = np.array([2.0, -3.0, 4.0])
    along = np.array([[0.0, 1.0], [0.0, 1.0], [1.0, 0.0]])
    on_a = np.concatenate([normal * offset[:, None] + along * s for s in (-1.0, 1.0)])  # (6,2)
    in_b = transform_points(compose(inverse(true_b), true_a), on_a)
    n = np.concatenate([normal, normal])
    return LineTies(np.full(6, 1), np.full(6, 2), in_b, n, np.concatenate([offset, offset]),
                    np.full(6, 1e4), np.zeros(6))  # fmt: skip


def test_walls_alone_place_a_node():
    true_a, true_b = np.array([1.0, 2.0, 0.3]), np.array([2.5, 1.0, -0.4])
    ties = _walls_seen(true_b, true_a)
    # node 1 held to the origin's frame by a stiff edge; node 2 only by the walls
    x0 = np.array([np.zeros(3), true_a, true_b + np.array([0.3, -0.2, 0.05])])
    x = optimize(
        x0, np.array([0]), np.array([1]), true_a[None], np.array([[1e6, 1e6, 1e6]]), iterations=10, lines=ties
    )
    np.testing.assert_allclose(x[2], true_b, atol=1e-6)
    np.testing.assert_allclose(line_residuals(x, ties)[0], 0.0, atol=1e-6)


def test_walls_of_one_direction_leave_the_other_free():
    true_a, true_b = np.zeros(3), np.array([2.5, 1.0, 0.0])
    ties = _walls_seen(true_b, true_a)
    keep = ties.n[:, 0] == 1.0  # only the walls facing x: nothing pins y
    along_x = LineTies(*(col[keep] for col in ties))
    x0 = np.array([np.zeros(3), true_a, true_b + np.array([0.3, -0.2, 0.02])])
    prior = np.array([[1e6, 1e6, 1e6], [1e-6, 1e-6, 1e-6]])  # (node 2 held only weakly where it starts)
    x = optimize(
        x0, np.array([0, 0]), np.array([1, 2]), np.array([true_a, x0[2]]), prior, iterations=10, lines=along_x
    )
    assert abs(x[2, 0] - true_b[0]) < 1e-4 and abs(x[2, 2]) < 1e-4  # across the walls and the turn: fixed
    assert abs(x[2, 1] - x0[2, 1]) < 1e-3  # along them: where it started
