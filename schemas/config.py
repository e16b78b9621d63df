"""Settings of every process: pydantic-settings classes read from ``FLEETSLAM_*``
environment variables (docker compose sets them) and overridden by CLI flags.

Each process has one class. :func:`add_settings_arguments` turns a class into
argparse flags (``--field-name``, help from the field description) and
:func:`settings_from_args` builds the settings with the flags that were given
taking precedence over the environment, which takes precedence over defaults.
"""

from __future__ import annotations

import argparse
import types
import typing
from typing import Any, Literal, TypeVar

from pydantic import Field
from pydantic_settings import BaseSettings, SettingsConfigDict

S = TypeVar("S", bound=BaseSettings)


class FleetSettings(BaseSettings):
    """Settings every process shares: key prefix, how to reach the router, stats period."""

    model_config = SettingsConfigDict(env_prefix="FLEETSLAM_", extra="ignore", validate_default=True)

    prefix: str = Field("fleet", pattern=r"^[A-Za-z0-9_-]+$", description="key-expression prefix of every key")
    zenoh_connect: str = Field("tcp/127.0.0.1:7447", description="router endpoint(s) to connect to, comma-separated")
    connect_timeout_s: float = Field(10.0, gt=0, description="how long to wait for the router before giving up (s)")
    zenoh_user: str | None = Field(None, description="user name for router authentication")
    zenoh_password: str | None = Field(None, description="password for router authentication")
    zenoh_password_file: str | None = Field(None, description="file holding the password (docker secret)")
    tls_root_ca: str | None = Field(None, description="CA certificate (PEM) to verify the router; enables tls/ endpoints")
    tls_cert: str | None = Field(None, description="client certificate (PEM) for mutual TLS")
    tls_key: str | None = Field(None, description="client private key (PEM) for mutual TLS")
    publisher_cache: int = Field(
        0, ge=0, description="samples an advanced publisher keeps for recovery by late or cut-off subscribers (0: plain publisher)"
    )
    subscriber_recovery: bool = Field(
        False, description="subscribe robot streams through an advanced subscriber that recovers samples missed "
        "during a link cut or router restart from the publishers' caches (needs publisher_cache > 0 on the robots)"
    )
    stats_period_s: float = Field(1.0, gt=0, description="period of the stats publication (s)")
    log_level: Literal["DEBUG", "INFO", "WARNING", "ERROR"] = Field("INFO", description="log level")


class RouterSettings(FleetSettings):
    """``fleetslam router``: the Zenoh router every other process connects to."""

    listen: str = Field("tcp/0.0.0.0:7447", description="endpoint(s) to listen on, comma-separated")
    router_config: str | None = Field(
        None, description="JSON5 file merged into the router config (access control, users, TLS)"
    )


class RobotSettings(FleetSettings):
    """``fleetslam robot``: a simulated robot, or a robot that replays a data set."""

    robot_id: str | None = Field(
        None, pattern=r"^[A-Za-z0-9_-]{1,64}$", description="robot id (default: r1, or the replayed robot's id)",
        json_schema_extra={"cli": "--id"},
    )
    world: str = Field("arena", description="simulated world: random, paper000, grid196, cross, arena, office")
    trajectory: Literal["auto", "circle", "waypoints", "random_walk"] = Field(
        "auto", description="trajectory (auto: the world's own)"
    )
    seed: int = Field(0, description="seed of every random draw of this robot")
    rate: float = Field(10.0, gt=0, description="scan rate (Hz); odometry runs at odom_factor times this")
    odom_factor: int = Field(1, ge=1, description="odometry messages per scan")
    speedup: float = Field(1.0, gt=0, description="run this many times faster than real time")
    duration: float = Field(60.0, gt=0, description="seconds of robot time to run (sim), or of data (replay)")
    start_delay: float = Field(0.5, ge=0, description="wall seconds to wait after declaring, so subscribers can match")
    unknown_start: bool = Field(False, description="announce no start pose (to be found by MCL)")
    publish_ids: bool = Field(True, description="publish true landmark ids with each scan")
    publish_truth: bool = Field(True, description="publish ground truth (and the world map)")
    detection_probability: float | None = Field(None, ge=0, le=1, description="override the world's detection probability")
    clutter_rate: float | None = Field(None, ge=0, description="override the world's clutter (false detections per scan)")
    replay: str | None = Field(None, description="replay a data set instead: mrclam:PATH:N, victoria-park:PATH, car-park:PATH")
    info_period_s: float = Field(1.0, gt=0, description="period of the RobotInfo re-publication (s)")


