"""A log's first scans through an agent core with its odometry report, as ``fleet-slam agent``
runs them: the core and what the report printed (tests of odometry faults)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from robot_agent.agent import AgentConfig, AgentCore
from robot_agent.service import OdometryReport
from robot_agent.slam.fastslam import FastSLAM, SlamConfig
from robot_agent.sources import read_log


def run_reported(path: Path, scans: int, cfg: SlamConfig | None = None, capsys=None) -> tuple[AgentCore, str]:
    """Seed 0, 10 particles unless ``cfg`` says otherwise; ``capsys``: collect the printed lines."""
    cfg = SlamConfig(particles=10) if cfg is None else cfg
    core = AgentCore("robot1", FastSLAM(cfg, np.random.default_rng(0)), AgentConfig())
    report = OdometryReport("robot1")
    out = []
    for i, scan in enumerate(read_log(path).scans()):
        if i == scans:
            break
        core.step(scan)
        report(core)
        if capsys is not None:
            out.append(capsys.readouterr().out)
    return core, "".join(out)
