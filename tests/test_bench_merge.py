"""benchmarks/bench_merge.py on a short run: the recordings hold what the agents publish (maps with
their graph, free space, the end of the run) and one seed's rows are made of them (evidence, the
fleet's placements, errors), with the contradiction check on and off."""

import numpy as np
import pytest

from tests.benchscripts import bench_script

DURATION_S = 40.0


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    cache = tmp_path_factory.mktemp("bench_merge")
    with bench_script("bench_merge") as module:
        paths = [module.cache_path(cache, "office", i, i, DURATION_S) for i in range(3)]
        for i, p in enumerate(paths):
            module.record("office", i, i, DURATION_S, p)
        yield module, paths


def test_a_recording_holds_the_maps_free_space_and_end_of_run(recorded):
    module, paths = recorded
    rec = module.load(paths[1])
    assert len(rec.maps) >= 20 and len(rec.free) >= 5
    assert np.all(np.diff(rec.stamps) >= 0) and rec.stamps[-1] == pytest.approx(DURATION_S, abs=1.0)
    assert rec.stamps[-1] == rec.stamps[-2] == rec.stamps[-3]  # the corrected map, then the rebuilt one
    assert all(m.has_graph for m in rec.maps[-2:]) and rec.maps[-1].prior is None
    assert rec.free[-1].robot == rec.maps[-1].robot == "robot2"
    np.testing.assert_allclose(rec.start, [15.0, 5.5, -np.pi / 2])  # the office's route 1 start


@pytest.mark.parametrize("enabled", [False, True])
def test_one_seed_gives_a_row_per_robot(recorded, enabled):
    module, paths = recorded
    sets = [f"contradiction.enabled={str(enabled).lower()}"]
    res = module.run_seed("office", 0, 3, paths, sets)
    rows = res["robots"]
    assert sorted(rows) == ["robot1", "robot2", "robot3"]
    ref = [n for n, r in rows.items() if r["reference"]]
    assert len(ref) == 1 and rows[ref[0]]["error_m"] == pytest.approx(0.0, abs=1e-9)
    # the reference's walls, alone in the fleet, where its own map at its true start has them; 40 s
    # of the office mapped within centimetres, and the fused map is the reference's
    r = rows[ref[0]]
    assert r["fleet_wall_median_m"] == pytest.approx(r["own_wall_median_m"], abs=1e-12)
    # (0.0025 m, measured with the start gauge, BackendConfig.gauge; 0.0060 before it; 0.0147
    # before the scan points were paired only along their own lines)
    assert 0.001 < r["own_wall_median_m"] < 0.008 and r["own_wall_within"] > 0.98, r
    assert res["wall_median_m"] == pytest.approx(r["own_wall_median_m"], abs=1e-12)  # (it alone placed)
    for r in rows.values():
        if r["reference"]:
            continue
        assert r["false_verdicts"] >= 0 and isinstance(r["verdicts"], list)
        # 40 s: young maps, the maturity window not passed — nobody is merged, and it says why
        assert r["placed_s"] is None and r["reason"], r
    with pytest.raises(AttributeError):
        module._with_overrides(module.FleetConfig(), ["no_such_field=1"])


def test_the_truth_simulated_again_is_the_truth_beside_the_scans():
    from robot_agent.sim import LiveSim, builtin_world

    with bench_script("bench_merge") as module:
        stamps, poses = module.true_path("office", 2, 7, 6.0)
    sim = LiveSim(builtin_world("office"), 2, seed=7)
    beside = [(s.stamp_s, *sim.truth) for s in sim.scans(6.0)]
    np.testing.assert_array_equal(np.column_stack([stamps, poses]), np.array(beside))