class MonitorSettings(FleetSettings):
    """``fleetslam monitor``: a live console of everything under the prefix."""

    duration: float | None = Field(None, gt=0, description="stop after this many seconds (default: until Ctrl-C)")
    refresh_hz: float = Field(2.0, gt=0, description="console refresh rate")
    rate_window_s: float = Field(2.0, gt=0, description="window over which message rates are measured (s)")
    plain: bool = Field(False, description="print plain lines instead of a live table (for logs)")
    json_out: str | None = Field(None, description="write the final counters to this JSON file")


class DemoSettings(FleetSettings):
    """``fleetslam demo``: a router, robots, the monitor and every service, as separate processes."""

    duration: float = Field(20.0, gt=0, description="wall seconds to run")
    world: str = Field("arena", description="simulated world")
    robots: int = Field(3, ge=1, le=50, description="number of simulated robots")
    unknown_start_robots: int = Field(1, ge=0, le=10, description="more robots that announce no start pose (found by MCL)")
    seed: int = Field(0, description="base seed (robot i uses seed + i)")
    speedup: float = Field(1.0, gt=0, description="robot speed-up over real time")
    rate: float = Field(10.0, gt=0, description="scan rate of every robot (Hz)")
    out: str = Field("reports/demo", description="folder for logs and results")
    port: int = Field(7447, ge=1, le=65535, description="router port on 127.0.0.1")


def _flag_type(annotation: Any) -> tuple[Any, bool]:
    """(argparse type, is_bool) of a settings field annotation."""
    origin = typing.get_origin(annotation)
    if origin in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(annotation) if a is not type(None)]
        return _flag_type(args[0])
    if origin is Literal:
        return str, False
    if annotation is bool:
        return None, True
    if annotation in (int, float, str):
        return annotation, False
    return str, False


def add_settings_arguments(parser: argparse.ArgumentParser, settings_cls: type[BaseSettings]) -> None:
    """Add one ``--flag`` per settings field; defaults stay None so the environment still applies."""
    group = parser.add_argument_group(
        "settings", f"each flag overrides the environment variable {settings_cls.model_config.get('env_prefix', '')}NAME"
    )
    for name, field in settings_cls.model_fields.items():
        extra = field.json_schema_extra if isinstance(field.json_schema_extra, dict) else {}
        flags = [f"--{name.replace('_', '-')}"]
        if extra.get("cli"):
            flags.insert(0, extra["cli"])
        arg_type, is_bool = _flag_type(field.annotation)
        default_text = "" if field.is_required() else f" (default: {field.get_default(call_default_factory=True)})"
        env_name = f"{settings_cls.model_config.get('env_prefix', '')}{name.upper()}"
        help_text = f"{field.description or name}{default_text} [{env_name}]"
        choices = None
        if typing.get_origin(field.annotation) is Literal:
            choices = list(typing.get_args(field.annotation))
        if is_bool:
            group.add_argument(*flags, dest=name, default=None, action=argparse.BooleanOptionalAction, help=help_text)
        else:
            group.add_argument(*flags, dest=name, default=None, type=arg_type, choices=choices, help=help_text)


def settings_from_args(settings_cls: type[S], args: argparse.Namespace, **overrides: Any) -> S:
    """Build settings: CLI flags that were given > ``overrides`` > environment > defaults."""
    given = {name: getattr(args, name) for name in settings_cls.model_fields if getattr(args, name, None) is not None}
    return settings_cls(**{**overrides, **given})



