"""Configuration of the FastSLAM core: a plain frozen model, never read from the environment (the
``fleetslam central`` settings class composes it; ``fleetslam run --set`` overrides it)."""

from __future__ import annotations

import math
import os
from typing import TYPE_CHECKING, Literal

from pydantic import Field, model_validator

from robots.odometry_noise import TURN_SCALE_BOUNDS
from schemas.contract import CoreConfig

if TYPE_CHECKING:  # the re-acquisition module loads numba and scipy: every process reads this config, few search
    from central.fastslam.reacquire import SearchRule

Probability = Field(gt=0.0, lt=1.0)


# the robots' fit of a held robot (central.fastslam.reacquire.beyond_caps), the same settings in FastSLAM and D-SLAM
ROBOTS_FIT_MIN = Field(
    8, ge=3, description="... a held robot whose detections of other robots, this many at least, are brought onto "
    "those robots by one rigid correction beyond the search's caps (any turn) takes it")
ROBOTS_FIT_SPREAD_M = Field(
    1.0, gt=0.0, description="... when the detections are spread this far (RMS, m): the turn is then fixed")
ROBOTS_FIT_RESIDUAL_M = Field(
    0.25, gt=0.0, description="... and each ends this near its robot (m), while the pose as it is leaves most "
    "farther (a robot held because the robots contradicted it)")


def available_cores() -> int:
    """The cores this process may run on: its CPU affinity where the system tells it, else the machine's count."""
    if hasattr(os, "sched_getaffinity"):
        return max(1, len(os.sched_getaffinity(0)))
    return max(1, os.cpu_count() or 1)


