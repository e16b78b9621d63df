"""Configuration of the D-SLAM core (:mod:`services.dslam.core`): a plain frozen model, never read from the
environment (the ``fleetslam dslam`` settings class composes it; ``fleetslam run --set`` overrides it)."""

from __future__ import annotations

from typing import Literal

from pydantic import Field, NonNegativeFloat

from central.fastslam.config import ROBOTS_FIT_MIN, ROBOTS_FIT_RESIDUAL_M, ROBOTS_FIT_SPREAD_M
from robots.odometry_noise import TURN_SCALE_BOUNDS
from schemas.contract import CoreConfig


class DslamConfig(CoreConfig):
    """The D-SLAM core: association, feature lists, recovery, localization."""

    association: Literal["known", "nn", "greedy", "ihgr", "exact", "jcbb", "auto"] = Field(
        "known",
        description="known (true ids from the scans) or a method of the association service: nn, greedy, ihgr, exact, jcbb, "
        "auto; the service and fleetslam run also take unknown: the recommended method without ids (auto)",
    )
    gate_probability: float = Field(0.99, gt=0, lt=1, description="chi-square gate of the association")
    new_feature_gate_probability: float = Field(0.9999, gt=0, lt=1, description="a measurement starts a feature only outside this gate of every landmark")
    gate_pose_floor: tuple[NonNegativeFloat, NonNegativeFloat, NonNegativeFloat] = Field(
        (0.3, 0.3, 0.05), description="σ (m, m, rad) added to the robot's pose covariance when associating without "
        "ids: CI-localised poses are tighter than real detections' tails (0.05 rad: at the car park's 30 m range 0.1 "
        "would span two beacons)")
    placement_bootstrap: bool = Field(
        True, description="a robot placed against the map (fleet placement) starts as from a known start pose with "
        "the placement's covariance: until it is localized against the map it maps its raw observations (phase I) "
        "while its position std is at most bootstrap_std and it sees fewer than two mapped features, as the robots "
        "with start poses do (MR.CLAM without start poses: map RMSE 0.58 -> 0.13 m with barcodes, 0.62 -> 0.11 m "
        "without; docs/dslam.md). Off: it starts localized, its covariance widened by placement_floor, and maps only "
        "through z_map")
    placement_floor: tuple[NonNegativeFloat, NonNegativeFloat, NonNegativeFloat] = Field(
        (0.3, 0.3, 0.1), description="with placement_bootstrap off: σ (m, m, rad) added to the covariance of a pose "
        "placed by global localization against the map (MCL's particle spread understates its error, on MR.CLAM "
        "0.4 m and 18° off with σ 0.05 m and 1.4°)")
    unique_pairs: bool = Field(
        False, description="association methods: a pairing is used only if no other jointly compatible hypothesis "
        "pairs as many measurements without it (JCBB; the measurement is set aside otherwise): under a wide pose "
        "uncertainty a wrong pairing passes every gate, and one taken by CI turns the robot for good")
    turn_slip: bool = Field(
        True, description="widen the association's gate by the heading variance per radian turned that the robot "
        "announces (RobotInfo.turn_slip_var, wheel slip: MR.CLAM 0.015), summed since its last full-rank localization: "
        "without it a turning MR.CLAM robot's heading error grows to 0.8 rad while its heading std stays at "
        "0.08–0.10 rad, and no detection gates again. The fused pose keeps the odometry's covariance: the slip in "
        "the prediction too made MR.CLAM with barcodes worse in every subset of robots tried")
    turn_slip_in_localization_gate: bool = Field(
        False, description="with turn_slip, the test that sets aside a full-rank localization beyond any doubt from "
        "the prediction widens the prediction's heading variance by the same slip (the fused pose still keeps the "
        "odometry's covariance)")
    turn_scale_adapt: bool = Field(
        False, description="without ids, (v, ω) odometry: each robot's turns are multiplied by a scale learned from "
        "pairs of its detections of one mapped landmark placed by its own dead reckoning (robots/odometry_noise.py, as "
        "FastSLAM's). Off by default: with start poses (seeds 0-4) it took the worst robot's median on MR.CLAM 1 / 2 / "
        "4 / 6 from 1.67 / 1.26 / 0.86 / 0.66 to 1.57 / 0.81 / 0.51 / 0.31 m, but MR.CLAM 1's map 0.10 -> 0.19 m and "
        "one seed of MR.CLAM 1 and 4 beyond 3 m (docs/dslam.md)")
    turn_scale_bounds: tuple[float, float] = Field(TURN_SCALE_BOUNDS, description="... the least and largest turn scale")
    new_feature_density: float = Field(1e-3, gt=0, description="expected new features per m·rad of measurement space")
    candidate_margin: float = Field(1.0, ge=0, description="landmarks up to max range + this (m) are association candidates")
    confirm_hits: int = Field(2, ge=1, description="sightings before a tentative feature enters the map (association methods; known ids map at once)")
    tentative_misses: int = Field(3, ge=1, description="scans in view without a sighting before a tentative feature is dropped")
    local_map_max_std: float = Field(
        0.5, ge=0, description="scans with fewer than two mapped features are collected into a local map (EKF in the "
        "robot's frame) until it holds two mapped features, or is given up when the robot's position std in it "
        "exceeds this (m); 0: one scan at a time, as in the paper",
    )
    local_map_max_features: int = Field(40, ge=2, description="a local map with more features than this is given up")
    min_reference_distance: float = Field(0.3, gt=0, description="smallest distance (m) between the two reference features of z_map")
    bootstrap_std: float = Field(
        0.1, ge=0, description="a robot that moved before seeing two mapped features maps raw observations from its "
        "dead-reckoned pose while its position std is below this (m; 0: only at the start pose)",
    )
    map_gate_probability: float = Field(0.9999, gt=0, lt=1, description="z_map is refused when its χ² test fails at this probability")
    recovery_tol: float = Field(1e-5, gt=0, description="mean recovery stops when every block-Jacobi step is below this (m)")
    recovery_max_iter: int = Field(200, ge=1, description="most PCG iterations of one mean recovery")
    column_tol: float = Field(1e-9, gt=0, description="covariance-column recovery tolerance, relative to the landmark's variance")
    column_max_iter: int = Field(100, ge=1, description="PCG iterations of a covariance-column solve before a fresh sparse LU solve finishes it")
    refactor_iterations: int = Field(15, ge=1, description="a column solve slower than this many iterations makes the next one factorise I afresh")
    column_solver: Literal["corrected", "pcg"] = Field(
        "corrected", description="a covariance column not cached is one solve with the stored sparse LU factor of an "
        "earlier I, made exact for the updates since by the cached columns of the landmarks they touched "
        "(corrected: no iterations, no refactorisation while those stay cached), or block PCG preconditioned by that "
        "factor, made afresh when it has grown stale (pcg: the reference)")
    column_correction_limit: int = Field(
        64, ge=0, description="corrected: landmarks touched since the factorisation kept cached (pinned) for the "
        "correction; beyond this many the next column solve factorises I afresh")
    column_prefetch_margin: float = Field(
        2.0, ge=0, description="the service solves, in a worker thread between scans, the covariance columns of the "
        "landmarks within max range + candidate_margin + this (m) of a placed robot that are not cached, so that a "
        "scan first seeing them does not stall on the solve (10^5 landmarks: about 160 ms a column); 0: off. "
        "Offline runs (no time between scans) never do")
    column_prefetch_batch: int = Field(4, ge=1, description="landmarks whose columns one such solve takes (nearest first): "
                                       "at 10^5 landmarks 8 took up to 565 ms, beyond the 500 ms between two scans, and the "
                                       "next scan 102 ms to take them in; 4: 296 and 52 ms")
    max_deferred_scans: int = Field(20, ge=0, description="scans of a robot without a pose kept while the columns of "
                                    "their mapped landmarks are solved between scans (a service only); beyond, they are "
                                    "handled, solving what they need")
    column_cache: int = Field(64, ge=1, description="covariance columns kept to warm-start the next solves (landmarks)")
    covariance_columns: Literal["factored", "explicit"] = Field(
        "factored", description="cached covariance columns kept as full-length base vectors times a small mixing "
        "matrix, so that an update corrects them and the mean in work independent of the map size (factored), or as "
        "full columns corrected in place, O(n) per update (explicit: the reference)")
    recovery_check_every: int = Field(
        16, ge=1, description="the mean is checked against I X = i (PCG, O(nnz)) every this many scans; in between the "
        "rank-k corrections keep it exact (1: every scan, the reference)")
    relocalize_after: int = Field(
        10, ge=1, description="scans whose full-rank observation estimate contradicts the prediction, with no "
        "full-rank agreement between them (one landmark's sighting leaves a turn free: it neither agrees nor "
        "disagrees), before the robot is relocalized")
    reacquire: bool = Field(
        True, description="without ids, a robot whose position std exceeds reacquire_position_sd is lost: its scans "
        "neither map nor localize it (the association that makes z_map and the observation estimate is made from the "
        "pose), its detections are held as points from its dead-reckoned pose, and a search for one rigid correction "
        "(services/dslam/core.py, the Hough vote of central/fastslam/reacquire.py) puts it back on the map. Victoria "
        "Park: the car's std grows to 4 m in the sparse north-west, trees mapped from there were wrongly paired, and "
        "the map they made in a wrong frame held it 100 m off for the rest of the run (docs/dslam.md)")
    reacquire_position_sd: float = Field(
        2.0, gt=0.0, description="... lost beyond this position std (m). Victoria Park, GPS RMSE by this limit: 0.75 m "
        "13.0, 1 m 7.0, 1.25 m 5.5, 1.5 m 5.1, 2 m 4.8, 2.5 m 4.0, 3 m 21.3 (lost before it counts as lost), none 58.0")
    reacquire_window_s: float = Field(15.0, gt=0.0, description="... its detections of the last this many seconds count")
    reacquire_every_s: float = Field(0.5, gt=0.0, description="... searched for a correction at most this often (s)")
    reacquire_inlier_sigmas: float = Field(
        2.0, gt=0.0, description="... a detection within this many range σ of the sensor of a landmark is explained "
        "(Victoria Park 1 m, MR.CLAM 0.3 m, the car park 0.2 m); the landmarks it reaches must be 4 such radii apart")
    reacquire_min_detections: int = Field(8, ge=1, description="... a correction must explain this many detections")
    reacquire_min_landmarks: int = Field(
        5, ge=2, description="... of this many distinct landmarks (a window of a car's scans sees few trees many "
        "times: on Victoria Park corrections onto 2 to 4 trees were wrong by up to 35° and 32 m; GPS RMSE 15.2 m with "
        "4, 7.0 m with 5, 6.4 m with 6, all at reacquire_position_sd 1 m)")
    reacquire_margin: float = Field(
        3.0, ge=0.0, description="... and no distinct correction may come within this many detections of it")
    reacquire_max_turn: float = Field(0.785, ge=0.0, description="... turning it by at most this (rad)")
    reacquire_by_robots: bool = Field(
        True, description="... and a robot whose detections of other robots contradict its pose (reacquire_robots_min "
        "of them in reacquire_robots_window_s beyond the chi-square 0.999 gate of the two robots' covariances, of two "
        "robots at least, four in five) is lost too, searched within reacquire_robots_shift_m and reacquire_max_turn, its "
        "robot detections voting in the search (as FastSLAM's reacquire_by_robots, central/fastslam/reacquire.py)")
    reacquire_robots_window_s: float = Field(10.0, gt=0.0, description="... over this many seconds")
    reacquire_robots_min: int = Field(6, ge=1, description="... this many unexplained detections of robots")
    reacquire_robots_shift_m: float = Field(2.0, gt=0.0, description="... shifting a contradicted robot by at most this (m)")
    reacquire_robots_min_landmarks: int = Field(
        2, ge=2, description="... its correction reaching this many distinct landmarks (its robot detections vote too; "
        "MR.CLAM's windows rarely reach reacquire_min_landmarks)")
    reacquire_robots_veto: int = Field(
        3, ge=0, description="... a held robot with this many detections of other robots in its window takes no "
        "correction that brings fewer than half of them near their robots (0: off)")
    reacquire_robots_fit_min: int = ROBOTS_FIT_MIN  # FastSLAM's settings (central.fastslam.config)
    reacquire_robots_fit_spread_m: float = ROBOTS_FIT_SPREAD_M
    reacquire_robots_fit_residual_m: float = ROBOTS_FIT_RESIDUAL_M
    robot_detection_noise_scale: float = Field(
        4.0, gt=0.0, description="... a robot detection's noise: the scan's covariance times this (a robot is a wide "
        "target; FastSLAM's robot_detection_noise_scale)")
    robot_detection_position_sd: float = Field(
        0.1, ge=0.0, description="... plus this much relative position between the two robots (m)")
    robot_detection_max_dt: float = Field(0.1, ge=0.0, description="... only when the other robot's pose is this recent (s)")
    ci_criterion: Literal["trace", "det"] = Field("trace", description="covariance intersection minimises the trace or the determinant")
    marginals_limit: int = Field(3000, ge=0, description="maps up to this many landmarks report every marginal covariance exactly")