class MclFilterSettings(BaseSettings):
    """The Monte Carlo localisation filter (paper 004): variant, sample sizes, likelihood, resetting, clusters, kidnap."""

    model_config = SettingsConfigDict(env_prefix="FLEETSLAM_", extra="ignore", validate_default=True)

    variant: Literal["mcl", "kld", "srl", "kld_srl", "csrl", "cluster_kld_srl"] = Field(
        "cluster_kld_srl", description="mcl, kld (Fox 2003), srl (Lenser 2000), kld_srl, csrl, cluster_kld_srl (paper 004 tables 2-4)"
    )
    seed: int = Field(0, description="seed of every random draw of the filter")
    particles: int = Field(1000, ge=10, description="sample size of the fixed-size variants; initial size of the adaptive ones")
    min_particles: int = Field(100, ge=10, description="smallest sample size KLD-sampling may choose")
    max_particles: int = Field(5000, ge=10, description="largest sample size KLD-sampling may choose")
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
    srl_threshold: float = Field(0.3, gt=0, description="P_t of sensor resetting, eq. 1, against the mean match quality")
    reset_oversample: int = Field(4, ge=1, description="sensor resetting draws this many candidate poses per sample kept")
    reset_prior: float = Field(
        0.01, gt=0, le=1, description="prior weight of a pose added from the scan (KLD-SRL), relative to a tracked particle's"
    )
    reset_draws: int = Field(8, ge=1, description="poses drawn per candidate kept; those that put one more observation on a landmark are kept first")
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
    localized_weight: float = Field(0.9, gt=0, le=1, description="localised when one hypothesis holds this share of the weight")
    localized_std_xy: float = Field(0.5, gt=0, description="... its position std is below this (m)")
    localized_std_theta: float = Field(0.2, gt=0, description="... its heading std is below this (rad)")
    localized_scans: int = Field(3, ge=1, description="... for this many scans in a row")
    kidnap_quality: float = Field(0.05, gt=0, lt=1, description="the expected match quality below which the robot may be lost")
    kidnap_scans: int = Field(3, ge=1, description="lost after this many scans in a row below kidnap_quality")
    kidnap_recovery: bool = Field(True, description="when lost, start global localisation again from the scan")
    kidnap_min_observations: int = Field(3, ge=1, description="scans with fewer observations do not count towards being lost")
    kidnap_probe: int = Field(200, ge=1, description="poses drawn from the scan to confirm that the robot is lost")
    kidnap_ratio: float = Field(3.0, ge=1, description="lost only if a drawn pose's match quality beats the best particle's by this factor")
    map_margin: float = Field(2.0, ge=0, description="uniform samples lie within the map's bounding box grown by this (m)")
    converge_xy: float = Field(0.5, gt=0, description="evaluation: converged when localised within this distance of the truth (m)")
    converge_theta: float = Field(0.2, gt=0, description="... and this heading error (rad)")
    chunk_particles: int = Field(400, ge=1, description="particles weighed at a time (keeps the work in the processor's cache)")


class MclSettings(MclFilterSettings, FleetSettings):
    """``fleetslam mcl``: localise robots against a map; publish hypotheses; answer one-shot localisation queries."""

    source: str = Field(
        "truth", pattern=r"^(central|dslam|truth|file:.+)$",
        description="map source: central (Estimate), dslam (MapEstimate), truth (WorldTruth) or file:PATH (.npy/.txt, (L,2))",
    )
    all_robots: bool = Field(False, description="localise every robot, not only those that announce no start pose")
    publish_every: int = Field(1, ge=1, description="publish a robot's MclPose every this many scans")
    map_period_s: float = Field(1.0, ge=0, description="take a new map from the source at most this often (s)")
    localize_particles: int = Field(2000, ge=10, description="sample size of a one-shot localisation query")


