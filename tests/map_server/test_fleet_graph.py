"""The fleet's pose graph (map_server/posegraph.py): a robot whose own map is bent (its heading
drifted slowly and no loop told it) is bent back into agreement with the others, which one rigid
transform cannot do; a robot without a graph stays placed as a whole; the solution survives a
restart; each robot's keyframes are answered where the graph put them."""

from __future__ import annotations

import dataclasses
import json
from functools import lru_cache

import numpy as np
import pytest

from map_server import posegraph
from map_server.config import FleetConfig, GraphConfig
from map_server.fleet import Fleet
from robot_agent.publish import directed
from robot_agent.sim import SimConfig, builtin_world, simulate_robot
from robot_agent.slam.extraction import extract_segments
from shared.geometry import compose, relative, wrap_angle
from shared.messages import GRAPH_FIELDS, RobotMap, info_upper


@lru_cache(maxsize=8)
def bent_run(robot_index: int, bend_rad_per_m: float, duration_s: float = 120.0, every: int = 5) -> tuple:
    """A robot of the office whose estimate turns by ``bend_rad_per_m`` more than it really does
    per metre: keyframes every ``every`` scans at the bent poses (its map frame: its start), their
    true poses in the world, and the map it draws from them (each scan's segments at the keyframe's
    bent pose, anchored to it). Returns ``(kf_scan, kf_stamp, est (K,3), truth (K,3), seg, anchor)``."""
    world = builtin_world("office")
    sim = simulate_robot(world, robot_index, duration_s, 0, SimConfig())
    ks = np.arange(0, len(sim.stamps_s), every)
    true_rel = relative(sim.truth[0], sim.truth[ks])
    step = relative(true_rel[:-1], true_rel[1:])
    step[:, 2] += bend_rad_per_m * np.hypot(step[:, 0], step[:, 1])
    est = [np.zeros(3)]
    for d in step:
        est.append(compose(est[-1], d))
    est = np.array(est)
    segs, anchor = [], []
    for i, k in enumerate(ks):
        s = extract_segments(sim.ranges_m[k], sim.angles_rad, range_max_m=sim.range_max_m)
        pose = compose(est[i], sim.laser_offset)
        facing = wrap_angle(s.alpha + np.pi + pose[2])
        segs.append(directed(s.transformed(pose).endpoints, facing))
        anchor.append(np.full(len(segs[-1]), k))
    return ks, sim.stamps_s[ks], est, sim.truth[ks], np.concatenate(segs), np.concatenate(anchor)


def graph_message(robot: str, run: tuple, prior: np.ndarray, seq: int = 1) -> RobotMap:
    """The robot's map with its graph: a chain of its own motions, held as an odometry chain is."""
    ks, stamps, est, _, seg, anchor = run
    z = relative(est[:-1], est[1:])
    d = np.hypot(z[:, 0], z[:, 1])
    sig = np.column_stack([0.01 + 0.02 * d, 0.01 + 0.02 * d, np.radians(0.2) + 0.02 * np.abs(z[:, 2])])
    info = np.zeros((len(z), 3, 3))
    info[:, [0, 1, 2], [0, 1, 2]] = 1.0 / sig**2
    n = len(seg)
    return RobotMap(
        robot, "s1", seq, float(stamps[-1]), 0, 1, np.ones(1), est[-1:], seg, np.arange(n, dtype=np.int64),
        np.ones(n, np.int64), np.full(n, 0.8), np.full(n, 10, np.int64), np.full(n, 100, np.int64),
        prior=prior, prior_sigma=np.array([0.05, 0.05, 0.01]), kf_id=ks.astype(np.int64), kf_stamp=stamps,
        kf_pose=est, edge_ids=np.column_stack([ks[:-1], ks[1:]]).astype(np.int64), edge_z=z,
        edge_info=info_upper(info), anchor=anchor.astype(np.int64), graph_seq=seq,
    )  # fmt: skip


BEND = np.radians(0.1)  # per metre: robot 1 drifts ~6° over its path


def fleet_of(
    enabled: bool = True, rigid_r0: bool = False, free_of=None, runs: dict | None = None, **graph
) -> tuple[Fleet, dict]:
    """Robots 0 (exact) and 1 (bent), placed by their true start poses as priors, fused until
    the graph has no keyframe left to match. ``rigid_r0``: robot 0's map comes without its graph;
    ``free_of``: the robots' free space (Fleet.free_of; none known by default); ``runs``: other
    runs (as :func:`bent_run` gives); ``graph``: GraphConfig overrides."""
    runs = runs or {"r0": bent_run(0, 0.0), "r1": bent_run(1, BEND)}
    graph_cfg = dataclasses.replace(GraphConfig(), enabled=enabled, **graph)
    cfg = dataclasses.replace(FleetConfig(), graph=graph_cfg)
    fleet = Fleet(cfg, "srv")
    fleet.free_of = free_of
    for name, run in runs.items():
        m = graph_message(name, run, prior=run[3][0])
        if rigid_r0 and name == "r0":
            m = dataclasses.replace(m, **dict.fromkeys(("kf_id", "kf_stamp", "kf_pose", "edge_ids", "edge_z",
                                                         "edge_info", "anchor", "graph_seq")))  # fmt: skip
        fleet.put_map(m, 0.0)
    fleet.fuse(0.0)
    fuse_on(fleet, 0.0, 200.0)
    return fleet, runs


def fuse_on(fleet: Fleet, t: float, until: float) -> float:
    """Fusions a second apart after ``t`` while the fleet has work pending, up to ``until``; the
    last one's time."""
    while fleet.pending_work and t < until:
        t += 1.0
        fleet.fuse(t)
    return t


def shape(x: np.ndarray) -> np.ndarray:
    """A path's shape: each keyframe seen from the one before (what a rigid motion keeps)."""
    return relative(x[:-1], x[1:])


def keyframe_errors(fleet: Fleet, runs: dict, robot: str) -> np.ndarray:
    """Each keyframe's distance [m] from its true place, where the fleet puts it."""
    path = {p.robot: p for p in fleet.paths(fleet.version)}[robot]
    _, stamps, est, truth, _, _ = runs[robot]
    placed = path.apply(stamps, est)
    return np.hypot(*(placed[:, :2] - truth[:, :2]).T)


@pytest.fixture(scope="module")
def bent():
    return fleet_of(True)


@pytest.mark.parametrize("lines", [True, False])
def test_a_bent_map_is_bent_back(bent, lines):
    """Placed as a whole, the bent map is off by more than a metre at its ends; bent back, within
    centimetres — within millimetres when the submaps' fits are held as the walls they matched
    (``line_ties``, the default) rather than as one relative pose each."""
    fleet, runs = bent if lines else fleet_of(True, line_ties=False)
    rigid, _ = fleet_of(False)
    before = keyframe_errors(rigid, runs, "r1")
    after = keyframe_errors(fleet, runs, "r1")
    assert fleet.graph.stats["constraints_kept"] >= 50  # measured 79 (either)
    assert np.percentile(before, 90) > 1.0  # measured 1.25 m
    # the exact robot gives way a little (its prior holds its start within 5 cm, no more)
    r0 = np.max(keyframe_errors(fleet, runs, "r0"))
    if lines:
        assert np.percentile(after, 90) < 0.015  # measured 0.0068 m
        assert np.median(after) < 0.006  # measured 0.0027 m
        assert r0 < 0.04  # measured 0.018 m
    else:
        assert np.percentile(after, 90) < 0.1  # measured 0.056 m (tying the keyframes tried: 0.085)
        assert np.median(after) < 0.05  # measured 0.025 m (0.054)
        assert r0 < 0.15  # measured 0.061 m (0.107)


