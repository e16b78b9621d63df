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
    world: str = Field("arena", description="simulated world: random, paper000, grid196, cross, arena")
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