class DslamFilterSettings(BaseSettings):
    """The D-SLAM core (paper 003): association, feature lists, recovery, localisation."""

    model_config = SettingsConfigDict(env_prefix="FLEETSLAM_", extra="ignore", validate_default=True)

    association: str = Field(
        "known", pattern=r"^(known|nn|greedy|ihgr|exact|jcbb|auto)$",
        description="known (true ids from the scans) or a method of the association service: nn, greedy, ihgr, exact, jcbb, auto",
    )
    gate_probability: float = Field(0.99, gt=0, lt=1, description="chi-square gate of the association")
    new_feature_gate_probability: float = Field(0.9999, gt=0, lt=1, description="a measurement starts a feature only outside this gate of every landmark")
    new_feature_density: float = Field(1e-3, gt=0, description="expected new features per m·rad of measurement space")
    candidate_margin: float = Field(1.0, ge=0, description="landmarks up to max range + this (m) are association candidates")
    confirm_hits: int = Field(2, ge=1, description="sightings before a tentative feature enters the map (association methods; known ids map at once)")
    tentative_misses: int = Field(3, ge=1, description="scans in view without a sighting before a tentative feature is dropped")
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
    column_cache: int = Field(64, ge=1, description="covariance columns kept to warm-start the next solves (landmarks)")
    relocalise_after: int = Field(
        10, ge=1, description="scans in a row whose observation estimate contradicts the prediction before the robot is relocalised"
    )
    ci_criterion: Literal["trace", "det"] = Field("trace", description="covariance intersection minimises the trace or the determinant")
    marginals_limit: int = Field(3000, ge=0, description="maps up to this many landmarks report every marginal covariance exactly")


class DslamSettings(DslamFilterSettings, FleetSettings):
    """``fleetslam dslam``: one D-SLAM map fed by every robot; association through the queryable."""

    assoc_timeout_s: float = Field(0.5, gt=0, description="how long to wait for the association queryable (s)")
    assoc_retry_s: float = Field(5.0, ge=0, description="after a failed query, associate in-process this long before asking again (s)")
    map_period_s: float = Field(1.0, gt=0, description="period of the map publication (s)")
    waiting_messages: int = Field(2000, ge=1, description="messages of a robot kept while its RobotInfo is awaited")


class RunSettings(BaseSettings):
    """``fleetslam run``: feed a data set straight into an estimator (no Zenoh) and score it."""

    model_config = SettingsConfigDict(env_prefix="FLEETSLAM_", extra="ignore", validate_default=True)

    dataset: str = Field(
        "sim:arena", description="mrclam:PATH[:N], victoria-park:PATH, car-park:PATH or sim:WORLD "
        "(a relative PATH is also looked for under FLEETSLAM_DATA)",
    )
    estimator: str = Field("odometry", description="estimator name (services/estimator.py ESTIMATORS)")
    association: str = Field("known", description="data association: known (true ids) or a method name")
    particles: int = Field(100, ge=1, description="particles of particle-filter estimators")
    seed: int = Field(0, description="seed of every random draw (estimator, and the simulator for sim:)")
    robot_ids: str | None = Field(
        None, description="comma-separated robot ids to use (default: all)", json_schema_extra={"cli": "--robots"}
    )
    duration: float | None = Field(None, gt=0, description="seconds of data from the start (default: all)")
    variant: str | None = Field(None, description="estimator variant")
    estimator_settings: str | None = Field(
        None, description="the estimator's own settings, comma-separated NAME=VALUE (e.g. max_obs_range=40 for "
        "fastslam, confirm_hits=3 for dslam); unknown names are refused", json_schema_extra={"cli": "--set"},
    )
    sim_robots: int = Field(3, ge=1, le=50, description="robots simulated for sim:WORLD when --robots is not given")
    sim_rate: float = Field(10.0, gt=0, description="scan rate of simulated robots (Hz)")
    sample_period_s: float = Field(0.2, gt=0, description="estimated poses are sampled this often in data time (s)")
    map_cutoff_m: float = Field(1.0, gt=0, description="farther estimated <-> true landmark pairs are not matches (m)")
    rpe_delta_s: float = Field(1.0, gt=0, description="time step of the relative pose error (s)")
    out: str | None = Field(None, description="write a report folder here (metrics.json, TUM trajectories, plots)")
    json_out: str | None = Field(None, description="write the results JSON to this file", json_schema_extra={"cli": "--json"})
    progress: bool = Field(True, description="show a progress bar on the terminal")
    log_level: Literal["DEBUG", "INFO", "WARNING", "ERROR"] = Field("INFO", description="log level")