def test_a_map_that_does_not_contradict_itself_is_held_to_its_own_shape(bent):
    """A robot whose walls stand nowhere in its own free space has its own edges' information
    taken ``consistent_scale`` times (a chain's odometry noise model lets an exact path bend by
    decimetres); one whose walls stand in it (here: a free space over all of robot 1's map, as a
    bent path's walls fall in the space its laser saw elsewhere) is bent as before: its own edges
    disagree less with its own solution, and the bent one is still bent back.

    Not asserted, because it does not hold here: that the exact robot then ends nearer the truth.
    Since constraints tie the keyframes their rows move with (``tie_own_anchor``), robot 0 held ends
    off by up to 0.093 m, loose 0.061 m (before: 0.072 against 0.107 m) — the chain's information
    lets a stiff path turn a little at every edge rather than bend where the constraints pull. The
    scale is kept for what bench_merge measures (office and warehouse, 10 seeds, tied: final errors
    over 0.05 m 12 of 40 at 10 times; at 1 time 14 of 38, one robot never placed and one undone)."""
    import shapely

    from shared import posegraph as solver

    areas = {"r0": shapely.box(500.0, 500.0, 510.0, 510.0), "r1": shapely.box(-500.0, -500.0, 500.0, 500.0)}
    fleet, runs = fleet_of(True, free_of=lambda robot, session: areas[robot])
    g = fleet.cfg.graph
    assert g.consistent_scale > 1.0
    assert fleet._consistent(fleet.robots["r0"]) and not fleet._consistent(fleet.robots["r1"])

    def own_chi2(f: Fleet) -> float:
        """Robot 0's own edges' chi-square (their own information) where the fleet's graph put it."""
        rg, x = f.robots["r0"].graph, f.graph.solution["r0"][1]
        r = relative(x[rg.a], x[rg.b]) - rg.z
        r[:, 2] = wrap_angle(r[:, 2])
        return float(solver.mahalanobis2(r, rg.info).sum())

    # measured 0.073 against 0.87 (no free space known: 1 each); tied by one relative pose per
    # submap (line_ties off) 0.13 against 1.95
    assert own_chi2(fleet) < 0.2 < 0.5 < own_chi2(bent[0])
    assert np.max(keyframe_errors(fleet, runs, "r0")) < 0.03  # measured 0.0097 m (line_ties off: 0.093)
    assert np.percentile(keyframe_errors(fleet, runs, "r1"), 90) < 0.015  # measured 0.0045 m (0.084)


def test_a_constraint_ties_the_keyframe_its_matched_rows_move_with():
    """An agent's map holds each wall once, anchored to the keyframe that first saw it: a long
    wall moves with one keyframe, and the keyframes that pass it later have none of their own
    (the simulated warehouse: 34-45 rows over 184 keyframes). A keyframe's submap is the rows
    anchored near it; the constraint its fit gives ties the keyframe those of its rows that
    matched move with (as the other side names the other robot's), its pose carried there by
    the fit's correction. Tied to the keyframe tried, the fit moved a keyframe the rows do not
    move with, and the rows followed only through the robot's own chain in between. Here every
    row of robot 1 is anchored two keyframes before the scan that drew it."""
    ks, stamps, est, truth, seg, anchor = bent_run(1, BEND)
    moved = ks[np.maximum(np.searchsorted(ks, anchor) - 2, 0)]
    runs = {"r0": bent_run(0, 0.0), "r1": (ks, stamps, est, truth, seg, moved)}
    fleet, _ = fleet_of(True, runs=runs, tie_own_anchor=True)
    cons = list(fleet.graph.constraints["r1"].values())
    assert len(cons) >= 30  # measured 38
    assert all(c.b_id in set(moved.tolist()) for c in cons)
    tried = {kid for kid, _ in fleet.graph.constraints["r1"]}
    assert sum(c.b_id not in tried for c in cons) >= len(cons) // 2  # measured 26 of 38 (0 tying those tried)
    # each tie says where the anchor is in the other robot's keyframe's frame, as the truth does
    own = dict(zip(ks.tolist(), truth, strict=True))
    other = dict(zip(runs["r0"][0].tolist(), runs["r0"][3], strict=True))
    err = np.array([np.hypot(*relative(relative(other[c.a_id], own[c.b_id]), c.z)[:2]) for c in cons])
    assert np.median(err) < 0.03 and np.percentile(err, 90) < 0.05  # measured 0.014, 0.029 m
    # and the bent robot is bent back closer (tying the keyframes tried: 0.082 m)
    assert np.percentile(keyframe_errors(fleet, runs, "r1"), 90) < 0.065  # measured 0.047 m


def test_a_map_that_agrees_with_itself_is_matched_with_wider_submaps():
    """A keyframe's submap is the rows anchored within ``window_keyframes`` of it: a bent map's
    rows anchored far apart disagree with each other. A map whose walls stand in none of its own
    free space (``Fleet._consistent``), matched against maps of which that holds too (here both), is
    matched with rows anchored within
    ``window_consistent_keyframes``: in a long aisle the narrow submap holds two parallel walls
    (nothing along it), the wide one the walls across it too (the simulated warehouse seed 4:
    final errors 0.124 / 0.120 m with 10, 0.043 / 0.035 m with 20). Here every row of robot 1 is
    anchored 18 keyframes before the scan that drew it: beyond the narrow window, within the wide."""
    import shapely

    ks, stamps, est, truth, seg, anchor = bent_run(1, 0.0)
    moved = ks[np.maximum(np.searchsorted(ks, anchor) - 18, 0)]
    runs = {"r0": bent_run(0, 0.0), "r1": (ks, stamps, est, truth, seg, moved)}
    unknown, _ = fleet_of(True, runs=runs)  # (no free space known: not taken as consistent)
    far = shapely.box(500.0, 500.0, 510.0, 510.0)
    agrees, _ = fleet_of(True, runs=runs, free_of=lambda robot, session: far)
    assert agrees._consistent(agrees.robots["r1"]) and not unknown._consistent(unknown.robots["r1"])
    narrow, wide = len(unknown.graph.constraints["r1"]), len(agrees.graph.constraints["r1"])
    assert wide >= 30 and wide >= 1.6 * narrow, (narrow, wide)  # measured 41 against 21
    # every keyframe's wide submap is large enough; 12 narrow ones are not
    assert unknown.graph.stats["refused_small"] >= 8 and not agrees.graph.stats.get("refused_small", 0)


def test_the_fused_map_is_the_bent_rows_and_the_status_follows_the_newest_keyframe(bent):
    fleet, runs = bent
    r1 = fleet.robots["r1"]
    assert r1.bent is not None and len(r1.bent.seg) == len(r1.layer.seg)
    s = fleet.latest().robot("r1")
    np.testing.assert_allclose(compose(s.transform, runs["r1"][2][-1]), r1.bent_x[-1], atol=1e-9)
    # (the maps move with the solution once a keyframe moved moved_m: within it of the last solve)
    d = relative(r1.bent_x[-1], fleet.graph.solution["r1"][1][-1])
    assert np.hypot(d[0], d[1]) < fleet.cfg.graph.moved_m and abs(d[2]) < fleet.cfg.graph.moved_rad


def test_the_solution_survives_a_restart(bent):
    fleet, _ = bent
    meta, maps = fleet.snapshot()
    meta = json.loads(json.dumps(meta, allow_nan=False))
    back = Fleet.restore(meta, maps, fleet.cfg, "srv", fleet.graph_state())
    np.testing.assert_array_equal(back.latest().seg, fleet.latest().seg)
    assert back.latest().version == fleet.latest().version
    for name in ("r0", "r1"):
        np.testing.assert_array_equal(back.robots[name].bent_x, fleet.robots[name].bent_x)


