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
    for r in rows.values():
        if r["reference"]:
            continue
        assert r["false_verdicts"] >= 0 and isinstance(r["verdicts"], list)
        # 40 s: young maps, the maturity window not passed — nobody is merged, and it says why
        assert r["placed_s"] is None and r["reason"], r
    with pytest.raises(AttributeError):
        module._with_overrides(module.FleetConfig(), ["no_such_field=1"])