def test_a_map_turned_from_its_first_pose_leaves_a_floor_to_any_rigid_merge():
    """A robot whose own map is turned 0.3° about a point 10 m from its first pose, placed where its
    map truly lies: its keyframes agree with the truth, its first one is 5 cm and 0.3° off — its own
    map frame's error (the reference's own frame is exact)."""
    from types import SimpleNamespace

    from shared.geometry import compose, inverse, relative

    t = np.arange(40.0)
    ref_true = np.column_stack([t * 0.5, np.zeros(40), np.zeros(40)])
    rob_true = np.column_stack([np.full(40, 3.0), 2.0 + t * 0.5, np.full(40, np.pi / 2)])
    turn = np.radians(0.3)
    pivot = np.array([10.0, 0.0, 0.0])  # (in the robot's own frame: its map's middle, 10 m ahead)
    own = relative(rob_true[0], rob_true)
    turned = compose(compose(pivot, np.array([0.0, 0.0, turn])), compose(inverse(pivot), own))
    truth = {"ref": np.zeros(3), "rob": relative(ref_true[0], rob_true[0])}
    # placed where its map truly lies: its turned keyframes put back on the truth as a whole
    place = compose(
        relative(ref_true[0], rob_true[0]), compose(pivot, compose([0.0, 0.0, -turn], inverse(pivot)))
    )
    paths = {
        "ref": SimpleNamespace(
            kf_stamp=t, local=relative(ref_true[0], ref_true), pose=relative(ref_true[0], ref_true)
        ),
        "rob": SimpleNamespace(kf_stamp=t, local=turned, pose=compose(place, turned)),
    }
    true = [(t, ref_true), (t, rob_true)]
    with bench_script("bench_merge") as module:
        rows = module._against_truth(paths, ["ref", "rob"], "ref", truth, true)
    assert rows["ref"]["floor_m"] == pytest.approx(0.0, abs=1e-9)
    assert rows["rob"]["own_ate_m"] == pytest.approx(0.0, abs=1e-9)
    assert rows["rob"]["fleet_ate_m"] == pytest.approx(0.0, abs=1e-9)
    assert rows["rob"]["floor_m"] == pytest.approx(10.0 * turn, rel=1e-3)  # 0.052 m
    assert rows["rob"]["floor_deg"] == pytest.approx(0.3, rel=1e-3)
    assert rows["ref"]["frame_m"] == pytest.approx(0.0, abs=1e-9)
    assert rows["ref"]["frame_deg"] == pytest.approx(0.0, abs=1e-7)
    assert rows["rob"]["frame_m"] == pytest.approx(10.0 * turn, rel=1e-3)
    assert rows["rob"]["frame_deg"] == pytest.approx(0.3, rel=1e-3)


def test_a_robot_placed_well_first_and_elsewhere_later_is_found_at_its_worst_place():
    """A robot's places after each fusion: at its true place, then bent 0.4 m off (a young map's
    drift: beyond the wrong-merge bound, not 3× it), then placed 34 m away turned half round (another
    place); against the truth in the reference of the moment (it changed once). The worst is the
    turned place, in units of the bound; a robot placed 0.1 m / 1° off only is within it."""
    truths = {"r1": np.array([10.0, 0.0, 0.0]), "r2": np.array([0.0, 5.0, np.pi / 2])}
    held = [
        (5.0, "r1", truths["r1"].copy(), None),
        (6.0, "r1", truths["r1"].copy(), truths["r1"] + [0.0, 0.4, 0.0]),
        (7.0, "r2", truths["r2"] + [34.0, 0.0, np.pi], None),
        (8.0, "r2", truths["r2"].copy(), None),
    ]
    with bench_script("bench_merge") as module:
        worst = module._worst_held(held, truths.__getitem__)
        assert worst[0] == pytest.approx(34.0) and worst[1] == pytest.approx(180.0) and worst[2] == 7.0
        assert module._worst_held(held[:2], truths.__getitem__) == pytest.approx((0.4, 0.0, 6.0))
        assert module._worst_held([], truths.__getitem__) is None
        row = dict(zip(("worst_held_m", "worst_held_deg", "worst_held_s"), worst, strict=True))
        assert module._held_wrong(row, 1.0) and module._held_wrong(row, module.FAR)
        row = dict(worst_held_m=0.4, worst_held_deg=0.0, worst_held_s=6.0)
        assert module._held_wrong(row, 1.0) and not module._held_wrong(row, module.FAR)
        row = dict(worst_held_m=0.1, worst_held_deg=1.0, worst_held_s=6.0)
        assert not module._held_wrong(row, 1.0)
        assert not module._held_wrong({}, 1.0)


