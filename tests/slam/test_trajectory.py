"""Ancestry-tree trajectories: resampling, injection and odometry-bridged scans."""

import numpy as np
import pytest

from robot_agent.slam.trajectory import Trajectory
from shared.geometry import compose


def poses_at(step, n_particles=3):
    """Distinct, recognizable poses: x = step, y = particle, theta = 0.1 · particle."""
    p = np.arange(n_particles, dtype=float)
    return np.column_stack([np.full(n_particles, float(step)), p, 0.1 * p])


def test_resampling_into_one_particle_gives_its_history_to_all():
    traj = Trajectory()
    traj.record(0.0, poses_at(0))
    traj.record(1.0, poses_at(1))
    traj.reparent(np.array([2, 2, 2]))  # particle 2 copied into every slot
    traj.record(2.0, poses_at(2))
    for j in range(3):
        stamps, poses = traj.backtrack(j)
        np.testing.assert_array_equal(stamps, [0.0, 1.0, 2.0])
        np.testing.assert_allclose(poses[:2], [poses_at(0)[2], poses_at(1)[2]])
        np.testing.assert_allclose(poses[2], poses_at(2)[j])  # after resampling: its own pose


def test_bridged_scans_hang_from_the_last_processed_step():
    traj = Trajectory()
    traj.record(10.0, poses_at(0))
    u1, u2 = np.array([0.05, 0.0, 0.01]), np.array([0.08, 0.01, 0.03])
    traj.bridge(10.2, u1)
    traj.bridge(10.4, u2)  # odometry from the last processed step, not from the previous bridge
    traj.record(10.6, poses_at(1))
    traj.reparent(np.array([1, 1, 0]))
    traj.bridge(10.8, u1)
    assert len(traj) == 5
    stamps, poses = traj.backtrack(2)  # particle 2 is now old particle 0
    np.testing.assert_array_equal(stamps, [10.0, 10.2, 10.4, 10.6, 10.8])
    p0, p1 = poses_at(0)[0], poses_at(1)[0]
    np.testing.assert_allclose(poses, [p0, compose(p0, u1), compose(p0, u2), p1, compose(p1, u1)], atol=1e-12)
    # with a rotated anchor the increment turns with it (pose ∘ u, not pose + u)
    _, poses = traj.backtrack(0)
    anchor = poses_at(0)[1]
    assert anchor[2] == pytest.approx(0.1)
    np.testing.assert_allclose(poses[1], compose(anchor, u1), atol=1e-12)
    assert not np.allclose(poses[1], anchor + u1)


def test_inherit_continues_another_particles_history():
    traj = Trajectory()
    traj.record(0.0, poses_at(0))
    traj.inherit(np.array([1]), np.array([0]))  # relocalization: particle 1 takes particle 0's past
    traj.record(1.0, poses_at(1))
    _, poses = traj.backtrack(1)
    np.testing.assert_allclose(poses, [poses_at(0)[0], poses_at(1)[1]])
    _, poses = traj.backtrack(2)
    np.testing.assert_allclose(poses, [poses_at(0)[2], poses_at(1)[2]])


def test_matches_a_reference_that_copies_every_history():
    rng = np.random.default_rng(11)
    n = 5
    traj = Trajectory()
    histories = [[] for _ in range(n)]  # reference: each particle's full list of scan poses
    stamps = []
    last = None
    for k in range(60):
        action = rng.choice(["record", "bridge", "reparent", "inherit"]) if k else "record"
        if action == "record":
            last = rng.normal(size=(n, 3))
            traj.record(float(k), last)
            for j in range(n):
                histories[j].append(last[j])
            stamps.append(float(k))
        elif action == "bridge":
            u = rng.normal(size=3) * 0.1
            traj.bridge(float(k), u)
            for j in range(n):
                histories[j].append(compose(last[j], u))
            stamps.append(float(k))
        elif action == "reparent":
            idx = rng.integers(0, n, n)
            traj.reparent(idx)
            histories = [list(histories[i]) for i in idx]
            last = last[idx]
        else:
            targets = rng.choice(n, 2, replace=False)
            sources = rng.integers(0, n, 2)
            traj.inherit(targets, sources)
            for t, s in zip(targets, sources, strict=True):
                histories[t] = list(histories[s])
            last = last.copy()
            last[targets] = last[sources]
    assert len(traj) == len(stamps)
    for j in range(n):
        s, poses = traj.backtrack(j)
        np.testing.assert_array_equal(s, stamps)
        np.testing.assert_allclose(poses, np.array(histories[j]), atol=1e-12)


