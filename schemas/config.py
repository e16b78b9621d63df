"""Settings of every process: pydantic-settings classes read from ``FLEETSLAM_*``
environment variables (docker compose sets them) and overridden by CLI flags.

Each process has one class, and it is the only thing that reads the
environment. A service whose core has a configuration (FastSLAM, D-SLAM, MCL)
inherits that plain frozen model's fields, so each knob is declared once, in
the core's ``config.py``, and its flag stays flat (``--particles``);
:meth:`ProcessSettings.core` hands the core its configuration.
:func:`add_settings_arguments` turns a class into argparse flags (``--field-name``,
help from the field description, choices listed) and :func:`settings_from_args`
builds the settings with the flags that were given taking precedence over the
environment, which takes precedence over defaults; a bad value, from a flag
or from the environment, is one :class:`SettingsError` line naming it.
"""

from __future__ import annotations

import argparse
import json
import types
import typing
from typing import Any, Literal, TypeVar

from pydantic import BaseModel, Field, ValidationError, field_validator
from pydantic_settings import BaseSettings, SettingsConfigDict, SettingsError as EnvironmentParseError

from central.fastslam.config import FastSlamConfig
from schemas.contract import C, SettingsError, describe_validation_error, resolve_association
from services.dslam.config import DslamConfig
from services.mcl.config import MclConfig
from services.viz.config import VizConfig

S = TypeVar("S", bound=BaseSettings)
ENV_PREFIX = "FLEETSLAM_"
WORLDS = Literal["random", "paper000", "grid196", "cross", "arena", "office"]
ESTIMATORS = Literal["odometry", "ekf", "fastslam", "dslam", "mcl"]
ASSOCIATIONS = Literal["known", "unknown", "shared", "nn", "mht", "greedy", "ihgr", "exact", "jcbb", "auto"]


class ProcessSettings(BaseSettings):
    """Base of every process's settings: read from ``FLEETSLAM_*``, never frozen, unknown variables ignored."""

    model_config = SettingsConfigDict(env_prefix=ENV_PREFIX, extra="ignore", validate_default=True, frozen=False)

    def core(self, config_cls: type[C]) -> C:
        """The core configuration ``config_cls`` made of this process's settings of the same names."""
        return config_cls(**self.model_dump(include=set(config_cls.model_fields)))