def test_the_graphs_edges_against_the_truth_in_units_of_their_stated_uncertainty():
    """A robot's own edges 1 cm long against a stated 2 cm (χ = 0.5/√3), a tie to another robot's
    keyframe 0.5° off against a stated 1° (χ = 0.5/√3 too), held as walls two points 1 cm from
    their line at the truth against a stated 2 cm (χ = 0.5); a tie to a keyframe gone is not
    counted."""
    from types import SimpleNamespace

    from map_server.posegraph import Walls
    from shared.geometry import relative, transform_points

    true_a = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [2.0, 0.0, 0.0]])
    true_b = np.array([[2.0, 1.0, np.pi / 2], [2.0, 2.0, np.pi / 2]])
    edge_info = np.diag([1 / 0.02**2, 1 / 0.02**2, 1 / 0.01**2])
    off_1cm, off_half_deg = np.array([0.01, 0.0, 0.0]), np.array([0.0, 0.0, np.radians(0.5)])
    a = SimpleNamespace(
        ids=np.array([10, 11, 12]),
        a=np.array([0, 1]),
        b=np.array([1, 2]),
        z=relative(true_a[:2], true_a[1:]) + off_1cm,
        info=np.stack([edge_info] * 2),
    )
    b = SimpleNamespace(
        ids=np.array([5, 6]),
        a=np.zeros(0, int),
        b=np.zeros(0, int),
        z=np.zeros((0, 3)),
        info=np.zeros((0, 3, 3)),
    )
    tie_info = np.diag([1e4, 1e4, 1 / np.radians(1.0) ** 2])
    # the walls: robot b's keyframe 6 holds two points 1 cm beyond the line x = 1 of a's keyframe 12
    on_a12 = np.array([[1.01, 0.3], [1.01, -0.5]])
    points = transform_points(relative(true_b[1], true_a[2]), on_a12)  # (in keyframe 6's frame)
    walls = Walls(np.array([6, 6]), np.array([12, 12]), points, np.array([[1.0, 0.0]] * 2), np.ones(2),
                  np.full(2, 1 / 0.02**2))  # fmt: skip
    tie_z = relative(true_a[2], true_b[1]) + off_half_deg
    tie = SimpleNamespace(b_id=6, other="a", a_id=12, z=tie_z, info=tie_info, lines=walls)
    gone = SimpleNamespace(b_id=5, other="a", a_id=99, z=np.zeros(3), info=tie_info, lines=None)
    with bench_script("bench_merge") as module:
        rows = module._edges_against_truth(
            {"a": a, "b": b}, {"b": {0: tie, 1: gone}}, {"a": true_a, "b": true_b}
        )
    assert rows["a"]["own_edge_m"] == pytest.approx(0.01)
    assert rows["a"]["own_edge_deg"] == pytest.approx(0.0, abs=1e-9)
    assert rows["a"]["own_edge_chi"] == pytest.approx(0.5 / np.sqrt(3.0))
    assert rows["a"]["constraints"] == 0 and "constraint_chi" not in rows["a"]
    assert "own_edge_m" not in rows["b"] and rows["b"]["constraints"] == 1
    assert rows["b"]["constraint_m"] == pytest.approx(0.0, abs=1e-9)
    assert rows["b"]["constraint_deg"] == pytest.approx(0.5)
    assert rows["b"]["constraint_chi"] == pytest.approx(0.5 / np.sqrt(3.0))
    assert rows["b"]["wall_tie_m"] == pytest.approx(0.01) and rows["b"]["wall_tie_chi"] == pytest.approx(0.5)
    assert "wall_tie_m" not in rows["a"]


def _side_by_side():
    """Two robots' graphs 2 m apart along x, four keyframes each; the second's own edge 1 -> 2
    turned 0.01 rad: their truths, graphs and placements (posegraph.Placed)."""
    from map_server.posegraph import Placed, RobotGraph
    from shared.geometry import compose, relative

    t = np.arange(4.0)
    true_r = np.column_stack([t, np.zeros(4), np.zeros(4)])
    true_s = np.column_stack([t, np.full(4, 2.0), np.zeros(4)])
    info = np.stack([np.diag([1e4, 1e4, 1e6])] * 3)

    def graph(true, turn):
        z = relative(true[:-1], true[1:])
        z[1, 2] += turn
        pose = [np.zeros(3)]
        for step in z:
            pose.append(compose(pose[-1], step))
        return RobotGraph(
            np.arange(4), np.array(pose), np.arange(3), np.arange(1, 4), z, info, np.zeros(0, int)
        )

    gr, gs = graph(true_r, 0.0), graph(true_s, 0.01)
    ref = Placed("r", gr, None, np.zeros(3), "reference")
    other = Placed("s", gs, None, relative(true_r[0], true_s[0]), "aligned")
    return true_r, true_s, gs, ref, other


