"""Robot frame -> global frame by map matching: accuracy on simulated maps, verdicts, priors.

Truths: a map built from scans at the true poses is in the robot's start frame exactly, so the
start pose is its true transform. A FastSLAM map's frame is the filter's origin, which differs
from the start by the filter's own first-pose error; its true transform is taken as the rigid
fit of the estimated trajectory to the true one (``shared.metrics.ate``).
"""

import dataclasses
from collections import Counter

import numpy as np
import pytest

from map_server import candidates, registration
from map_server.alignment import Alignment, estimate_alignment, prior_gauge
from map_server.config import AlignmentConfig
from map_server.fusion import FusionConfig, fuse_particles
from map_server.registration import Samples
from shared.geometry import apply_segments, compose, inverse
from shared.kernels import NearIndex
from shared.metrics import ate, transform_error
from tests.map_server.robots import robot_map_from_slam, scan_map, slam_run

CFG = AlignmentConfig()
HALF_TURN = np.array([30.0, 20.0, np.pi])  # the office is nearly symmetric under this half turn


def pair(duration_s, a=0, b=1, world="office"):
    """Placed map (robot ``a``'s exact map in the world frame), robot ``b``'s map, its truth."""
    seg_a, start_a = scan_map(world, a, duration_s)
    seg_b, start_b = scan_map(world, b, duration_s)
    return apply_segments(start_a, seg_a), seg_b, start_b


@pytest.fixture
def work(monkeypatch) -> Counter:
    """What an alignment attempt does, counted around its costly steps (the code is unchanged):
    pose hypotheses, refinements, nearest-sample indexes built and queried, and the points queried."""
    counts = Counter()

    class CountingIndex(NearIndex):
        def __init__(self, *args, **kwargs):
            counts["trees"] += 1
            super().__init__(*args, **kwargs)

        def query(self, q, *args, **kwargs):
            counts["queries"] += 1
            counts["query_points"] += len(q)
            return super().query(q, *args, **kwargs)

    hypotheses, refine = candidates.pose_hypotheses, candidates.refine

    def counted_hypotheses(*args, **kwargs):
        out = hypotheses(*args, **kwargs)
        counts["hypotheses"] += len(out)
        return out

    def counted_refine(*args, **kwargs):
        counts["refinements"] += 1
        return refine(*args, **kwargs)

    monkeypatch.setattr(registration, "NearIndex", CountingIndex)
    monkeypatch.setattr(candidates, "pose_hypotheses", counted_hypotheses)
    monkeypatch.setattr(candidates, "refine", counted_refine)
    return counts


def test_exact_maps_give_the_exact_frame_within_the_work_budget(work):
    placed, seg, truth = pair(150.0)
    a = estimate_alignment(seg, placed, CFG)
    assert a.status == "aligned", a.reason
    err_m, err_deg = transform_error(a.transform, truth)
    assert err_m < 0.01 and err_deg < 0.05  # measured 0.0003 m, 0.001 deg
    assert np.all(a.sigma[:2] < 0.02) and a.sigma[2] < np.radians(0.2)
    assert a.score_m > 150.0 and a.inlier_share > 0.6
    # the half-turned placement is the rival: the office is 89 % self-similar under it
    assert 1.10 <= a.rival_ratio < 1.3
    # The work of one attempt stays within what its config allows (its time is measured by
    # benchmarks/bench_fleet.py, fusion without priors, per attempt): the placed map indexed once;
    # index queries: the vote peaks pre-scored, the best refined (one query per stage) and scored
    # strictly, and the winner's opposed-wall check — coarse samples for the first two, fine ones after.
    fine, coarse = len(Samples.of(seg, CFG.sample_step_m)), len(Samples.of(seg, CFG.coarse_step_m))
    stages = len(CFG.refine_stages)
    assert work["trees"] == 1
    assert 0 < work["hypotheses"] <= 5_000  # measured 1178 (96 robot x 113 placed segments)
    assert 0 < work["refinements"] <= CFG.max_refined
    assert 0 < work["queries"] <= CFG.max_peaks + CFG.max_refined * (stages + 1) + 1  # measured 113
    point_budget = (CFG.max_peaks + CFG.max_refined * stages) * coarse + (CFG.max_refined + 1) * fine
    assert 0 < work["query_points"] <= point_budget  # measured 134,918: the whole budget
    assert point_budget <= 250_000  # the config's budget itself (134,918 here): no inflated config


