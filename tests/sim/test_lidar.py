"""Ray casting against hand-computed hits, chunking, broad phase, noise and dropouts."""

from __future__ import annotations

import numpy as np
import pytest
from shapely.geometry import LineString, Point

from robot_agent.sim import lidar
from robot_agent.sim.lidar import LidarConfig, beam_angles, cast_rays, simulate_scans, walls_in_range

BOX_4x3 = np.array(
    [
        [[0.0, 0.0], [4.0, 0.0]],
        [[4.0, 0.0], [4.0, 3.0]],
        [[4.0, 3.0], [0.0, 3.0]],
        [[0.0, 3.0], [0.0, 0.0]],
    ]
)


def cast_one(origin, angles, walls, range_max=30.0, **kw):
    return cast_rays(np.array([origin]), np.array([angles], dtype=float), walls, range_max, **kw)[0]


def brute_force(origins, directions, walls, range_max):
    """Reference without broad phase or chunking: every ray against every wall."""
    o = origins[:, None, None, :]
    d = np.stack([np.cos(directions), np.sin(directions)], axis=-1)[:, :, None, :]
    a, e = walls[None, None, :, 0], walls[None, None, :, 1] - walls[None, None, :, 0]
    p = a - o
    den = d[..., 0] * e[..., 1] - d[..., 1] * e[..., 0]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (p[..., 0] * e[..., 1] - p[..., 1] * e[..., 0]) / den
        u = (p[..., 0] * d[..., 1] - p[..., 1] * d[..., 0]) / den
    t = np.where((t >= 0) & (u >= 0) & (u <= 1), t, np.inf).min(axis=-1)
    return np.minimum(t, range_max)


def test_hand_computed_hits_in_a_4x3_box():
    angles = [0.0, np.pi / 2, np.pi, -np.pi / 2, np.pi / 4, -3 * np.pi / 4]
    r = cast_one([1.0, 1.0], angles, BOX_4x3)
    # right wall 3 m, top wall 2 m, left 1 m, bottom 1 m,
    # 45°: top wall at (3, 3) -> 2*sqrt(2); -135°: exactly the corner (0, 0) -> sqrt(2)
    np.testing.assert_allclose(r, [3.0, 2.0, 1.0, 1.0, 2 * np.sqrt(2), np.sqrt(2)], atol=1e-12)


def test_ray_parallel_to_a_wall_passes_it():
    offset = np.array([[[2.0, 1.5], [3.5, 1.5]]])  # parallel, 0.5 m beside the ray
    collinear = np.array([[[2.0, 1.0], [3.0, 1.0]]])  # on the ray's line: grazing, not a hit
    walls = np.concatenate([BOX_4x3, offset, collinear])
    assert cast_one([1.0, 1.0], [0.0], walls)[0] == pytest.approx(3.0)
    # the same walls do block a ray that crosses them
    assert cast_one([2.5, 0.5], [np.pi / 2], walls)[0] == pytest.approx(0.5)


def test_no_hit_gives_range_max():
    wall_behind = np.array([[[-1.0, -5.0], [-1.0, 5.0]]])
    np.testing.assert_array_equal(cast_one([0.0, 0.0], [0.0, 0.5, -0.5], wall_behind, 8.0), 8.0)
    far_wall = np.array([[[50.0, -5.0], [50.0, 5.0]]])
    assert cast_one([0.0, 0.0], [0.0], far_wall, 30.0)[0] == 30.0
    no_walls = np.zeros((0, 2, 2))
    np.testing.assert_array_equal(cast_rays(np.zeros((3, 2)), np.zeros((3, 5)), no_walls, 7.0), 7.0)


def random_scene(rng, n_walls=60, n_scans=25, n_beams=181, fov=np.pi):
    a = rng.uniform(0, 20, (n_walls, 2))
    walls = np.stack([a, a + rng.normal(0, 3, (n_walls, 2))], axis=1)
    origins = rng.uniform(0, 20, (n_scans, 2))
    directions = rng.uniform(-np.pi, np.pi, (n_scans, 1)) + np.linspace(-fov / 2, fov / 2, n_beams)
    return origins, directions, walls


@pytest.mark.parametrize("range_max", [30.0, 4.0])
@pytest.mark.parametrize("fov", [np.pi, 0.4, 1.5 * np.pi, 2 * np.pi])
def test_chunked_equals_unchunked_and_brute_force(range_max, fov):
    origins, directions, walls = random_scene(np.random.default_rng(3), fov=fov)
    whole = cast_rays(origins, directions, walls, range_max, max_pairs_per_chunk=10**9)
    for chunk in (1, 100, 5_000):
        chunked = cast_rays(origins, directions, walls, range_max, max_pairs_per_chunk=chunk)
        np.testing.assert_array_equal(chunked, whole)
    reference = brute_force(origins, directions, walls, range_max)
    np.testing.assert_allclose(whole, reference, rtol=0, atol=1e-9)
    assert np.mean(whole < range_max) > 0.2  # the scene is not empty: the check compares hits