class FleetSettings(ProcessSettings):
    """Settings every process shares: key prefix, how to reach the router, stats period."""

    prefix: str = Field("fleet", pattern=r"^[A-Za-z0-9_-]+$", description="key-expression prefix of every key")
    zenoh_connect: str = Field("tcp/127.0.0.1:7447", description="router endpoint(s) to connect to, comma-separated")
    connect_timeout_s: float = Field(10.0, gt=0, description="how long to wait for the router before giving up (s)")
    zenoh_user: str | None = Field(None, description="user name for router authentication")
    zenoh_password: str | None = Field(None, description="password for router authentication")
    zenoh_password_file: str | None = Field(None, description="file holding the password (docker secret)")
    tls_root_ca: str | None = Field(None, description="CA certificate (PEM) to verify the router; enables tls/ endpoints")
    tls_cert: str | None = Field(None, description="client certificate (PEM) for mutual TLS")
    tls_key: str | None = Field(None, description="client private key (PEM) for mutual TLS")
    publisher_cache: int | None = Field(
        None, ge=0, description="samples each advanced publisher keeps for receivers that were cut off, restarted or "
        "late (default: the stream's rate times outage_budget_s; 0: a plain publisher, nothing to recover)"
    )
    outage_budget_s: float = Field(
        60.0, gt=0, description="longest outage (link cut, router or service restart) that loses nothing: the "
        "publishers' caches hold this many wall seconds of their streams (s)")
    heartbeat_period_s: float = Field(
        1.0, gt=0, le=60, description="period of the advanced publishers' heartbeats (each sends its stream's last "
        "sequence number, so that a receiver learns of samples it lost when no sample follows them: a lost tail). "
        "Default 1 s: while a robot streams, its samples carry the sequence numbers anyway, and each heartbeat is a "
        "message of its own on every link (mostly a TCP segment and an acknowledgement of its own): the heartbeats "
        "of a robot's odometry and scans cost 370 B/s on its site's link at 0.5 s, 200 B/s at 1 s "
        "(benchmarks/bandwidth.py); a lost tail is still known within 1 s, and a robot stopped by a signal, which "
        "keeps its publishers 1 s, still sends one")
    info_max_period_s: float = Field(
        30.0, gt=0, description="a robot's RobotInfo is published again after info_period_s, then after twice as "
        "long each time, up to this period (s); a new RobotInfo starts again from info_period_s. Default 30 s: "
        "services ask a robot for its RobotInfo (a queryable that always answers) when its liveliness token "
        "appears and while its messages come unannounced, so the re-publication is only a fallback, and every "
        "second it cost 680 B/s per robot on its site's link (600-byte messages; benchmarks/bandwidth.py); a value "
        "equal to info_period_s publishes it every period, as before")
    subscriber_recovery: bool = Field(
        True, description="subscribe robot streams through an advanced subscriber that fetches what it missed (late "
        "start, link cut, router restart, its own restart) from the publishers' caches; heartbeats tell it of a lost tail"
    )
    stats_period_s: float = Field(1.0, gt=0, description="period of the stats publication (s)")
    info_timeout_s: float = Field(2.0, gt=0, description="how long a query for a robot's RobotInfo waits for its answer, "
                                  "and how long before a robot still unannounced is asked again (s)")
    reorder_window_s: float = Field(0.1, ge=0, le=10, description="longest wall time a robot message waits for the "
                                    "other streams (the robot's own, other robots') so that events are handled in time "
                                    "order, also when a link cut or restart recovers one stream later (0: as they come)")
    partition_wait_s: float = Field(0.0, ge=0, le=600, description="longest wall time the fleet's messages wait "
                                    "for a robot that went silent or whose session token went away (its site's link "
                                    "cut, its router restarting): its messages, recovered from its caches when it is "
                                    "back, are then still handled in stamp order; a robot that ends its run before the "
                                    "others holds them back this long. Default 0: a silent robot is waited for "
                                    "reorder_window_s, one whose token went not at all (the others go on)")
    join_wait_s: float = Field(1.0, ge=0, le=30, description="longest wall time the fleet's messages wait for a robot "
                               "that has announced itself (session token) and sent nothing yet, so that robots starting "
                               "a moment apart are still handled in time order")
    waiting_mb: float = Field(64.0, gt=0, description="megabytes of a robot's messages kept while it waits to join "
                              "(for its RobotInfo, or for a pose from MCL); the oldest go, counted, past this")
    unannounced_mb: float = Field(8.0, gt=0, description="megabytes of messages kept, all robot ids together, for ids "
                                  "that no session holds yet (no session liveliness token); the oldest go, counted, past this")
    unannounced_s: float = Field(30.0, gt=0, description="how long messages of a robot id that no session holds wait "
                                 "for one to declare its token before they go, counted (s)")
    max_stamp_jump_s: float = Field(3600.0, gt=0, description="largest forward jump of a robot stream's stamp between "
                                    "two messages; a message further ahead is refused as stamp_jump (s)")
    dt_tolerance_s: float = Field(0.1, ge=0, description="how far an odometry dt may differ from the time between its "
                                  "stamp and the previous odometry's (plus 5 percent) before it is refused as dt_mismatch (s)")
    max_scan_kb: int = Field(1024, gt=0, description="largest scan payload taken; a larger one is refused as oversize "
                             "before it is decoded (KiB)")
    max_message_kb: int = Field(64, gt=0, description="largest odometry or RobotInfo payload taken; a larger one is "
                                "refused as oversize before it is decoded (KiB)")
    lane_mb: float = Field(32.0, gt=0, description="megabytes of received messages waiting per (robot, publishing "
                           "session) lane; a lane that sends faster than the service handles is refused past this "
                           "(rate_limited), and lanes are served in turn, so one robot's flood cannot starve the others")
    queue_mb: float = Field(96.0, gt=0, description="megabytes of received messages waiting, every lane together; "
                            "refused past this (queue_full)")
    log_level: Literal["DEBUG", "INFO", "WARNING", "ERROR"] = Field("INFO", description="log level")


class RouterSettings(FleetSettings):
    """``fleetslam router``: the Zenoh router every other process connects to."""

    listen: str = Field("tcp/0.0.0.0:7447", description="endpoint(s) to listen on, comma-separated")
    connect_routers: str | None = Field(
        None, description="other routers of the fleet to connect to, comma-separated (tcp/HOST:7447): the routers form "
        "a mesh, a client of any reaches every other; secured, every router needs the same secrets folder and "
        "mutual TLS (tls_dir, its certificate named 'router'): routers know each other by their certificates",
        json_schema_extra={"cli": "--connect"})
    router_config: str | None = Field(
        None, description="JSON5 file merged into the router config (access control, users, TLS); without it or "
        "secrets_dir the router is open: any process that reaches it reads and writes everything"
    )
    secrets_dir: str | None = Field(
        None, description="run secured: make (first start) or reuse one random password per user in this folder, the "
        "user dictionary and the access control (deny by default: each robot writes only its own keys, each service "
        "only its own root, only the user 'world' the world map); a client logs in with FLEETSLAM_ZENOH_USER=USER "
        "and FLEETSLAM_ZENOH_PASSWORD_FILE=DIR/USER.password"
    )
    robot_users: str = Field("r1,r2,r3,r4,r5", pattern=r"^[A-Za-z0-9_-]+(,[A-Za-z0-9_-]+)*$",
                             description="with secrets_dir: the robot ids given a user, comma-separated")
    service_users: str = Field(
        "central,dslam,assoc,mcl,evaluate=eval,monitor,viz,record", pattern=r"^[A-Za-z0-9_=+-]+(,[A-Za-z0-9_=+-]+)*$",
        description="with secrets_dir: the services given a user, comma-separated; NAME=ROOT+ROOT when the keys it "
        "writes ({prefix}/ROOT/**) are not its name's")
    router_timestamps: bool = Field(
        False, description="stamp every sample that has no timestamp with the router's clock (Zenoh's "
        "timestamping). Default off: nothing in fleetslam reads Zenoh timestamps (messages carry their own stamp; "
        "fleetslam record then stores its reception time as publish time), and the first router a sample crosses "
        "adds 27 bytes to it on every link after: 520-550 B/s per robot at 10 Hz on its site's link")
    link_compression: bool = Field(
        True, description="offer lz4 compression of the batches on this router's links (Zenoh's transport "
        "compression): a link is compressed when both ends offer it, so router-to-router links (sites to depot) are "
        "and links to clients are not (they do not offer it). Default on: on a site's link the robots' odometry "
        "shrinks by 14 percent and their scans by 19 percent (more when messages share a batch), about 700 B/s per robot, for "
        "about 4 µs of lz4 per batch; a batch that would not shrink is sent as it is")
    tls_dir: str | None = Field(
        None, description="with secrets_dir: mutual TLS too (listen on tls/...): the folder of ca.pem, router.pem and "
        "router-key.pem (deploy/make-certs.sh); a client then needs a certificate of that CA whose common name is "
        "its user, as well as its password")