def test_partial_maps_of_the_symmetric_office_match_their_mirror_image():
    """Why the Fleet waits for mature maps: at 90 s robot 1's map matches robot 0's better when
    half-turned (both robots explored mirror-image halves). The pairwise verdict is wrong."""
    placed, seg, truth = pair(90.0)
    a = estimate_alignment(seg, placed, CFG)
    assert transform_error(a.transform, compose(HALF_TURN, truth))[0] < 0.05
    assert a.status == "aligned"  # passes every pairwise check: ratio 1.4


def test_a_search_keeps_its_other_distinct_places_most_matched_first():
    """The mirror-image verdict above keeps the truth among its other places (Alignment.others:
    what a trial of a bent robot's rivals looks at), each distinct from the best and from each
    other, most matched wall first."""
    from map_server.alignment import MOST_MATCHED

    placed, seg, truth = pair(90.0)
    a = estimate_alignment(seg, placed, CFG)
    assert a.others is not None and 1 <= len(a.others) <= MOST_MATCHED
    assert np.all(np.diff(a.others[:, 3]) <= 0) and a.others[0, 3] <= a.score_m
    pts = Samples.of(seg, CFG.coarse_step_m).points
    poses = [a.transform, *a.others[:, :3]]
    for i, p in enumerate(poses):
        for q in poses[i + 1 :]:
            assert candidates.mean_displacement(p, q, pts) > CFG.distinct_m
    assert min(transform_error(p, truth)[0] for p in a.others[:, :3]) < 0.05


def test_too_little_overlap_is_not_merged():
    placed, seg, _ = pair(40.0)
    a = estimate_alignment(seg, placed, CFG)
    assert a.status == "unaligned"
    assert "overlap" in a.reason


@pytest.mark.parametrize(("a", "b", "duration_s"), [(2, 3, 120.0), (1, 3, 200.0)])
def test_warehouse_aisles_unaligned_or_right(a, b, duration_s):
    # aisles repeat every 3.7 m; (2, 3) at 120 s: the aisle-shifted twin scores alike -> refused
    placed, seg, truth = pair(duration_s, a, b, "warehouse")
    al = estimate_alignment(seg, placed, CFG)
    err_m, _ = transform_error(al.transform, truth)
    assert al.status == "unaligned" or err_m < 0.3, al.reason


WAREHOUSE_LIMIT = (
    "known limit: the warehouse is nearly symmetric under a half turn (pallets differ by ~1 m); "
    "partial maps match their mirror image (ratio 1.26)"
)


@pytest.mark.xfail(strict=True, reason=WAREHOUSE_LIMIT)
def test_warehouse_half_turn_of_partial_maps():
    placed, seg, truth = pair(60.0, 0, 1, "warehouse")
    al = estimate_alignment(seg, placed, CFG)
    assert al.status == "unaligned" or transform_error(al.transform, truth)[0] < 0.3


@pytest.fixture(scope="module")
def slam_pair():
    """Robot 0's and robot 1's published maps after 150 s of FastSLAM (seed 0), with truths."""
    out = []
    for r in (0, 1):
        slam, sim = slam_run("office", r, 150.0, 0)
        stamps, poses = slam.best_trajectory()
        frame = ate(stamps, poses, sim.stamps_s, sim.truth).alignment
        out.append((fuse_particles(robot_map_from_slam(slam, f"r{r}"), FusionConfig()), frame))
    return out


def test_fastslam_maps_align_within_the_demo_bounds(slam_pair):
    (l0, frame0), (l1, frame1) = slam_pair
    a = estimate_alignment(l1.seg, l0.seg, CFG)  # global frame = robot 0's map frame
    assert a.status == "aligned", a.reason
    err_m, err_deg = transform_error(a.transform, compose(inverse(frame0), frame1))
    assert err_m < 0.10 and err_deg < 1.0  # measured 0.01 m, 0.05 deg


