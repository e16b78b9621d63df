"""``fleetslam`` command line: one sub-command per process, each in its own module.

Every command module exposes ``add_arguments(parser)`` and ``main(args) -> int``
and keeps its pipeline apart from parsing (the CLI only parses and calls).
Each command is loaded by a plain import inside its loader function, so only
the chosen command's module is imported (a robot does not pay for the filters)
and a reader can follow every command to its code. Ordinary mistakes (a bad
flag value, a bad ``FLEETSLAM_*`` variable, an unknown ``--set`` name) end
with one line and exit code 2, never a traceback.
"""

from __future__ import annotations

import argparse
import faulthandler
import io
import logging
import signal
import sys
from importlib.metadata import PackageNotFoundError, version
from types import ModuleType
from typing import Callable


def _router() -> ModuleType:
    from services import router
    return router


def _robot() -> ModuleType:
    from robots import process
    return process


def _swarm() -> ModuleType:
    from services import swarm
    return swarm


def _world() -> ModuleType:
    from robots import truth
    return truth


def _monitor() -> ModuleType:
    from services import monitor
    return monitor


def _demo() -> ModuleType:
    from services import launcher
    return launcher


def _run() -> ModuleType:
    from services import offline
    return offline


def _record() -> ModuleType:
    from services import record
    return record


def _export() -> ModuleType:
    from services import export
    return export


def _replay() -> ModuleType:
    from services import replay
    return replay


def _evaluate() -> ModuleType:
    from services.evaluation import service
    return service


def _assoc() -> ModuleType:
    from services.association import service
    return service


def _central() -> ModuleType:
    from central import service
    return service


def _dslam() -> ModuleType:
    from services.dslam import service
    return service


def _mcl() -> ModuleType:
    from services.mcl import service
    return service


def _ros2() -> ModuleType:
    from services.ros2 import service
    return service


def _viz() -> ModuleType:
    from services.viz import service
    return service


COMMANDS: dict[str, tuple[Callable[[], ModuleType], str]] = {
    "router": (_router, "run the Zenoh router (router mode; access control and TLS optional)"),
    "robot": (_robot, "run one robot: simulated in a named world, or replaying a data set"),
    "swarm": (_swarm, "simulate many robots in one process (each on its own keys, with its own token): load tests"),
    "world": (_world, "publish the world's true landmark map (a simulated world's or a data set's) as the user 'world'"),
    "monitor": (_monitor, "live console of robots, message rates, gaps, rejections and service stats"),
    "demo": (_demo, "start a router, robots, the monitor and every service; print what was measured"),
    "run": (_run, "offline: feed a data set straight into an estimator, no Zenoh; results and plots in reports/run/"),
    "record": (_record, "record every message under the prefix to an MCAP file (ROS 2, Foxglove, Rerun read it)"),
    "export": (_export, "write a data set as a ROS 2 bag (MCAP or sqlite3) with its fleet file"),
    "replay": (_replay, "publish the robots of an MCAP recording again as live robots"),
    "evaluate": (_evaluate, "live evaluator: compare estimates with truth, write a report folder"),
    "assoc": (_assoc, "data-association queryable on {prefix}/assoc/{method}"),
    "central": (_central, "central multi-robot FastSLAM service"),
    "dslam": (_dslam, "D-SLAM map service (sparse information-filter map) and localization"),
    "mcl": (_mcl, "Monte Carlo localization service (global localization, kidnapping)"),
    "ros2": (_ros2, "ROS 2 robots on rmw_zenoh join fleetslam (no bridge, no ROS install); estimates back as ROS 2 messages"),
    "viz": (_viz, "live view of the fleet in Rerun: trajectories, maps with ellipses, MCL hypotheses, latency"),
}


def package_version() -> str:
    try:
        return version("fleetslam")
    except PackageNotFoundError:
        return "unknown (not installed)"


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The CLI parser; only ``command``'s module is imported (each process pays for its own imports only)."""
    parser = argparse.ArgumentParser(
        prog="fleetslam",
        description="Distributed multi-robot landmark SLAM over Eclipse Zenoh. "
        "Every setting can also come from a FLEETSLAM_* environment variable.",
    )
    parser.add_argument("--version", action="version", version=f"fleetslam {package_version()}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True,
                                help=f"one of: {', '.join(COMMANDS)}")
    for name, (load, text) in COMMANDS.items():
        if name != command:
            sub.add_parser(name, help=text, add_help=False)
            continue
        module = load()
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
    from schemas.contract import SettingsError

    argv = sys.argv[1:] if argv is None else argv
    command = next((word for word in argv if not word.startswith("-")), None)
    args = build_parser(command if command in COMMANDS else None).parse_args(argv)
    level = getattr(args, "log_level", None)
    configure_logging(level if level in ("DEBUG", "INFO", "WARNING", "ERROR") else "INFO")
    if hasattr(signal, "SIGUSR1"):  # `kill -USR1 PID` prints where every thread is: for a process that hangs
        try:
            faulthandler.register(signal.SIGUSR1, all_threads=True)
        except (AttributeError, ValueError, io.UnsupportedOperation):  # a stderr without a file (called in-process)
            pass
    try:
        return int(args._module.main(args) or 0)
    except SettingsError as error:
        print(f"fleetslam {args.command}: error: {error}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