class EvaluateSettings(FleetSettings):
    """``fleetslam evaluate``: compare every live estimate with the truth; publish stats; write a report on exit."""

    out: str = Field("reports/evaluate", description="report folder written on exit")
    duration: float | None = Field(None, gt=0, description="stop after this many seconds (default: until SIGINT/SIGTERM)")
    map_cutoff_m: float = Field(1.0, gt=0, description="farther estimated <-> true landmark pairs are not matches (m)")
    rpe_delta_s: float = Field(1.0, gt=0, description="time step of the relative pose error (s)")
    max_gap_s: float = Field(1.0, gt=0, description="truth is not interpolated across gaps longer than this (s)")
    truth_offset_x: float = Field(0.0, description="body-frame x (m) of the point the truth positions refer to (GPS antenna)")
    truth_offset_y: float = Field(0.0, description="body-frame y (m) of that point")
    max_samples: int = Field(200000, ge=100, description="most samples kept per trajectory (older ones are thinned)")


class AssocSettings(FleetSettings):
    """``fleetslam assoc``: the data-association queryable on ``{prefix}/assoc/{method}``."""

    methods: str = Field(
        "nn,greedy,ihgr,exact,jcbb,auto", pattern=r"^(nn|greedy|ihgr|exact|jcbb|auto)(,(nn|greedy|ihgr|exact|jcbb|auto))*$",
        description="methods to serve, comma-separated (one queryable each)",
    )
    complete: bool = Field(True, description="declare the queryables complete, so a BEST_MATCHING query reaches one instance")
    max_measurements: int = Field(2000, ge=1, description="larger requests are refused (measurements)")
    max_landmarks: int = Field(5000, ge=1, description="larger requests are refused (landmarks)")
    max_jcbb_nodes: int = Field(20_000, ge=1, description="cap on a request's JCBB search budget (keeps one query short)")
    duration: float | None = Field(None, gt=0, description="stop after this many seconds (default: until SIGINT/SIGTERM)")


class CentralSettings(FleetSettings):
    """``fleetslam central``: the central multi-robot FastSLAM service (every robot in one filter)."""

    association: Literal["known", "nn", "mht"] = Field("nn", description="data association: known (scan ids), nn or mht")
    particles: int = Field(100, ge=1, le=100000, description="particles of the filter")
    seed: int = Field(0, description="seed of every random draw of the filter")
    proposal: Literal["fastslam1", "fastslam2"] = Field("fastslam1", description="FastSLAM 1.0 or 2.0 proposal")
    estimate_rate_hz: float = Field(2.0, gt=0, le=100, description="rate of the estimate publication on {prefix}/central/estimate")
    reorder_window_s: float = Field(0.1, ge=0, le=10, description="longest wall time a message waits for other robots' "
                                    "streams so that robots are processed in time order (0: as they come)")
    waiting_messages: int = Field(2000, ge=1, description="messages of a robot kept while its RobotInfo or its placement by MCL is awaited")
    robot_detections: bool = Field(False, description="weight particles by robot-to-robot detections")
    late_join: Literal["start_pose", "wait"] = Field(
        "start_pose", description="a robot whose first odometry was missed: keep its announced start pose, "
        "or wait for MCL to place it")
    filter_options: str | None = Field(None, description="JSON object of extra FastSLAM settings (central/fastslam/config.py)")
    duration: float | None = Field(None, gt=0, description="stop after this many seconds (default: until SIGINT/SIGTERM)")
