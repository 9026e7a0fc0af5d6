"""A keyframe scan matched near a guess (shared/scanmatch.window_match): the window re-centred on
a best pose that lies on its edge."""

import dataclasses

import numpy as np
import pytest

from shared.geometry import apply_points, compose, inverse, relative, wrap_angle
from shared.scanmatch import MatchConfig, likelihood_field, window_match

ROOM = np.array(
    [[[0, 0], [6, 0]], [[6, 0], [6, 4]], [[6, 4], [0, 4]], [[0, 4], [0, 0]],
     [[2, 2], [3.5, 2]], [[3.5, 2], [3.5, 3]]],
    float,
)  # fmt: skip
CORRIDOR = np.array([[[-20, 0], [20, 0]], [[-20, 2], [20, 2]]], float)


def _seen(walls: np.ndarray, pose: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Points on ``walls`` (no occlusion) in the frame of ``pose``."""
    pts = []
    for p, q in walls:
        t = rng.uniform(0, 1, int(np.hypot(*(q - p)) / 0.05))[:, None]
        pts.append(p + t * (q - p))
    return apply_points(inverse(pose), np.vstack(pts) + rng.normal(0, 0.01, (sum(map(len, pts)), 2)))


def _match(walls: np.ndarray, off: np.ndarray, recentre: int):
    """Keyframe b's points matched against keyframe a's from a guess ``off`` (in a's frame) from
    the truth: (the truth, the match, its covariance, the stats)."""
    rng = np.random.default_rng(3)
    a, b = np.array([1.0, 1.0, 0.1]), np.array([4.5, 1.2, 2.0])
    cloud, query = _seen(walls, a, rng), _seen(walls, b, rng)[::3]
    cfg = dataclasses.replace(MatchConfig(), recentre=recentre)
    fld = likelihood_field(cloud, cfg.search_step_m, cfg.field_sigma_m, 4.0 * cfg.field_sigma_m)
    true = relative(a, b)
    stats: dict = {}
    found = window_match(fld, cloud, query, compose(np.array([off[0], off[1], 0.0]), true), cfg, stats)
    assert found is not None
    return true, found[0], np.linalg.inv(found[2]), stats


def _sigmas(cov: np.ndarray) -> np.ndarray:
    return np.sqrt(np.linalg.eigvalsh(cov[:2, :2]))


def test_a_guess_off_by_the_window_leaves_the_match_unbounded_unless_recentred():
    """The true place beyond the window's edge: ICP brings the match there either way, but only a
    window centred on it says how well it is determined (a fleet's keyframes the graph put 0.9 m
    apart: their scan matches said nothing along one axis, and the graph left them apart)."""
    off = np.array([0.9, 0.35])  # (beyond the 0.8 m half width in x)
    true, z, cov, stats = _match(ROOM, off, recentre=0)
    assert np.hypot(*(z[:2] - true[:2])) < 0.03
    assert _sigmas(cov)[1] > 2.0 and "recentred" not in stats
    true, z, cov, stats = _match(ROOM, off, recentre=1)
    assert np.hypot(*(z[:2] - true[:2])) < 0.03
    assert _sigmas(cov)[1] < 0.1 and stats["recentred"] == 1


def test_a_good_guess_is_not_searched_again():
    true, z, cov, stats = _match(ROOM, np.array([0.2, -0.1]), recentre=2)
    assert np.hypot(*(z[:2] - true[:2])) < 0.03 and _sigmas(cov)[1] < 0.1
    assert "recentred" not in stats


@pytest.mark.parametrize("recentre", [0, 2])
def test_a_corridor_stays_unbounded_along_it_however_often_recentred(recentre):
    true, z, cov, _ = _match(CORRIDOR, np.array([0.3, 0.1]), recentre=recentre)
    assert _sigmas(cov)[1] > 2.0 and _sigmas(cov)[0] < 0.1  # along it nothing, across it a lot
    across = np.array([-np.sin(-0.1), np.cos(-0.1)])  # (the corridor's normal in the cloud's frame)
    assert abs(across @ (z[:2] - true[:2])) < 0.03 and abs(wrap_angle(z[2] - true[2])) < np.radians(1.0)