class FastSlamConfig(CoreConfig):
    """Every knob of the centralised multi-robot FastSLAM filter, with the reason for its default."""

    particles: int = Field(100, ge=1, le=100_000, description="particles of the filter")
    association: Literal["known", "shared", "nn", "mht"] = Field(
        "shared", description="known (scan ids), shared (one JCBB assignment per scan on the marginal map, for "
        "every particle), nn (per particle: maximum likelihood, gated) or mht (per particle: paper 001's n+2 split); "
        "the service and fleetslam run also take unknown: the recommended method without ids (shared)")
    seed: int = Field(0, description="seed of every random draw of the filter")
    proposal: Literal["auto", "fastslam1", "fastslam2"] = Field(
        "auto", description="fastslam1: sample from the motion model; fastslam2: fold the scan into the proposal "
        "(Montemerlo et al., FastSLAM 2.0); auto: fastslam2 with shared association (better on MR.CLAM, Victoria Park "
        "and the car park over 20 seeds, one kernel per scan), fastslam1 otherwise")
    gate_probability: float = Field(0.99, gt=0.0, lt=1.0, description="χ²(2) gate for association: 9.21 (DESIGN §4)")
    new_landmark_probability: float = Field(
        0.999, gt=0.0, lt=1.0, description="nn: outside this χ²(2) region of every landmark a detection is new (13.8)")
    shared_solver: Literal["jcbb", "exact"] = Field(
        "jcbb", description="shared: joint compatibility (JCBB) or the optimal one-to-one assignment of gated pairs")
    gate_pose_floor: tuple[float, float, float] = Field(
        (0.3, 0.3, 0.1), description="shared: σ (m, m, rad) added to the robot's pose spread when gating")
    gate_pose_growth: tuple[float, float, float] = Field(
        (0.0, 0.0, 0.0), description="shared: σ (m, m, rad) per √s since the robot last matched a landmark")
    association_particles: int = Field(
        200, ge=0, description="shared: the landmark mixtures a scan is gated against are estimated from this many "
        "particles, drawn by weight (systematic, fixed offset), when the filter holds more (0: all of them); their cost "
        "follows the particles, and the association needs the mixture, not every particle. The published map uses all")
    ambiguity_margin: float = Field(
        0.0, ge=0.0, description="shared: leave out a detection whose two best distinct landmarks differ by less than "
        "this in d² (0: off)")
    unique_pairs: bool = Field(
        False, description="shared, jcbb: keep a pairing only if no other jointly compatible hypothesis has as many "
        "pairings without it (the detection is ignored otherwise)")
    tentative_misses: int = Field(
        3, ge=1, description="shared: a tentative landmark in view and not seen this many times is dropped")
    silence: bool = Field(
        True, description="shared: delete a confirmed landmark once the robots whose scans other landmarks pin have "
        "missed it longer than the silences this map's landmarks survived say a true one would (the tail fitted to "
        "them; central/fastslam/silence.py): the copies a robot maps while its pose is wrong, which no robot sees "
        "again. MR.CLAM 1 / 2 / 4 without barcodes, 5 seeds: spurious landmarks 14 / 12 / 2 -> 2 / 2 / 0 (median)")
    silence_alpha: float = Field(
        0.05, gt=0.0, lt=1.0, description="... the chance that a silence some landmark of the map ended would have "
        "passed the threshold (its exponential tail fitted to the silences ended so far)")
    silence_tail_quantile: float = Field(
        0.95, gt=0.0, lt=1.0, description="... the tail is fitted above this quantile of the ended silences")
    silence_min_ended: int = Field(
        200, ge=1, description="... no landmark is deleted before this many silences have ended (the tail needs "
        "ten values above its quantile)")
    silence_memory: int = Field(20_000, ge=1, description="... the latest this many ended silences are the null")
    exclusive: bool = Field(True, description="one detection per landmark per scan (paper 001's NN does not assume it)")
    mht_prune: float = Field(0.3, gt=0.0, le=1.0,
                             description="mht: drop a child whose weight is below this fraction of its parent's best child")
    mht_max_factor: float = Field(4.0, ge=1.0, description="mht: resample back to N as soon as the split set exceeds this many times N")
    new_landmark_rate: float = Field(0.5, gt=0.0, description="mht: expected new landmarks per scan (λ_n), against the clutter rate")
    clutter_rate: float | None = Field(None, ge=0.0, description="mht: false detections per scan (λ_c); None: the sensor's")
    resample_ess: float = Field(0.5, ge=0.0, le=1.0, description="resample (systematic) when the ESS falls below this fraction")
    motion_noise_scale: float | None = Field(
        None, gt=0.0, description="multiplies the control covariance of every odometry message, in the particles' "
        "draws and in the drift re-acquisition tracks (None: 1, the covariance the robot announces). With "
        "motion_noise_adapt each robot's gain on it then follows its scans")
    motion_noise_adapt: bool = Field(
        True, description="shared association: each robot's odometry covariance is scaled by a gain that follows the "
        "pairs of its detections of one landmark placed by its own dead reckoning (robots/odometry_noise.py), between "
        "motion_noise_min_gain and motion_noise_max_gain. Replaces the quarter of the announced covariance fitted on "
        "Victoria Park, which left MR.CLAM's particles too narrow (docs/fastslam.md)")
    motion_noise_min_gain: float = Field(
        2.0**-6, gt=0.0, le=1.0, description="... the least gain: the announced covariance may be this much too loose")
    motion_noise_max_gain: float = Field(
        1.0, gt=0.0, description="... the largest gain (1: never looser than announced). Most MR.CLAM robots sit at "
        "1; with 4 the gains ran to 3-4, pairs of detections of two different landmarks pushing them up, and the data "
        "sets not tuned on got worse (5 seeds: MR.CLAM 2 worst robot 0.82 / 1.11 -> 1.38 / 3.53 m, MR.CLAM 4 without "
        "start poses 1.77 / 2.82 -> 2.08 / 5.57 m)")
    motion_noise_step: float = Field(0.02, gt=0.0, le=1.0, description="... the gain's step per pair of detections, in powers of 2")
    pose_noise_per_s: tuple[float, float, float] = Field(
        (0.0, 0.0, 0.0), description="extra σ (m, m, rad) per √s of motion: slip, unmodelled")
    turn_scale_adapt: bool = Field(
        False, description="shared association, (v, ω) odometry: each robot's turns are multiplied by a scale that "
        "follows pairs of its detections of one landmark (robots/odometry_noise.py; MR.CLAM's robots over-count their "
        "turns by 4-10 %). Off by default: with start poses it took MR.CLAM 6's worst robot (10 seeds) 0.40 / 1.30 -> "
        "0.37 / 0.76 m and MR.CLAM 2's 0.86 / 1.20 -> 0.63 / 0.99 m, but without start poses MR.CLAM 4's spurious "
        "landmarks went 1 -> 12 (median of 5 seeds) and MR.CLAM 6's worst robot 0.99 -> 1.61 m (docs/fastslam.md)")
    turn_scale_bounds: tuple[float, float] = Field(
        TURN_SCALE_BOUNDS, description="... the least and largest turn scale: odometry off by more than this is not "
        "a calibration to learn")
    turn_slip: bool = Field(
        False, description="add the heading variance per radian turned that the robot announces (RobotInfo."
        "turn_slip_var, wheel slip) to the motion. Off: without ids it made MR.CLAM worse over 10 seeds (the wider "
        "heading spread lets the shared association pair a cluster's detections with a neighbouring cluster's "
        "landmark); with barcodes it helps when every start pose is given, but MCL then placed a robot 160° off in "
        "1 of 10 seeds without start poses (measured when it was chosen; git show 300b99e:docs/results-central-fastslam.md)")
    turn_gain_std: float = Field(
        0.0, ge=0.0, le=0.5, description="σ of each particle's turn gain for each robot at placement: the particle "
        "turns by gain × the odometry's turn, so particles carry hypotheses of how much a robot's odometry over- or "
        "under-counts its turns (0: off, no draw). Off by default: on MR.CLAM without barcodes (40 seeds) 0.04 with "
        "a walk of 0.002 took the worst robot's median 1.37 -> 1.19 m but its worst seed 2.33 -> 3.16 m, and its "
        "neighbours were not better (measured when it was chosen; git show 300b99e:docs/results-central-fastslam.md)")
    turn_gain_walk: float = Field(
        0.0, ge=0.0, le=0.5, description="σ per √s of motion of the turn gain's random walk (lets it follow a robot "
        "whose wheels or floor change, and keeps the particles' gains diverse after resampling)")
    reacquire: bool = Field(
        True, description="shared: a robot whose dead reckoning (its drift, conditioned on each match) exceeds the "
        "thresholds below stops associating scan by scan and is put back on the map by one rigid correction of its "
        "recent detections (central/fastslam/reacquire.py). MR.CLAM without barcodes, 80 seeds: worst robot median "
        "1.24 -> 0.64 m, seeds with a robot above 1.5 m 23 -> 2; Victoria Park and the car park unchanged (measured when it was chosen; git show 300b99e:docs/results-central-fastslam.md)")
    reacquire_heading_sd: float = Field(0.15, gt=0.0, description="... when the drift's heading σ exceeds this (rad)")
    reacquire_position_sd: float = Field(0.4, gt=0.0, description="... or its position σ exceeds this (m)")
    reacquire_window_s: float = Field(15.0, gt=0.0, description="... its detections of the last this many seconds count")
    reacquire_every_s: float = Field(0.5, gt=0.0, description="... searched for a correction at most this often (s)")
    reacquire_inlier_m: float = Field(0.25, gt=0.0, description="... a detection this close to a landmark is explained")
    reacquire_min_detections: int = Field(5, ge=1, description="... a correction must explain this many detections")
    reacquire_span_m: float = Field(1.0, ge=0.0, description="... reaching landmarks at least this far apart (m)")
    reacquire_margin: float = Field(
        3.0, ge=0.0, description="... and explain this many detections more than any distinct correction")
    reacquire_max_turn: float = Field(
        math.pi, ge=0.0, description="... turning it by at most this (rad); within that, by at most 3σ of its drift. "
        "Half a turn: the drift bounds the search. The cap was 45° (fitted on MR.CLAM 6), and a robot turned further "
        "(MR.CLAM 1's r1, 90-110° off for 200 s) never came back; with 2 m for the shift below, over 5 seeds without "
        "barcodes, worst robot against the run with barcodes: MR.CLAM 1 2.29 / 2.58 -> 1.43 / 1.72 m, MR.CLAM 2 1.07 / "
        "1.61 -> 0.82 / 1.11 m, MR.CLAM 4 0.59 / 2.97 -> 0.61 / 0.73 m, without start poses 4.33 / 4.39 -> 1.77 / "
        "2.82 m (with reacquire_confirmations 2); MR.CLAM 6 (10 seeds) 0.41 / 1.30 m against Vicon, r4 above 1.2 m in "
        "2 seeds where either change alone keeps it below 0.4 m (docs/results.md)")
    reacquire_max_shift_m: float = Field(
        8.0, ge=0.0, description="... and shifting it by at most this (m); within that, by at most 3σ of its drift "
        "plus reacquire_inlier_m (was 2 m, with the turn's cap above)")
    reacquire_confirm_sigmas: float = Field(
        1.0, ge=0.0, description="... or, failing that, a correction within this many σ of the drift that explains "
        "as many detections (one landmark in view is enough: the drift bounds the turn); 0: off")
    reacquire_confirm_max_turn: float = Field(0.2, ge=0.0, description="... turning it by at most this (rad)")
    reacquire_confirm_max_shift_m: float = Field(0.5, ge=0.0, description="... and shifting it by at most this (m)")
    reacquire_confirm_tolerance: float = Field(
        0.0, ge=0.0, description="... the confirmation takes, of the near corrections within this many detections of "
        "the best, the one nearest the dead reckoning (0: the best, the prior breaking its ties). Off by default: on "
        "MR.CLAM without barcodes 1 took the worst robot 0.56 / 1.09 -> 0.49 / 1.52 m over 80 seeds (50 better, 30 "
        "worse; 0.53 / 1.24 -> 0.51 / 1.28 m held out) and changed nothing clear on MR.CLAM Dataset 1 (measured when it was chosen; git show 300b99e:docs/results-central-fastslam.md)")
    reacquire_confirmations: int = Field(
        2, ge=1, description="... a correction the search finds is taken only once this many searches in a row, each "
        "with reacquire_min_detections new detections, agree on it (one rigid transform within the distinct bounds): "
        "a window's chance alignment is not confirmed by the next (1: at once, the default before)")
    reacquire_prior_weight: float = Field(
        0.5, ge=0.0, description="... each correction scored by its detections less this times its squared size in σ "
        "of the drift (a Gaussian prior on the correction: of two that explain about as much, the one the dead "
        "reckoning makes likelier wins; 0: every correction within the window alike)")
    reacquire_by_robots: bool = Field(
        True, description="... and a robot whose detections of other robots contradict its pose (reacquire_robots_min "
        "of them in reacquire_robots_window_s that no particle explains, of two robots at least, four in five) is "
        "counted as lost, its drift widened to the search's limits; while held, its robot detections vote in the "
        "search with the robot each saw. MR.CLAM 6 without barcodes, seeds 0-79: worst robot 0.56 / 1.09 -> "
        "0.38 / 2.92 m (64 better, 16 worse; seed 19 the one above 1.5 m), held out 0.53 / 1.24 -> 0.37 / 0.55 m; "
        "without start poses 0.49 / 1.42 -> 0.42 / 1.45 m; MR.CLAM 1 against its run with barcodes 3.43 / 4.39 -> "
        "1.82 / 4.48 m, spurious 32 -> 20; with the held window following the estimate (a later mend) 0.37 / 0.83 m, held "
        "out 0.364 / 0.548 m, without start poses 0.43 / 0.91 m (measured when it was chosen; git show 300b99e:docs/results-central-fastslam.md)")
    reacquire_robots_window_s: float = Field(10.0, gt=0.0, description="... over this many seconds")
    reacquire_robots_min: int = Field(6, ge=1, description="... this many unexplained detections of robots")
    reacquire_robots_veto: int = Field(
        0, ge=0, description="... a held robot with this many detections of other robots in its window takes no "
        "correction that brings fewer than half of them near their robots (0: off)")
    reacquire_robots_fit_min: int = ROBOTS_FIT_MIN
    reacquire_robots_fit_spread_m: float = ROBOTS_FIT_SPREAD_M
    reacquire_robots_fit_residual_m: float = ROBOTS_FIT_RESIDUAL_M
    reacquire_drift_update: bool = Field(
        True, description="... a match conditions the drift on the matched detections (a Kalman update: one landmark "
        "leaves the turn about it free) instead of starting it from zero (False, the default before). MR.CLAM without "
        "barcodes, 80 seeds: worst robot 0.55 / 1.48 m against 0.56 / 1.29, robot-median 0.35 / 0.69 against "
        "0.39 / 0.96 m, every block of ten seeds within the targets (7 of 8 before); Victoria Park, car park unchanged")
    sensor_noise_scale: float = Field(1.0, gt=0.0, description="multiplies the scan's noise covariance")
    max_batch_s: float = Field(1.0, gt=0.0, description="integrate buffered controls at least this often (s)")
    max_extrapolation_s: float = Field(
        0.2, ge=0.0, description="extend the last control to a scan stamp (or over an odometry gap) by at most this (s)")
    exist_init: float = Field(1.0, description="landmark existence score at creation")
    exist_hit: float = Field(1.0, gt=0.0, description="added to the existence score when the landmark is associated")
    exist_miss: float = Field(1.0, ge=0.0, description="a miss adds exist_miss · ln(1 − P_D·v) (v: visibility)")
    exist_min: float = Field(0.0, description="below this existence score the landmark is deleted")
    exist_max: float = Field(6.0, description="upper clamp of the existence score (a long-known landmark survives misses)")
    permanent_hits: int | None = Field(5, ge=1, description="a landmark associated this many times is never deleted (None: any may die)")
    merge_duplicates: bool = Field(True, description="delete a confirmed landmark statistically identical to one just associated")
    confirm_hits: int = Field(3, ge=1, description="a landmark appears in the published map once associated this many times")
    miss_weight: bool = Field(True, description="weight particles by (1 − P_D) per landmark in view and not detected")
    detection_probability: float | None = Field(None, gt=0.0, le=1.0, description="P_D of a landmark in view; None: the sensor's")
    max_detection_probability: float = Field(0.95, gt=0.0, lt=1.0, description="P_D is capped here (a miss never costs log 0)")
    max_obs_range: float | None = Field(None, gt=0.0, description="ignore detections farther than this (m); None: the sensor's range")
    robot_detections: bool = Field(
        True, description="weight particles by robot-to-robot detections (relative pose likelihood): a robot out of "
        "sight of landmarks stays tied to the ones it sees (MR.CLAM without barcodes, 40 seeds: worst robot median "
        "2.57 -> 1.37 m, worst 4.46 -> 2.33 m; with barcodes better too; measured when it was chosen; git show 300b99e:docs/results-central-fastslam.md)")
    robot_detection_noise_scale: float = Field(
        4.0, gt=0.0, description="multiplies the scan's noise covariance for robot-to-robot detections: on MR.CLAM "
        "their innovations against the true poses are heavy-tailed (bearing std 3.6x the scan's, median d² 0.4), and "
        "the scan's covariance let a few of them collapse the fleet's particles (1: MR.CLAM worst robot 1.66/2.50 m "
        "over 10 seeds; 2, 4, 8, 16 all 1.3-1.6 m median, 4 the best worst case)")
    workers: int | None = Field(
        1, ge=1, le=1024, description="threads of the per-particle kernels (the FastSLAM 2.0 step and the EKF "
        "updates with ids: numba's parallel loops over particles); any count gives the same results, bit for bit. "
        "None: the cores this process may run on; capped at numba's pool (NUMBA_NUM_THREADS); 1: the serial "
        "kernels. 1 by default: 2 workers were slower on a shared 2-core machine (MR.CLAM without barcodes, time per "
        "scan x1.07 at 100 particles, x1.31 at 1000; a simulated fleet with ids x0.91 and x1.13): the rest of a scan "
        "(association, resampling, the event loop) stays on one core, the kernels are a few per cent of a scan at "
        "100 particles and about a fifth at 1000, and waking the second thread for each kernel cost about what it "
        "saved (docs/results.md, issue 54)")
    compiled: bool = Field(True, description="EKF updates with known ids, control integration, pose and map mixtures and the "
                           "re-acquisition vote by the numba kernels (False: the numpy references)")
    robot_detection_max_dt: float = Field(0.1, ge=0.0, description="... only when the other robot's pose is this recent (s)")
    robot_detection_position_sd: float | None = Field(
        None, ge=0.0, description="σ (m) of the two robots' relative position that a robot detection's likelihood "
        "allows beyond the particles' own spread, propagated through the detection's Jacobian: an error of 0.5 m "
        "seen at 1.7 m is a 17° bearing innovation, which particles whose positions the fleet's resampling has "
        "collapsed explain by turning the robot (MR.CLAM seed 1: r5 turned 17° in 8 s by its detections of r2). "
        "None: 0.1 with the shared association (MR.CLAM without barcodes, 110 seeds: worst robot 0.53 / 1.48 -> "
        "0.53 / 1.24 m, seeds above 1.0 m 9 -> 5; 0.2 and 0.4 had worse tails), 0 with known ids (with barcodes "
        "0.1 was worse: 0.46 / 0.55 -> 0.53 / 0.65 m; measured when it was chosen; git show 300b99e:docs/results-central-fastslam.md)")

    @property
    def reacquire_rule(self) -> SearchRule:
        """When re-acquisition's search takes a correction (:class:`central.fastslam.reacquire.SearchRule`)."""
        from central.fastslam.reacquire import SearchRule

        return SearchRule(self.reacquire_min_detections, self.reacquire_inlier_m, self.reacquire_span_m,
                          self.reacquire_margin, compiled=self.compiled, confirm_sigmas=self.reacquire_confirm_sigmas,
                          confirm_max_turn=self.reacquire_confirm_max_turn,
                          confirm_max_shift=self.reacquire_confirm_max_shift_m,
                          prior_weight=self.reacquire_prior_weight,
                          confirm_tolerance=self.reacquire_confirm_tolerance,
                          robots_veto=self.reacquire_robots_veto if self.reacquires_by_robots else 0)

    @property
    def reacquires_by_robots(self) -> bool:
        """Whether robot detections may count a robot as lost and vote in its search (shared association only)."""
        return self.reacquire_by_robots and self.reacquire and self.association == "shared"

    @property
    def robot_detection_relative_sd(self) -> float:
        """``robot_detection_position_sd`` with None resolved: 0.1 m with the shared association, else 0."""
        if self.robot_detection_position_sd is not None:
            return self.robot_detection_position_sd
        return 0.1 if self.association == "shared" else 0.0

    @property
    def worker_count(self) -> int:
        """``workers`` with None resolved: the cores this process may run on (its CPU affinity), at least 1."""
        if self.workers is not None:
            return self.workers
        return available_cores()

    @property
    def motion_scale(self) -> float:
        """``motion_noise_scale`` with None resolved: 1."""
        return 1.0 if self.motion_noise_scale is None else self.motion_noise_scale

    @property
    def adapts_motion_noise(self) -> bool:
        """Whether each robot's odometry noise gain follows its scans (shared association only)."""
        return self.motion_noise_adapt and self.association == "shared"

    @property
    def fastslam2(self) -> bool:
        """Whether scans are folded into the proposal (``proposal``, with ``auto`` resolved)."""
        return self.proposal == "fastslam2" or (self.proposal == "auto" and self.association == "shared")

    @model_validator(mode="after")
    def _consistent(self) -> "FastSlamConfig":
        if self.new_landmark_probability < self.gate_probability:
            raise ValueError("new_landmark_probability must be at least gate_probability")
        if min(self.pose_noise_per_s + self.gate_pose_floor + self.gate_pose_growth) < 0:
            raise ValueError("pose_noise_per_s, gate_pose_floor and gate_pose_growth are non-negative standard deviations")
        if not self.exist_min < self.exist_init <= self.exist_max:
            raise ValueError("existence scores: need exist_min < exist_init <= exist_max")
        return self