class RobotSettings(FleetSettings):
    """``fleetslam robot``: a simulated robot, or a robot that replays a data set."""

    robot_id: str | None = Field(
        None, pattern=r"^[A-Za-z0-9_-]{1,64}$", description="robot id (default: r1, or the replayed robot's id)",
        json_schema_extra={"cli": "--id"},
    )
    world: WORLDS = Field("arena", description="simulated world")
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
    fleet: str = Field("", pattern=r"^([A-Za-z0-9_-]{1,64}(,[A-Za-z0-9_-]{1,64})*)?$",
                       description="comma-separated ids of the simulated robots this robot drives among (each started "
                       "with the same world and seed): it detects them, as they detect it, and MCL uses those "
                       "detections to place robots without a start pose (default: none, it sees no robot)")
    publish_ids: bool = Field(True, description="publish true landmark ids with each scan")
    publish_truth: bool = Field(True, description="publish ground truth (and the world map)")
    publish_world: bool = Field(True, description="with publish_truth: publish the world's true map on "
                                "{prefix}/world/truth too (off where fleetslam world publishes it: a secured router lets "
                                "only the user 'world' write it)")
    detection_probability: float | None = Field(None, ge=0, le=1, description="override the world's detection probability")
    clutter_rate: float | None = Field(None, ge=0, description="override the world's clutter (false detections per scan)")
    replay: str | None = Field(None, description="replay a data set instead: mrclam:PATH:N, victoria-park:PATH, car-park:PATH")
    info_period_s: float = Field(1.0, gt=0, description="first period of the RobotInfo re-publication (s; then "
                                 "doubled each time up to info_max_period_s)")
    publish_together: bool = Field(
        True, description="publish the messages of one instant (a scan and the odometry that ends with it) back to "
        "back, both encoded before the first is sent. Default on: they then share a Zenoh batch, a packet and its "
        "acknowledgement on the links more often (each packet costs 132 bytes of Ethernet, IP and TCP headers and "
        "acknowledgement): on a site's link 64 percent of the scans share one with their odometry instead of 27 percent, about "
        "800 B/s less per robot (benchmarks/bandwidth.py); the odometry waits for the scan's encoding (0.1 ms)")
    linger_s: float = Field(2.0, ge=0, description="wall seconds the robot keeps its publishers (their caches and "
                            "heartbeats) after its last message, so a receiver cut off just before can recover the tail")


class SwarmSettings(FleetSettings):
    """``fleetslam swarm``: many simulated robots in one process, each on its own keys with its own token (load tests)."""

    robots: int = Field(10, ge=1, le=5000, description="simulated robots")
    id_prefix: str = Field("s", pattern=r"^[A-Za-z]$", description="one letter: the robots are PREFIX1..PREFIXN, and "
                           "robot PREFIXK draws from the simulator's streams of robot K, as fleetslam robot --id "
                           "PREFIXK does (--no-detect-robots: the same data)")
    first: int = Field(1, ge=1, description="number of the first robot (PREFIXFIRST..): swarms with different "
                       "numbers side by side on one router are different robots")
    world: WORLDS = Field("arena", description="simulated world")
    seed: int = Field(0, description="seed of the world and of every robot's streams")
    rate: float = Field(10.0, gt=0, description="scan rate of every robot (Hz); odometry at the same rate")
    duration: float = Field(60.0, gt=0, description="seconds of robot time to run")
    speedup: float = Field(1.0, gt=0, description="run this many times faster than real time")
    start_delay: float = Field(0.5, ge=0, description="wall seconds to wait after declaring, so subscribers can match")
    unknown_start: float = Field(0.0, ge=0, le=1, description="share of the robots (the last ones) that announce no "
                                 "start pose (to be found by MCL)")
    publish_ids: bool = Field(False, description="publish true landmark ids with each scan (off: the services must "
                              "associate, the load a fleet without ids puts on them)")
    publish_truth: bool = Field(False, description="publish ground truth (and the world map): a third stream per robot")
    detect_robots: bool = Field(False, description="robots detect each other (Scan's robot detections, for MCL): the "
                                "whole swarm is then simulated in one piece, at a cost quadratic in its size")
    simulate_chunk: int = Field(25, ge=1, description="robots simulated at a time (without detect_robots): bounds "
                                "the simulator's working memory")
    info_period_s: float = Field(1.0, gt=0, description="first period of each robot's RobotInfo re-publication (s; "
                                 "then doubled each time up to info_max_period_s)")
    linger_s: float = Field(2.0, ge=0, description="wall seconds the robots keep their publishers (caches, "
                            "heartbeats) after their last message, for a receiver that missed the tail")
    progress_period_s: float = Field(5.0, gt=0, description="wall seconds between progress lines (messages sent, "
                                     "how far behind schedule the swarm runs)")
    behind_warning_s: float = Field(0.5, gt=0, description="a progress line is a warning when the swarm ran this "
                                    "far behind its schedule in the period (s): it cannot keep up")
    json_out: str | None = Field(None, description="write the counts sent (per robot and stream) to this JSON file")


