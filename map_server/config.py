"""The map server's configuration: alignment (a robot map's frame in the global frame,
alignment.py, candidates.py, registration.py), the fleet's pose graph (posegraph.py) and the
fleet (scheduling of alignment attempts, maturity, confirmations, settling, budgets: fleet.py).
Its own module so that those import it and not each other."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from map_server.contradiction import ContradictionConfig
from map_server.fusion import FusionConfig
from shared.matching import MatchingConfig
from shared.scanmatch import MatchConfig


def _server_matching() -> MatchingConfig:
    # whole maps: corners on both sides (robot pairs gap-limited too), all of them, long walls only
    return MatchingConfig(max_pair_gap_m=1.0, obs_max_pair_gap_m=1.0, max_obs_pairs=100_000, min_length_m=0.8)


@dataclass(frozen=True)
class AlignmentConfig:
    matching: MatchingConfig = field(default_factory=_server_matching)
    # a hypothesis's votes: those within this cell of it (map drift spreads a true overlap's votes
    # over ~0.3 m, 2°; candidates.vote_peaks)
    vote_cell_m: float = 0.5
    vote_cell_rad: float = np.radians(3.0)
    # vote peaks pre-scored: MIT-CSAIL's middle piece in 3, its true place 4 of 1,688 hypotheses,
    # is the 66th-90th densest (the others' corners agree among themselves); 0.05 s a search at 40,
    # 0.08 s at 100
    max_peaks: int = 100
    # ... and this many when no place among them stands on min_overlap_m of wall: MIT-CSAIL's middle
    # piece, searched against the other two placed in the third's frame, had its true place beyond
    # the 100 densest (best found 4.9 m; at 200: its truth, 45.9 m, 2.05x). Not the first search's
    # depth: at 200 peaks ACES's third piece, placed at its truth at 100 (1.18x), is placed 18.9 m
    # off (1.29x) on the same maps
    deep_peaks: int = 200
    max_refined: int = 12  # best pre-scored peaks refined and scored strictly
    refine_best: bool = True  # a best only pre-scored is refined before it decides (_best_refined)
    sample_step_m: float = 0.10  # maps are sampled this densely for the strict scores ...
    coarse_step_m: float = 0.25  # ... and this densely for pre-scores and refinement (speed)
    prescore_perp_m: float = 0.30  # generous tolerances for unrefined candidates (bin size, drift)
    prescore_angle_rad: float = np.radians(6.0)
    score_perp_m: float = 0.10  # strict: a robot sample lies on a placed wall within this offset ...
    score_angle_rad: float = np.radians(5.0)  # ... and facing difference
    conflict_m: float = 0.30  # a robot sample not on the placed map but this close to a placed wall
    conflict_weight: float = 1.0  # net score = matched length - this × conflicting length
    # refinement: one Gauss-Newton iteration per (gate [m], facing tolerance [rad]), gates shrinking
    refine_stages: tuple[tuple[float, float], ...] = (
        (0.6, np.radians(8.0)),
        (0.4, np.radians(6.0)),
        (0.25, np.radians(5.0)),
        (0.15, np.radians(5.0)),
        (0.15, np.radians(5.0)),
    )
    point_sigma_m: float = 0.05  # wall-point noise incl. map drift (Huber threshold, information)
    correlation_m: float = 1.0  # samples closer than this along a wall are not independent
    # verification
    min_overlap_m: float = 30.0  # robot-map length on placed walls (a merge rests on this much wall)
    # ... as a share of the robot map's length. A bent piece matches the others rigidly by one part
    # only (ACES's first piece of 3 at its true place: 10-14 % at the end of a run), but 0.10 let
    # a wrong place through while the maps grew (ACES in 3 pieces, seed 0, at 55 s: 36 m, 11 %, its
    # true place set aside as outshone), although every place found with 10-15 % at the end of 82
    # stored real-log runs was true
    min_share: float = 0.15
    max_conflict_share: float = 1.0  # conflicting length / matched length (Intel pieces: up to 0.77)
    min_rival_ratio: float = 1.10  # net score / best distinct rival's net score (office truth vs
    # half turn once the maps are mature: 1.1-1.3; 1.08 let one mirror image through in 10 runs)
    distinct_m: float = 0.5  # two poses are distinct places when they move the robot map apart by
    # more than this on average
    opposed_perp_m: float = 0.05  # a robot wall this close to a placed wall's line facing the other way
    max_opposed_share: float = 0.2  # ... may amount to this share of the matched length
    cross_margin_m: float = 0.25  # a crossing cuts both walls farther than this from their ends ...
    cross_min_angle_rad: float = np.radians(20.0)  # ... at this angle or more
    max_crossing_share: float = 1.0  # crossing robot walls' length / matched length (Intel: ~0.9)
    max_sigma_m: float = 0.10  # a fit this loose (one direction unconstrained: a corridor) is refused
    max_sigma_rad: float = np.radians(1.0)
    # the placed map's nearest-sample index searched by the compiled kernel (shared/kernels.py;
    # False, or not built: scipy's k-d tree, the same answer)
    compiled: bool = True
    # prior
    prior_gate_sigmas: float = 4.0  # refinement may move the prior this far (Mahalanobis, 99.9 %)
    prior_min_sigma_m: float = 0.01  # floors of the prior's sigma (a zero sigma pins the pose)
    prior_min_sigma_rad: float = np.radians(0.2)
    # a robot's claim of its place in the fused map (agent --join; alignment.verify_join): verified
    # on less wall than a search needs (it comes seconds after the robot's start)
    join_min_overlap_m: float = 8.0
    join_min_share: float = 0.5
    # revision of a current alignment
    revise_ratio: float = 1.15  # a new place that beats the current one's net score by this factor
    # takes over (the current one lost its support), if it passes every check and the free space
    # seen does not prefer the current one (contradiction.Check.outshone, at any ratio: bench_merge
    # seeds 10-19, two warehouse robots held at their truth were moved to the half-turn image at
    # 3.1-3.9x, one ending there 32.9 m off; with it none, seeds 0-9 unchanged)


@dataclass(frozen=True)
class GraphConfig:
    """The fleet's pose graph (map_server/posegraph.py)."""

    enabled: bool = True
    every_keyframes: int = 3  # a constraint is sought around every this many keyframes ...
    crop_radius_m: float = 6.0  # ... from the robot's elements this near it (where the graph puts them)
    window_keyframes: int = 10  # ... and anchored this many keyframes before or after it
    # ... or this many, of a robot whose walls stand in none of its own free space (Fleet._consistent)
    # matched against robots of which that holds too: their rows anchored far apart agree with each other
    # (a bent robot's do not, even where the graph put them: the graph's test, 0.21 m against 0.09 m), and
    # the wider submap holds what a narrow one in a long aisle lacks (walls across it). bench_merge
    # (office and warehouse, 10 seeds, --evidence-from the same run): 10 for all — final errors over 0.05
    # m 8 of 40, mean 0.034 m, worst 0.124 m (warehouse seed 4, whose maps placed as a whole would be
    # 0.021 m off); 20 — 6, 0.030 m, 0.079 m, each of the 6 a robot whose own map leaves more than 0.05 m
    # to any rigid merge (bench_merge's floor); 30 — 9, 0.031 m, 0.071 m. A real log's pieces contradict
    # themselves by metres and keep 10 (30 for every piece, on one Intel run's final maps rebuilt offline:
    # 0.050 m against 0.037 m)
    window_consistent_keyframes: int = 20
    # a constraint ties the keyframe the submap's matched rows move with (their most common
    # anchor), its pose carried there by the fit's correction, rather than the keyframe tried: an
    # agent anchors each wall to the keyframe that first saw it, and one long wall moves with one
    # keyframe. A bent robot in the graph's test: 0.085 -> 0.056 m (90th percentile). bench_merge
    # (office and warehouse, 10 seeds, --evidence-from the same run): final transform errors over
    # 0.05 m 14 -> 12 of 40, worst 0.181 -> 0.141 m, mean 0.048 -> 0.045 m — within the figure's
    # own spread (untied with floor_sigma_m 0.0301: 11, 0.179 m, 0.045 m); with min_submap_m 2
    # as well: 13, worst 0.201 m
    tie_own_anchor: bool = True
    # a keyframe whose submap meets the walls of more than one other robot, each enough for a
    # constraint, gets one with each (a fit against that robot's walls alone) rather than with the
    # robot most of the matched walls are of only: two pieces of Intel that revisit a place a
    # third also mapped were tied only through the third there (their relations 0.12-0.2 m off)
    each_robot: bool = True
    # a rebuild (FleetGraph.reset: a robot left) matches the keyframes from the placements, unless
    # the last solution put more than this share of some robot's keyframes beyond a wide search's
    # reach (first_shift_m) from its placement: then from that solution (robots placed against bent
    # maps are placed where the bend put the others; FleetGraph._bent_far). Offline, on 40 stored
    # final states of Intel, ACES and MIT-CSAIL in 3 pieces (sessions 36-37), rebuilt from the
    # placements and from the bend: 0.25 left a share of 0.13 to the placements (Intel: 0.41 m,
    # two pairs of pieces 2 m apart; from the bend 0.051 m); 0.1 changes four rebuilds, 0.409 ->
    # 0.051, 0.0353 -> 0.0337, 0.0377 -> 0.0395 m (Intel), 0.0404 -> 0.0396 m (ACES)
    rebuild_from_bend_share: float = 0.1
    # a robot placed (or placed again) while two robots are solved makes the graph matched and solved
    # anew, as a departure does (FleetGraph.sync); off: the others' keyframes near it are matched
    # again. On, Intel in 3 pieces ended 0.032-0.037 m (off 0.037-0.045 m), but a newcomer whose
    # placement is metres from its bent place (ACES's middle piece) is rebuilt from there: 0.78 m
    # off the first piece where going on gives 0.19 m on the same maps (a pair flagged wrong), and
    # the one run that placed ACES's first piece wrongly made it 3 m off. Off by default: no run
    # of it merged wrongly (9 runs)
    rebuild_on_arrival: bool = False
    # a robot new to the graph starts where the bend moved the others around it rather than at its
    # placement (FleetGraph._carry_in): placed against the unbent maps, its keyframes were matched
    # from there against the others' bent keyframes, metres apart where the bend moved them (Intel in
    # 3 pieces, 1 run of 4: the last piece placed 9 s after the second, which the bend had moved
    # 2.4 m; scans matched none of its keyframes, 8 submaps tied it 2 m off, it ended 2.7 m from
    # the reference piece's relations)
    carry_arrivals: bool = True
    min_submap_m: float = 4.0  # a submap with less wall than this is not matched
    min_matched_m: float = 2.0  # a constraint rests on this much matched wall ...
    min_matched_share: float = 0.4  # ... and this share of the submap
    # registration (registration.refine): one iteration per (gate [m], facing tolerance [rad]);
    # a keyframe's first match searches wide (the rigid placement may be off by decimetres where
    # the robots' paths bent), later ones narrow around where the graph put it
    first_stages: tuple[tuple[float, float], ...] = (
        (1.0, np.radians(8.0)),
        (0.7, np.radians(7.0)),
        (0.5, np.radians(6.0)),
        (0.35, np.radians(6.0)),
        (0.25, np.radians(5.0)),
        (0.15, np.radians(5.0)),
        (0.1, np.radians(5.0)),
        (0.1, np.radians(5.0)),
    )
    first_shift_m: float = 1.5  # the fit may move the keyframe this far (first match) ...
    first_turn_rad: float = np.radians(8.0)
    stages: tuple[tuple[float, float], ...] = (
        (0.4, np.radians(6.0)),
        (0.25, np.radians(5.0)),
        (0.15, np.radians(5.0)),
        (0.1, np.radians(5.0)),
        (0.1, np.radians(5.0)),
    )
    max_shift_m: float = 0.5  # ... and this far later
    max_turn_rad: float = np.radians(4.0)
    rematch_m: float = 0.05  # a keyframe the graph moved this much since its match is matched again
    rematch_rad: float = np.radians(0.5)
    sample_step_m: float = 0.1
    point_sigma_m: float = 0.05
    correlation_m: float = 1.0
    floor_sigma_m: float = 0.03  # added to a constraint's fit (the submaps' own errors)
    floor_sigma_rad: float = np.radians(0.5)
    # a submap's fit is held as the walls it matched — each pair of walls met, two points on this
    # robot's wall in the frame of the keyframe it moves with, on the other's line in the frame of
    # the keyframe that one moves with (posegraph.py) — rather than as one relative pose between two
    # keyframes, measured where the graph had put the other's walls then. The graph's test of a
    # bent robot: 90th percentile 0.056 -> 0.0068 m. bench_merge (session 50's recordings): final
    # errors over 0.05 m 6 -> 4 of 40, mean 0.028 -> 0.024 m, worst 0.074 -> 0.061 m; with
    # line_floor_m 0.005 / 0.02, robust_k_consistent 0.25 / 1.5: 4 each; consistent_scale 3 / 30:
    # 6 / 5. Real logs in 3 pieces (their pieces mostly tied by scans): docs/fleet-history.md
    line_ties: bool = True
    line_floor_m: float = 0.01  # a matched wall's own error (each pair of walls met)
    line_sigma_m: float = 0.05  # a matched sample's distance sigma in them (as point_sigma_m)
    robust_k: float = 3.0  # Cauchy kernel on constraints (normalized residual units) ...
    # ... and on those between two robots whose maps agree with themselves (Fleet._consistent): their
    # ties state sigmas four times their errors (bench_merge: χ 0.27 at the median), so 3 never acted;
    # 0.5 (about two true sigmas) weighs down the ties biased by walls matched far from the keyframe
    # they move with. bench_merge, session 50's recordings: final errors over 0.05 m 6 -> 6 of 40 (mean
    # 0.030 -> 0.028 m, worst 0.079 -> 0.074 m), robots held beyond the wrong-merge bound for a while
    # 7 -> 2, the fused map within 0.05 m 94.9 -> 95.7 %; recorded with sample_scale 0.7: 10 -> 7 of 40,
    # 4 -> 0, 92.9 -> 94.4 %. Not for a bent robot's (a real log's piece): its ties must bend it —
    # 0.5 for every tie (bench_demo --logs ... --splits 3, seeds 10 and 11): Intel 0.024 / 0.026 m and
    # ACES 0.043 m / 2/3 (its first piece lost to a trial bend) against 0.023 / 0.023 and 0.041 / 0.041
    # m; for these ties only: Intel 0.024 / 0.023, ACES 0.040 / 0.041, MIT-CSAIL 0.031 / 0.032 m
    # (0.032 / 0.032 at 3), every piece placed, 0 wrong
    robust_k_consistent: float = 0.5
    max_chi: float = 5.0  # constraints beyond this after the solve are dropped
    iterations: int = 4  # Gauss-Newton iterations a solve (warm-started from the last one) ...
    # ... stopping once a step moves no pose by more than this (m, rad): a new map moves the
    # solution by 1-5 cm, the next step by 0.02-0.8 mm, the third by microns (16 robots), and
    # keyframes moving less than ``moved_m`` are not moved in the map; 1e-5 ran 3 iterations a
    # solve where 2 do
    tol: float = 1e-3
    # a robot whose walls stand in its own free space by at most this much (m; contradiction.py:
    # own_noise) has its own edges' information taken this many times (posegraph.py): bench_merge,
    # office and warehouse, 10 seeds, constraints tied to the matched rows' keyframes — times 1:
    # 14 of 38 final errors over 0.05 m, worst 0.315 m, one robot never placed and one undone;
    # times 10: 12 of 40, worst 0.141 m; times 30: 9, worst 0.097 m, but one merge 37 s after its
    # evidence (the bound: 30 s). The simulated maps contradict themselves by 0-1 m, a real log's
    # piece by metres
    consistent_self_m: float = 1.0
    consistent_scale: float = 10.0
    reference_sigma_m: float = 1e-4  # the reference robot's placement edge (the gauge)
    reference_sigma_rad: float = 1e-5
    placement_sigma_m: float = 2.0  # an aligned robot's placement edge (weak)
    placement_sigma_rad: float = np.radians(10.0)
    moved_m: float = 0.005  # a robot's elements are moved again when a keyframe moved this much
    moved_rad: float = np.radians(0.05)
    budget_keyframes: int = 40  # keyframes matched per fusion (the rest in the next ones)
    # constraints on the same pair of keyframes (neighbouring tried keyframes tied to one anchor:
    # overlapping submaps, one piece of evidence) share one constraint's information. bench_merge
    # (session 38): 6 of 40 over 0.05 m either way, mean 0.0295 -> 0.0289 m, worst 0.079 -> 0.067 m;
    # offline rebuilds of 51 stored real-log final states (3 pieces): Intel mean 0.0366 -> 0.0365 m
    # (9 better, 5 worse by over 0.5 mm), ACES 0.0489 -> 0.0480 (4 better, 0 worse), MIT-CSAIL
    # 0.0318 -> 0.0316 — within the spread; and the graph's test of anchored ties (rows anchored two
    # keyframes back, every anchor tied by several tried keyframes) bends its bent robot back less
    # (90th percentile 0.047 -> 0.067 m): off
    share_pairs: bool = False
    # constraints between robots that both send keyframe scans (schema 7) come from matching the
    # scans — a keyframe's (with the ones before it) against the cloud of the other robot's nearest
    # keyframe and its neighbours, where the graph puts them, by the agents' own loop matcher
    # (shared/scanmatch.window_match) — rather than the segment submaps: a segment map is a summary
    # of the scans (an Intel piece's submap constraints, fitted where a single-robot run puts both
    # keyframes, were 0.067 m off it at the median, the scan matches 0.038 m) and the relations
    # across pieces followed (offline rebuilds of 12 stored runs' final states in 3 pieces: Intel
    # 0.0302-0.0365 -> 0.0243-0.0269 m, its single-robot error 0.024; ACES 0.0401-0.0416 ->
    # 0.0394-0.0410; MIT-CSAIL 0.0309-0.0326 -> 0.0313-0.0325). Keyframes without scans on either
    # side: the submaps
    scans: bool = True
    scan_radius_m: float = 1.5  # the other robot's keyframes this near (where the graph puts them) ...
    scan_candidates: int = 3  # ... nearest first, this many tried (the first match is kept) ...
    scan_max_turn_rad: float = np.radians(90.0)  # ... facing within this of the keyframe
    scan_cloud_neighbours: int = 4  # the other robot's cloud: its keyframe and this many each side
    scan_query_neighbours: int = 2  # the query: the keyframe's scan and this many before it
    scan_voxel_m: float = 0.05  # both thinned to a point per voxel ...
    scan_query_points: int = 200  # ... the query to at most this many points
    # the window, its covariance, ICP; a best pose on the window's edge searched again around it:
    # keyframes the graph put ~1 m apart (a bent piece's start) met the truth on the edge, and the
    # match said nothing along that axis (std 3-5 m) — ACES in 3 pieces, one run's final maps:
    # the first two pieces 0.95 m apart at the median of their relations, 0.049 m over the log;
    # re-centred 0.12 m, 0.040 m (the single robot's 0.040); 11 other runs' within 0.3 mm
    scan_match: MatchConfig = field(default_factory=lambda: MatchConfig(recentre=1))
    # two robots are tied by scans only when one of their maps was found contradicting its own
    # free space by more than consistent_self_m (a real log's piece, within seconds of its start);
    # clean maps by submaps (False): bench_merge's simulated robots tied by scans: 15 of 39 final
    # errors over 0.05 m, worst 0.097 m, the fleet's ATE 0.027 m; by submaps 6 of 40, 0.079 m,
    # 0.023 m; by scans unless both were found consistent (their free space not known yet: scans)
    # 7 of 40, warehouse seed 2's robot2 0.190 m (0.022)
    scans_always: bool = False
    # a pair of robots that no scan match ties yet is matched by submaps: scans need the robots to
    # have passed within scan_radius_m of each other facing alike, walls do not (bench_merge
    # warehouse seed 2: robot2, found contradicting itself by 1.0 m, met no keyframe of the others
    # within 1.5 m and ended 0.190 m off, tied by nothing). Per keyframe instead (its submap where
    # the scans left it untied to a robot): the graph's bent-robot test 0.069 m at the 90th
    # percentile (scans alone 0.032, submaps alone 0.056), an Intel run's final state offline
    # 0.0282 m (scans alone 0.0260)
    scan_fallback: bool = True


