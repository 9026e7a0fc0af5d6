"""The incremental merge (map_server/incremental.py) against the full merge it stands for
(fusion.merge_segments over every placed layer), on random fleets: layers replaced, frames moved,
sources added, removed and reordered, a common rigid motion; then the Fleet that uses it, on random
put sequences (robots refined, new sessions and retired pieces, a robot leaving, a restore from a
snapshot), and the cropped refinement against the one over the whole placed map."""

from __future__ import annotations

import copy

import numpy as np
import pytest

from map_server import incremental
from map_server.alignment import estimate_alignment
from map_server.config import FleetConfig
from map_server.fleet import Fleet
from map_server.fusion import FusionConfig, RobotLayer, fuse_particles, merge_segments
from map_server.incremental import MergedMap, Source
from map_server.registration import MapIndex, OutsideIndex, Samples
from shared.geometry import apply_segments, compose, inverse
from tests.map_server.robots import robot_map_from_segments

CFG = FusionConfig()
SIGMA = np.array([0.05, 0.05, np.radians(1.0)])


def building(rng: np.random.Generator, size_m: float = 40.0, pitch_m: float = 4.0) -> np.ndarray:
    """Walls ``(W,2,2)`` of a grid of rooms, both faces of each (0.1 m apart), with door gaps."""
    walls = []
    for k in np.arange(0.0, size_m + 1e-9, pitch_m):
        for along in np.arange(0.0, size_m, pitch_m):
            if rng.random() < 0.25:
                continue  # a door-sized opening: no wall on this stretch
            a, b = along + rng.uniform(0, 0.4), along + pitch_m - rng.uniform(0, 0.4)
            walls += [[(a, k), (b, k)], [(b, k + 0.1), (a, k + 0.1)]]  # horizontal, both faces
            walls += [[(k, b), (k, a)], [(k + 0.1, a), (k + 0.1, b)]]  # vertical
    return np.array(walls, float)


def seen(rng: np.random.Generator, walls: np.ndarray, lo, hi, noise_m: float = 0.01) -> np.ndarray:
    """The walls inside the box ``lo``-``hi``, cut into pieces of 0.5-3 m with endpoint noise."""
    out = []
    for p, q in walls:
        if not (np.all(np.minimum(p, q) >= lo) and np.all(np.maximum(p, q) <= hi)):
            continue
        length = np.hypot(*(q - p))
        t = 0.0
        while t < length - 0.2:
            s = min(length, t + rng.uniform(0.5, 3.0))
            a, b = p + (q - p) * t / length, p + (q - p) * s / length
            out.append([a + rng.normal(0, noise_m, 2), b + rng.normal(0, noise_m, 2)])
            t = s + rng.uniform(0.0, 0.2)
    return np.array(out, float).reshape(-1, 2, 2)


def layer(seg: np.ndarray, rng: np.random.Generator) -> RobotLayer:
    n = len(seg)
    z = np.ones(n)
    return RobotLayer(seg, rng.uniform(0.2, 1.0, n), z, z, np.zeros(n, np.int64), np.arange(n))


def full(sources: list[Source]) -> tuple:
    """fusion.merge_segments of the stacked sources (Fleet's merge before incremental.py)."""
    robots = sorted({s.robot for s in sources})
    seg = np.concatenate([np.zeros((0, 2, 2))] + [apply_segments(s.transform, s.layer.seg) for s in sources])
    w = np.concatenate([np.zeros(0)] + [s.layer.weight for s in sources])
    owner = np.concatenate(
        [np.zeros(0, np.int64)] + [np.full(len(s.layer), robots.index(s.robot)) for s in sources]
    )
    return merge_segments(seg, w, owner, CFG), {r: i for i, r in enumerate(robots)}


def assert_same(a: tuple, b: tuple, atol: float = 0.0) -> None:
    assert a[0].shape == b[0].shape
    if atol == 0.0:
        np.testing.assert_array_equal(a[0], b[0])
    else:
        np.testing.assert_allclose(a[0], b[0], rtol=0, atol=atol)
    for x, y in zip(a[1:], b[1:], strict=True):
        np.testing.assert_array_equal(x, y)


