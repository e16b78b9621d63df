"""ROS 2 robots live against native robots: the same MR.CLAM replay fused by central FastSLAM and D-SLAM, once
published by ``fleetslam robot`` processes and once as ROS 2 robots over rmw_zenoh (zenoh-ros2-sdk publishing
nav_msgs/Odometry and geometry_msgs/PoseArray, tests/integration/ros2_side.py) through ``fleetslam ros2``.

Both paths carry the same information: no landmark ids (PoseArray has none; the native robots run with
``--no-publish-ids``). They differ in one thing PoseArray cannot carry, the detections of other robots. Per seed
and path: each robot's ATE (central, D-SLAM) against the truth, each map's RMSE and spurious landmarks against the
survey, and the messages that reached fleetslam's keys against those the data holds (lost = their difference).

    python benchmarks/ros2_live.py --seeds 3 --duration 300 --speedup 10 --out reports/ros2_live.json
"""

from __future__ import annotations

import argparse
import logging
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from benchmarks.report import emit, over_seeds, summary  # noqa: E402
from robots.loaders import load_dataset  # noqa: E402
from schemas.messages import Estimate, MapEstimate, PoseEstimate  # noqa: E402
from services.evaluation.metrics import ate, interpolate_poses, map_error  # noqa: E402
from services.ros2.core import fleet_entry_for  # noqa: E402
from services.ros2.fleet import FleetFile, save_fleet  # noqa: E402
from services.mapfeed import assemble  # noqa: E402
from tests.helpers import Collector, Processes, client_session, free_port, wait_for_port, wait_until  # noqa: E402

log = logging.getLogger("ros2_live")


def trajectories(collector: Collector, model, robots: list[str]) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """(stamps, poses) of each robot from every estimate a collector kept."""
    paths: dict[str, list] = {rid: [] for rid in robots}
    for message in collector.decoded(model):
        entries = message.robots if isinstance(message, Estimate) else [message]
        for entry in entries:
            if entry.robot_id in paths:
                paths[entry.robot_id].append((entry.stamp, entry.pose))
    out = {}
    for rid, samples in paths.items():
        samples.sort(key=lambda item: item[0])
        stamps = np.array([s for s, _ in samples])
        poses = np.array([p for _, p in samples]).reshape(-1, 3)
        out[rid] = (stamps, poses)
    return out


def robot_ates(paths, dataset, robots) -> dict[str, float | None]:
    result = {}
    for rid in robots:
        stamps, poses = paths[rid]
        log_ = dataset.robots[rid]
        if stamps.size == 0:
            result[rid] = None
            continue
        truth = interpolate_poses(log_.truth_stamp, log_.truth_pose, stamps, 1.0)
        valid = np.all(np.isfinite(truth[:, :2]), axis=-1)
        result[rid] = ate(poses[valid, :2], truth[valid, :2])["rmse_m"]
    return result


