"""``fleetslam`` command line: one sub-command per process, each in its own module.

Every command module exposes ``add_arguments(parser)`` and ``main(args) -> int``
and keeps its pipeline apart from parsing (the CLI only parses and calls).
A command whose module is not installed is simply not listed.
"""

from __future__ import annotations

import argparse
import importlib
import importlib.util
import logging
import sys

COMMANDS: dict[str, tuple[str, str]] = {
    "router": ("services.router", "run the Zenoh router (router mode; access control and TLS optional)"),
    "robot": ("robots.process", "run one robot: simulated in a named world, or replaying a data set"),
    "monitor": ("services.monitor", "live console of robots, message rates, gaps, rejections and service stats"),
    "demo": ("services.launcher", "start a router, robots, the monitor and every service; print what was measured"),
    "run": ("services.offline", "offline: feed a data set straight into an estimator, no Zenoh; JSON results"),
    "evaluate": ("services.evaluation.service", "live evaluator: compare estimates with truth, write a report folder"),
    "assoc": ("services.association.service", "data-association queryable on {prefix}/assoc/{method}"),
    "central": ("central.service", "central multi-robot FastSLAM service"),
    "dslam": ("services.dslam.service", "D-SLAM map service (sparse information-filter map) and localisation"),
    "mcl": ("services.mcl.service", "Monte Carlo localisation service (global localisation, kidnapping)"),
}


def available_commands() -> dict[str, tuple[str, str]]:
    """The commands whose modules exist in this installation."""
    found = {}
    for name, (module, text) in COMMANDS.items():
        try:
            if importlib.util.find_spec(module) is not None:
                found[name] = (module, text)
        except ModuleNotFoundError:
            continue
    return found


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The CLI parser; only ``command``'s module is imported (each process pays for its own imports only)."""
    parser = argparse.ArgumentParser(
        prog="fleetslam",
        description="Distributed multi-robot landmark SLAM over Eclipse Zenoh. "
        "Every setting can also come from a FLEETSLAM_* environment variable.",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name, (module_name, text) in available_commands().items():
        if name != command:
            sub.add_parser(name, help=text, add_help=False)
            continue
        module = importlib.import_module(module_name)
        parsed = sub.add_parser(name, help=text, description=(module.__doc__ or text).strip().splitlines()[0])
        module.add_arguments(parsed)
        parsed.set_defaults(_module=module)
    return parser


def configure_logging(level: str = "INFO") -> None:
    logging.basicConfig(
        level=getattr(logging, level.upper(), logging.INFO),
        format="%(asctime)s %(levelname)-7s %(name)s: %(message)s",
        datefmt="%H:%M:%S",
        stream=sys.stderr,
        force=True,
    )


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    command = next((word for word in argv if not word.startswith("-")), None)
    args = build_parser(command).parse_args(argv)
    configure_logging(getattr(args, "log_level", None) or "INFO")
    try:
        return int(args._module.main(args) or 0)
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