def test_broad_phase_blocks_and_counts(monkeypatch):
    origins, directions, walls = random_scene(np.random.default_rng(5), n_scans=40, n_beams=31)
    whole = cast_rays(origins, directions, walls, 6.0)
    monkeypatch.setattr(lidar, "BROAD_PHASE_SCANS_PER_BLOCK", 7)  # 40 scans in 6 blocks
    np.testing.assert_array_equal(cast_rays(origins, directions, walls, 6.0), whole)
    near, count = walls_in_range(origins, walls, 6.0)
    for s in (0, 17, 39):
        dist = np.array([LineString(w).distance(Point(origins[s])) for w in walls])
        np.testing.assert_array_equal(np.sort(near[s, : count[s]]), np.nonzero(dist <= 6.0)[0])
        assert np.all(near[s, count[s] :] == len(walls))  # padding slots
    assert 0 < count.mean() < len(walls)  # the cull does something
    _, count_fov = walls_in_range(origins, walls, 6.0, directions)
    assert np.all(count_fov <= count) and count_fov.sum() < count.sum()  # walls behind dropped


def test_beam_angles_include_both_ends():
    a = beam_angles(LidarConfig(beams=181, fov_rad=np.pi))
    assert a.shape == (181,)
    assert a[0] == pytest.approx(-np.pi / 2) and a[-1] == pytest.approx(np.pi / 2)
    assert a[90] == pytest.approx(0.0)
    np.testing.assert_allclose(np.diff(a), np.pi / 180)


def test_laser_offset_moves_the_origin_and_turns_the_beams():
    cfg = LidarConfig(beams=3, fov_rad=np.pi, range_sigma_m=0.0)
    rng = np.random.default_rng(0)
    pose = np.array([[1.0, 1.0, 0.0]])
    ahead = simulate_scans(rng, pose, BOX_4x3, cfg, laser_offset=(0.5, 0.0, 0.0))
    np.testing.assert_allclose(ahead[0], [1.0, 2.5, 2.0])  # beams at -90°, 0°, +90°
    turned = simulate_scans(rng, pose, BOX_4x3, cfg, laser_offset=(0.0, 0.0, np.pi / 2))
    np.testing.assert_allclose(turned[0], [3.0, 2.0, 1.0])


def test_noise_statistics():
    cfg = LidarConfig(range_sigma_m=0.05)
    poses = np.tile([[1.0, 1.0, 0.3]], (300, 1))
    exact = simulate_scans(np.random.default_rng(1), poses[:1], BOX_4x3, LidarConfig(range_sigma_m=0.0))[0]
    noisy = simulate_scans(np.random.default_rng(1), poses, BOX_4x3, cfg)
    err = noisy - exact
    assert err.std() == pytest.approx(0.05, rel=0.03)
    assert abs(err.mean()) < 0.002
    assert noisy.min() >= 0.0 and noisy.max() <= cfg.range_max_m


def test_noise_never_leaves_zero_to_range_max():
    cfg = LidarConfig(range_sigma_m=0.5, range_max_m=3.2)
    r = simulate_scans(np.random.default_rng(2), np.tile([[0.2, 0.2, 0.0]], (50, 1)), BOX_4x3, cfg)
    assert r.min() == 0.0 and r.max() == 3.2  # clipped at both ends


def test_dropout_fraction():
    cfg = LidarConfig(range_sigma_m=0.0, dropout_prob=0.3)
    r = simulate_scans(np.random.default_rng(4), np.tile([[1.0, 1.0, 0.0]], (200, 1)), BOX_4x3, cfg)
    dropped = r == cfg.range_max_m  # every beam hits a wall in the box, so a max reading is a dropout
    assert dropped.mean() == pytest.approx(0.3, abs=0.01)


def test_simulate_scans_is_reproducible():
    poses = np.array([[1.0, 1.0, 0.0], [2.0, 1.5, 1.0]])
    cfg = LidarConfig(dropout_prob=0.1)
    a = simulate_scans(np.random.default_rng(9), poses, BOX_4x3, cfg)
    b = simulate_scans(np.random.default_rng(9), poses, BOX_4x3, cfg)
    c = simulate_scans(np.random.default_rng(10), poses, BOX_4x3, cfg)
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)


@pytest.mark.parametrize(
    "kwargs, field",
    [({"beams": 0}, "beams"), ({"range_max_m": 0.0}, "range_max_m"), ({"dropout_prob": 1.5}, "dropout_prob")],
)
def test_bad_config_names_the_field(kwargs, field):
    with pytest.raises(ValueError, match=field):
        LidarConfig(**kwargs)