class WorldSettings(FleetSettings):
    """``fleetslam world``: the world's true landmark map, published under its own identity (user ``world``)."""

    world: WORLDS = Field("arena", description="simulated world (its map is drawn from seed, as the robots' is)")
    seed: int = Field(0, description="seed of the simulated world (the robots' --seed)")
    replay: str | None = Field(None, description="take the true map of this data set instead: mrclam:PATH:N, "
                               "victoria-park:PATH, car-park:PATH (as fleetslam robot --replay)")


class MonitorSettings(FleetSettings):
    """``fleetslam monitor``: a live console of everything under the prefix."""

    duration: float | None = Field(None, gt=0, description="stop after this many seconds (default: until Ctrl-C)")
    refresh_hz: float = Field(2.0, gt=0, description="console refresh rate")
    rate_window_s: float = Field(2.0, gt=0, description="window over which message rates are measured (s)")
    plain: bool = Field(False, description="print plain lines instead of a live table (for logs)")
    json_out: str | None = Field(None, description="write the final counters to this JSON file")


class VizSettings(FleetSettings, VizConfig):
    """``fleetslam viz``: log the live fleet to Rerun (native viewer, web viewer and/or an .rrd recording).

    With none of ``--spawn``, ``--serve``, ``--save``: serve the web viewer on port 9090.
    """

    spawn: bool = Field(False, description="open the native Rerun viewer (needs a display)")
    serve: int | None = Field(None, ge=1, le=65535, description="serve the web viewer on http://127.0.0.1:PORT (its "
                              "data over gRPC on --grpc-port); with none of --spawn, --serve, --save: 9090")
    save: str | None = Field(None, description="write the recording to this .rrd file (replay: rerun FILE.rrd)")
    grpc_port: int = Field(9876, ge=1, le=65535, description="gRPC port of the served data (--serve) or of the "
                           "spawned viewer (--spawn; GRPC_PORT+1 with --serve too)")
    grpc_bind: str = Field("127.0.0.1", description="address the served gRPC data listens on (0.0.0.0 to reach it from "
                           "other machines or out of a container; the web viewer's page itself listens on every address)")
    duration: float | None = Field(None, gt=0, description="stop after this many seconds (default: until Ctrl-C)")


class DemoSettings(FleetSettings):
    """``fleetslam demo``: a router, robots, the monitor and every service, as separate processes."""

    duration: float = Field(20.0, gt=0, description="wall seconds to run")
    world: WORLDS = Field("arena", description="simulated world")
    robots: int = Field(3, ge=1, le=50, description="number of simulated robots")
    unknown_start_robots: int = Field(1, ge=0, le=10, description="more robots that announce no start pose (found by MCL)")
    seed: int = Field(0, description="base seed (robot i uses seed + i)")
    speedup: float = Field(1.0, gt=0, description="robot speed-up over real time")
    rate: float = Field(10.0, gt=0, description="scan rate of every robot (Hz)")
    out: str = Field("reports/demo", description="folder for logs and results")
    port: int = Field(7447, ge=1, le=65535, description="router port on 127.0.0.1")
    viz: bool = Field(False, description="also start fleetslam viz: the live fleet in the Rerun web viewer on "
                      "http://127.0.0.1:9090 (data on gRPC port 9876), recorded to OUT/fleet.rrd")
    record: str | None = Field(None, description="record every message of the demo to this MCAP file "
                               "(fleetslam record; replay it with fleetslam replay, or fleetslam run --dataset mcap:FILE)")
    open: bool = Field(False, description="run the router open, without passwords or access control, as before: any "
                       "process that reaches the port reads and writes everything (default: secured)")
    guest_robots: str = Field("guest", pattern=r"^([A-Za-z0-9_-]{1,64}(,[A-Za-z0-9_-]{1,64})*)?$",
                              description="robot ids the secured demo's router also admits, for robots of your own "
                              "(services.client.RobotLink, docs/robots.md); each logs in with "
                              "SECRETS_DIR/ID.password")
    secrets_dir: str = Field(".fleetslam/secrets", description="folder of the secured demo's credentials: one random "
                             "password per robot and service, made on the first run and reused (never commit it)")