def test_after_a_restart_the_restored_bend_stays_out_until_the_graph_is_matched_again(bent):
    """The constraints are not persisted: a restarted server matches every keyframe again
    (``budget_keyframes`` a fusion), and a solve over the first few would bend the maps less
    meanwhile. The restored bend is published until the graph is whole again."""
    fleet, _ = bent
    meta, maps = fleet.snapshot()
    back = Fleet.restore(json.loads(json.dumps(meta)), maps, fleet.cfg, "srv", fleet.graph_state())
    t = fleet.epoch_s + 400.0
    back.fuse(t)
    assert back.graph.pending and back.graph.rebuilding  # (a fusion's share of the keyframes matched)
    for name in ("r0", "r1"):  # (moved only as every frame is: the prior gauge)
        np.testing.assert_allclose(
            shape(back.robots[name].bent_x), shape(fleet.robots[name].bent_x), atol=1e-9
        )
    fuse_on(back, t, t + 100.0)
    assert not back.graph.pending and not back.graph.rebuilding
    np.testing.assert_array_equal(back.robots["r1"].bent_x, back.graph.solution["r1"][1])


def test_a_robot_unplaced_or_moved_far_is_forgotten_by_the_graph(bent):
    """What the graph found where a robot was (its solution, its constraints and the others' on
    it) would hold it there: a robot undone and placed elsewhere ended 34 m / 180 deg from where
    its alignment put it (bench_merge, warehouse seed 2). Unplaced, or moved by more than twice
    the placement edge's sigma since the last solve, it is forgotten; a refinement is not."""
    import copy

    from map_server.fleet import _graph_item

    fleet, _ = bent
    items = {name: _graph_item(fleet.robots[name]) for name in ("r0", "r1")}
    g = copy.deepcopy(fleet.graph)
    assert "r1" in g.solution and any(c.other == "r1" for c in g.constraints["r0"].values())
    assert g.sync([items["r0"]]) == ["r1"]  # r1 unplaced
    assert "r1" not in g.solution and "r1" not in g.constraints
    assert all(c.other != "r1" for cons in g.constraints.values() for c in cons.values())
    g = copy.deepcopy(fleet.graph)
    t = items["r1"].transform
    near = dataclasses.replace(items["r1"], transform=compose(t, np.array([0.3, 0.0, 0.01])))
    assert g.sync([items["r0"], near]) == [] and "r1" in g.solution
    far = dataclasses.replace(items["r1"], transform=compose(t, np.array([0.0, 0.0, np.pi])))
    assert g.sync([items["r0"], far]) == ["r1"] and "r1" not in g.solution


def test_a_map_without_a_graph_stays_whole_and_the_others_bend_to_it():
    fleet, runs = fleet_of(True, rigid_r0=True)
    r0 = fleet.robots["r0"]
    assert r0.graph.rigid and r0.bent is None  # merged at its alignment's transform, as before
    path = {p.robot: p for p in fleet.paths(fleet.version)}["r0"]
    assert len(path.kf_stamp) == 1 and np.array_equal(path.pose[0], r0.alignment.transform)
    after = keyframe_errors(fleet, runs, "r1")
    assert np.percentile(after, 90) < 0.15  # measured 0.111 m


def test_a_graph_sent_once_serves_the_maps_after_it():
    """An agent sends its graph only when it changed; a map in between names it (``graph_seq``)
    and the server takes it from the map before. A graph the server missed: the last one it has
    if it holds every keyframe the anchors name, else the map is placed as a whole for now."""
    run = bent_run(1, BEND)
    fleet = Fleet(FleetConfig(), "srv")
    first = graph_message("r1", run, prior=run[3][0], seq=1)
    fleet.put_map(first, 0.0)
    graph = dict.fromkeys(("kf_id", "kf_stamp", "kf_pose", "edge_ids", "edge_z", "edge_info"))
    fleet.put_map(dataclasses.replace(first, seq=2, **graph), 1.0)  # (graph_seq stays 1)
    m = fleet.robots["r1"].map
    assert m.seq == 2 and m.has_graph and m.graph_seq == 1
    np.testing.assert_array_equal(m.kf_pose, first.kf_pose)
    # a later graph missed, anchors all known: the last graph serves
    fleet.put_map(dataclasses.replace(first, seq=3, graph_seq=3, **graph), 2.0)
    assert fleet.robots["r1"].map.has_graph and fleet.robots["r1"].map.graph_seq == 1
    # anchors naming a keyframe the server never saw: placed as a whole until the next graph
    unknown = np.full(len(first.seg), int(first.kf_id[-1]) + 1)
    fleet.put_map(dataclasses.replace(first, seq=4, graph_seq=4, anchor=unknown, **graph), 3.0)
    m = fleet.robots["r1"].map
    assert not m.has_graph and m.anchor is None and m.graph_seq is None


def test_what_the_graph_keeps_per_robot_is_bounded_by_its_graph(monkeypatch):
    """Keyframes that leave a robot's graph (retired, thinned by its back end) leave the fleet
    graph's bookkeeping too (beyond a slack, here none): it does not grow with the run."""
    monkeypatch.setattr(posegraph, "PRUNE_SLACK", 0)
    fleet, runs = fleet_of(True)
    assert len(fleet.graph._matched["r1"]) > 30  # every third of its ~120 keyframes: 41
    ks, stamps, est, truth, seg, anchor = runs["r1"]
    keep = anchor <= ks[9]  # a graph of its first 10 keyframes, and the rows made there
    small = graph_message("r1", (ks[:10], stamps[:10], est[:10], truth[:10], seg[keep], anchor[keep]),
                          prior=truth[0], seq=2)  # fmt: skip
    fleet.put_map(small, 300.0)
    fleet.fuse(300.0)
    assert len(fleet.graph._matched["r1"]) <= 10 and len(fleet.graph.constraints["r1"]) <= 10


def test_the_graph_can_run_after_the_fused_map_and_its_result_goes_out_next():
    """The server builds the fused map before it matches and solves the fleet's graph
    (``Fleet.fuse(bend=False)``, then ``Fleet.bend``): the graph is most of a fusion at 16 robots
    and need not stand between a map and the fused map that holds it. A robot's new map is in that
    fused map at once, bent by the last solution (its new keyframes carried by their neighbours'
    correction: not its old layer, not rigid); the graph's result goes out with the next fusion,
    and the state the rounds see is the one they see with the graph first."""
    import copy

    runs = {"r0": bent_run(0, 0.0), "r1": bent_run(1, BEND)}
    ks, stamps, est, truth, seg, anchor = runs["r1"]
    n = len(ks) * 2 // 3
    early = (ks[:n], stamps[:n], est[:n], truth[:n], seg[anchor <= ks[n - 1]], anchor[anchor <= ks[n - 1]])
    fleet = Fleet(FleetConfig(), "srv")
    fleet.put_map(graph_message("r0", runs["r0"], prior=runs["r0"][3][0]), 0.0)
    fleet.put_map(graph_message("r1", early, prior=truth[0]), 0.0)
    fleet.fuse(0.0)
    t = fuse_on(fleet, 0.0, 200.0)
    graph_first = copy.deepcopy(fleet)
    whole = graph_message("r1", runs["r1"], prior=truth[0], seq=2)
    for f in (fleet, graph_first):
        f.put_map(whole, t + 1.0)
    old_x = fleet.robots["r1"].bent_x
    fused = fleet.fuse(t + 1.0, bend=False)
    r1 = fleet.robots["r1"]
    assert fused.robot("r1").map_seq == 2 and r1.bent_of is r1.layer and len(r1.bent.seg) == len(r1.layer.seg)
    # the old keyframes as the last solution had them (moved as a whole only: r1's prior
    # placement was refined in this fusion, and the prior gauge moves every frame with it)
    np.testing.assert_allclose(relative(r1.bent_x[0], r1.bent_x[:n]), relative(old_x[0], old_x), atol=1e-9)
    assert np.percentile(keyframe_errors(fleet, runs, "r1"), 90) < 0.3  # the new ones carried
    graph_first.fuse(t + 1.0)
    fleet.bend()
    for name in ("r0", "r1"):
        np.testing.assert_allclose(fleet.robots[name].bent_x, graph_first.robots[name].bent_x, atol=1e-9)
    after = fleet.fuse(t + 2.0, bend=False)
    assert after is not None and after.version == fused.version + 1  # what the graph moved goes out
    np.testing.assert_allclose(after.seg, graph_first.latest().seg, atol=1e-9)
    assert np.percentile(keyframe_errors(fleet, runs, "r1"), 90) < 0.15


