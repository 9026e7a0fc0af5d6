"""benchmarks/bench_logs.py without running SLAM: finding logs and relations, folding seeds."""

from argparse import Namespace
from pathlib import Path

import pytest

from tests.benchscripts import BENCHMARKS, bench_script

SCRIPT = BENCHMARKS / "bench_logs.py"


@pytest.fixture(scope="module")
def bench():
    with bench_script("bench_logs") as module:
        yield module


def touch(path: Path) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("")
    return path


def test_log_stem(bench):
    assert bench.log_stem(Path("d/intel.clf")) == "intel"
    assert bench.log_stem(Path("intel_head.clf.gz")) == "intel_head"
    assert bench.log_stem(Path("mit-csail.clf")) == "mit-csail"
    for other in ("intel.relations", "intel.log", "intel.gz", ".clf", "clf"):
        assert bench.log_stem(Path(other)) is None


def test_discover_dirs_files_and_skips(bench, tmp_path):
    touch(tmp_path / "a" / "a.clf")
    touch(tmp_path / "a" / "a.relations")
    touch(tmp_path / "a" / "notes.txt")
    touch(tmp_path / "b" / "b_head.clf.gz")
    touch(tmp_path / "b" / "b_head.relations")
    touch(tmp_path / "c" / "c.clf.gz")
    touch(tmp_path / "c" / "c.clf.relations")  # not the stem's name: no relations for c
    (tmp_path / "empty").mkdir()
    given = [tmp_path / "a", tmp_path / "b" / "b_head.clf.gz", tmp_path / "c", tmp_path / "empty"]
    entries, skipped = bench.discover([*given, tmp_path / "a" / "a.clf"])  # a twice: once
    assert [(e.name, e.log.name, e.relations.name) for e in entries] == [
        ("a", "a.clf", "a.relations"),
        ("b_head", "b_head.clf.gz", "b_head.relations"),
    ]
    assert len(skipped) == 2
    assert "c.clf.gz" in skipped[0] and "c.relations" in skipped[0]
    assert str(tmp_path / "empty") in skipped[1]


def test_discover_rejects_missing_paths_and_clashing_stems(bench, tmp_path):
    with pytest.raises(bench.BenchInputError, match="no such file"):
        bench.discover([tmp_path / "nowhere"])
    with pytest.raises(bench.BenchInputError, match="not a directory nor"):
        bench.discover([touch(tmp_path / "x.relations")])
    for d in ("one", "two"):
        touch(tmp_path / d / "log.clf")
        touch(tmp_path / d / "log.relations")
    with pytest.raises(bench.BenchInputError, match="two logs named log"):
        bench.discover([tmp_path / "one", tmp_path / "two"])


def run(seed, trans, trans_std, rot, rot_std, filt, wall, rtf, rss, backend_s=0.5, live=None, online=None):
    relations = {
        "n": 10,
        "trans_mean_m": trans,
        "trans_std_m": trans_std,
        "rot_mean_deg": rot,
        "rot_std_deg": rot_std,
    }
    metrics = {
        "relations": relations,
        "relations_filter_only": {"trans_mean_m": filt},
        "wall_time_s": wall,
        "real_time_factor": rtf,
        "peak_rss_mb": rss,
        "backend_s": backend_s,
    }
    if live is not None:
        metrics["live_worst_trans_m"] = live
    if online is not None:
        metrics["relations_online"] = {"trans_mean_m": online}
        metrics["online_backend_share"] = 0.01 * seed
    return {"log": "x", "seed": seed, "returncode": 0, "metrics": metrics}


def test_aggregate_folds_seeds_and_leaves_failures_out(bench):
    runs = [
        run(0, 0.10, 0.05, 1.0, 2.0, 0.20, 10.0, 8.0, 100.0, live=0.7, online=0.35),
        run(1, 0.40, 0.15, 3.0, 4.0, 0.30, 20.0, 4.0, 150.0, backend_s=1.5, live=0.5, online=0.40),
        {"log": "x", "seed": 2, "returncode": 2, "stderr_tail": ["boom"]},
    ]
    a = bench.aggregate(runs)
    assert (a["runs"], a["failed"], a["n_relations"]) == (2, 1, 10)
    assert a["trans_mean_m"] == pytest.approx(0.25)  # mean of the seeds' means
    assert a["trans_std_m"] == pytest.approx(0.10)  # mean of the seeds' stds
    assert a["trans_worst_mean_m"] == pytest.approx(0.40)
    assert (a["rot_mean_deg"], a["rot_std_deg"], a["rot_worst_mean_deg"]) == pytest.approx((2.0, 3.0, 3.0))
    assert a["filter_only_trans_mean_m"] == pytest.approx(0.25)
    assert a["wall_time_s"] == pytest.approx(15.0)
    assert a["real_time_factor_min"] == 4.0  # the worst seed
    assert a["peak_rss_mb_max"] == 150.0
    assert a["backend_s"] == pytest.approx(1.0)
    assert a["live_worst_trans_m"] == 0.7  # the worst snapshot of any seed
    assert a["online_end_trans_mean_m"] == pytest.approx(0.375)
    assert a["live_over_end_worst"] == pytest.approx(2.0)  # seed 0: 0.7 / 0.35, per seed
    assert a["online_over_offline_worst"] == pytest.approx(3.5)  # seed 0: 0.35 / 0.10
    assert a["online_backend_share_max"] == pytest.approx(0.01)


def test_aggregate_of_only_failures_is_empty_not_an_error(bench):
    a = bench.aggregate([{"log": "x", "seed": 0, "returncode": 1, "stderr_tail": []}])
    assert (a["runs"], a["failed"]) == (0, 1)
    assert a["trans_mean_m"] is None and a["real_time_factor_min"] is None and a["peak_rss_mb_max"] is None
    assert bench._pm(a["trans_mean_m"], a["trans_std_m"]) == "—"


def test_published_cells_by_stem(bench):
    gmapping, graph, carto = bench.published_cells("intel")
    assert (gmapping, graph) == ("0.070 ± 0.083", "0.031 ± 0.026")
    assert carto == "0.0229 ± 0.0239\n0.453 ± 1.335°"
    assert bench.published_cells("intel_head") == ["—", "—", "—"]


def test_replay_command_and_one_core_env(bench):
    entry = bench.LogEntry("a", Path("/d/a.clf.gz"), Path("/d/a.relations"))
    args = Namespace(particles=7, set=["backend.enabled=false", "proposal.enabled=false"], limit=300)
    cmd = bench.replay_command(entry, 3, Path("/o"), args)
    assert cmd[1:5] == ["-m", "fleet_slam.cli", "replay", "/d/a.clf.gz"]
    tail = " ".join(cmd[5:])
    assert tail == (
        "--relations /d/a.relations --seed 3 --particles 7 --out /o --set backend.enabled=false "
        "--set proposal.enabled=false --limit 300"
    )
    live = " ".join(bench.replay_command(entry, 3, Path("/o"), args, live=True)[5:])
    assert live == tail.replace("--out /o", "--out /o --live 10")
    env = bench.child_env()
    assert env["OMP_NUM_THREADS"] == env["OPENBLAS_NUM_THREADS"] == env["MKL_NUM_THREADS"] == "1"
    assert env["PYTHONPATH"].split(":")[0] == str(SCRIPT.parents[1])
