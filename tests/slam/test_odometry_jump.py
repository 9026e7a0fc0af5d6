"""Issue 24 row 1: a robot's odometry jumps by 1 km in the middle of its log (one line edited, or
every line from there on). Before, the agent went on without a word and a third of its map
landed ~1 km away. Now the scans contradict the jump, the increment is not used, the agent says
so, and its map stays where the building is."""

from __future__ import annotations

import gzip
import re
from pathlib import Path

import numpy as np
import pytest

from robot_agent.agent import AgentConfig, AgentCore
from robot_agent.slam.fastslam import FastSLAM, SlamConfig
from robot_agent.sources import read_log
from shared.geometry import point_segment_distance
from tests.reported import run_reported

LOG = Path(__file__).parents[1] / "data" / "intel_head.clf.gz"
SCANS = 700
JUMP_AT = 400  # the FLASER line edited (0-based among the FLASER lines)


def _edited(tmp_path: Path, persistent: bool) -> Path:
    lines = gzip.open(LOG, "rt").read().splitlines()
    k = 0
    for i, line in enumerate(lines):
        if not line.startswith("FLASER"):
            continue
        if k == JUMP_AT or (persistent and k > JUMP_AT):
            p = line.split()
            n = int(p[1])
            for j in (2 + n, 2 + n + 3):  # the laser's and the odometry's x
                p[j] = f"{float(p[j]) + 1000.0:.6f}"
            lines[i] = " ".join(p)
        k += 1
    path = tmp_path / f"jump_{'persistent' if persistent else 'once'}.clf"
    path.write_text("\n".join(lines) + "\n")
    return path


def _run(path: Path, capsys) -> tuple[AgentCore, str]:
    return run_reported(path, SCANS, capsys=capsys)


def reference_map() -> np.ndarray:
    """The map of the unedited scans: where the building is."""
    core = AgentCore("robot1", FastSLAM(SlamConfig(particles=10), np.random.default_rng(0)), AgentConfig())
    for i, scan in enumerate(read_log(LOG).scans()):
        if i == SCANS:
            break
        core.step(scan)
    gm, trusted = core.slam.published_map()
    return gm.seg[trusted]


@pytest.fixture(scope="module")
def reference():
    return reference_map()


@pytest.mark.parametrize("persistent", [False, True], ids=["one line", "from a line on"])
def test_row1_an_odometry_jump_is_noticed_and_the_map_stays_where_the_building_is(
    reference, tmp_path, capsys, persistent
):
    core, out = _run(_edited(tmp_path, persistent), capsys)
    gm, trusted = core.slam.published_map()
    seg = gm.seg[trusted]
    ends = seg.reshape(-1, 2)
    far = point_segment_distance(ends[:, None, :], reference[None, :, :, :]).min(axis=1)
    assert far.max() < 5.0, f"{int((far > 5).sum())} segment ends more than 5 m from the building"
    jumps = core.slam.stats["odometry_jumps"]
    assert jumps == (1 if persistent else 2), core.slam.stats  # one line: out and back again
    assert re.search(rf"odometry jumped 100\d\.\d m and -?\d+° at scan {JUMP_AT};", out), out[-2000:]
