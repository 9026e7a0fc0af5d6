"""Issue 24 item 1, a teleport: the robot is moved without odometry seeing it (carried, pushed, a
log spliced). Before, the filter found a fit near where odometry put it and mapped the new place
over the old one (Intel carried back to scan 150's place at scan 1000: the robot 21 m off for
good, 38 % of its map's segment ends more than 1 m from any wall it had mapped). Now the scans
disagree with odometry, the map is held, the robot is found in its own map (or, nowhere to be
found, the agent starts a new session), and no map bent by it is published."""

from __future__ import annotations

import functools
import gzip
import re
from pathlib import Path

import numpy as np

from robot_agent.agent import AgentConfig, AgentCore
from robot_agent.service import OdometryReport
from robot_agent.slam.fastslam import FastSLAM, SlamConfig
from robot_agent.sources import read_log
from shared.geometry import compose, inverse, point_segment_distance, relative

DATA = Path(__file__).parents[1] / "data"
INTEL = DATA / "intel_head.clf.gz"
ACES = DATA / "aces_head.clf.gz"
MIT = DATA / "mit_csail_head.clf.gz"


def _flaser(path: Path) -> tuple[list[str], list[str]]:
    lines = gzip.open(path, "rt").read().splitlines()
    return [ln for ln in lines if ln.startswith(("#", "PARAM"))], [
        ln for ln in lines if ln.startswith("FLASER")
    ]


def _poses(line: str) -> tuple[list[str], int]:
    p = line.split()
    return p, int(p[1])


def _odometry(line: str) -> np.ndarray:
    p, n = _poses(line)
    return np.array([float(v) for v in p[2 + n + 3 : 2 + n + 6]])


def teleported(tmp_path: Path, at: int, source: Path, start: int, count: int) -> Path:
    """Intel's first ``at`` scans, then ``count`` scans of ``source`` from ``start`` on, their
    odometry (and laser pose) continuing from scan ``at - 1``'s and their clock 0.2 s after it:
    the robot was carried there and odometry did not see it."""
    head, lines = _flaser(INTEL)
    tail = _flaser(source)[1][start : start + count]
    t = compose(_odometry(lines[at - 1]), inverse(_odometry(tail[0])))
    dt = float(lines[at - 1].split()[-3]) + 0.2 - float(tail[0].split()[-3])
    moved = []
    for line in tail:
        p, n = _poses(line)
        for j in (2 + n, 2 + n + 3):  # the laser's pose and odometry's
            q = compose(t, np.array([float(v) for v in p[j : j + 3]]))
            p[j : j + 3] = [f"{v:.6f}" for v in q]
        p[-3], p[-1] = f"{float(p[-3]) + dt:.6f}", f"{float(p[-1]) + dt:.6f}"
        moved.append(" ".join(p))
    path = tmp_path / f"teleported_{at}_{source.name.split('.')[0]}_{start}.clf"
    path.write_text("\n".join(head + lines[:at] + moved) + "\n")
    return path


def _run(path: Path, capsys, held_at: int, cfg: SlamConfig | None = None):
    """The agent core over the log with its odometry report; the map it published by session
    (each session's last), the last it published before scan ``held_at`` and every estimate."""
    cfg = SlamConfig(particles=10) if cfg is None else cfg
    core = AgentCore("robot1", FastSLAM(cfg, np.random.default_rng(0)), AgentConfig())
    report = OdometryReport("robot1")
    published: dict[str, np.ndarray] = {}
    held = None
    poses, out, doubt = [], [], []
    for i, scan in enumerate(read_log(path).scans()):
        if i == held_at:
            held = published.get(core.session)
        poses.append(core.step(scan).pose)
        report(core)
        pose_msg = core.pose_message()
        if pose_msg is not None:  # what the robot's pose messages say, by scan
            doubt.append((i, pose_msg.status["odometry_doubt"], pose_msg.status["sessions_ended"]))
        msgs = core.map_messages()
        if msgs:
            published[core.session] = np.concatenate([m.seg for m in msgs])
        out.append(capsys.readouterr().out)
    core.doubt_said = np.array(doubt)
    return core, published, held, np.array(poses), "".join(out)


def _far(seg: np.ndarray, building: np.ndarray) -> np.ndarray:
    """Each endpoint of ``seg``'s distance to the nearest segment of ``building``."""
    ends = seg.reshape(-1, 2)
    return point_segment_distance(ends[:, None, :], building[None, :, :, :]).min(axis=1)