def _server_of_two(graph_every_s: float):
    """A map server (no bus) that has been sent two bent robots' maps with their priors (seq 1);
    returns it, the runs and ``send(name, run, seq)``, which sends one robot's map again."""
    from map_server.server import MapServer, ServerConfig
    from shared import codec
    from shared.keys import Keys

    class Bus:
        def put(self, key, payload, reliable=True):
            pass

    keys = Keys()
    server = MapServer(Bus(), keys, ServerConfig(graph_every_s=graph_every_s))
    runs = {"r0": bent_run(0, 0.0), "r1": bent_run(1, BEND)}

    def send(name, run, seq):
        for chunk in codec.split(graph_message(name, run, prior=run[3][0], seq=seq)):
            server.on_map(keys.robot_map(name), codec.encode(chunk))

    for name, run in runs.items():
        send(name, run, 1)
    return server, runs, send


def test_the_server_solves_the_graph_after_publishing_and_at_most_every_graph_every_s():
    """The server's tick publishes first (Fleet.fuse without the graph), then matches and solves
    the graph if it has work and ``graph_every_s`` passed; a held-back graph keeps the loop at the
    fusion pace (``owes``) and its result goes out with the next tick's fusion."""
    server, runs, send = _server_of_two(graph_every_s=3600.0)
    first = server.tick()  # both placed by their priors; the graph's first bend after it
    assert first is not None and len(server.bend_ms) == 1 and server.owes
    bent = server.tick()  # the bend goes out
    assert bent is not None and bent.version == first.version + 1 and not np.array_equal(bent.seg, first.seg)
    for _ in range(50):  # keyframes left to match, re-matched where the solve moved them: held
        # back by graph_every_s
        if not server.fleet.graph_stale:
            break
        assert server.owes
        n = len(server.bend_ms)
        server.tick()
        assert len(server.bend_ms) == n
        server._bend_s = -np.inf  # (as if graph_every_s had passed)
        server.tick()
        assert len(server.bend_ms) == n + 1
    assert not server.fleet.graph_stale
    server.tick()  # (the last bend goes out)
    assert not server.owes
    n = len(server.bend_ms)
    send("r1", runs["r1"], 2)  # a new map: out at once, carried by the last solution; no bend yet
    fused = server.tick()
    assert fused.robot("r1").map_seq == 2 and len(server.bend_ms) == n and server.owes
    server._bend_s = -np.inf
    server.tick()
    assert len(server.bend_ms) == n + 1


def test_the_server_runs_the_graphs_trials_after_publishing():
    """A trial the rounds ask for in a fusion (Fleet.trial, map_server/trials.py) is queued, not run
    there: the server steps it after publishing, keeps the loop at the fusion pace while one is
    under way (``owes``), and times its steps (``trial_ms``); a trial of a robot placed meanwhile
    is dropped."""
    server, _, _ = _server_of_two(graph_every_s=0.0)
    server.tick()
    for _ in range(50):  # (the graph's own work first)
        if not server.owes:
            break
        server.tick()
    assert not server.owes and not server.trial_ms
    from map_server.alignment import Alignment

    r = server.fleet.robots["r1"]
    place, r.alignment = r.alignment.transform, Alignment("unaligned", np.zeros(3), np.zeros(3))
    assert server.fleet.trial(r, [place]) is None and server.owes
    server._bend()  # (what a tick does after publishing)
    assert len(server.trial_ms) == 1 and not server.fleet.trials.busy and r.attempt_len_m is None
    assert server.fleet.trial(r, [place])[0] > 100.0  # (its walls on r0's)
    server.fleet.trial(r, [compose(place, np.array([0.0, 5.0, 0.0]))])
    r.alignment = Alignment("aligned", place, np.zeros(3))  # placed meanwhile: its trial is dropped
    server._bend()
    assert len(server.trial_ms) == 2 and not server.fleet.trials.busy and "r1" in server.fleet.trials.finished
    assert [t.places.shape for t in server.fleet.trials.finished["r1"]] == [(1, 3)]


def test_a_bend_cut_short_for_a_waiting_map_goes_on_in_the_next():
    """The server cuts the graph's work short when a map waits (``Fleet.bend(stop)``): one robot's
    keyframes matched and one iteration of the solve, the rest left due (``graph_stale``) and
    done by the next bends, as well as the uncut graph does."""
    runs = {"r0": bent_run(0, 0.0), "r1": bent_run(1, BEND)}
    fleet = Fleet(FleetConfig(), "srv")
    for name, run in runs.items():
        fleet.put_map(graph_message(name, run, prior=run[3][0]), 0.0)
    fleet.fuse(0.0, bend=False)  # placed by their priors
    fleet.bend(stop=lambda: True)
    g = fleet.graph
    assert len(g._matched["r0"]) > 0 and len(g._matched["r1"]) == 0  # r1's turn did not come
    assert g.pending and g.unsolved and fleet.graph_stale
    for _ in range(100):
        if not fleet.graph_stale:
            break
        fleet.bend()
    assert not fleet.graph_stale and not g.unsolved
    fleet.fuse(1.0, bend=False)
    after = keyframe_errors(fleet, runs, "r1")  # the bounds of the uncut graph (test_a_bent_map_is_bent_back;
    # the order keyframes are matched in moves them: measured 0.056 / 0.085 m at the 90th percentile)
    assert np.percentile(after, 90) < 0.15 and np.median(after) < 0.08


def test_a_robot_placed_elsewhere_before_the_graph_runs_is_merged_where_it_is_now():
    """Between a placement that jumps (undone and placed again, revised far) and the graph's next
    solve, the fused map has the robot rigidly at its new place, not bent where it was."""
    fleet, _ = fleet_of(True)
    r1 = fleet.robots["r1"]
    assert r1.bent is not None
    near = compose(r1.alignment.transform, np.array([0.5, 0.0, 0.0]))  # within the graph's reach
    r1.alignment = dataclasses.replace(r1.alignment, transform=near)
    fleet._carry()
    assert r1.bent is not None  # (the graph's next solve moves it)
    far = compose(r1.alignment.transform, np.array([10.0, 0.0, np.pi / 2]))
    r1.alignment = dataclasses.replace(r1.alignment, transform=far)
    fleet._carry()
    source = {s.robot: s for s in fleet._sources()}["r1"]
    assert r1.bent is None and source.layer is r1.layer and np.array_equal(source.transform, far)


