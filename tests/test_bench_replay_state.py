"""benchmarks/replay_state.py: a map server's saved state restored offline, its unplaced robots
searched again — without touching the state."""

import json

import numpy as np

from map_server.config import FleetConfig
from map_server.fleet import Fleet
from map_server.store import Store
from shared import codec
from shared.geometry import compose, inverse
from shared.metrics import transform_error
from tests.benchscripts import bench_script
from tests.map_server.robots import robot_map_from_segments, scan_map


def _saved_state(directory) -> np.ndarray:
    """Two office robots' exact maps fused, robot1 not placed yet (its map young), saved as the
    server saves its state; robot1's true place."""
    f = Fleet(FleetConfig(), "server")
    (seg0, start0), (seg1, start1) = scan_map("office", 0, 175.0), scan_map("office", 1, 175.0)
    f.put_map(robot_map_from_segments(seg0, "robot0"), 0.0)
    f.put_map(robot_map_from_segments(seg1, "robot1"), 1.0)
    f.fuse(1.0)
    assert not f.robots["robot1"].alignment.placed
    meta, maps = f.snapshot()
    blobs = {name: codec.encode_stored_map(m) for name, m in maps.items()}
    Store(directory).save({"fleet": meta, "now_s": 1.0, "server": "server"}, blobs)
    return compose(inverse(start0), start1)


def test_a_saved_state_is_replayed_offline_and_left_as_it_was(tmp_path):
    state = tmp_path / "state"
    truth = _saved_state(state)
    before = {p.name: p.read_bytes() for p in state.rglob("*") if p.is_file()}
    with bench_script("replay_state") as rs:
        fleet = rs.restore(state, FleetConfig())
        noise = rs.self_contradiction(fleet)
        rows = rs.replay(fleet, rounds=3)
        assert rs.main([str(state), "--json", str(tmp_path / "out.json")]) == 0
    assert [(r["round"], r["robot"], r["status"]) for r in rows[:2]] == [
        (0, "robot0", "reference"),
        (0, "robot1", "unaligned"),
    ]
    searched = [r for r in rows if r["round"] == 1 and r["robot"] == "robot1"]
    assert len(searched) == 1 and searched[0]["status"] == "aligned"
    err_m, err_rad = transform_error(np.array(searched[0]["transform"]), truth)
    assert err_m < 0.05 and err_rad < np.radians(0.5)
    assert all(r["round"] <= 2 for r in rows)  # a round placing nobody ends it
    # the state holds no free space: how much each map contradicts itself is not known
    assert set(noise) == {"robot0", "robot1"} and all(n["self_m"] is None for n in noise.values())
    assert all(n["length_m"] > 50.0 for n in noise.values())
    out = json.loads((tmp_path / "out.json").read_text())
    assert out["rows"] == rows and out["self_contradiction"] == noise
    assert {p.name: p.read_bytes() for p in state.rglob("*") if p.is_file()} == before