class RecordSettings(FleetSettings):
    """``fleetslam record``: write every sample under the prefix to an MCAP file."""

    out: str | None = Field(None, description="MCAP file to write (default: recordings/PREFIX-YYYYmmdd-HHMMSS.mcap); "
                            "it is written as FILE.part and renamed when complete")
    duration: float | None = Field(None, gt=0, description="stop after this many seconds (default: until Ctrl-C/SIGTERM)")
    compression: Literal["zstd", "lz4", "none"] = Field("zstd", description="compression of the MCAP chunks")
    progress_period_s: float = Field(5.0, gt=0, description="period of the progress line in the log (s)")


class ReplaySettings(FleetSettings):
    """``fleetslam replay``: the robots of a recording published again as live robots."""

    speedup: float = Field(1.0, gt=0, description="replay this many times faster than recorded")
    robot_ids: str | None = Field(None, description="comma-separated robot ids to replay (default: every recorded robot)",
                                  json_schema_extra={"cli": "--robots"})
    start_s: float = Field(0.0, ge=0, description="skip this many seconds from the start of the recording")
    start_delay: float = Field(0.5, ge=0, description="wall seconds to wait after declaring, so subscribers can match")
    progress_period_s: float = Field(5.0, gt=0, description="period of the progress line in the log (s)")
    linger_s: float = Field(2.0, ge=0, description="wall seconds the replayed robots keep their publishers (their "
                            "caches and heartbeats) after the last message, so a receiver cut off just before can "
                            "recover the tail")


def _json_value(text: str) -> Any:
    """A flag value for a structured setting (a tuple, a list): JSON, e.g. ``[0.1, 0.1, 0.01]``."""
    try:
        return json.loads(text)
    except json.JSONDecodeError:
        raise argparse.ArgumentTypeError(f"expected a JSON value, got {text!r}") from None


def _flag_type(annotation: Any) -> tuple[Any, bool]:
    """(argparse type, is_bool) of a settings field annotation (None for a value pydantic checks itself)."""
    origin = typing.get_origin(annotation)
    if origin in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(annotation) if a is not type(None)]
        return _flag_type(args[0])
    if origin is Literal or annotation in (int, float, str):
        return None, False
    if annotation is bool:
        return None, True
    return _json_value, False


def _choices(annotation: Any) -> list | None:
    origin = typing.get_origin(annotation)
    if origin in (typing.Union, types.UnionType):
        for arg in typing.get_args(annotation):
            if typing.get_origin(arg) is Literal:
                return list(typing.get_args(arg))
    if origin is Literal:
        return list(typing.get_args(annotation))
    return None


def _flag_name(settings_cls: type[BaseSettings], name: str) -> str:
    field = settings_cls.model_fields.get(name)
    extra = field.json_schema_extra if field is not None and isinstance(field.json_schema_extra, dict) else {}
    return extra.get("cli") or f"--{name.replace('_', '-')}"


def add_settings_arguments(parser: argparse.ArgumentParser, settings_cls: type[BaseSettings]) -> None:
    """Add one ``--flag`` per settings field; defaults stay None so the environment still applies.

    Values stay text here: pydantic checks them with the environment's values, so a bad flag and a bad
    variable give the same one-line error.
    """
    group = parser.add_argument_group(
        "settings", f"each flag overrides the environment variable {ENV_PREFIX}NAME shown in brackets"
    )
    for name, field in settings_cls.model_fields.items():
        extra = field.json_schema_extra if isinstance(field.json_schema_extra, dict) else {}
        flags = [f"--{name.replace('_', '-')}"]
        if extra.get("cli"):
            flags.insert(0, extra["cli"])
        arg_type, is_bool = _flag_type(field.annotation)
        choices = _choices(field.annotation)
        default_text = "" if field.is_required() else f" (default: {field.get_default(call_default_factory=True)})"
        choice_text = f"; one of: {', '.join(map(str, choices))}" if choices else ""
        help_text = f"{field.description or name}{choice_text}{default_text} [{ENV_PREFIX}{name.upper()}]"
        help_text = help_text.replace("%", "%%")  # argparse formats help with %: a "4-10 %" would end --help
        metavar = "{" + ",".join(map(str, choices)) + "}" if choices else None
        if is_bool:
            group.add_argument(*flags, dest=name, default=None, action=argparse.BooleanOptionalAction, help=help_text)
        else:
            group.add_argument(*flags, dest=name, default=None, type=arg_type, metavar=metavar, help=help_text)


def build_settings(settings_cls: type[S], **given: Any) -> S:
    """``settings_cls(**given)`` (the environment fills the rest) with one-line :class:`SettingsError` messages."""
    try:
        return settings_cls(**given)
    except ValidationError as error:
        name, problem = describe_validation_error(error)
        field = name.split(".")[0]
        origin = _flag_name(settings_cls, field) if field in given else f"{ENV_PREFIX}{field.upper()}"
        raise SettingsError(f"{origin}: {problem}" if name else f"{settings_cls.__name__}: {problem}") from None
    except EnvironmentParseError as error:
        raise SettingsError(str(error).splitlines()[0]) from None


def settings_from_args(settings_cls: type[S], args: argparse.Namespace, **overrides: Any) -> S:
    """Build settings: CLI flags that were given > ``overrides`` > environment > defaults."""
    given = {name: getattr(args, name) for name in settings_cls.model_fields if getattr(args, name, None) is not None}
    return build_settings(settings_cls, **{**overrides, **given})


