"""The command line: ordinary mistakes end with one line and exit code 2, never a traceback; --help lists the
choices of every choice flag; --version."""

import argparse
import os
import subprocess
import sys
import typing

import pytest

from schemas import config
from services.cli import COMMANDS, build_parser, main as cli_main
from tests.helpers import REPO


def one_error_line(capsys) -> str:
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert len(err) == 1, err
    assert "Traceback" not in err[0]
    return err[0]


@pytest.mark.parametrize("words, expected", [
    (["--set", "max_obs_range=abc"], ["max_obs_range='abc'", "valid number"]),
    (["--set", "particles=abc"], ["particles='abc'", "valid integer"]),
    (["--set", "foo=1"], ["unknown fastslam setting foo", "(known: ", "max_obs_range"]),
    (["--set", "proposal=fastslam3"], ["proposal='fastslam3'", "'auto', 'fastslam1' or 'fastslam2'"]),
])
def test_bad_estimator_settings_give_one_line(words, expected, capsys):
    code = cli_main(["run", "--dataset", "sim:arena", "--estimator", "fastslam", "--duration", "1", "--no-progress",
                     *words])
    line = one_error_line(capsys)
    assert code == 2 and line.startswith("fleetslam run: error: ")
    for text in expected:
        assert text in line, line


def test_a_bad_environment_variable_gives_one_line(monkeypatch, capsys):
    monkeypatch.setenv("FLEETSLAM_RATE", "abc")
    assert cli_main(["robot"]) == 2
    line = one_error_line(capsys)
    assert line.startswith("fleetslam robot: error: FLEETSLAM_RATE: rate='abc'"), line


def test_a_bad_choice_gives_one_line(capsys):
    assert cli_main(["mcl", "--variant", "xyz"]) == 2
    line = one_error_line(capsys)
    assert line.startswith("fleetslam mcl: error: --variant: variant='xyz': Input should be 'mcl', 'kld'"), line


def test_the_cli_process_prints_no_traceback_for_a_bad_variable():
    env = {k: v for k, v in os.environ.items() if not k.startswith("FLEETSLAM_")}
    result = subprocess.run([sys.executable, "-m", "services.cli", "central", "--particles", "0"], cwd=REPO,
                            capture_output=True, text=True, timeout=60, env={**env, "FLEETSLAM_PREFIX": "a b"})
    assert result.returncode == 2
    assert "Traceback" not in result.stderr and len(result.stderr.strip().splitlines()) == 1, result.stderr


def test_version(capsys):
    with pytest.raises(SystemExit) as stop:
        build_parser().parse_args(["--version"])
    assert stop.value.code == 0 and capsys.readouterr().out.startswith("fleetslam 0.")


def _settings_classes() -> dict[str, type]:
    return {"router": config.RouterSettings, "robot": config.RobotSettings, "monitor": config.MonitorSettings,
            "demo": config.DemoSettings, "run": config.RunSettings, "evaluate": config.EvaluateSettings,
            "assoc": config.AssocSettings, "central": config.CentralSettings, "dslam": config.DslamSettings,
            "mcl": config.MclSettings, "viz": config.VizSettings, "record": config.RecordSettings,
            "replay": config.ReplaySettings, "world": config.WorldSettings, "export": config.ExportSettings,
            "ros2": config.Ros2Settings, "swarm": config.SwarmSettings}


@pytest.mark.parametrize("command", list(COMMANDS))
def test_help_lists_the_choices_of_every_choice_flag(command):
    parser = build_parser(command)
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction)).choices[command]
    text = sub.format_help()
    settings_cls = _settings_classes()[command]
    for name, field in settings_cls.model_fields.items():
        choices = config._choices(field.annotation)
        if choices:
            assert "one of: " + ", ".join(map(str, choices)) in " ".join(text.split()), (command, name)
    if command == "run":
        assert "one of: odometry, ekf, fastslam, dslam, mcl" in " ".join(text.split())
    assert set(_settings_classes()) == set(COMMANDS)
    assert all(typing.get_origin(f.annotation) is not None or f.annotation is not None
               for f in settings_cls.model_fields.values())


