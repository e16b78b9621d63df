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
    assert set(COMMANDS) == {"router", "robot", "monitor", "demo", "run", "evaluate", "assoc", "central", "dslam", "mcl"}