def test_empty_and_bridge_before_record():
    traj = Trajectory()
    stamps, poses = traj.backtrack(0)
    assert stamps.shape == (0,) and poses.shape == (0, 3)
    with pytest.raises(ValueError, match="bridge"):
        traj.bridge(0.0, np.zeros(3))


def test_recorded_poses_are_copied():
    traj = Trajectory()
    p = poses_at(0)
    traj.record(0.0, p)
    p[:] = 99.0
    _, poses = traj.backtrack(0)
    np.testing.assert_allclose(poses[0], poses_at(0)[0])


def test_an_injected_particle_reached_its_next_pose_by_a_jump():
    traj = Trajectory()
    traj.record(0.0, poses_at(0))
    traj.bridge(0.5, np.array([0.1, 0.0, 0.0]))
    traj.record(1.0, poses_at(1))
    traj.inherit(np.array([0]), np.array([2]))  # particle 0 now continues particle 2, relocalized
    traj.reparent(np.array([0, 1, 1]))  # resampling keeps the flag with the particle
    traj.record(2.0, poses_at(2))
    traj.bridge(2.5, np.array([0.1, 0.0, 0.0]))
    traj.record(3.0, poses_at(3))
    np.testing.assert_array_equal(traj.jumps(0), [False, False, False, True, False, False])
    _, poses = traj.backtrack(0)
    np.testing.assert_allclose(poses[2], poses_at(1)[2])  # its history is particle 2's
    for j in (1, 2):
        assert not traj.jumps(j).any()


def test_closing_coalesced_steps_changes_no_path_and_keeps_few_open():
    """The steps up to the particles' newest common ancestor are kept as one history: the best
    path, its jumps and any scans' poses read back exactly as with every step kept open."""
    from pathlib import Path

    from robot_agent.backend import feed
    from robot_agent.slam.fastslam import FastSLAM, SlamConfig
    from robot_agent.sources import read_log

    log = read_log(Path(__file__).parents[1] / "data" / "intel_head.clf.gz")
    n_scans = 1000
    runs = []
    for every in (0, 8):
        slam = FastSLAM(SlamConfig(particles=10), np.random.default_rng(0))
        slam.trajectory = Trajectory(compact_every=every)
        for i in range(n_scans):
            feed(slam, log, i)
        best = slam.particles.best()
        idx = np.arange(0, n_scans, 3)
        at = slam.trajectory.lineage_at(best, idx)
        runs.append((*slam.best_trajectory(), slam.best_jumps(), *at, slam))
    (s0, p0, j0, lp0, lj0, open_all), (s1, p1, j1, lp1, lj1, closed) = runs
    for a, b in ((s0, s1), (p0, p1), (j0, j1), (lp0, lp1), (lj0, lj1)):
        np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(lp1, p1[np.arange(0, n_scans, 3)])
    assert open_all.trajectory.open_steps == open_all.trajectory.steps
    # (the particles coalesce in bursts: seed 0 at the default sampling keeps 222 of 247 steps open
    # after 700 scans and 91 of 357 after 1000; seed 1 at sample_scale 1.0 205 of 247 after 700)
    assert closed.trajectory.open_steps < 0.5 * closed.trajectory.steps


def test_particles_that_never_coalesce_keep_a_bounded_history():
    """Without resampling every particle keeps its own path: beyond the bound the older steps
    are closed along the given particle's history (others' older parts become its)."""
    traj = Trajectory(compact_every=4)
    for k in range(50):
        traj.record(float(k), poses_at(k))
        if traj.open_steps > 10:
            traj.close(1, 5)
    assert traj.open_steps <= 10 and traj.steps == 50
    _, p1 = traj.backtrack(1)
    np.testing.assert_allclose(p1[:, 1], 1.0)  # particle 1's own path throughout
    _, p2 = traj.backtrack(2)
    assert np.all(p2[-5:, 1] == 2.0) and np.all(p2[:40, 1] == 1.0)  # its older part: particle 1's


