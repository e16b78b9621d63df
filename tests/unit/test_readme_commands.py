"""Every ``fleetslam`` command that README.md and the pages of docs/ show runs as written: the command exists, each
of its flags is one its parser declares (spelled out, not abbreviated), the whole line parses with the real
command-line parser (``services.cli.build_parser``: choices, types, required values), and ``--help`` appended exits
0. Lines are taken from fenced code blocks (except ``text`` and ``mermaid`` diagrams) and, in README.md, from inline
code spans that start with ``fleetslam``. A routine that cannot fail proves nothing: made-up commands and flags are
refused by the same routine."""

from __future__ import annotations

import argparse
import contextlib
import io
import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

from pydantic_settings import BaseSettings

from schemas import config
from schemas.contract import SettingsError
from services.cli import COMMANDS, build_parser, main as cli_main

REPO = Path(__file__).resolve().parents[2]
README = REPO / "README.md"
PROGRAMS = ("fleetslam", ".venv/bin/fleetslam")
NOT_SHELL = ("text", "mermaid", "json", "python", "yaml", "toml")  # fenced blocks that hold no commands
SHELL_STOPS = {"&", "&&", "||", ";", "|", ">", ">>", "2>", "2>&1"}
FENCE = re.compile(r"^(```|~~~)\s*([\w+-]*)")
ENV_ASSIGNMENT = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*=")


def fenced_blocks(text: str) -> list[tuple[str, list[str]]]:
    """(info string, lines) of every fenced code block of a Markdown text."""
    blocks, current, info, fence = [], None, "", ""
    for line in text.splitlines():
        match = FENCE.match(line.strip())
        if current is None and match:
            current, fence, info = [], match.group(1), match.group(2).lower()
        elif current is not None and line.strip().startswith(fence):
            blocks.append((info, current))
            current = None
        elif current is not None:
            current.append(line)
    return blocks


def without_fences(text: str) -> str:
    kept, inside = [], False
    for line in text.splitlines():
        if FENCE.match(line.strip()):
            inside = not inside
            continue
        if not inside:
            kept.append(line)
    return "\n".join(kept)


def command_words(line: str) -> list[str] | None:
    """The words of a shell line if it runs fleetslam (after any VAR=value assignments), cut at the first shell
    operator, with comments dropped; None otherwise."""
    line = line.strip()
    if line.startswith("$ "):
        line = line[2:]
    try:
        words = shlex.split(line, comments=True)
    except ValueError:
        return None
    while words and ENV_ASSIGNMENT.match(words[0]):
        words = words[1:]
    if not words or words[0] not in PROGRAMS:
        return None
    for i, word in enumerate(words):
        if word in SHELL_STOPS:
            return words[:i]
    return words


def commands_in(path: Path, inline: bool = False) -> list[str]:
    """Every fleetslam command line of a Markdown file (continuation lines joined)."""
    text = path.read_text()
    found = []
    for info, lines in fenced_blocks(text):
        if info in NOT_SHELL:
            continue
        joined, pending = [], ""
        for line in lines:
            if line.rstrip().endswith("\\"):
                pending += line.rstrip()[:-1] + " "
                continue
            joined.append(pending + line)
            pending = ""
        found += [line.strip() for line in joined if command_words(line)]
    if inline:
        found += [span for span in re.findall(r"`([^`\n]+)`", without_fences(text))
                  if len(command_words(span) or ()) >= 2]  # a command, not the bare program's name
    return found


def settings_class(sub: argparse.ArgumentParser) -> type[BaseSettings]:
    """The settings class behind a command's flags: the one of ``schemas.config`` whose fields are its flags. Flag
    values stay text in argparse; the command checks them by building this class, as :func:`parse_problem` does."""
    flags = {action.dest for action in sub._actions if action.option_strings and action.dest != "help"}
    found = [cls for cls in vars(config).values()
             if isinstance(cls, type) and issubclass(cls, BaseSettings) and set(cls.model_fields) == flags]
    assert len(found) == 1, (sub.prog, found)
    return found[0]


