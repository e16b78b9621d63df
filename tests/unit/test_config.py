"""Settings: defaults < FLEETSLAM_* environment < CLI flags; the CLI lists every command."""

import argparse

import pytest

from schemas.config import RobotSettings, add_settings_arguments, settings_from_args
from schemas.contract import SettingsError
from services.cli import COMMANDS, build_parser


def parse(argv):
    parser = argparse.ArgumentParser()
    add_settings_arguments(parser, RobotSettings)
    return parser.parse_args(argv)


def test_defaults_environment_and_flags_in_that_order(monkeypatch):
    assert settings_from_args(RobotSettings, parse([])).rate == 10.0
    monkeypatch.setenv("FLEETSLAM_RATE", "5")
    monkeypatch.setenv("FLEETSLAM_ZENOH_CONNECT", "tcp/10.0.0.1:7447")
    assert settings_from_args(RobotSettings, parse([])).rate == 5.0
    settings = settings_from_args(RobotSettings, parse(["--rate", "20", "--id", "r9", "--no-publish-ids"]))
    assert settings.rate == 20.0 and settings.robot_id == "r9" and settings.publish_ids is False
    assert settings.zenoh_connect == "tcp/10.0.0.1:7447"


def test_invalid_settings_are_refused_with_the_field_named():
    with pytest.raises(SettingsError, match="^--id: robot_id='bad id/with slash': String should match pattern"):
        settings_from_args(RobotSettings, parse(["--id", "bad id/with slash"]))
    with pytest.raises(SettingsError, match="^--rate: rate='-1': Input should be greater than 0$"):
        settings_from_args(RobotSettings, parse(["--rate", "-1"]))


def test_help_lists_every_installed_command():
    text = build_parser().format_help()
    for name in COMMANDS:
        assert name in text
    assert set(COMMANDS) == {"router", "robot", "monitor", "demo", "run", "evaluate", "assoc", "central", "dslam", "mcl", "viz",
                             "record", "replay", "world", "export", "ros2", "swarm"}


def test_core_configurations_never_read_the_environment(monkeypatch):
    from central.fastslam.config import FastSlamConfig
    from schemas.config import CentralSettings, MclSettings
    from services.dslam.config import DslamConfig
    from services.mcl.config import MclConfig

    for name, value in {"ASSOCIATION": "nn", "VARIANT": "kld", "PARTICLES": "7"}.items():
        monkeypatch.setenv(f"FLEETSLAM_{name}", value)
    assert FastSlamConfig().particles == 100 and FastSlamConfig().association == "shared"
    assert MclConfig().variant == "cluster_kld_srl" and MclConfig().particles == 1000
    assert DslamConfig().association == "known"
    # only a process's settings class reads them, and composes its core's configuration from them
    assert CentralSettings().core(FastSlamConfig).particles == 7
    monkeypatch.setenv("FLEETSLAM_PARTICLES", "70")  # MCL needs at least 10
    mcl = MclSettings().core(MclConfig)
    assert mcl.variant == "kld" and mcl.particles == 70


def test_services_take_unknown_association_as_their_recommended_method():
    """``--association unknown`` means the same in a service as in ``fleetslam run``; a bad name is still refused."""
    from schemas.config import CentralSettings, DslamSettings, settings_from_args

    assert CentralSettings(association="unknown").association == "shared"
    assert DslamSettings(association="unknown").association == "auto"
    assert CentralSettings(association="nn").association == "nn"
    with pytest.raises(SettingsError, match="association"):
        settings_from_args(CentralSettings, argparse.Namespace(association="nearest"))