def random_fleet(rng: np.random.Generator, n: int):
    walls = building(rng)
    layers, frames = {}, {}
    for k in range(n):
        lo = rng.uniform(0, 20, 2)
        frames[f"r{k}"] = np.array([*rng.uniform(-5, 5, 2), rng.uniform(-np.pi, np.pi)])
        layers[f"r{k}"] = layer(apply_segments(inverse(frames[f"r{k}"]), seen(rng, walls, lo, lo + 20)), rng)
    return walls, layers, frames


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_incremental_merge_is_the_full_merge_bit_for_bit(seed, monkeypatch):
    if seed == 2:  # the pair array compacted whenever half its rows are out (else only after thousands)
        monkeypatch.setattr(incremental, "EDGES_COMPACT_MIN", 0)
    rng = np.random.default_rng(seed)
    walls, layers, frames = random_fleet(rng, 6)
    merged = MergedMap(CFG)
    merges = 0
    for step in range(40):
        name = f"r{rng.integers(6)}"
        what = rng.random()
        if what < 0.4:  # a new map: part of the old one and new walls
            lo = rng.uniform(0, 20, 2)
            seg = apply_segments(inverse(frames[name]), seen(rng, walls, lo, lo + 20))
            layers[name] = layer(np.concatenate([layers[name].seg[: len(layers[name]) // 2], seg]), rng)
        elif what < 0.8:  # refined or moved
            frames[name] = frames[name] + rng.normal(0, [0.03, 0.03, 0.003])
        # a changing set of sources, in name order, with a retired piece or two at the end
        names = sorted(rng.choice(sorted(layers), rng.integers(2, 7), replace=False))
        sources = [Source(("robot", k), k, layers[k], frames[k]) for k in names]
        if step % 3:
            sources.append(Source(("piece", "r0", "old"), "r0", layers["r5"], frames["r5"] + [0.2, 0.0, 0.0]))
        merged.update(sources)
        want, rows = full(sources)
        assert_same(merged.result(rows), want)
        assert len(merged) == sum(len(s.layer) for s in sources)
        merges += int(want[1].max() > 1)
    assert merges == 40  # walls did merge across robots: the comparison is not between trivial maps
    if seed == 2:
        assert merged.compactions > 10


def merged_fleet(rng: np.random.Generator, n: int) -> tuple:
    """A random fleet of ``n`` robots (its layers and frames), one source each in name order, and
    their merge."""
    _, layers, frames = random_fleet(rng, n)
    sources = [Source(("robot", k), k, layers[k], frames[k]) for k in sorted(layers)]
    merged = MergedMap(CFG)
    merged.update(sources)
    return layers, frames, sources, merged


def test_a_change_the_merge_was_not_told_of_shows():
    """The comparison can fail: a source changed behind the merge's back is not in its result."""
    rng = np.random.default_rng(5)
    layers, frames, sources, merged = merged_fleet(rng, 3)
    moved = [*sources[:-1], Source(sources[-1].key, "r2", layers["r2"], frames["r2"] + [0.5, 0.0, 0.0])]
    want, rows = full(moved)
    with pytest.raises(AssertionError):
        assert_same(merged.result(rows), want)
    merged.update(moved)
    assert_same(merged.result(rows), want)


def test_a_common_rigid_motion_moves_the_merged_map():
    rng = np.random.default_rng(3)
    layers, _, sources, merged = merged_fleet(rng, 5)
    g = np.array([0.004, -0.003, 0.0002])
    sources = [Source(s.key, s.robot, s.layer, compose(g, s.transform)) for s in sources]
    merged.moved(g, sources)
    want, rows = full(sources)
    assert_same(merged.result(rows), want, atol=1e-9)
    assert not merged.update(sources)  # the transforms it holds are the fleet's
    name = sorted(layers)[2]
    sources[2] = Source(sources[2].key, name, layers[name], sources[2].transform + np.array([0.05, 0.0, 0.0]))
    merged.update(sources)
    assert_same(merged.result(rows), full(sources)[0], atol=1e-9)


def rows_sorted(seg: np.ndarray) -> np.ndarray:
    flat = np.round(seg.reshape(-1, 4), 9)
    return flat[np.lexsort(flat.T[::-1])]


def test_without_one_source_is_the_merge_of_the_others_and_crops_by_box():
    rng = np.random.default_rng(4)
    _, _, sources, merged = merged_fleet(rng, 5)
    for s in sources:
        others = [o for o in sources if o is not s]
        want = full(others)[0][0]
        got = merged.without(s.key)
        np.testing.assert_allclose(rows_sorted(got), rows_sorted(want), atol=1e-8)
        lo, hi = np.array([5.0, 5.0]), np.array([12.0, 9.0])
        a, b = want.min(axis=1), want.max(axis=1)
        inside = want[(a[:, 0] <= hi[0]) & (b[:, 0] >= lo[0]) & (a[:, 1] <= hi[1]) & (b[:, 1] >= lo[1])]
        assert 0 < len(inside) < len(want)
        np.testing.assert_allclose(rows_sorted(merged.without(s.key, lo, hi)), rows_sorted(inside), atol=1e-8)
    np.testing.assert_array_equal(
        rows_sorted(merged.without(("robot", "nobody"))), rows_sorted(full(sources)[0][0])
    )
    # a source held back from an update: the merge of the others is the same, and the next update
    # takes the source's change
    held = Source(
        sources[1].key, sources[1].robot, layer(sources[1].layer.seg[::2], rng), sources[1].transform
    )
    moved = Source(
        sources[3].key, sources[3].robot, sources[3].layer, sources[3].transform + np.array([0.3, 0, 0])
    )
    later = [sources[0], held, sources[2], moved, sources[4]]
    merged.update(later, hold=held.key)
    others = [later[0], *later[2:]]
    np.testing.assert_allclose(
        rows_sorted(merged.without(held.key)), rows_sorted(full(others)[0][0]), atol=1e-8
    )
    merged.update(later)
    want, rows = full(later)
    assert_same(merged.result(rows), want)


# --- the fleet -------------------------------------------------------------------------------------


def offline(fleet: Fleet) -> tuple:
    """The fused arrays a full merge gives for the fleet as it is: placed robots by name, then the
    retired pieces, each layer under its transform, provenance by the fused map's rows."""
    fm = fleet.latest()
    rows = {s.robot: i for i, s in enumerate(fm.robots)}
    placed = sorted(
        (r for r in fleet.robots.values() if r.alignment.placed and r.layer is not None),
        key=lambda r: r.robot,
    )
    pieces = [p for name in sorted(fleet.retired) for p in fleet.retired[name]]
    parts = placed + pieces
    seg = np.concatenate([apply_segments(x.alignment.transform, x.layer.seg) for x in parts])
    w = np.concatenate([x.layer.weight for x in parts])
    owner = np.concatenate([np.full(len(x.layer), rows[x.robot]) for x in parts])
    return merge_segments(seg, w, owner, fleet.cfg.fusion)


def assert_fused_as_offline(fleet: Fleet) -> None:
    fm = fleet.latest()
    assert_same((fm.seg, fm.support, fm.prov_offsets, fm.prov_robot), offline(fleet), atol=1e-9)


class RandomFleet:
    """Robots with priors mapping parts of one building, each in its own frame."""

    def __init__(self, seed: int, n: int):
        self.rng = np.random.default_rng(seed)
        self.walls = building(self.rng)
        self.frames = {
            f"r{k}": np.array([*self.rng.uniform(-5, 5, 2), self.rng.uniform(-3, 3)]) for k in range(n)
        }
        self.session = dict.fromkeys(self.frames, 1)
        self.seq = dict.fromkeys(self.frames, 0)

    def map(self, name: str):
        self.seq[name] += 1
        lo = self.rng.uniform(0, 18, 2)
        seg = apply_segments(inverse(self.frames[name]), seen(self.rng, self.walls, lo, lo + 22))
        prior = self.frames[name] + self.rng.normal(0, [0.02, 0.02, 0.003])
        return robot_map_from_segments(
            seg, name, session=f"s{self.session[name]}", seq=self.seq[name], prior=prior, prior_sigma=SIGMA
        )

    def restart(self, name: str):
        self.session[name] += 1
        self.seq[name] = 0
        self.frames[name] = np.array([*self.rng.uniform(-5, 5, 2), self.rng.uniform(-3, 3)])
        return self.map(name)


@pytest.mark.parametrize("seed", [0, 1])
def test_the_fleet_fuses_as_a_full_merge_through_random_puts(seed):
    world = RandomFleet(seed, 5)
    fleet = Fleet(FleetConfig(), "srv")
    for name in world.frames:
        fleet.put_map(world.map(name), 0.0)
    assert fleet.fuse(0.0) is not None
    assert_fused_as_offline(fleet)
    t, restored, refined, retired = 0.0, False, 0, 0
    for step in range(36):
        t += 3.0
        name = f"r{world.rng.integers(5)}"
        if step % 11 == 5:
            fleet.put_map(world.restart(name), t)  # a new session: the old map is a retired piece
        elif step == 20:
            fleet.set_online(name, False)  # leaves: every placed robot refined at once
        else:
            fleet.put_map(world.map(name), t)
        before = {n: r.alignment.transform.copy() for n, r in fleet.robots.items()}
        fleet.fuse(t)
        refined += sum(
            not np.array_equal(before[n], r.alignment.transform)
            for n, r in fleet.robots.items()
            if n in before
        )
        assert_fused_as_offline(fleet)
        retired = max(retired, sum(len(p) for p in fleet.retired.values()))
        if step == 24:  # a restart of the server: restored from the snapshot, fused in full
            meta, maps = fleet.snapshot()
            back = Fleet.restore(meta, maps, fleet.cfg, "srv")
            a, b = fleet.latest(), back.latest()
            restored_arrays = (b.seg, b.support, b.prov_offsets, b.prov_robot)
            assert_same((a.seg, a.support, a.prov_offsets, a.prov_robot), restored_arrays, atol=1e-9)
            fleet, restored = back, True
    assert restored and retired >= 2 and refined >= 5  # the sequence did what it is meant to
    assert fleet.latest().support.max() > 1


def test_a_refinement_on_the_crop_is_the_one_on_the_whole_placed_map():
    world = RandomFleet(2, 4)
    fleet = Fleet(FleetConfig(), "srv")
    for name in world.frames:
        fleet.put_map(world.map(name), 0.0)
    fleet.fuse(0.0)
    c = fleet.cfg.alignment
    for margin in (2.0, 0.0):  # 0: the refinement leaves the crop and is done again on the whole map
        f = copy.deepcopy(fleet)
        f.cfg = FleetConfig(refine_margin_m=margin)
        for name, r in sorted(f.robots.items()):
            got = f.placer.estimate(r, r.map.prior, r.map.prior_sigma, None, False)
            want = estimate_alignment(r.layer.seg, f.global_segments(name), c, r.map.prior, r.map.prior_sigma)
            assert (got.status, got.reason) == (want.status, want.reason)
            np.testing.assert_allclose(got.transform, want.transform, rtol=0, atol=1e-9)
            assert got.score_m == pytest.approx(want.score_m, abs=1e-6)
    assert any(r.alignment.reason.startswith("prior refined") for r in fleet.robots.values())


def test_a_cropped_index_refuses_queries_outside_its_box():
    seg = np.array([[(0.0, 0.0), (4.0, 0.0)], [(4.0, 0.0), (4.0, 4.0)]])
    index = MapIndex(seg, 0.1, inner=(np.array([-1.0, -1.0]), np.array([5.0, 5.0])))
    robot = Samples.of(np.array([[(1.0, 0.05), (3.0, 0.05)]]), 0.1)
    assert index.overlap(np.zeros(3), robot, 0.1, 0.1) > 1.9
    with pytest.raises(OutsideIndex):
        index.overlap(np.array([10.0, 0.0, 0.0]), robot, 0.1, 0.1)


def test_layers_cache_their_length_and_box():
    m = robot_map_from_segments(np.array([[(0.0, 0.0), (3.0, 4.0)]]), "r")
    lay = fuse_particles(m, CFG)
    assert lay.length_m == pytest.approx(5.0)
    np.testing.assert_array_equal(lay.bounds, [0.0, 0.0, 3.0, 4.0])