class CheckpointSettings(BaseModel):
    """The crash-safe state flags of the stateful services (``fleetslam central``, ``dslam``, ``mcl``)."""

    state_dir: str | None = Field(
        None, description="folder for this service's checkpoints (the whole filter state with its random generator, "
        "the robots' RobotInfo and last seq), written atomically every checkpoint_period_s and on exit; on start the "
        "service resumes from the newest valid one and recovers the rest from the robots' publisher caches")
    checkpoint_period_s: float = Field(1.0, gt=0, description="with state_dir: period of the checkpoints (s)")


class MclSettings(FleetSettings, MclConfig, CheckpointSettings):
    """``fleetslam mcl``: localize robots against a map; publish hypotheses; answer one-shot localization queries."""

    source: str = Field(
        "dslam", pattern=r"^(central|dslam|truth|file:.+)$",
        description="map source: the fleet's own map, dslam (MapEstimate; from a fresh start it localizes better than "
        "central) or central (Estimate); truth (WorldTruth: the simulator's or data set's true map, for tests and "
        "benchmarks); or file:PATH (a fleetslam-map .json saved by --map-out, or an (L,2) array in .npy/.txt/.csv)",
    )
    all_robots: bool = Field(False, description="localize every robot, not only those that announce no start pose")
    robot_meetings: bool = Field(True, description="use the robots' detections of each other: a robot being localized "
                                 "that detects, or is detected by, a robot the central estimate holds (one MCL does not "
                                 "localize) is placed once those meetings fix its pose, and localized again when they "
                                 "contradict MCL's hypotheses (the poses come from {prefix}/central/estimate)")
    publish_every: int = Field(1, ge=1, description="publish a robot's MclPose every this many scans")
    map_period_s: float = Field(1.0, ge=0, description="take a new map from the source at most this often (s)")
    localize_particles: int = Field(2000, ge=10, description="sample size of a one-shot localization query")
    max_localize_particles: int = Field(5_000, ge=10, description="localization queries asking for more particles are "
                                        "refused (too_large)")
    max_localize_cells: int = Field(
        1_000_000, ge=1, description="localization queries whose observations × particles exceed this are refused "
        "(too_large)")
    max_localize_map_cells: int = Field(
        250_000, ge=1, description="localization queries whose sensor needs more landmark lookup-grid cells plus "
        "landmark pairs on the map (a wide gate, a long range) than this are refused (too_large)")
    query_workers: int = Field(2, ge=1, le=16, description="threads that solve localization queries (robot tracking "
                               "keeps its own path)")
    query_queue: int = Field(4, ge=0, description="localization queries that may wait for a worker (each takes tens to "
                             "hundreds of ms); more are answered busy at once")
    query_deadline_s: float = Field(5.0, gt=0, description="a localization query that waited this long is dropped "
                                    "(expired), and a solve is cut at it (deadline) (s)")
    query_nice: int = Field(10, ge=0, le=19, description="niceness the query workers add to the process's (Linux), so "
                            "that on a busy processor the robots' tracking goes first")



class AnchorSettings(BaseModel):
    """How the mapping services (``fleetslam central``, ``fleetslam dslam``) start a world frame when no robot has a
    start pose (DESIGN §3: the first robot's start pose)."""

    anchor_first: bool = Field(
        True, description="when no robot is placed anchor_after_s after the first robot without a start pose was "
        "announced, it anchors the world frame at the origin (DESIGN §3); the others wait for MCL")
    anchor_after_s: float = Field(2.0, ge=0, description="wall seconds a robot without a start pose waits before it "
                                  "may anchor the frame (a robot with a start pose announced meanwhile comes first)")


class SavedMapSettings(BaseModel):
    """The saved-map flags of the mapping services (``fleetslam central``, ``fleetslam dslam``)."""

    map: str | None = Field(
        None, description="start from this saved map (a fleetslam-map JSON file written by --map-out), in its frame; "
        "robots without a start pose are then placed by localization against it instead of anchoring a new frame")
    map_out: str | None = Field(None, description="save the map here (fleetslam-map JSON, written atomically) on exit "
                                "(SIGINT/SIGTERM too) and every map_out_period_s")
    map_out_period_s: float = Field(30.0, ge=0, description="with map_out: rewrite the map file this often (s; 0: on exit only)")


class MapOutputSettings(BaseModel):
    """How a mapping service sends its map (:mod:`schemas.maptiles`): the tiles that changed, a full map on request."""

    map_tile_m: float = Field(5.0, gt=0, description="side of the square tiles the map is sent by (m): a published "
                              "map lists only the tiles whose landmarks changed; the first one, and the answer to a "
                              "state query, list every tile")
    map_tolerance_m: float = Field(0.01, ge=0, description="a landmark whose mean moved less than this (m), and whose "
                                   "covariance changed less than map_cov_tolerance, is not sent again: receivers' maps "
                                   "stay within this of the service's")
    map_cov_tolerance: float = Field(0.1, ge=0, description="... relative change of a landmark covariance (Frobenius "
                                     "norm of the change over the norm of the covariance sent) that sends it again")
    max_state_queries: int = Field(64, ge=1, description="queries of the state queryable ({prefix}/central/state, "
                                   "{prefix}/dslam/state) that may wait for the next turn of the loop (all get the one "
                                   "full map built then); more are answered busy at once")


