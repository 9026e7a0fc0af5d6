"""benchmarks/bench_soak.py runs as documented: a few simulated minutes of an exploring robot with
its online back end in its own process give rows of resident memory, keyframes and loops, and
the JSON. (``--explore`` failed at its first scan from 2026-11-26 until 2026-12-05: the explorer
reads the filter's map through ``SimSource.core``, which only the agent's service set.)"""

import json

from tests.benchscripts import bench_script


def test_a_short_exploring_soak_writes_its_rows_and_the_backend_works(tmp_path, capsys):
    out = tmp_path / "soak.json"
    with bench_script("bench_soak") as bench:
        code = bench.main(
            ["--hours", "0.05", "--explore", "--particles", "3", "--every-min", "1", "--json", str(out)]
        )
    assert code == 0
    result = json.loads(out.read_text())
    rows = result["rows"]
    assert result["finished"] and len(rows) == 3, rows  # at 1, 2 and 3 minutes
    assert [round(r["sim_h"] * 60) for r in rows] == [1, 2, 3]
    last = rows[-1]
    assert last["rss_agent_mb"] > 10 and last["rss_backend_mb"] > 10
    assert last["keyframes"] > 5 and last["updates"] >= 2 and last["map_bytes"] > 1000
    assert "RSS agent" in capsys.readouterr().out