def test_a_final_error_decomposed_into_what_the_ties_and_the_own_edges_leave():
    """Two robots side by side, tied once at their last keyframes: the tie 5 cm off and one of the
    second robot's own edges turned 0.01 rad. Solved again with the tie at the truth only the turn is
    left (at its first keyframe, 1 m from the turn), with its own edges at the truth only the tie's
    5 cm, with both nothing; the graph given is left as it was."""
    from map_server.posegraph import Constraint, FleetGraph
    from shared.geometry import compose, inverse, relative

    true_r, true_s, gs, ref, other = _side_by_side()
    tie_z = relative(true_r[3], true_s[3]) + np.array([0.05, 0.0, 0.0])
    fg = FleetGraph()
    fg.constraints = {"s": {(3, "r"): Constraint(3, "r", 3, tie_z, np.diag([1e4, 1e4, 1e6]))}}
    with bench_script("bench_merge") as module:
        out = module.decompose(fg, [ref, other], {"r": true_r, "s": true_s}, "r")["s"]
    assert fg.solution == {} and fg.constraints["s"][(3, "r")].z is tie_z  # (solved on copies)
    assert out["both"][0] == pytest.approx(0.0, abs=1e-4) and out["both"][1] == pytest.approx(0.0, abs=1e-3)
    assert out["true_own"][0] == pytest.approx(0.05, abs=1e-3)
    # the tie at the truth: its first keyframe walked back from the last one along its own edges
    kf0 = compose(compose(compose(true_s[3], inverse(gs.z[2])), inverse(gs.z[1])), inverse(gs.z[0]))
    d = relative(kf0, true_s[0])
    assert out["true_ties"][0] == pytest.approx(np.hypot(d[0], d[1]), rel=0.02)
    assert out["true_ties"][1] == pytest.approx(np.degrees(0.01), rel=0.02)
    # as it is, both: the tie's 5 cm along the robots' way, the turn's 2 cm across it
    assert out["as_is"][0] == pytest.approx(np.hypot(out["true_ties"][0], out["true_own"][0]), rel=0.02)
    assert out["as_is"][1] == pytest.approx(np.degrees(0.01), rel=0.02)


def test_a_final_error_decomposed_with_the_ties_held_as_walls():
    """As above, the tie held as walls (graph.line_ties): three walls of robot r's last keyframe met
    by points of robot s's, the two facing x 5 cm off at the truth. With every robot's own edges at
    the truth the 5 cm are left; with the ties at the truth too (each line through its point),
    nothing."""
    from map_server.posegraph import Constraint, FleetGraph, Walls
    from shared.geometry import relative, transform_points

    true_r, true_s, _, ref, other = _side_by_side()
    normal = np.array([[1.0, 0.0], [1.0, 0.0], [0.0, 1.0]] * 2)
    on_r3 = np.array([[1.0, 0.5], [-2.0, 1.5], [0.5, 3.0], [1.0, 2.5], [-2.0, 2.0], [0.0, 3.0]])  # (r3 frame)
    d = np.sum(normal * on_r3, axis=1) + np.where(normal[:, 0] == 1.0, 0.05, 0.0)  # (x walls 5 cm off)
    points = transform_points(relative(true_s[3], true_r[3]), on_r3)  # (in s3's frame)
    walls = Walls(np.full(6, 3), np.full(6, 3), points, normal, d, np.full(6, 1e6))
    tie = Constraint(3, "r", 3, relative(true_r[3], true_s[3]), np.diag([1e4, 1e4, 1e6]), lines=walls)
    fg = FleetGraph()
    fg.constraints = {"s": {(3, "r"): tie}}
    with bench_script("bench_merge") as module:
        out = module.decompose(fg, [ref, other], {"r": true_r, "s": true_s}, "r")["s"]
    assert fg.constraints["s"][(3, "r")].lines.d is d  # (solved on copies)
    assert out["both"][0] == pytest.approx(0.0, abs=1e-4) and out["both"][1] == pytest.approx(0.0, abs=1e-3)
    assert out["true_own"][0] == pytest.approx(0.05, abs=2e-3)


def test_a_fused_map_against_the_true_walls():
    """Two true walls; a map of one of them 3 cm off along its whole length and of the other 20 cm
    off over a quarter of it: the distance every 0.1 m, over the map's length."""
    walls = np.array([[[0.0, 0.0], [10.0, 0.0]], [[0.0, 5.0], [0.0, 15.0]]])
    seg = np.array([[[0.0, 0.03], [10.0, 0.03]], [[0.2, 5.0], [0.2, 7.5]]])
    with bench_script("bench_merge") as module:
        e = module.wall_error(seg, walls)
        assert e["wall_median_m"] == pytest.approx(0.03)
        assert e["wall_p90_m"] == pytest.approx(0.2)
        assert e["wall_within"] == pytest.approx(100 / 125)
        assert module.wall_error(np.zeros((0, 2, 2)), walls)["wall_median_m"] is None