def parse_problem(words: list[str]) -> str | None:
    """Why ``words`` (a fleetslam command line) would not run as written; None when it parses."""
    args = words[1:]
    if not args:
        return "no command"
    if args[0] in ("--help", "-h", "--version"):
        return None if len(args) == 1 else f"{args[0]} takes nothing after it"
    command = args[0]
    if command not in COMMANDS:
        return f"unknown command {command!r} (known: {', '.join(COMMANDS)})"
    parser = build_parser(command)
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction)).choices[command]
    declared = set(sub._option_string_actions)
    for word in args[1:]:
        flag = word.split("=", 1)[0]
        if flag.startswith("-") and flag not in declared and not re.fullmatch(r"-\d+(\.\d+)?", flag):
            return f"fleetslam {command} has no flag {flag}"
    err = io.StringIO()
    try:
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
            parsed = parser.parse_args(args)
    except SystemExit as stop:
        if stop.code in (0, None):
            return None  # --help
        return err.getvalue().strip().splitlines()[-1] if err.getvalue().strip() else f"exit {stop.code}"
    try:
        config.settings_from_args(settings_class(sub), parsed)  # the values, checked as the command checks them
    except SettingsError as error:
        return f"fleetslam {command}: {error}"
    return None


README_COMMANDS = list(dict.fromkeys(commands_in(README, inline=True)))
DOCS_COMMANDS = sorted({line for page in sorted((REPO / "docs").glob("*.md")) for line in commands_in(page)})


def test_the_readme_shows_commands():
    assert len(README_COMMANDS) >= 8, README_COMMANDS
    assert any(line.split()[1] == "run" and "--dataset" in line for line in README_COMMANDS)


@pytest.mark.parametrize("line", README_COMMANDS + [c for c in DOCS_COMMANDS if c not in README_COMMANDS])
def test_every_shown_command_parses_and_its_help_exits_0(line, capsys):
    words = command_words(line)
    assert parse_problem(words) is None, f"{line}: {parse_problem(words)}"
    args = [w for w in words[1:] if w not in ("--help", "-h")]
    with pytest.raises(SystemExit) as stop:
        cli_main([*args, "--help"])
    assert stop.value.code == 0, line
    assert "usage: fleetslam" in capsys.readouterr().out


@pytest.mark.parametrize("line, reason", [
    ("fleetslam run --no-such-flag", "has no flag --no-such-flag"),
    ("fleetslam robot --estimator fastslam", "has no flag --estimator"),   # a flag of another command
    ("fleetslam run --dur 5", "has no flag --dur"),                        # argparse would take the abbreviation
    ("fleetslam run --estimator kalman", "estimator='kalman'"),           # values are checked too
    ("fleetslam run --seed many", "seed='many'"),
    ("fleetslam teleport --now", "unknown command 'teleport'"),
])
def test_made_up_commands_and_flags_are_refused_by_the_same_routine(line, reason):
    problem = parse_problem(command_words(line))
    assert problem is not None and reason in problem, problem


def test_lines_are_read_as_a_shell_would():
    assert command_words("FLEETSLAM_ZENOH_USER=monitor fleetslam monitor   # watch") == ["fleetslam", "monitor"]
    assert command_words("fleetslam router &") == ["fleetslam", "router"]
    assert command_words(".venv/bin/fleetslam --help | less") == [".venv/bin/fleetslam", "--help"]
    assert command_words("docker compose up") is None
    blocks = fenced_blocks("```bash\nfleetslam demo\n```\n```text\nfleetslam robot ─┐\n```\n")
    assert blocks == [("bash", ["fleetslam demo"]), ("text", ["fleetslam robot ─┐"])]


def test_the_console_script_lists_every_command():
    script = Path(sys.executable).with_name("fleetslam")
    argv = [str(script)] if script.exists() else [sys.executable, "-m", "services.cli"]
    env = {k: v for k, v in os.environ.items() if not k.startswith("FLEETSLAM_")}
    result = subprocess.run([*argv, "--help"], cwd=REPO, capture_output=True, text=True, timeout=120, env=env)
    assert result.returncode == 0, result.stderr
    for command in COMMANDS:
        assert re.search(rf"^\s+{command}\s", result.stdout, re.M), command