class DslamSettings(FleetSettings, DslamConfig, SavedMapSettings, MapOutputSettings, AnchorSettings,
                    CheckpointSettings):
    """``fleetslam dslam``: one D-SLAM map fed by every robot; association through the queryable."""

    assoc_timeout_s: float = Field(0.5, gt=0, description="how long to wait for the association queryable (s)")
    assoc_retry_s: float = Field(5.0, ge=0, description="after a failed query, associate in-process this long before asking again (s)")
    map_period_s: float = Field(1.0, gt=0, description="period of the map publication on {prefix}/dslam/map (s): "
                                "its bound on the map output's rate")

    @field_validator("association", mode="before")
    @classmethod
    def _unknown_is_recommended(cls, value):
        """``unknown``: D-SLAM's recommended association without landmark ids, as for ``fleetslam run``."""
        return resolve_association("dslam", value) if isinstance(value, str) else value


class RunSettings(ProcessSettings):
    """``fleetslam run``: feed a data set straight into an estimator (no Zenoh) and score it."""

    dataset: str = Field(
        "sim:arena", description="mrclam:PATH[:N], victoria-park:PATH, car-park:PATH, mcap:FILE (a fleetslam record "
        "file), rosbag2:PATH (a ROS 2 bag, with --fleet) or sim:WORLD "
        "(a relative PATH is also looked for under FLEETSLAM_DATA)",
    )
    fleet_file: str | None = Field(
        None, description="fleet file (YAML) of a rosbag2:PATH data set: which topics are whose odometry and "
        "landmarks (default: the bag folder's fleet.yaml, as fleetslam export rosbag2 writes it)",
        json_schema_extra={"cli": "--fleet"})
    estimator: ESTIMATORS = Field("odometry", description="estimator")
    association: ASSOCIATIONS = Field(
        "known", description="data association: known (true ids); unknown (each estimator's recommended method "
        "without ids: fastslam shared, dslam auto, ekf jcbb); or a method the estimator offers "
        "(fastslam: shared, nn, mht; dslam and ekf: nn, greedy, ihgr, exact, jcbb, auto)")
    particles: int | None = Field(
        None, ge=1, le=100_000, description="particles of particle-filter estimators (default: the estimator's own)")
    workers: int | None = Field(
        None, ge=1, le=1024, description="fastslam: threads of its per-particle kernels, the same results for any "
        "count (default: the estimator's own, 1; 1: the serial kernels); other estimators use one core")
    seed: int = Field(0, description="seed of every random draw (estimator, and the simulator for sim:)")
    robot_ids: str | None = Field(
        None, description="comma-separated robot ids to use (default: all)", json_schema_extra={"cli": "--robots"}
    )
    duration: float | None = Field(None, gt=0, description="seconds of data from the start (default: all)")
    start_poses: Literal["known", "first", "none"] | None = Field(
        None, description="start poses the estimator is given: known (all the data has), first (the first robot's "
        "only), none (the first robot to scan anchors the frame at the origin); robots without one are placed by "
        "MCL against the map so far (default: known when the data has them, else none)")
    robot_meetings: bool = Field(
        True, description="robots without a start pose are also localized by the detections between them and robots "
        "already placed (the robots' own ids; collaborative MCL)")
    estimator_settings: str | None = Field(
        None, description="the estimator's own settings, comma-separated NAME=VALUE (e.g. max_obs_range=40 or "
        "proposal=fastslam2 for fastslam, confirm_hits=3 for dslam, variant=kld for mcl); unknown names and bad "
        "values are refused with the known names", json_schema_extra={"cli": "--set"},
    )
    sim_robots: int = Field(3, ge=1, le=50, description="robots simulated for sim:WORLD when --robots is not given")
    sim_rate: float = Field(10.0, gt=0, description="scan rate of simulated robots (Hz)")
    sample_period_s: float = Field(0.2, gt=0, description="estimated poses are sampled this often in data time (s)")
    map: str | None = Field(
        None, description="start from this saved map (a fleetslam-map JSON file written by --map-out), in its frame: "
        "fastslam and dslam extend it, mcl localizes against it; robots without a start pose are placed by "
        "localization against it instead of anchoring a new frame")
    map_out: str | None = Field(None, description="save the final map here (fleetslam-map JSON, written atomically; "
                                "also when interrupted)")
    map_cutoff_m: float = Field(1.0, gt=0, description="farther estimated <-> true landmark pairs are not matches (m)")
    rpe_delta_s: float = Field(1.0, gt=0, description="time step of the relative pose error (s)")
    out: str | None = Field(
        "reports/run", description="report folder: results.json, metrics.json, TUM trajectories and plots (files of an "
        "earlier report there are removed first)")
    json_out: str | None = Field(None, description="also write the results JSON to this file", json_schema_extra={"cli": "--json"})
    rerun: str | None = Field(
        None, pattern=r"\.rrd$", description="also write a Rerun recording (FILE.rrd) of the run on the data's clock: "
        "true and estimated trajectories, true landmarks, the final map with covariance ellipses (open: rerun FILE.rrd)")
    progress: bool = Field(True, description="show a progress bar on the terminal")
    log_level: Literal["DEBUG", "INFO", "WARNING", "ERROR"] = Field("INFO", description="log level")


