"""benchmarks/bench_demo.py: its rows as printed (the pure part of a script that runs demos)."""

from tests.benchscripts import bench_script


def test_a_real_log_row_names_each_piece_merged_or_its_status_whole():
    """A piece never merged is named with its status in full ("unaligned", not "una"), one that
    merged (the reference at once) with the time it did; the count of pieces placed and the
    relations errors lead."""
    m = {
        "robots": {
            "robot1": {"status": "unaligned", "time_to_first_merge_s": None},
            "robot2": {"status": "reference", "time_to_first_merge_s": 2.0},
            "robot3": {"status": "aligned", "time_to_first_merge_s": 41.6},
        },
        "wrong_merges": [],
        "relations": {"trans_mean_m": 0.0391, "rot_mean_deg": 0.41, "n": 1279},
        "relations_across": {"trans_mean_m": 0.0652, "rot_mean_deg": 0.73, "n": 210},
    }
    with bench_script("bench_demo") as bd:
        line = bd.log_row("aces", 3, 20, m)
    assert line.startswith("aces           3   20  2/3 placed  wrong 0  all 0.039 m 0.41° (n=1279)")
    assert "across 0.065 m 0.73° (n=210)" in line
    assert line.endswith("robot1:unaligned robot2@2s robot3@42s")