def test_when_a_robot_leaves_the_graph_is_matched_and_solved_anew_on_the_final_maps():
    """A constraint found on a young map, and a solve that goes on from the last solution,
    hold the fleet near where the young maps needed it: in bench_merge's warehouse the robots
    ended 0.12-0.14 m off where their final maps, placed on the reference's, are within 0.012 m.
    When a robot leaves (its map is final) the graph forgets its solution and constraints and is
    matched (wide, from the placements) and solved anew: the fleet ends exactly as the same one
    whose graph held nothing astray."""
    fleet, runs = fleet_of(True)
    x = fleet.graph.solution["r1"][1]
    x[len(x) // 2 :, :2] += 0.2  # a solution that went astray
    kid, c = next(iter(fleet.graph.constraints["r1"].items()))
    stale = c.z + np.array([0.3, 0.0, 0.02])
    fleet.graph.constraints["r1"][kid] = dataclasses.replace(c, z=stale)  # one found on a young map
    fresh, _ = fleet_of(True)
    for f in (fleet, fresh):
        f.set_online("r1", False)
        f.fuse(300.0)
        fuse_on(f, 300.0, 400.0)
    for robot in ("r0", "r1"):
        np.testing.assert_array_equal(fleet.graph.solution[robot][1], fresh.graph.solution[robot][1])
    assert not any(np.array_equal(c.z, stale) for c in fleet.graph.constraints["r1"].values())
    # measured 0.038 m (0.056 before it left; going on from the last solution, as before, 0.125 m;
    # matched anew but the maps bent by each partial solution meanwhile, 0.126 m)
    assert np.percentile(keyframe_errors(fleet, runs, "r1"), 90) < 0.05


def test_while_the_graph_is_matched_anew_the_last_whole_bend_stays_out():
    """Matching every keyframe again takes fusions (``budget_keyframes`` a fusion); a solve over
    the first few constraints would bend the maps less meanwhile. The robots' maps and paths keep
    the shape the last whole solution gave them (moved only as every frame is: the prior gauge)
    until the new one is whole; a map that comes meanwhile is merged at once, bent as they were."""
    fleet, runs = fleet_of(True)
    before = {name: shape(fleet.graph.solution[name][1]) for name in ("r0", "r1")}
    run = runs["r1"]
    fleet.put_map(graph_message("r1", run, prior=run[3][0], seq=2), 300.0)  # its final map
    fleet.set_online("r1", False)
    fleet.fuse(300.0)
    assert fleet.graph.pending  # (a fusion's share of the keyframes matched)
    for name in ("r0", "r1"):
        np.testing.assert_allclose(shape(fleet.robots[name].bent_x), before[name], atol=1e-9)
    r1 = fleet.robots["r1"]  # the final map is merged at once, bent as before
    assert r1.map.seq == 2 and r1.bent_of is r1.layer
    assert fleet.latest().robot("r1").map_seq == 2
    assert fleet.latest().extra["graph_rebuilding"] == 1.0  # (a subscriber sees it is under way)
    fuse_on(fleet, 300.0, 400.0)
    assert not fleet.graph.pending and not fleet.graph.rebuilding
    assert fleet.latest().extra["graph_rebuilding"] == 0.0
    new = fleet.graph.solution["r1"][1]  # (the maps within moved_m of the new solution)
    d = relative(fleet.robots["r1"].bent_x, new)
    assert np.hypot(d[:, 0], d[:, 1]).max() < fleet.cfg.graph.moved_m
    assert np.abs(shape(new) - before["r1"]).max() > 1e-3


def test_a_robot_placed_elsewhere_while_the_graph_is_matched_anew_is_merged_where_it_is_now():
    """The solution held during a rebuild carries no robot whose placement jumped since — also
    before the rebuild's first solve (the server's fusion: the graph after publishing)."""
    fleet, _ = fleet_of(True)
    fleet.set_online("r1", False)
    fleet.fuse(300.0, bend=False)
    r1 = fleet.robots["r1"]
    assert fleet.graph.rebuilding and r1.bent is not None
    far = compose(r1.alignment.transform, np.array([10.0, 0.0, np.pi / 2]))
    r1.alignment = dataclasses.replace(r1.alignment, transform=far)
    fleet._carry()
    assert r1.bent is None


def test_a_keyframe_that_meets_two_robots_is_tied_to_each():
    """A keyframe whose submap meets enough wall of each of two other robots gets a constraint
    with each, from a fit against that robot's walls alone (``each_robot``), rather than only with
    the robot most of the matched walls are of: two robots that both revisit a place a third also
    mapped were tied only through the third there. Each tie says where the other robot's keyframe
    is as the truth does."""
    runs = {"r0": bent_run(0, 0.0), "r1": bent_run(1, BEND), "r2": bent_run(2, 0.0)}

    def pairs(fleet: Fleet) -> dict[int, set[str]]:
        out: dict[int, set[str]] = {}
        for kid, other in fleet.graph.constraints["r1"]:
            out.setdefault(kid, set()).add(other)
        return out

    fleet, _ = fleet_of(True, runs=runs)
    both = [kid for kid, others in pairs(fleet).items() if others == {"r0", "r2"}]
    assert len(both) >= 8, pairs(fleet)  # measured 17 of 41 keyframes with a constraint
    single, _ = fleet_of(True, runs=runs, each_robot=False)
    assert all(len(others) == 1 for others in pairs(single).values())
    own = dict(zip(runs["r1"][0].tolist(), runs["r1"][3], strict=True))
    for other in ("r0", "r2"):
        truth = dict(zip(runs[other][0].tolist(), runs[other][3], strict=True))
        cons = [c for (kid, o), c in fleet.graph.constraints["r1"].items() if o == other and kid in both]
        err = [np.hypot(*relative(relative(truth[c.a_id], own[c.b_id]), c.z)[:2]) for c in cons]
        assert np.median(err) < 0.03, (other, err)  # measured 0.012 m (r0), 0.008 m (r2)


def test_a_departure_with_no_bend_to_hold_holds_nothing():
    """A robot that leaves while at most one robot is solved (the reference alone placed) leaves
    no bend to hold: the robots placed after it are bent as the graph finds their constraints
    (held, they stayed rigid until every keyframe had been matched again: Intel in 3 pieces ended
    0.10 m, two pairs of pieces 0.3 m off, when the demo's fused map went quiet first)."""
    g = posegraph.FleetGraph()
    g.solution = {"r0": (None, np.zeros((1, 3)))}
    g.reset()
    assert not g.rebuilding and g.held == {} and g.solution == {}
    g.solution = {"r0": (None, np.zeros((1, 3))), "r1": (None, np.zeros((1, 3)))}
    g.reset()
    assert g.rebuilding and set(g.held) == {"r0", "r1"}
    g.solution = {}
    g.reset()  # (a reset during a rebuild keeps the bend before the first)
    assert g.rebuilding and set(g.held) == {"r0", "r1"}


@pytest.mark.parametrize("rebuild", [True, False])
def test_a_robot_placed_after_the_others_were_matched_is_sought_from_their_side_too(rebuild):
    """The others' keyframes tried before a robot was placed met none of its walls. When it
    arrives the graph is matched and solved anew (``rebuild_on_arrival``), or — arriving during a
    rebuild, or with that off — the others' keyframes near its map are due again; either way they
    are tied to it as when all came at once (Intel in 3 pieces, the last placed after the others'
    rebuild: tied from its own side only, 0.041 m over the log against 0.033 m)."""
    runs = {"r0": bent_run(0, 0.0), "r1": bent_run(1, BEND), "r2": bent_run(2, 0.0)}

    def tied_to(fleet: Fleet, robot: str, other: str) -> int:
        return sum(o == other for _, o in fleet.graph.constraints.get(robot, {}))

    together, _ = fleet_of(True, runs=runs)
    fleet, _ = fleet_of(True, runs={k: runs[k] for k in ("r0", "r1")}, rebuild_on_arrival=rebuild)
    assert tied_to(fleet, "r1", "r0") >= 20  # measured 39
    fleet.put_map(graph_message("r2", runs["r2"], prior=runs["r2"][3][0]), 200.0)
    fleet.fuse(200.0)
    assert fleet.graph.rebuilding == rebuild
    fuse_on(fleet, 200.0, 400.0)
    assert fleet.graph.stats.get("rebuilds_on_arrival", 0) == int(rebuild)
    assert tied_to(together, "r1", "r2") >= 8  # measured 22
    assert tied_to(fleet, "r1", "r2") >= 0.7 * tied_to(together, "r1", "r2")  # measured 22 (without: 0)


def test_a_rebuild_starts_from_the_bend_when_robots_were_placed_against_it_far_from_their_placements():
    """A robot placed by matching is placed (and refined) against the maps as the graph bent
    them: where the bend moved the others by metres (a real log's pieces), a rebuild from the
    placements put it metres from the others' unbent walls, out of a wide search's reach (Intel
    in 3 pieces: 0.41 m over the log, two pairs of pieces 2 m apart; from the bend 0.045 m). Then
    a departure's rebuild matches and solves from the bend; robots placed by priors, or bends
    within a wide search's reach, are rebuilt from their placements, as before."""
    from map_server.fleet import _graph_item

    for aligned, far in ((False, True), (True, False), (True, True)):
        fleet, _ = fleet_of(True)
        r1 = fleet.robots["r1"]
        if aligned:
            r1.alignment = dataclasses.replace(r1.alignment, status="aligned")
        if far:  # a bend that put r1 2 m from its placement (beyond the wide search's 1.5 m)
            g1, x1 = fleet.graph.solution["r1"]
            fleet.graph.solution["r1"] = (g1, x1 + np.array([2.0, 0.0, 0.0]))
        items = {r.robot: _graph_item(r) for r in fleet._bend_placed()}
        bend = {robot: x.copy() for robot, (_, x) in fleet.graph.solution.items()}
        fleet.set_online("r1", False)
        fleet.fuse(300.0)  # (a departure: the graph matched anew, a share of its keyframes a fusion)
        assert fleet.graph.rebuilding and fleet.graph.pending
        assert fleet.graph._from_bend == (aligned and far)
        if aligned and far:  # matched where the bend has them (its shape: the prior gauge moves
            # every frame) until every keyframe has been
            for robot, p in items.items():
                np.testing.assert_allclose(shape(fleet.graph.poses(p)), shape(bend[robot]), atol=1e-6)
        fuse_on(fleet, 300.0, 400.0)
        assert not fleet.graph.rebuilding and not fleet.graph._from_bend


@pytest.mark.parametrize(("beyond", "far"), [(5, False), (13, True)])
def test_a_tenth_of_a_robots_keyframes_beyond_reach_makes_the_rebuild_start_from_the_bend(beyond, far):
    """An Intel run whose last two pieces were placed after the departures had 13 % of one piece's
    keyframes beyond a wide search's reach of its placement (its median 1.26 m off): rebuilt from
    the placements, 0.41 m over the log; from the bend, 0.051 m."""
    from types import SimpleNamespace

    graph = posegraph.FleetGraph()
    own = np.column_stack([np.arange(100) * 0.5, np.zeros(100), np.zeros(100)])
    graph._placed_at["r1"] = np.zeros(3)
    bent = own.copy()
    bent[:, 1] += 1.0  # (within reach: 1 m)
    bent[-beyond:, 1] += 1.0  # (beyond: 2 m)
    assert graph._bent_far({"r1": (SimpleNamespace(pose=own), bent)}) == far


def test_a_robot_placed_while_the_bend_is_beyond_reach_joins_without_a_rebuild():
    """A robot placed by a search against the unbent maps while the graph holds the others bent
    beyond a wide search's reach of their placements is not rebuilt from there (the others would
    be matched from their bend, the newcomer from its placement: ACES in 3 pieces, the new piece
    ended 3 m off); the others' keyframes near it are matched again instead."""
    runs = {"r0": bent_run(0, 0.0), "r1": bent_run(1, BEND), "r2": bent_run(2, 0.0)}
    fleet, _ = fleet_of(True, runs={k: runs[k] for k in ("r0", "r1")})
    g1, x1 = fleet.graph.solution["r1"]
    fleet.graph.solution["r1"] = (g1, x1 + np.array([2.0, 0.0, 0.0]))  # (bent 2 m from its placement)
    fleet.put_map(graph_message("r2", runs["r2"], prior=runs["r2"][3][0]), 200.0)
    fleet.fuse(200.0)
    assert not fleet.graph.rebuilding and "rebuilds_on_arrival" not in fleet.graph.stats
    assert any(o == "r2" for _, o in fleet.graph.constraints.get("r0", {}))  # (r0 near r2: matched again)


@pytest.mark.parametrize("carry", [True, False])
def test_a_robot_placed_against_the_unbent_maps_starts_where_the_bend_moved_the_others(carry):
    """A robot placed against the unbent maps meets the others' walls at its placement; the bend
    may have moved them beyond a first match's reach (Intel in 3 pieces: the second piece bent
    2.4 m from its placement, the third placed 9 s later, tied 2 m off by 8 submaps and no scan).
    Its keyframes start where the bend moved the others' nearest keyframes from their placements
    (``carry_arrivals``) — unless it was placed against the bent maps: then as it is."""
    from map_server.fleet import _graph_item

    runs = {"r0": bent_run(0, 0.0), "r1": bent_run(1, BEND), "r2": bent_run(2, 0.0)}
    shift = np.array([2.0, 0.0, 0.0])  # the bend moved r0 and r1 2 m (a wide first match: 1.5 m)
    for against_bend in (False, True):
        fleet, _ = fleet_of(True, runs={k: runs[k] for k in ("r0", "r1")}, carry_arrivals=carry)
        for robot in ("r0", "r1"):
            g, x = fleet.graph.solution[robot]
            fleet.graph.solution[robot] = (g, compose(shift, x))
        prior = compose(shift, runs["r2"][3][0]) if against_bend else runs["r2"][3][0]
        fleet.put_map(graph_message("r2", runs["r2"], prior), 200.0)
        fleet.fuse(200.0, bend=False)  # (placed, not yet in the graph)
        items = {r.robot: _graph_item(r) for r in fleet._bend_placed()}
        fleet.graph.sync(list(items.values()))
        p = items["r2"]
        moved = np.hypot(*(fleet.graph.poses(p)[:, :2] - compose(p.transform, p.graph.pose)[:, :2]).T)
        carried = carry and not against_bend
        if carried:
            assert np.median(moved) == pytest.approx(2.0, abs=0.2)
        else:
            assert np.all(moved == 0.0)
        fleet.fuse(201.0)  # (one fusion's share of keyframes matched)
        tied = sum(o == "r1" for _, o in fleet.graph.constraints.get("r2", {}))
        if carry or against_bend:
            assert tied >= 3  # measured 5
        else:
            assert tied < 3  # (its keyframes 2 m from the others' bent ones: measured 2; line_ties off 0)


@pytest.mark.parametrize("share", [True, False])
def test_constraints_on_one_pair_of_keyframes_share_its_information(monkeypatch, share):
    """Neighbouring keyframes' submaps overlap, and tied to the keyframe their matched rows move
    with they constrain the same pair of keyframes again and again (robot 1's rows anchored two
    keyframes back: several tried keyframes tie one anchor) — one piece of evidence, not several:
    with ``share_pairs`` each of the N constraints on a pair enters the solve with 1/N of its
    information (the pair's total the mean of theirs)."""
    ks, stamps, est, truth, seg, anchor = bent_run(1, BEND)
    moved = ks[np.maximum(np.searchsorted(ks, anchor) - 2, 0)]
    runs = {"r0": bent_run(0, 0.0), "r1": (ks, stamps, est, truth, seg, moved)}
    seen = []
    solve = posegraph.posegraph.optimize

    def spy(x0, a, b, z, info, **kw):
        seen.append((a.copy(), b.copy(), info.copy(), kw["robust_from"]))
        return solve(x0, a, b, z, info, **kw)

    monkeypatch.setattr(posegraph.posegraph, "optimize", spy)
    fleet, _ = fleet_of(True, runs=runs, tie_own_anchor=True, share_pairs=share, line_ties=False)
    cons = list(fleet.graph.constraints["r1"].values()) + list(fleet.graph.constraints["r0"].values())
    pairs: dict = {}
    for c in cons:
        pairs.setdefault((c.b_id, c.a_id), []).append(c.info)
    assert max(len(v) for v in pairs.values()) >= 2  # pairs constrained more than once
    a, b, info, robust_from = seen[-1]
    given = {}
    for i in range(robust_from, len(a)):
        given.setdefault((a[i], b[i]), []).append(info[i])
    many = [v for v in given.values() if len(v) >= 2]
    assert many
    found = [c.info for c in cons]
    for v in many:  # each the information a constraint was found with, or 1/N of it
        scale = len(v) if share else 1
        assert all(any(np.allclose(m * scale, f) for f in found) for m in v)


@lru_cache(maxsize=4)
def keyframe_scans(robot_index: int, duration_s: float = 120.0, every: int = 5) -> tuple:
    """The scans of :func:`bent_run`'s keyframes as an agent sends them (robot frame, laser mount
    applied, a point per 5 cm, at most SCAN_POINTS evenly along the scan)."""
    from robot_agent.backend.online import scan_sample
    from shared.geometry import apply_points
    from shared.scanmatch import voxel_thin

    sim = simulate_robot(builtin_world("office"), robot_index, duration_s, 0, SimConfig())
    out = []
    for k in np.arange(0, len(sim.stamps_s), every):
        r = sim.ranges_m[k]
        ok = (r > 0) & (r < sim.range_max_m)
        xy = np.column_stack([r[ok] * np.cos(sim.angles_rad[ok]), r[ok] * np.sin(sim.angles_rad[ok])])
        out.append(scan_sample(voxel_thin(apply_points(sim.laser_offset, xy), 0.05)))
    return tuple(out)


def send_scans(monkeypatch, senders: set) -> set:
    """Robots ``senders`` (r0, r1) send their keyframes' scans with their maps (Fleet.put_map
    patched); the set, which the test may change."""
    original_put = Fleet.put_map

    def put(self, m, now_s):
        if m.robot in senders:
            pts = keyframe_scans(0 if m.robot == "r0" else 1)
            m = dataclasses.replace(
                m, scan_id=m.kf_id, scan_count=np.array([len(p) for p in pts]),
                scan_xy=np.concatenate(pts).astype(float),
            )  # fmt: skip
        return original_put(self, m, now_s)

    monkeypatch.setattr(Fleet, "put_map", put)
    return senders


def test_robots_that_send_keyframe_scans_are_tied_by_matching_them(monkeypatch):
    """Both robots send their keyframes' scans (schema 7) and are tied by them (``scans_always``;
    by default a pair of which one map contradicts its own free space — a real log's piece): the
    constraints come from matching the scans (the agents' loop matcher), not the segment submaps,
    and bend the bent robot back at least as closely; a pair the scans do not tie (they never
    passed near each other's keyframes) is tied by submaps (``scan_fallback``). With a robot that
    sends none, or maps not known to contradict themselves (no free space here), the submaps tie
    them."""
    runs = {"r0": bent_run(0, 0.0), "r1": bent_run(1, BEND)}
    submaps = []
    original_match = posegraph.FleetGraph._match_segments
    senders = send_scans(monkeypatch, {"r0", "r1"})

    def counted(self, p, ks, first, others, where):
        submaps.append(p.robot)
        return original_match(self, p, ks, first, others, where)

    monkeypatch.setattr(posegraph.FleetGraph, "_match_segments", counted)
    fleet, _ = fleet_of(True, runs=runs, scans_always=True)
    assert not submaps  # every constraint from the scans
    assert fleet.graph.stats["constraints_kept"] >= 20  # measured 33 (by submaps: 79)
    after = keyframe_errors(fleet, runs, "r1")
    assert np.percentile(after, 90) < 0.045  # measured 0.032 m (by submaps: 0.056 m)
    assert np.median(after) < 0.03  # measured 0.021 m (0.025 m)
    assert np.max(keyframe_errors(fleet, runs, "r0")) < 0.07  # measured 0.049 m (0.061 m)
    # robots that never pass near each other's keyframes (here: no radius) are tied by submaps
    fleet, _ = fleet_of(True, runs=runs, scans_always=True, scan_radius_m=0.0)
    assert set(submaps) == {"r0", "r1"} and fleet.graph.stats["constraints_kept"] >= 50
    assert np.percentile(keyframe_errors(fleet, runs, "r1"), 90) < 0.1  # (as by submaps alone)
    submaps.clear()
    fleet, _ = fleet_of(True, runs=runs)
    assert set(submaps) == {"r0", "r1"} and fleet.graph.stats["constraints_kept"] >= 50  # (as above)
    submaps.clear()
    senders.discard("r0")
    fleet, _ = fleet_of(True, runs=runs, scans_always=True)
    assert set(submaps) == {"r0", "r1"} and fleet.graph.stats["constraints_kept"] >= 50


@pytest.mark.parametrize("recentre", [True, False])
def test_a_scan_match_whose_best_lies_on_the_windows_edge_is_searched_again_around_it(monkeypatch, recentre):
    """A robot bent 0.25°/m (15° over its path), tied by scans: where the graph first puts its
    keyframes, the others' lie about a window's half width (0.8 m) from them, the true places on
    the window's edge. ICP brings each match there, but the score surface said nothing along the
    edge's axis (std 5 m) and the graph left the robot metres off; the window centred on its best
    and searched again (the default, ``scan_match.recentre``) says how well the place is known."""
    runs = {"r0": bent_run(0, 0.0), "r1": bent_run(1, np.radians(0.25))}
    send_scans(monkeypatch, {"r0", "r1"})
    over = {} if recentre else {"scan_match": dataclasses.replace(GraphConfig().scan_match, recentre=0)}
    fleet, _ = fleet_of(True, runs=runs, scans_always=True, line_ties=False, **over)
    errors = keyframe_errors(fleet, runs, "r1")
    if recentre:
        assert fleet.graph.stats["scan_recentred"] >= 5  # measured 14
        assert np.median(errors) < 0.15 and np.percentile(errors, 90) < 0.25  # measured 0.089, 0.162 m
    else:
        assert "scan_recentred" not in fleet.graph.stats
        assert np.median(errors) > 0.5  # measured 1.02 m (90th percentile 3.2 m)


def test_the_keyframe_scans_that_came_map_by_map_are_kept_whole_and_survive_a_restart():
    """An agent sends each keyframe's scan once (and a few again): the server keeps every scan of
    the graph's keyframes with the robot's map, a map whose graph went out before (``graph_seq``)
    included, stores them with it, and its graph has them all after a restart."""
    from shared import codec

    run = bent_run(0, 0.0)
    pts = keyframe_scans(0)
    whole = graph_message("r0", run, prior=run[3][0])
    k = len(whole.kf_id)

    def carrying(m: RobotMap, lo: int, hi: int) -> RobotMap:
        return dataclasses.replace(
            m, scan_id=m.kf_id[lo:hi], scan_count=np.array([len(p) for p in pts[lo:hi]]),
            scan_xy=np.concatenate(pts[lo:hi]).astype(float),
        )  # fmt: skip

    fleet = Fleet(FleetConfig(), "srv")
    fleet.put_map(carrying(whole, 0, k // 2), 0.0)
    fleet.put_map(carrying(dataclasses.replace(whole, seq=2, graph_seq=2), k // 2 - 3, k), 1.0)
    later = dataclasses.replace(whole, seq=3, **dict.fromkeys(GRAPH_FIELDS))  # (graph_seq 1: unchanged)
    fleet.put_map(dataclasses.replace(later, graph_seq=2), 2.0)
    kept = fleet.robots["r0"].map
    assert kept.seq == 3 and np.array_equal(kept.scan_id, whole.kf_id)
    _, maps = fleet.snapshot()
    stored = {n: codec.decode_stored_map(codec.encode_stored_map(m)) for n, m in maps.items()}
    meta, _ = fleet.snapshot()
    back = Fleet.restore(json.loads(json.dumps(meta)), stored, fleet.cfg, "srv")
    g = back.robots["r0"].graph
    assert g is not None and len(g.points) == k and all(p is not None for p in g.points)
    np.testing.assert_allclose(g.points[k - 1], pts[k - 1], atol=0.006)


@pytest.mark.parametrize(
    "scans, contradicts, always, by_scans",
    [
        ((True, True), (False, False), False, False),  # clean maps (a simulated world's): submaps
        ((True, True), (True, False), False, True),  # one found contradicting itself: scans
        ((True, True), (False, True), False, True),
        ((True, True), (False, False), True, True),  # scans_always
        ((True, False), (True, True), True, False),  # one sends none: submaps
    ],
)
def test_a_pair_is_tied_by_scans_when_both_send_them_and_a_map_contradicts_itself(
    scans, contradicts, always, by_scans
):
    def placed(name: str, sends: bool, bad: bool) -> posegraph.Placed:
        e, pts = np.zeros(0, np.int64), (np.zeros((40, 2)),) if sends else ()
        g = posegraph.RobotGraph(np.zeros(1, np.int64), np.zeros((1, 3)), e, e, np.zeros((0, 3)),
                                 np.zeros((0, 3, 3)), e, points=pts)  # fmt: skip
        return posegraph.Placed(name, g, None, np.zeros(3), "aligned", contradicts=bad)

    graph = posegraph.FleetGraph(GraphConfig(scans_always=always))
    a, b = placed("a", scans[0], contradicts[0]), placed("b", scans[1], contradicts[1])
    assert graph._by_scans(a, b) == graph._by_scans(b, a) == by_scans
    assert not posegraph.FleetGraph(GraphConfig(scans=False, scans_always=True))._by_scans(a, b)


def test_a_trial_bend_meets_the_others_walls_at_a_bent_robots_true_place_not_at_a_wrong_one():
    """Fleet.trial: a copy of the graph tries an unplaced robot at each place given, its keyframes
    matched and solved; at its true place its bent map is bent back onto the others' walls (more
    than it meets placed there whole), at a wrong place its keyframes meet nothing that holds. The
    live graph is not touched."""
    from map_server.alignment import Alignment
    from map_server.registration import MapIndex, Samples
    from shared.geometry import apply_segments

    fleet, runs = fleet_of(True)
    r = fleet.robots["r1"]
    r.alignment = Alignment("unaligned", np.zeros(3), np.zeros(3), reason="unplaced for the test")
    r.bent = r.bent_x = r.bent_of = None
    fleet.graph.forget("r1")
    before = (dict(fleet.graph.solution), {k: dict(v) for k, v in fleet.graph.constraints.items()})
    truth = runs["r1"][3][0]
    wrong = compose(truth, np.array([3.0, 1.5, np.radians(20.0)]))
    at_truth, at_wrong = fleet.trial(r, [truth, wrong])
    cfg = fleet.cfg.graph
    r0 = fleet.robots["r0"]
    theirs = MapIndex(apply_segments(r0.alignment.transform, r0.layer.seg), cfg.sample_step_m)
    whole = theirs.overlap(np.zeros(3), Samples.of(apply_segments(truth, r.layer.seg), cfg.sample_step_m),
                           *cfg.stages[-1])  # fmt: skip
    assert at_truth > 2.5 * whole  # measured 1104 m against 330 m (of 1344 m)
    assert at_wrong < 0.1 * at_truth  # measured 0 m
    assert fleet.graph.solution == before[0] and fleet.graph.constraints == before[1]
    assert "r1" not in fleet.graph.solution


def test_a_trial_run_after_publishing_in_steps_answers_as_one_run_at_once():
    """The server runs the graph's trials after publishing (map_server/trials.py): Fleet.trial
    queues one and says None until it is done, in steps cut short by ``stop()`` (a map waits), and
    then answers as a trial run at once does, for places within ``trial_same_m`` of those tried;
    the robot is searched again once it is in, and other places ask for a new trial."""
    from map_server.alignment import Alignment

    fleet, runs = fleet_of(True)
    r = fleet.robots["r1"]
    r.alignment = Alignment("unaligned", np.zeros(3), np.zeros(3), reason="unplaced for the test")
    r.bent = r.bent_x = r.bent_of = None
    fleet.graph.forget("r1")
    truth = runs["r1"][3][0]
    places = [truth, compose(truth, np.array([3.0, 1.5, np.radians(20.0)]))]
    at_once = fleet.trial(r, places)
    before = (dict(fleet.graph.solution), {k: dict(v) for k, v in fleet.graph.constraints.items()})

    fleet._defer_trials = True  # (as fuse(bend=False) sets it: the server's way)
    r.attempt_len_m = 100.0
    assert fleet.trial(r, places) is None and fleet.trials.busy and fleet.pending_work
    assert fleet.trial(r, places) is None and len(fleet.trials.queue) == 1  # (not asked twice)
    steps = 0
    while fleet.trials.busy:
        fleet.try_places(stop=lambda: True)  # (a map always waits: the least work each step)
        steps += 1
        assert steps < 1000
    assert steps >= 4 and r.attempt_len_m is None  # (measured: 16 steps; due: searched again)
    nearby = [compose(p, np.array([0.3, 0.0, 0.0])) for p in places]
    # measured: 1103.7 m and 0 m, at once 1104.0 m and 0 m
    assert fleet.trial(r, nearby) == pytest.approx(at_once, rel=0.02)
    assert fleet.graph.solution == before[0] and fleet.graph.constraints == before[1]
    other = [truth, compose(truth, np.array([0.0, 5.0, 0.0]))]
    assert fleet.trial(r, other) is None  # another place: a new trial
    assert fleet.trial(r, places[:1]) is None and len(fleet.trials.queue) == 1  # (replaces it)
    fleet.trial(r, other)
    fleet.try_places()
    # both finished trials answer (an attempt can ask for two: Placer._search, then _rival_trial)
    assert fleet.trial(r, other) is not None and fleet.trial(r, places) == pytest.approx(at_once, rel=0.02)


@pytest.mark.parametrize("lines", [True, False])
@pytest.mark.parametrize("consistent", [True, False])
def test_ties_between_maps_that_agree_with_themselves_get_the_narrower_kernel(monkeypatch, consistent, lines):
    """The robust kernel's width on each constraint between robots (each of its walls' ties, with
    ``line_ties``): ``robust_k_consistent`` where both robots' maps stand in none of their own free
    space (their ties state sigmas four times their errors: a narrower kernel weighs down the biased
    ones), ``robust_k`` where either does not (a bent piece's ties must bend it). The robots' own
    edges and placements get none."""
    seen = []
    solve = posegraph.posegraph.optimize

    def spy(x0, a, b, z, info, **kw):
        width = np.broadcast_to(kw["robust_k"], (len(a) - kw["robust_from"],))
        if kw.get("lines") is not None:
            width = np.concatenate([width, kw["lines"].k])
        seen.append((kw["robust_from"], width))
        return solve(x0, a, b, z, info, **kw)

    monkeypatch.setattr(posegraph.posegraph, "optimize", spy)
    monkeypatch.setattr(Fleet, "_consistent", lambda self, r: consistent)
    fleet_of(True, line_ties=lines)
    robust_from, width = seen[-1]
    assert robust_from > 0 and len(width) > 0
    cfg = GraphConfig()
    assert np.all(width == (cfg.robust_k_consistent if consistent else cfg.robust_k))
    assert cfg.robust_k_consistent < cfg.robust_k