def test_a_robot_carried_elsewhere_in_its_map_is_found_there_and_its_map_is_not_bent(tmp_path, capsys):
    at, start = 1000, 150  # carried from scan 999's place back to scan 150's, 21 m away
    path = teleported(tmp_path, at, INTEL, start, 150)
    core, published, held, poses, out = _run(path, capsys, at)
    intact = _intact_poses(start + 150)
    assert len(published) == 1, "one session: the robot was found in its own map"
    far = _far(published[core.session], held)
    # measured: 5 of 146 ends beyond 0.5 m, 0.67 m at most (walls seen longer than before
    # along their line); before: 38 % beyond 1 m at the end of the excerpt, the path 21 m off
    assert np.mean(far > 0.3) < 0.05 and far.max() < 1.0, (
        f"{int((far > 0.3).sum())} of {len(far)} segment ends off the map held, {far.max():.2f} m at most"
    )
    st = core.slam.stats
    assert (st["kidnap_doubts"], st["kidnappings"], st["lost"]) == (1, 1, 0), st
    found = int(re.search(r"the robot was moved: found at scan (\d+) ([\d.]+) m", out).group(1))
    assert at < found < at + 60, out  # measured: scan 1040
    assert re.search(rf"from scan {at} the scans disagree with odometry", out), out
    said = core.doubt_said  # the pose messages say the doubt while it lasts, and only then
    in_doubt = said[(said[:, 0] > at + 1) & (said[:, 0] < found)]
    assert len(in_doubt) and in_doubt[:, 1].all() and not said[said[:, 0] > found + 1][:, 1].any()
    # from where it was found on, the path is where the intact run's is (measured: 0.02 m)
    k = np.arange(found + 10, len(poses))
    d = relative(intact[start + k - at], poses[k])
    err = np.hypot(d[:, 0], d[:, 1])
    assert err.max() < 0.1, f"pose error after relocalization up to {err.max():.2f} m"


@functools.cache
def _intact(n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The agent on the intact excerpt's first ``n`` scans: the map it publishes (its trusted
    segments), its poses ``(n,3)``, and every scan point ``(K,2)`` where those put them."""
    from robot_agent.slam.extraction import scan_points
    from shared.geometry import apply_points

    core = AgentCore("robot1", FastSLAM(SlamConfig(particles=10), np.random.default_rng(0)), AgentConfig())
    cfg, poses, points = core.slam.cfg.extraction, [], []
    for i, scan in enumerate(read_log(INTEL).scans()):
        if i == n:
            break
        poses.append(core.step(scan).pose)
        xy = scan_points(scan.ranges_m, scan.angles_rad, cfg, scan.range_max_m)
        points.append(apply_points(poses[-1], apply_points(scan.laser_offset, xy)))
    seg = np.concatenate([m.seg for m in core.map_messages(force=True)]).astype(float)
    return seg, np.array(poses), np.concatenate(points)


def building_map(n: int) -> np.ndarray:
    """The map the agent publishes after the intact excerpt's first ``n`` scans (its trusted
    segments): where the building's walls are."""
    return _intact(n)[0]


def building_points(n: int) -> np.ndarray:
    """Every scan point ``(K,2)`` of the intact excerpt's first ``n`` scans where its run put them:
    the building as measured, with the walls its published map does not trust yet."""
    return _intact(n)[2]


def _intact_poses(n: int) -> np.ndarray:
    return _intact(n)[1]


def test_a_robot_carried_where_its_map_does_not_reach_starts_a_new_session(tmp_path, capsys):
    at = 700  # Intel's scan 699, then ACES's scans from its start: another building
    path = teleported(tmp_path, at, ACES, 0, 250)
    core, published, held, _, out = _run(path, capsys, at)
    assert len(core.ended) == 1, f"sessions ended: {core.ended}"
    old, first, last, stats = core.ended[0]
    assert (first, stats["kidnap_doubts"], stats["lost"], stats["kidnappings"]) == (0, 1, 1, 0), stats
    assert at < last < at + 200  # measured: 851 (150 scans of doubt: the robot barely moves)
    # the ended session's map is the one held when the doubt began: nothing of ACES in it
    far = _far(published[old], held)
    assert far.max() < 0.05, f"{int((far > 0.05).sum())} of {len(far)} ends off the map held"
    assert core.session != old and core.first_scan == last + 1
    assert len(published[core.session]) > 0, "the new session maps and publishes"
    assert core.doubt_said[-1, 2] == 1  # the pose messages count the ended session
    stamps, poses = core.ended_paths[0]  # its path, every scan of it, for the agent's --out
    assert len(stamps) == len(poses) == last + 1 and np.isfinite(poses).all()
    assert re.search(
        rf"warning: lost at scan {last}: .* session {old} ends .* \(session {core.session}\)", out
    ), out


def test_odometry_that_errs_where_the_estimate_fits_is_doubted_and_cleared(capsys):
    """MIT-CSAIL's odometry disagrees with its scans from scan 115 on (as at 3 more places of the
    whole log, ACES at 2): the estimate fits the map where the doubt began, nothing better is
    found elsewhere, the doubt is cleared and mapping goes on (what doubts cost the whole logs'
    accuracy: benchmarks/bench_logs.py; Intel's and ACES's excerpts have none)."""
    core, published, _, _, out = _run(MIT, capsys, 0)
    st = core.slam.stats
    assert (st["kidnap_doubts"], st["kidnap_cleared"], st["kidnappings"], st["lost"]) == (1, 1, 0, 0), st
    assert not core.ended and len(published) == 1
    assert re.search(r"odometry erred, the robot was not moved \(scan 1\d\d:", out), out
