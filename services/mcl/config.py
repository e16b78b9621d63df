"""Configuration of the Monte Carlo localization core: a plain frozen model, never read from the environment
(the ``fleetslam mcl`` settings class composes it; ``fleetslam run --set`` overrides it).

Sehestedt and Schneider, "Monte Carlo Localization in Highly Symmetric Environments".
"""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from schemas.contract import CoreConfig


class MclConfig(CoreConfig):
    """The Monte Carlo localization filter: variant, sample sizes, likelihood, resetting, clusters, kidnap."""

    variant: Literal["mcl", "kld", "srl", "kld_srl", "csrl", "cluster_kld_srl"] = Field(
        "cluster_kld_srl", description="mcl, kld (Fox 2003), srl (Lenser 2000), kld_srl, csrl, cluster_kld_srl (Sehestedt and Schneider, tables 2-4)"
    )
    seed: int = Field(0, description="seed of every random draw of the filter")
    particles: int = Field(1000, ge=10, description="sample size of the fixed-size variants; initial size of the adaptive ones")
    min_particles: int = Field(100, ge=10, description="smallest sample size KLD-sampling may choose")
    max_particles: int = Field(5000, ge=10, description="largest sample size KLD-sampling may choose")
    use_signatures: bool = Field(True, description="weigh detections that carry landmark ids against their own landmark")
    init: Literal["sensor", "uniform"] = Field("sensor", description="global initialisation: from the first scan and the map, or uniform")
    kld_epsilon: float = Field(0.05, gt=0, description="KLD-sampling error bound ε (eq. 2)")
    kld_delta: float = Field(0.01, gt=0, lt=1, description="KLD-sampling probability δ; the bound uses the normal quantile z_(1-δ)")
    kld_bin_xy: float = Field(0.5, gt=0, description="KLD-sampling bin size in x and y (m)")
    kld_bin_theta: float = Field(0.17453292519943295, gt=0, description="KLD-sampling bin size in heading (rad, 10°)")
    noise_scale: float = Field(2.0, gt=0, description="the likelihood uses the sensor's standard deviations times this")
    clutter_weight: float = Field(0.05, gt=0, lt=1, description="weight of the uniform clutter floor in each observation's likelihood")
    miss_floor: float = Field(0.2, gt=0, le=1, description="smallest probability of missing a landmark predicted well inside the view")
    view_margin_range: float = Field(0.3, ge=0, description="a landmark counts as surely visible this far (m) inside the range limits")
    view_margin_bearing: float = Field(0.05, ge=0, description="... and this far (rad) inside the field of view")
    match_sigmas: float = Field(3.0, gt=0, description="gate of the best-matching landmark, in standard deviations")
    lookup_cell: float = Field(0.25, gt=0, description="cell size (m) of the grid that lists the candidate landmarks of a point")
    match_candidates: int = Field(2, ge=1, description="landmarks (nearest the point's cell) an observation is matched against")
    motion_noise_scale: float = Field(1.5, gt=0, description="the prediction samples the control noise with this times its std")
    diffusion_xy: float = Field(0.05, ge=0, description="extra position diffusion per sqrt(second) (m)")
    diffusion_theta: float = Field(0.02, ge=0, description="extra heading diffusion per sqrt(second) (rad)")
    max_batch_s: float = Field(1.0, gt=0, description="buffered odometry moves the particles at the next scan or "
                               "after this much time (s)")
    srl_threshold: float = Field(0.3, gt=0, description="P_t of sensor resetting, eq. 1, against the mean match quality")
    reset_oversample: int = Field(4, ge=1, description="sensor resetting draws this many candidate poses per sample kept")
    reset_prior: float = Field(
        0.01, gt=0, le=1, description="prior weight of a pose added from the scan (KLD-SRL), relative to a tracked particle's"
    )
    reset_draws: int = Field(8, ge=1, description="poses drawn per candidate kept; those that put one more observation on a landmark are kept first")
    history_scans: int = Field(
        10, ge=0, description="poses drawn from a scan must also explain up to this many earlier scans with detections, "
        "carried back along the odometry (services.mcl.history); 0: the scan alone")
    history_turn: float = Field(
        1.0, ge=0, description="... among those after which the robot has turned at most this far in all (rad; dead "
        "reckoning drifts in turns)")
    reset_jitter_xy: float = Field(0.1, ge=0, description="std (m) added to poses drawn from a scan")
    reset_jitter_theta: float = Field(0.03, ge=0, description="std (rad) added to headings drawn from a scan")
    pair_sigmas: float = Field(3.0, gt=0, description="two observations match a landmark pair when distances agree within this many std")
    cluster_cell_xy: float = Field(2.0, gt=0, description="cluster grid cell size in x and y (m)")
    cluster_cell_theta: float = Field(0.7853981633974483, gt=0, description="cluster grid cell size in heading (rad, 45°)")
    cluster_merge_xy: float = Field(2.0, ge=0, description="adjacent cells merge when their means are this close (m)")
    cluster_merge_theta: float = Field(0.7853981633974483, ge=0, description="... and their mean headings this close (rad)")
    cluster_prune: float = Field(1e-4, ge=0, lt=1, description="particles lighter than this times the heaviest join no cluster")
    cluster_min_weight: float = Field(0.001, ge=0, lt=1, description="a cluster is significant when it holds this share of the weight")
    cluster_min_quality: float = Field(0.02, ge=0, lt=1, description="... and its particles' mean match quality is at least this")
    max_hypotheses: int = Field(16, ge=1, description="most significant clusters kept (heaviest first)")
    cluster_memory: float = Field(
        0.9, ge=0, le=1, description="share of a cluster's log-weight carried to the next step (0: all clusters equal after "
        "resampling, as eq. 7; 1: full Bayesian weight)"
    )
    localized_weight: float = Field(0.9, gt=0, le=1, description="localized when one hypothesis holds this share of the weight")
    localized_std_xy: float = Field(0.5, gt=0, description="... its position std is below this (m)")
    localized_std_theta: float = Field(0.2, gt=0, description="... its heading std is below this (rad)")
    localized_scans: int = Field(3, ge=1, description="... for this many scans in a row")
    localized_baseline_m: float = Field(
        0.3, ge=0, description="with signatures, after global localization: localized only once the hypothesis has "
        "explained (within the χ²(2) 0.999 gate) detections of two landmarks this far apart by id, and a signed detection "
        "it contradicts starts global localization again. Resampling can collapse the particles on one arc of the "
        "circle a single landmark allows, which passes the tests above (MR.CLAM: a robot that sees one landmark for "
        "30 s); 0: off")
    map_min_landmarks: int = Field(3, ge=1, description="global localization starts once the map holds this many "
                                   "landmarks with ids (signatures)")
    map_min_landmarks_unsigned: int = Field(
        6, ge=1, description="... and this many without ids: a few landmarks without ids fit more than one pose "
        "(MR.CLAM's clusters nearly repeat under a half turn; on three to five of them MCL placed robots 46-155 deg off)")
    kidnap_quality: float = Field(0.05, gt=0, lt=1, description="the expected match quality below which the robot may be lost")
    kidnap_scans: int = Field(3, ge=1, description="lost after this many scans in a row below kidnap_quality")
    kidnap_recovery: bool = Field(True, description="when lost, start global localization again from the scan")
    kidnap_min_observations: int = Field(3, ge=1, description="scans with fewer observations do not count towards being lost")
    kidnap_probe: int = Field(200, ge=1, description="poses drawn from the scan to confirm that the robot is lost")
    kidnap_ratio: float = Field(3.0, ge=1, description="lost only if a drawn pose's match quality beats the best particle's by this factor")
    map_margin: float = Field(2.0, ge=0, description="uniform samples lie within the map's bounding box grown by this (m)")
    converge_xy: float = Field(0.5, gt=0, description="evaluation: converged when localized within this distance of the truth (m)")
    converge_theta: float = Field(0.2, gt=0, description="... and this heading error (rad)")
    compiled: bool = Field(True, description="scan likelihood, cluster merging and sensor resetting by the numba kernels (False: the numpy "
                           "and scipy references)")
    chunk_particles: int = Field(400, ge=1, description="particles weighed at a time (keeps the work in the processor's cache)")

    def map_min(self, signed: bool) -> int:
        """The landmarks a map needs before global localization starts on it: ``map_min_landmarks`` when its ids are
        the scans' (signatures), ``map_min_landmarks_unsigned`` otherwise."""
        return self.map_min_landmarks if signed else self.map_min_landmarks_unsigned