def test_a_prior_is_refined_within_its_sigma():
    placed, seg, truth = pair(150.0)
    off = compose(truth, np.array([0.08, -0.05, np.radians(1.0)]))
    a = estimate_alignment(seg, placed, CFG, prior=off, prior_sigma=np.array([0.1, 0.1, np.radians(2.0)]))
    assert a.status == "prior" and a.reason.startswith("prior refined"), a.reason
    err_m, err_deg = transform_error(a.transform, truth)
    assert err_m < 0.02 and err_deg < 0.1
    # a prior 0.5 m off with a 0.02 m sigma stays within its 3 sigma: matching cannot drag it
    far = compose(truth, np.array([0.5, 0.0, 0.0]))
    b = estimate_alignment(seg, placed, CFG, prior=far, prior_sigma=np.array([0.02, 0.02, 0.01]))
    assert b.status == "prior"
    assert transform_error(b.transform, far)[0] < 0.06


def test_the_prior_gauge_undoes_a_common_motion_and_balances_the_priors():
    rng = np.random.default_rng(4)
    priors = np.c_[rng.uniform(-20.0, 20.0, (4, 2)), rng.uniform(-np.pi, np.pi, 4)]
    sigma = np.tile([0.05, 0.05, np.radians(1.0)], (4, 1))
    # frames consistent with each other, all moved together: the common motion comes back exactly
    common = np.array([0.3, -0.2, np.radians(2.0)])
    g = prior_gauge(compose(inverse(common), priors), priors, sigma)
    np.testing.assert_allclose(g, common, atol=1e-9)
    # frames that disagree with their priors: after g the weighted residuals balance (no common
    # motion would bring them closer), and a much surer prior pulls the set to itself
    frames = compose(priors, np.c_[rng.normal(0.0, 0.05, (4, 2)), rng.normal(0.0, 0.01, 4)])
    g = prior_gauge(frames, priors, sigma)
    r = compose(g, frames) - priors
    moved = compose(g, frames)
    jac = np.zeros((4, 3, 3))
    jac[:, 0, 0] = jac[:, 1, 1] = jac[:, 2, 2] = 1.0
    jac[:, 0, 2], jac[:, 1, 2] = -(moved[:, 1] - g[1]), moved[:, 0] - g[0]
    np.testing.assert_allclose(np.einsum("kri,kr->i", jac / sigma[:, :, None] ** 2, r), 0.0, atol=1e-6)
    sure = sigma.copy()
    sure[2] = [1e-4, 1e-4, 1e-5]
    g = prior_gauge(frames, priors, sure)
    assert transform_error(compose(g, frames[2]), priors[2])[0] < 1e-3
    assert np.linalg.norm(prior_gauge(priors, priors, sigma)) < 1e-12  # at the priors: identity


def test_a_prior_is_kept_when_the_evidence_is_thin():
    placed, seg, truth = pair(150.0)
    prior = compose(truth, np.array([0.05, 0.0, 0.0]))
    a = estimate_alignment(seg[:3], placed, CFG, prior=prior, prior_sigma=np.array([0.1, 0.1, 0.05]))
    assert a.status == "prior" and a.reason.startswith("prior kept")
    np.testing.assert_array_equal(a.transform, prior)
    assert estimate_alignment(seg, np.zeros((0, 2, 2)), CFG, prior=prior, prior_sigma=np.ones(3)).placed


def test_a_current_alignment_is_kept_and_refined():
    placed, seg, truth = pair(150.0)
    nudged = compose(truth, np.array([0.04, 0.03, np.radians(0.3)]))
    current = Alignment("aligned", nudged, np.full(3, 0.01), reason="earlier")
    a = estimate_alignment(seg, placed, CFG, current=current)
    assert a.status == "aligned" and a.reason.startswith("kept and refined"), a.reason
    assert transform_error(a.transform, truth)[0] < 0.01


def test_a_wrong_current_alignment_that_lost_support_is_revised():
    placed, seg, truth = pair(150.0)
    wrong = compose(truth, np.array([6.0, 0.0, 0.0]))  # one room along the corridor
    a = estimate_alignment(seg, placed, CFG, current=Alignment("aligned", wrong, np.zeros(3)))
    assert a.status == "aligned" and a.reason.startswith("revised"), a.reason
    assert transform_error(a.transform, truth)[0] < 0.01


def test_nothing_placed_and_tiny_maps():
    placed, seg, _ = pair(150.0)
    assert estimate_alignment(seg, np.zeros((0, 2, 2)), CFG).reason == "nothing placed yet"
    tiny = estimate_alignment(seg[:2], placed, CFG)
    assert tiny.status == "unaligned" and "robot map only" in tiny.reason