def test_a_run_without_end_keeps_its_newest_scans_and_the_steps_its_map_refers_to():
    """With ``max_scans`` the oldest scans (and the closed steps they hang from) are forgotten;
    what is kept reads back exactly as without forgetting, scan and step numbers stay the
    run's, and the scans of forgotten steps the map still refers to are remembered."""
    rng = np.random.default_rng(3)
    runs = []
    for max_scans in (0, 40):
        traj = Trajectory(compact_every=4, max_scans=max_scans)
        forgotten = 0
        rng = np.random.default_rng(3)
        for k in range(300):
            traj.record(float(k), poses_at(k) + rng.normal(0, 0.01, (3, 3)))
            for b in range(int(rng.integers(0, 3))):  # bridged scans between steps
                traj.bridge(k + 0.1 * (b + 1), np.array([0.01 * (b + 1), 0.0, 0.0]))
            traj.reparent(np.array([0, 0, 1]))  # lineages coalesce
            if traj.over:
                forgotten += traj.forget(keep_steps=np.array([3, 7, 150]))
        runs.append((traj, forgotten))
    (whole, _), (window, forgotten) = runs
    assert forgotten > 0 and len(window) == len(whole)  # the run's count of scans
    assert window.kept_scans <= 50 and window.first_scan == len(whole) - window.kept_scans
    s0, p0 = whole.backtrack(0)
    s1, p1 = window.backtrack(0)
    np.testing.assert_array_equal(s1, s0[window.first_scan :])
    np.testing.assert_allclose(p1, p0[window.first_scan :])
    np.testing.assert_array_equal(window.jumps(0), whole.jumps(0)[window.first_scan :])
    idx = np.arange(window.first_scan, len(whole), 3)
    np.testing.assert_allclose(window.lineage_at(0, idx)[0], whole.lineage_at(0, idx)[0])
    assert window.steps == whole.steps
    kept_steps = np.arange(window.steps - 5, window.steps + 1)
    np.testing.assert_array_equal(window.scan_of_step(kept_steps), whole.scan_of_step(kept_steps))
    np.testing.assert_array_equal(window.scan_of_step([3, 7, 150]), whole.scan_of_step([3, 7, 150]))
    with pytest.raises(ValueError, match="forgotten"):
        window.lineage_at(0, np.array([window.first_scan - 1]))


def test_forgetting_keeps_the_open_steps():
    """Steps whose particles have not coalesced are never forgotten, whatever max_scans says."""
    traj = Trajectory(compact_every=1000, max_scans=5)  # nothing closes
    for k in range(30):
        traj.record(float(k), poses_at(k))
    assert traj.over and traj.forget(np.zeros(0, int)) == 0
    assert traj.first_scan == 0 and traj.kept_scans == 30


def test_moving_the_frame_moves_every_history_piecewise_by_step():
    """``move``: every kept step's poses (closed and open, every particle's) by the transform of
    the last keyframe at or before its scan; bridged scans keep their offsets from their step."""
    traj = Trajectory(compact_every=2)
    rng = np.random.default_rng(0)
    for k in range(12):
        traj.record(float(k), poses_at(k))
        traj.bridge(k + 0.5, np.array([0.1, 0.0, 0.02]))
        traj.reparent(rng.integers(0, 3, 3) if k % 3 else np.array([1, 1, 1]))
    assert len(traj._frozen) > 0 and traj.open_steps > 0  # both kinds are moved
    before = [traj.backtrack(j)[1] for j in range(3)]
    kf = np.array([4, 10, 17])  # scans: 4 and 10 processed, 17 bridged (hangs from 16)
    moves = np.array([[1.0, 2.0, 0.1], [-0.5, 0.3, -0.2], [0.2, 0.2, 0.3]])
    traj.move(kf, moves)
    anchor = traj.anchor_scans(np.arange(len(traj)))
    np.testing.assert_array_equal(anchor, np.repeat(np.arange(0, 24, 2), 2))
    which = np.maximum(np.searchsorted(kf, anchor, side="right") - 1, 0)
    for j in range(3):
        np.testing.assert_allclose(traj.backtrack(j)[1], compose(moves[which], before[j]), atol=1e-12)
