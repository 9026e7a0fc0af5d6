"""The online back end beside a running filter, as an agent runs it: what reaches it, what the
agent publishes with its corrections, the process it runs in."""

import numpy as np
import pytest

from robot_agent.agent import AgentConfig, AgentCore
from robot_agent.backend.live import InlineRunner, LiveCorrector, ProcessRunner
from robot_agent.sim import LiveSim, builtin_world
from robot_agent.slam.fastslam import FastSLAM, SlamConfig
from shared import codec
from shared.geometry import compose, inverse


class Recording(InlineRunner):
    """An inline runner that keeps every job it was given."""

    def __init__(self, cfg):
        super().__init__(cfg)
        self.jobs = []

    def submit(self, job):
        self.jobs.append(job)
        super().submit(job)


@pytest.fixture(scope="module")
def office_run():
    """200 s of robot 0 in the office (it comes back to where it started), 10 particles; the
    online back end beside the filter; every published pose and map kept."""
    return _office(SlamConfig(particles=10))


def _office(cfg: SlamConfig):
    """``office_run`` with the filter's configuration ``cfg``."""
    sim = LiveSim(builtin_world("office"), 0, seed=0)
    slam = FastSLAM(cfg, np.random.default_rng(0))
    runner = Recording(slam.cfg)
    core = AgentCore("robot1", slam, AgentConfig(), corrector=LiveCorrector(slam, runner))
    poses, maps, truth = [], [], []
    for s in sim.scans(200.0):
        est = core.step(s)
        truth.append(sim.truth)
        if (p := core.pose_message()) is not None:
            poses.append((p, est.pose.copy(), len(slam.trajectory) - 1))
        if (m := core.map_messages()) is not None:
            maps.append(m)
    return core, runner, poses, maps, np.array(truth)


def test_updates_come_every_few_seconds_and_find_the_loop(office_run):
    core, runner, _, _, _ = office_run
    c = core.corrector
    assert c.updates >= 35  # every 5 s of the source's 200 s: measured 41
    assert c.stats["loops"] >= 20 and c.stats["keyframes"] >= 150  # measured 39 and 228
    # what went over stayed bounded: the path from the last keyframe on, not the whole run
    assert max(len(j.track.scan) for j in runner.jobs[1:]) < 100  # measured 30
    assert sum(len(j.hints) for j in runner.jobs) == len(core.slam.loop_hints)


def test_the_published_pose_and_map_follow_the_correction(office_run):
    core, _, poses, maps, truth = office_run
    c = core.corrector
    msg, filt, scan = poses[-1]
    np.testing.assert_allclose(msg.pose, c.correction.pose(scan, filt), atol=1e-9)
    whole = codec.Assembler().add(codec.decode(codec.encode(maps[-1][0])))
    # each element moved with the keyframe of the scan that made it: moved back, it is the filter's
    from robot_agent.publish import top_particle_maps

    raw = top_particle_maps(core.slam, core.cfg.publish)
    np.testing.assert_allclose(
        whole.seg.astype(float), c.segments(raw.seg, core.slam.step_index - raw.age), atol=1e-3
    )
    # the correction is a real one (the loop moved the path) and not a worse one
    _, filter_path = core.slam.best_trajectory()
    corrected = c.correction.apply(filter_path)
    gauge = compose(truth[0], inverse(filter_path[0]))
    err_filter = np.hypot(*(compose(gauge, filter_path)[:, :2] - truth[:, :2]).T).mean()
    err_corrected = np.hypot(*(compose(gauge, corrected)[:, :2] - truth[:, :2]).T).mean()
    assert np.abs(corrected - filter_path)[:, :2].max() > 0.02  # measured 0.041 m
    assert err_corrected < 0.8 * err_filter  # measured 0.035 m against 0.053 m


def test_the_process_runner_computes_what_the_inline_one_does_and_leaves_nothing_behind(office_run):
    _, runner, _, _, _ = office_run
    jobs = runner.jobs[:12]
    inline = InlineRunner(SlamConfig(particles=10))
    proc = ProcessRunner(SlamConfig(particles=10))
    try:
        for job in jobs:
            inline.submit(job)
            a, _ = inline.poll()
            proc.submit(job)
            with pytest.raises(RuntimeError, match="still working"):
                proc.submit(job)
            got = None
            for _ in range(600):
                got = proc.poll(0.1)
                if got is not None:
                    break
            assert got is not None
            np.testing.assert_array_equal(got[0].kf_scan, a.kf_scan)
            np.testing.assert_allclose(got[0].corrected, a.corrected, atol=1e-12)
    finally:
        proc.close()
    assert not proc._proc.is_alive()


def test_a_tail_too_long_keeps_its_first_and_newest_scans():
    slam = FastSLAM(SlamConfig(particles=5), np.random.default_rng(0))
    c = LiveCorrector(slam, max_tail=10)
    sim = LiveSim(builtin_world("office"), 0, seed=0)
    for s in sim.scans(6.0):
        slam.step(s.stamp_s, s.odometry, s.ranges_m, s.angles_rad, s.laser_offset, s.range_max_m)
        c.on_scan(s.stamp_s, s.odometry, s.ranges_m, s.angles_rad, s.laser_offset, s.range_max_m)
    idx = [r.index for r in c._tail]
    assert len(idx) == 10 and idx[0] == 0 and idx[-1] == len(slam.trajectory) - 1
    assert c.dropped_tail == len(slam.trajectory) - 10


def test_a_run_without_end_forgets_its_oldest_path_and_publishes_the_same(office_run):
    """The same 200 s with the filter keeping its path for the newest 200 scans only (as a
    source without end does, for days): the oldest path, relocalization hints and retired
    keyframes nothing refers to forgotten, yet the filter, its corrections, the published
    poses and maps are exactly those of the run that keeps everything."""
    import dataclasses

    core0, _, poses0, maps0, _ = office_run
    cfg = SlamConfig(particles=10)
    core, runner, poses, maps, _ = _office(
        dataclasses.replace(cfg, filter=dataclasses.replace(cfg.filter, history_scans=200))
    )
    slam = core.slam
    traj = slam.trajectory
    # 426 forgotten: the open steps (particles not yet coalesced) stay whatever the bound
    assert traj.first_scan > 400 and slam.stats["scans_forgotten"] == traj.first_scan
    assert len(traj) == len(core0.slam.trajectory)
    # what the map and the kept path refer to went with each update once the path was cut
    # (retired keyframes nothing refers to are forgotten: test_online_backend)
    assert runner.jobs[-1].keep is not None and runner.jobs[-1].keep[1] == traj.first_scan
    assert len(poses) == len(poses0) and len(maps) == len(maps0)
    for a, b in zip(poses, poses0, strict=True):
        np.testing.assert_allclose(a[0].pose, b[0].pose, atol=1e-9)
    for a, b in zip(maps[-5:], maps0[-5:], strict=True):
        got = codec.Assembler().add(codec.decode(codec.encode(a[0])))
        want = codec.Assembler().add(codec.decode(codec.encode(b[0])))
        np.testing.assert_array_equal(got.seg, want.seg)
    stamps, filt = slam.best_trajectory()
    stamps0, filt0 = core0.slam.best_trajectory()
    np.testing.assert_array_equal(stamps, stamps0[traj.first_scan :])
    np.testing.assert_allclose(filt, filt0[traj.first_scan :], atol=1e-12)
    np.testing.assert_allclose(
        core.corrector.correction.apply(filt, traj.first_scan),
        core0.corrector.correction.apply(filt0)[traj.first_scan :],
        atol=1e-9,
    )