def run_once(path: str, seed: int, args, dataset, robots: list[str], fleet_file: Path, folder: Path) -> dict:
    """One live run: router, central, assoc, D-SLAM and the robots of ``path`` ("native" or "ros2")."""
    port, prefix = free_port(), f"b{seed}{path}"
    endpoint = f"tcp/127.0.0.1:{port}"
    env = {k: v for k, v in os.environ.items() if not k.startswith("FLEETSLAM_")}
    env.update(FLEETSLAM_ZENOH_CONNECT=endpoint, FLEETSLAM_PREFIX=prefix, PYTHONUNBUFFERED="1")
    logs = folder / f"{path}-{seed}"
    logs.mkdir(parents=True, exist_ok=True)
    processes = Processes(logs, env)
    processes.start("router", "router", "--listen", endpoint)
    wait_for_port(port)
    session = client_session(endpoint)
    try:
        central = Collector(session, f"{prefix}/central/estimate")
        dslam_poses = Collector(session, f"{prefix}/dslam/pose/*")
        dslam_map = Collector(session, f"{prefix}/dslam/map")
        forwarded = Collector(session, f"{prefix}/robots/*/*")
        stats = Collector(session, f"{prefix}/**/stats")
        processes.start("central", "central", "--association", "shared", "--seed", str(seed))
        processes.start("assoc", "assoc")
        processes.start("dslam", "dslam", "--association", "auto")
        services = ["central", "dslam", "assoc"]
        if path == "ros2":
            processes.start("ros2", "ros2", "--fleet", str(fleet_file))
            services.append("ros2")
        wait_until(lambda: {k.split("/")[1] for k, _ in stats.snapshot()} >= set(services), 120,
                   what="the services' first stats")
        started = time.monotonic()
        if path == "native":
            children = [processes.start(rid, "robot", "--replay", f"{args.dataset}:{rid.removeprefix('r')}",
                                        "--speedup", str(args.speedup), "--duration", str(args.duration),
                                        "--no-publish-ids", "--no-publish-world")
                        for rid in robots]
            for child in children:
                child.wait(timeout=args.duration / args.speedup * 4 + 120)
        else:
            out = logs / "side.json"
            subprocess.run([sys.executable, str(REPO / "tests" / "integration" / "ros2_side.py"), "--port", str(port),
                            "--fleet", str(fleet_file), "--dataset", args.dataset, "--duration", str(args.duration),
                            "--speedup", str(args.speedup), "--settle-s", "1", "--out", str(out)],
                           check=True, timeout=args.duration / args.speedup * 6 + 180, env=env,
                           stdout=open(logs / "side.log", "w"), stderr=subprocess.STDOUT)
        wall_s = time.monotonic() - started
        ends = {rid: dataset.robots[rid].start_stamp + args.duration for rid in robots}  # each robot's own start
        expected = {rid: {"odom": int((dataset.robots[rid].odom_stamp <= ends[rid]).sum()),
                          "scan": int((dataset.robots[rid].scan_stamp <= ends[rid]).sum())} for rid in robots}

        def arrived() -> dict:
            return {rid: {stream: forwarded.count(lambda k, rid=rid, s=stream: k == f"{prefix}/robots/{rid}/{s}")
                          for stream in ("odom", "scan")} for rid in robots}

        try:
            wait_until(lambda: arrived() == expected, 30, what="every message on fleetslam's keys")
        except AssertionError:
            log.warning("%s seed %d: %s arrived of %s", path, seed, arrived(), expected)
        time.sleep(args.drain_s)  # the services finish what they hold, then publish their estimates
        central_paths = trajectories(central, Estimate, robots)
        dslam_paths = trajectories(dslam_poses, PoseEstimate, robots)
        last_central = assemble(central.decoded(Estimate))
        last_dslam = assemble(dslam_map.decoded(MapEstimate))
        got = arrived()
        run = {
            "path": path, "seed": seed, "wall_s": wall_s,
            "lost": sum(expected[r][s] - got[r][s] for r in robots for s in ("odom", "scan")),
            "central_ate_m": robot_ates(central_paths, dataset, robots),
            "dslam_ate_m": robot_ates(dslam_paths, dataset, robots),
            "central_map": None if last_central is None else map_error(last_central.landmarks, dataset.landmarks),
            "dslam_map": None if last_dslam is None else map_error(last_dslam.landmarks, dataset.landmarks),
        }
        for name in ("central_map", "dslam_map"):
            if run[name] is not None:
                run[name].pop("pairs", None)
        return run
    finally:
        session.close()
        processes.stop_all()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dataset", default="mrclam:", help="MR.CLAM data set spec (robots taken by number)")
    parser.add_argument("--robots", default="r1,r2")
    parser.add_argument("--seeds", type=int, default=3, help="seeds 0..N-1 of central")
    parser.add_argument("--duration", type=float, default=300.0, help="seconds of data from the start")
    parser.add_argument("--speedup", type=float, default=10.0)
    parser.add_argument("--drain-s", type=float, default=5.0)
    parser.add_argument("--out", default=None)
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s", datefmt="%H:%M:%S")
    robots = args.robots.split(",")
    dataset = load_dataset(args.dataset)
    folder = Path(tempfile.mkdtemp(prefix="ros2-live-"))
    fleet_file = folder / "fleet.yaml"
    save_fleet(FleetFile(robots=[fleet_entry_for(dataset.robots[rid]) for rid in robots]), fleet_file)
    runs = []
    for seed in range(args.seeds):
        for path in ("native", "ros2"):
            run = run_once(path, seed, args, dataset, robots, fleet_file, folder)
            log.info("%s seed %d: lost %d, central ATE %s, D-SLAM ATE %s, maps %s / %s", path, seed, run["lost"],
                     run["central_ate_m"], run["dslam_ate_m"], (run["central_map"] or {}).get("rmse_m"),
                     (run["dslam_map"] or {}).get("rmse_m"))
            runs.append(run)
    flat = [{"path": r["path"], "lost": r["lost"], "wall_s": r["wall_s"],
             **{f"central_{rid}": r["central_ate_m"][rid] for rid in robots},
             **{f"dslam_{rid}": r["dslam_ate_m"][rid] for rid in robots},
             "central_map_rmse_m": (r["central_map"] or {}).get("rmse_m"),
             "central_spurious": (r["central_map"] or {}).get("spurious"),
             "dslam_map_rmse_m": (r["dslam_map"] or {}).get("rmse_m")} for r in runs]
    keys = [k for k in flat[0] if k != "path"]
    result = {"benchmark": "ros2_live", "dataset": args.dataset, "robots": robots, "duration_s": args.duration,
              "speedup": args.speedup, "seeds": args.seeds, "logs": str(folder),
              "by_path": {path: over_seeds([f for f in flat if f["path"] == path], keys) for path in ("native", "ros2")},
              "runs": runs}
    emit(summary(result), args.out)


if __name__ == "__main__":
    main()