def test_demo_problems_flag_lagging_services_backlogs_lost_messages_and_unlocalized_robots():
    from services.launcher import problems

    def stats(median, p99, queue, odom, scan):
        return {"latency_ms_median": median, "latency_ms_p99": p99, "queue_depth": queue,
                "messages_in": {"odom": odom, "scan": scan}}

    summary = {
        "elapsed_s": 10.0,
        "monitor": {
            "robots": {"r1": {"odom": 100, "scan": 100, "truth": 100, "missing": 0},
                       "r2": {"odom": 100, "scan": 100, "truth": 100, "missing": 3}},
            "services": {"central:a": stats(2.0, 20.0, 0, 200, 200), "dslam:b": stats(12000.0, 20000.0, 81, 150, 100),
                         "mcl:c": stats(3.0, 40.0, 80, 195, 195), "assoc:d": stats(1.0, 2.0, 0, 0, 0)},
        },
        "metrics": {"mcl_never_localized": ["r6"]},
    }
    found = problems(summary)
    assert found == [
        "robot r2: 3 messages lost on the way (seq gaps seen by the monitor)",
        "dslam lagged: latency median 12000 ms, p99 20000 ms",
        "dslam had 81 messages queued at its last stats",  # more than two seconds of the fleet's 40 messages/s
        "dslam never processed about 150 of the 400 robot messages",
        "MCL never localized robot r6: no error figure for it",
    ]
    healthy = {**summary, "metrics": {}, "monitor": {**summary["monitor"], "services": {"central:a": stats(2.0, 20.0, 0, 200, 200)},
                                                      "robots": {"r1": summary["monitor"]["robots"]["r1"]}}}
    assert problems(healthy) == []
    mid_burst = {**healthy, "monitor": {**healthy["monitor"], "services": {"mcl:c": stats(3.0, 40.0, 40, 200, 200)}}}
    assert problems(mid_burst) == []  # 40 queued at 20 messages/s: two seconds' worth, not a backlog
    mid_burst["monitor"]["services"]["mcl:c"]["queue_depth"] = 41
    assert problems(mid_burst) == ["mcl had 41 messages queued at its last stats"]


def test_the_router_gives_a_user_to_every_default_robot_and_service_and_refuses_bad_ones(capsys, tmp_path):
    from services.credentials import DEFAULT_ROBOTS, DEFAULT_SERVICES, format_services, parse_services

    fields = config.RouterSettings.model_fields
    assert fields["robot_users"].default == ",".join(DEFAULT_ROBOTS)
    assert parse_services(fields["service_users"].default) == DEFAULT_SERVICES
    assert parse_services(format_services(DEFAULT_SERVICES)) == DEFAULT_SERVICES
    assert cli_main(["router", "--secrets-dir", str(tmp_path), "--router-config", "x.json5"]) == 2
    assert "give one" in one_error_line(capsys)
    assert cli_main(["router", "--robot-users", "r1,bad:id"]) == 2
    assert one_error_line(capsys).startswith("fleetslam router: error: --robot-users:")
    assert cli_main(["router", "--secrets-dir", str(tmp_path), "--robot-users", "r1,world"]) == 2
    assert "given twice" in capsys.readouterr().err and not list(tmp_path.iterdir())


def test_credentials_are_made_once_and_kept(tmp_path):
    from services.credentials import secure_folder

    config_path = secure_folder(tmp_path / "s", "fleet", ["r1"], {"central": ("central",)})
    first = {p.name: p.read_text() for p in (tmp_path / "s").glob("*.password")}
    assert set(first) == {"r1.password", "central.password", "world.password", "router.password"}
    assert len(set(first.values())) == 4 and all(len(v.strip()) >= 32 for v in first.values())
    secure_folder(tmp_path / "s", "fleet", ["r1", "r2"], {"central": ("central",)})
    again = {p.name: p.read_text() for p in (tmp_path / "s").glob("*.password")}
    assert {k: again[k] for k in first} == first and "r2.password" in again
    users = dict(line.split(":", 1) for line in (tmp_path / "s" / "users.txt").read_text().split())
    assert users == {name.removesuffix(".password"): text.strip() for name, text in again.items()}
    assert str((tmp_path / "s" / "users.txt").resolve()) in config_path.read_text()
    assert not list((tmp_path / "s").glob("*.part"))
