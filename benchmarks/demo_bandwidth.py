"""What the demo fleet sends, per robot stream and per service output: payload bytes per second, from a recording.

Runs ``fleetslam demo --record FILE`` (its defaults: 3 simulated robots at 10 Hz, every service) and reads every
message of the recording back (``schemas.mcap_file.read_recording``): per kind of key (a robot's odometry, scans,
RobotInfo, truth; central's estimate, D-SLAM's map and poses, MCL's poses, the services' stats) the payload bytes per
second while the robots drive, after their first ``--skip-s`` (the fleet starting). Zenoh, TCP and IP add to every message on
the wire: ``benchmarks/bandwidth.py`` measures a robot's cost on a real link.

    .venv/bin/python benchmarks/demo_bandwidth.py [--duration 60] [--robots 3] [--skip-s 10] [--out FILE]
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
from collections import defaultdict
from pathlib import Path

from report import emit
from schemas.mcap_file import read_recording
from schemas.recording import topic_kind

ROBOT_STREAMS = ("odom", "scan", "info", "truth")


def measure(recording_path: Path, skip_s: float) -> dict:
    recording = read_recording(recording_path)
    odometry = [m.log_time_ns for m in recording.messages if topic_kind(recording.prefix, m.topic) == "odom"]
    start, end = odometry[0] + int(skip_s * 1e9), odometry[-1]  # while the robots drive, after the fleet started
    kept = [m for m in recording.messages if start <= m.log_time_ns <= end]
    seconds = (end - start) / 1e9
    by_kind: dict[str, list[int]] = defaultdict(list)
    robots: set[str] = set()
    for message in kept:
        kind = topic_kind(recording.prefix, message.topic)
        by_kind[kind].append(len(message.data))
        if kind in ROBOT_STREAMS:
            robots.add(message.topic[len(recording.prefix) + 1:].split("/")[1])
    per_kind = {kind: {"bytes_per_s": sum(sizes) / seconds, "messages_per_s": len(sizes) / seconds,
                       "bytes_median": sorted(sizes)[len(sizes) // 2]} for kind, sizes in sorted(by_kind.items())}
    per_robot = {kind: per_kind[kind]["bytes_per_s"] / len(robots) for kind in ROBOT_STREAMS if kind in per_kind}
    return {"seconds": seconds, "robots": len(robots), "per_kind": per_kind,
            "per_robot_bytes_per_s": {**per_robot, "total": sum(per_robot.values())},
            "services_bytes_per_s": {kind: v["bytes_per_s"] for kind, v in per_kind.items()
                                     if kind not in ROBOT_STREAMS}}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--duration", type=float, default=60.0, help="wall seconds of the demo")
    parser.add_argument("--robots", type=int, default=3)
    parser.add_argument("--skip-s", type=float, default=10.0, help="seconds of the recording left out at its start")
    parser.add_argument("--port", type=int, default=7461, help="the demo router's port")
    parser.add_argument("--out")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "demo.mcap"
        demo = subprocess.run([sys.executable, "-m", "services.cli", "demo", "--duration", str(args.duration),
                               "--robots", str(args.robots), "--record", str(path), "--out", folder,
                               "--port", str(args.port)], capture_output=True, text=True)
        if demo.returncode != 0:
            sys.exit(f"fleetslam demo failed ({demo.returncode}):\n{demo.stdout[-2000:]}{demo.stderr[-2000:]}")
        emit({"benchmark": "demo_bandwidth", "settings": vars(args), **measure(path, args.skip_s)}, args.out)


if __name__ == "__main__":
    main()