class Ros2Settings(FleetSettings):
    """``fleetslam ros2``: ROS 2 robots on rmw_zenoh join fleetslam; their estimates go back as ROS 2 messages."""

    fleet_file: str = Field(description="fleet file (YAML): the ROS 2 robots, their topics and models (docs/robots.md)",
                            json_schema_extra={"cli": "--fleet"})
    duration: float | None = Field(None, gt=0, description="stop after this many seconds (default: until SIGINT/SIGTERM)")
    node_name: str = Field("fleetslam", pattern=r"^[A-Za-z_][A-Za-z0-9_]*$",
                           description="ROS 2 node name of the bridge (what ros2 node list shows)")
    pose_topic: str = Field("fleetslam/odom", pattern=r"^[A-Za-z_][A-Za-z0-9_/]*$",
                            description="each robot's fused pose (nav_msgs/Odometry), under the robot's namespace")
    map_topic: str = Field("/fleetslam/map", description="the central and D-SLAM maps (visualization_msgs/MarkerArray)")
    tf_topic: str = Field("/tf", description="where each robot's map → odom transform goes (tf2_msgs/TFMessage)")
    map_period_s: float = Field(1.0, gt=0, description="the map markers are sent at most this often (s)")


class ExportSettings(ProcessSettings):
    """``fleetslam export rosbag2``: a data set as a ROS 2 bag plus its fleet file."""

    dataset: str = Field(description="data set spec, as fleetslam run takes it: mrclam:PATH[:N], victoria-park:PATH, "
                         "car-park:PATH, mcap:FILE or sim:WORLD")
    out: str = Field(description="bag folder to write (must not exist, unless --force)")
    storage: Literal["mcap", "sqlite3"] = Field("mcap", description="rosbag2 storage plugin")
    distro: Literal["humble", "jazzy", "kilted", "rolling"] = Field(
        "jazzy", description="ROS distribution whose message definitions and type hashes the bag carries")
    duration: float | None = Field(None, gt=0, description="seconds of data from the start (default: all; sim: 60)")
    seed: int = Field(0, description="seed of the simulator (sim: data sets only)")
    force: bool = Field(False, description="replace an existing bag folder at --out (nothing else is removed)")
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
    max_samples: int = Field(8192, ge=100, description="samples kept per trajectory, in arrays allocated when it starts "
                             "(memory stays flat: when full, every other sample is dropped, the span stays)")


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
    max_query_cells: int = Field(
        1_000_000, ge=1, description="requests whose largest array exceeds this many cells are refused (too_large): "
        "measurements × landmarks, (measurements + landmarks)² for exact and auto, + 4 landmarks² + 4 measurements² for "
        "jcbb and auto")
    query_workers: int = Field(2, ge=1, le=16, description="threads that solve association queries")
    query_queue: int = Field(8, ge=0, description="association queries that may wait for a worker; more are answered "
                             "busy at once")
    query_deadline_s: float = Field(5.0, gt=0, description="a query that waited this long is dropped (expired), and a "
                                    "solve is cut at it: the best found so far (truncated), or deadline (s)")
    query_nice: int = Field(10, ge=0, le=19, description="niceness the query workers add to the process's (Linux), so "
                            "that on a busy processor the other services go first")
    light_query_cells: int = Field(
        100_000, ge=0, description="queries of at most this many cells (a robot's scan against the landmarks near it, "
        "as D-SLAM asks) have a worker of their own at the service's priority, so heavy queries never hold them up; "
        "0: one lane for all")
    light_query_queue: int = Field(8, ge=0, description="light queries that may wait for their worker; more are "
                                   "answered busy at once")
    duration: float | None = Field(None, gt=0, description="stop after this many seconds (default: until SIGINT/SIGTERM)")


class CentralSettings(FleetSettings, FastSlamConfig, SavedMapSettings, MapOutputSettings, AnchorSettings,
                      CheckpointSettings):
    """``fleetslam central``: the central multi-robot FastSLAM service (every robot in one filter)."""

    estimate_rate_hz: float = Field(2.0, gt=0, le=100, description="rate of the estimate publication on "
                                    "{prefix}/central/estimate: its bound on the estimate output's rate")
    late_join: Literal["start_pose", "wait"] = Field(
        "start_pose", description="a robot whose first odometry was missed: keep its announced start pose, "
        "or wait for MCL to place it")
    replace_after: int = Field(
        20, ge=0, description="a robot MCL placed is placed again when this many localized MCL poses in a row lie "
        "farther than replace_distance_m from the filter's (MCL relocalized it: its first hypothesis was wrong); 0: never")
    replace_distance_m: float = Field(2.0, gt=0, description="... how far MCL's pose must be from the filter's")
    duration: float | None = Field(None, gt=0, description="stop after this many seconds (default: until SIGINT/SIGTERM)")

    @field_validator("association", mode="before")
    @classmethod
    def _unknown_is_recommended(cls, value):
        """``unknown``: FastSLAM's recommended association without landmark ids, as for ``fleetslam run``."""
        return resolve_association("fastslam", value) if isinstance(value, str) else value