@dataclass(frozen=True)
class FleetConfig:
    fusion: FusionConfig = field(default_factory=FusionConfig)
    alignment: AlignmentConfig = field(default_factory=AlignmentConfig)
    graph: GraphConfig = field(default_factory=GraphConfig)
    contradiction: ContradictionConfig = field(default_factory=ContradictionConfig)  # a found place
    # whose walls fall where other robots saw free space is set aside (contradiction.py)
    retry_growth_m: float = 5.0  # re-attempt a robot's alignment when its map grew by this much ...
    retry_growth_share: float = 0.05  # ... or by this share of its length (whichever is larger)
    retry_placed_growth_m: float = 10.0  # an unaligned robot is retried when the placed map grew so
    retry_interval_s: float = 10.0  # ... or when anything changed (or a candidate waits) this long ago
    regroup_pairs: int = 2  # pairs of unplaced robots matched with each other a fusion while the
    # reference is the only placed robot (placing.Placer.regroup)
    confirmations: int = 2  # consecutive attempts that must agree on a new place ...
    confirm_s: float = 0.0  # ... over this long at least (the first to the last)
    same_place_m: float = 0.3  # two verdicts agree when they move the robot map this little (mean)
    # maturity (module docstring). Office, 3 robots, 10 seeds, 180 s: no wrong merge with 0.2-0.3
    # (placed at 125-170 s), one with 0.4; warehouse: maps never mature below 0.15
    mature_window_s: float = 30.0
    mature_growth: float = 0.25
    # ... unless nothing contradicts the place found: a verdict on young maps counts (confirmed as
    # any) when at most this much wall falls where free space was seen (both ways) ...
    young_max_contradicted_m: float = 0.0
    # ... over at least this much free space both sides saw there (bench_merge, office and
    # warehouse, 10 seeds: each of the 190 verdicts at a wrong place contradicted 0.095-9.2 m, 96 %
    # of the 2,429 at the true place 0, over 36-225 m2 seen by both; the margin is one 0.1 m
    # sample). Negative: young maps wait for maturity
    young_min_seen_m2: float = 20.0
    # ... and such an attempt is made at most this often a robot (a young map grows fast: a real
    # log's piece was searched every 0.5-2 s, 0.3-1 s a search, and its verdicts are never quiet:
    # a real map contradicts itself); once the maps are mature the robot is attempted at once
    young_retry_s: float = 5.0
    # ... and only while its own walls stand in its own free space by at most this much (m): a map
    # that contradicts itself (a real log's piece: 3-8 m by 11 s of ACES, doors, people, its bent
    # path) will not be found quiet against another, and its searches cost the server (and, on
    # one machine, the agents: Intel and ACES in 3 pieces merged a piece wrongly when its maps grew
    # slower and matured early); the simulated maps contradict themselves by 0-1 m
    young_max_self_m: float = 1.0
    # ... and a quiet verdict places the robot after this many attempts in a row at the place (not
    # ``confirmations``): the free-space check is the second, independent test a mature verdict's
    # repetition stands for (a revision of a placed robot is confirmed as any). bench_merge, office
    # and warehouse, 10 seeds: with 2, delay from evidence to merge median 12 s, worst 32 s, one
    # robot never placed; with 1, median 0.5 s, worst 9 s, every robot placed, 0 wrong merges
    young_confirmations: int = 1
    # ... when both sides saw at least this much free space there (else ``confirmations``):
    # bench_join (a young robot matched against a mature fused map) placed warehouse 0->1 on one
    # quiet verdict at a half-turned place (36.8 m matched, ratio 1.24, 0 m contradicted over
    # 55 m2 seen), undone 23 s later; with 100 m2 bench_merge's delays are median 7 s, worst 21 s
    # (0.5 / 9 s with 0), every robot placed, 0 wrong
    young_once_seen_m2: float = 100.0
    # retired pieces (module docstring) kept per robot: a robot that keeps restarting re-maps the
    # same places, so the oldest piece is mostly covered by the newer ones; bounds memory and state
    max_retired: int = 3
    # when a robot leaves, placed robots are refined against each other in rounds until no frame
    # moves by more than these (one round is one Gauss-Seidel sweep: office, 3 robots, the final
    # maps: 3.3 cm / 0.19° left after one sweep, converged in 5), at most ``settle_rounds``
    settle_rounds: int = 8
    settle_m: float = 1e-3
    settle_rad: float = 1e-4
    # a settle's refinements are spread over fusions too: at most this many layer segments a
    # fusion (the first robot always), the sweeps going on where they stopped. 64 robots leaving
    # at once took one fusion of ~20 s before (every robot refined up to 8 times), in which no
    # new map was fused; a refinement costs ~6-14 ms (each one re-merges the robot refined before
    # it), so their count is bounded too: 4 keeps a settle's fusion near a normal one (16 made
    # fusions of ~220 ms at 64 robots, and seconds while 64 agent processes exited on 2 cores)
    settle_budget_segments: int = 1000
    settle_refinements: int = 4
    # a placed robot is refined against the placed map near it (module docstring: "Cost"): the
    # crop reaches this much beyond the robot map's box at its starting pose (plus the gates)
    refine_margin_m: float = 2.0
    # a search is made against the placed maps as placed (rigidly) and, once the fleet's graph bends
    # them, as it bent them (placing.Placer.estimate): a place found against the rigid maps stands
    # unless the bent maps' best place (placed or not, on min_overlap_m of wall at least) lies
    # farther than this (mean displacement of the robot map) from it; then the bent maps' place is
    # taken, or none. ACES's first piece (of 3), bent, was placed half-turned by the rigid search in
    # 3 of 10 live runs (36.1 / 51.4 / 51.6 m matched, 1.30 / 1.58 / 1.65x the best rival; 23.6 m
    # off across the pieces) where the bent maps put its truth first (51-52 m; placed in one). A
    # bent piece's rigid and bent places of its truth lie 1-4 m apart, its wrong places 20-60 m
    # away. Searched again at the end of 82 stored real-log runs, 3 true places of that piece are
    # refused (its bent search led to a wrong place on 43-51 m)
    search_agree_m: float = 5.0
    # ... where the two searches place apart, the fleet's graph tries the robot at each place
    # (Fleet.trial: a copy of the graph, the robot's keyframes matched and solved, at most
    # ``trial_keyframes`` matched) and a place whose walls then meet the others' ``trial_ratio``
    # times as much as at the other place stands, if its own search placed it (the other is not
    # taken on the trial alone; one refused may be verified again: Placer._settle_unplaced). ACES
    # in 3 pieces, the first piece on two runs' final maps: 68.9 m at its truth against 29.6 m at
    # the bent maps' best (25 m away), and 61.4 m against 28.6 m at the rigid maps' (16.6 m away);
    # the searches over the same maps said 1.18-1.32x
    trial_ratio: float = 1.5
    trial_keyframes: int = 4000
    # ... and a search's place for a robot whose map contradicts itself, with a distinct rival
    # within this ratio, is tried against that rival (placing.Placer._rival_trial)
    trial_rival_ratio: float = 2.0
    # the server runs trials after publishing, in steps (map_server/trials.py): a finished trial
    # answers a later search of the same session whose places lie within this of its own (mean
    # displacement of the robot's walls) while its map grew by less than this share of its length
    # (or 4 retry_growth_m); a robot whose placement waits on a trial stays unplaced meanwhile
    trial_same_m: float = 1.0
    trial_growth_share: float = 0.25
    # refinements of placed robots (not urgent) are spread over the fusions: a fusion refines
    # due robots, the first in arrival order whose turn it is, until they add up to this many
    # layer segments (the first one always: its cost grows with its map); the others wait for the
    # next fusion (each waits ``retry_interval_s`` after its own last attempt, so every due robot
    # gets its turn). 100 robots x 1,000 rows: one refinement (~450 segments) per fusion instead
    # of a round of 100 every ``retry_interval_s``; office-sized maps (~140 segments) one or two:
    # robots placed together fall due together, and 600 made a burst of fusions with 4-5
    # refinements each (64 agents: the latency tail) where 200 spreads them out
    refine_budget_segments: int = 200