def test_a_wall_seen_from_the_other_side_is_opposed_unless_both_faces_are_placed():
    """A robot wall on a placed wall's line facing the other way contradicts the place — unless
    the placed map holds that face too: a thin partition both sides of which were seen (MIT-CSAIL
    cut in 3: 40 m of a room's walls, seen from the corridor and from inside by both pieces, had
    the true place refused)."""
    outside = np.array([[[0.0, 0.0], [10.0, 0.0]]])  # faces +y (left normal of p0 -> p1)
    inside = outside[:, ::-1]  # the same wall's other face, 3 cm across
    inside = inside + np.array([0.0, 0.03])
    robot = Samples.of(inside, CFG.sample_step_m)
    one_face = registration.MapIndex(outside, CFG.sample_step_m)
    both_faces = registration.MapIndex(np.concatenate([outside, inside]), CFG.sample_step_m)
    at = np.zeros(3)
    assert one_face.opposed(at, robot, CFG.opposed_perp_m) == pytest.approx(10.0, abs=0.2)
    assert both_faces.opposed(at, robot, CFG.opposed_perp_m) == 0.0


def test_vote_peaks_do_not_depend_on_where_the_placed_frame_lies():
    """The candidates' votes are counted around each hypothesis, not in bins fixed in the placed
    map's frame: the placed maps moved by a rigid motion (another robot as the reference) give the
    same peaks, moved by it. With bins a true overlap's four hypotheses fell 3 in one bin with one
    reference and 2 + 1 with another (MIT-CSAIL's middle piece: a candidate, then not)."""
    rng = np.random.default_rng(3)
    true = np.array([4.0, -2.0, 0.7])
    hyp = np.vstack(
        [
            true + rng.normal(0.0, [0.08, 0.08, np.radians(0.5)], (4, 3)),  # a true overlap: 4 votes
            rng.uniform(
                [-30.0, -30.0, -np.pi], [30.0, 30.0, np.pi], (400, 3)
            ),  # corners that agree by chance
        ]
    )
    cfg = AlignmentConfig()
    peaks, votes = candidates.vote_peaks(hyp, cfg.vote_cell_m, cfg.vote_cell_rad, 20)
    assert np.hypot(*(peaks[0, :2] - true[:2])) < 0.3 and votes[0] == 4
    for move in (np.array([0.26, -0.13, 0.0]), np.array([57.3, 21.9, 2.5])):
        moved, moved_votes = candidates.vote_peaks(compose(move, hyp), cfg.vote_cell_m, cfg.vote_cell_rad, 20)
        np.testing.assert_array_equal(moved_votes, votes)
        d = compose(inverse(move), moved) - peaks
        d[:, 2] = (d[:, 2] + np.pi) % (2 * np.pi) - np.pi
        assert np.abs(d).max() < 1e-9


def test_a_search_with_no_place_on_enough_wall_among_the_densest_peaks_looks_deeper(monkeypatch):
    """A piece that overlaps the others little shares few corners with them: its true place may
    lie beyond the ``max_peaks`` densest vote peaks (MIT-CSAIL's middle piece against the other two,
    best found 4.9 m). When no place among them stands on ``min_overlap_m`` of wall, the search
    looks among ``deep_peaks``; a place found there is verified as any other."""
    placed, seg, truth = pair(150.0)
    real = candidates.vote_peaks

    def nothing_among_the_densest(hyp, cell_m, cell_rad, max_peaks):
        peaks, votes = real(hyp, cell_m, cell_rad, max_peaks)
        if max_peaks >= CFG.deep_peaks:
            return peaks, votes
        return peaks[-5:], votes[-5:]  # (as if the densest held no place on the others' walls)

    monkeypatch.setattr(candidates, "vote_peaks", nothing_among_the_densest)
    shallow = estimate_alignment(seg, placed, dataclasses.replace(CFG, deep_peaks=CFG.max_peaks))
    assert shallow.status == "unaligned" and shallow.score_m < CFG.min_overlap_m, shallow.reason
    a = estimate_alignment(seg, placed, CFG)
    assert a.status == "aligned" and f"among the {CFG.deep_peaks} densest" in a.reason, a.reason
    err_m, err_deg = transform_error(a.transform, truth)
    assert err_m < 0.01 and err_deg < 0.05
