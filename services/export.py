"""``fleetslam export rosbag2``: write a data set as a ROS 2 bag (MCAP or sqlite3) with its fleet file.

Any data set ``load_dataset`` reads (``mrclam:``, ``victoria-park:``, ``car-park:``, ``sim:WORLD``, ``mcap:``)
becomes a rosbag2 folder: per robot ``/<robot>/odom`` (nav_msgs/Odometry, one per control), ``/<robot>/landmarks``
(geometry_msgs/PoseArray, one per scan, detections in the sensor frame) and, when the data has truth,
``/<robot>/ground_truth`` (geometry_msgs/PoseStamped) and ``/world/landmarks_truth`` (visualization_msgs/MarkerArray).
``fleet.yaml`` beside the bag describes the robots (:mod:`services.ros2.fleet`), so ``fleetslam run --dataset
rosbag2:DIR`` reads it back. The conversions are :mod:`services.ros2.core`'s; landmark ids and detections of other
robots do not fit these messages and are not written. An existing DIR is kept unless ``--force`` (and then only
a bag folder is removed). Ctrl-C stops between two messages: the bag written so far is closed and usable.
"""

from __future__ import annotations

import argparse
import heapq
import logging
import shutil
import time
from pathlib import Path
from typing import Callable

from robots.dataset import Dataset
from schemas.config import ExportSettings, add_settings_arguments, settings_from_args

log = logging.getLogger("fleetslam.export")

LANDMARKS_TRUTH_TOPIC = "/world/landmarks_truth"
PROGRESS_PERIOD_S = 5.0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("format", choices=["rosbag2"], help="what to write: rosbag2 (a ROS 2 bag and its fleet.yaml)")
    add_settings_arguments(parser, ExportSettings)


def prepare_out(out: Path, force: bool) -> None:
    """Make room for the bag: refuse an existing ``out`` without ``force``; with it, remove only a bag folder."""
    if not out.exists():
        return
    if not force:
        raise FileExistsError(f"{out} exists (use --force to replace it)")
    if not out.is_dir() or not ((out / "metadata.yaml").is_file() or not any(out.iterdir())):
        raise FileExistsError(f"{out} is not a bag folder (no metadata.yaml): not replacing it")
    shutil.rmtree(out)


def export_fleet(dataset: Dataset, distro: str):
    """The fleet file describing the data set's robots as exported (and its true map's topic when it has one)."""
    from services.ros2.core import fleet_entry_for
    from services.ros2.fleet import FleetFile

    truth_offset = tuple(float(v) for v in dataset.meta.get("truth_offset", (0.0, 0.0)))
    entries = [fleet_entry_for(log).model_copy(update={"truth_offset": truth_offset})
               for log in dataset.robots.values()]
    return FleetFile(ros_distro=distro, robots=entries,
                     landmarks_truth_topic=LANDMARKS_TRUTH_TOPIC if dataset.landmarks is not None else None)


def export_rosbag2(dataset: Dataset, out: str | Path, storage: str = "mcap", distro: str = "jazzy",
                   duration: float | None = None, should_stop: Callable[[], bool] | None = None) -> dict:
    """Write ``dataset`` (its first ``duration`` s) as a rosbag2 folder ``out`` (which must not exist) with its
    ``fleet.yaml``; returns what was written (messages per topic, seconds of data, wall time, interrupted)."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    from robots.loaders.rosbag2 import FLEET_FILE_NAME
    from services.ros2.core import landmarks_truth_message, robot_log_messages, stamp_to_ns, typestore_for
    from services.ros2.fleet import save_fleet

    out = Path(out)
    fleet = export_fleet(dataset, distro)
    typestore = typestore_for(distro)
    start_ns = stamp_to_ns(dataset.start_stamp)
    until_ns = None if duration is None else stamp_to_ns(dataset.start_stamp + duration)
    streams = [robot_log_messages(dataset.robots[entry.robot_id], entry, typestore, fleet.map_frame)
               for entry in fleet.robots]
    if fleet.landmarks_truth_topic:
        truth_map = landmarks_truth_message(typestore, fleet.map_frame, start_ns, dataset.landmarks,
                                            dataset.landmark_ids)
        streams.insert(0, iter([(fleet.landmarks_truth_topic, truth_map.__msgtype__, start_ns, truth_map)]))
    counts: dict[str, int] = {}
    interrupted = False
    first_ns = last_ns = None
    wall0 = next_report = time.perf_counter()
    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    with Writer(out, version=9, storage_plugin=plugin) as writer:
        connections = {}
        try:
            for topic, msgtype, stamp_ns, msg in heapq.merge(*streams, key=lambda item: item[2]):
                if until_ns is not None and stamp_ns > until_ns:
                    break
                if should_stop is not None and should_stop():
                    raise KeyboardInterrupt
                if topic not in connections:
                    connections[topic] = writer.add_connection(topic, msgtype, typestore=typestore)
                writer.write(connections[topic], stamp_ns, typestore.serialize_cdr(msg, msgtype))
                counts[topic] = counts.get(topic, 0) + 1
                first_ns = stamp_ns if first_ns is None else first_ns
                last_ns = stamp_ns
                if time.perf_counter() >= next_report:
                    log.info("%.0f s of data written, %d messages", (last_ns - first_ns) / 1e9, sum(counts.values()))
                    next_report = time.perf_counter() + PROGRESS_PERIOD_S
        except KeyboardInterrupt:
            interrupted = True
            log.warning("interrupted: closing the bag written so far")
    save_fleet(fleet, out / FLEET_FILE_NAME)
    return {"out": str(out), "storage": storage, "distro": distro, "dataset": dataset.name,
            "robots": [entry.robot_id for entry in fleet.robots], "messages": counts,
            "data_s": 0.0 if first_ns is None else (last_ns - first_ns) / 1e9,
            "wall_s": time.perf_counter() - wall0, "interrupted": interrupted}


def load_for_export(settings: ExportSettings) -> Dataset:
    """The data set to export (a simulation takes the seed and the duration, 60 s by default)."""
    from robots.loaders import load_dataset

    if settings.dataset.partition(":")[0] == "sim":
        return load_dataset(settings.dataset, seed=settings.seed, duration=settings.duration or 60.0)
    return load_dataset(settings.dataset)


def main(args: argparse.Namespace) -> int:
    from schemas.transport import Shutdown

    settings = settings_from_args(ExportSettings, args)
    stop = Shutdown(notice="stopping after the current message; the bag written so far is closed",
                    second_interrupts=True)
    try:
        prepare_out(Path(settings.out), settings.force)
        dataset = load_for_export(settings)
        log.info("exporting %s (%s) to %s (%s, ROS %s)", dataset.name, ", ".join(dataset.robots), settings.out,
                 settings.storage, settings.distro)
        summary = export_rosbag2(dataset, settings.out, settings.storage, settings.distro, settings.duration,
                                 should_stop=stop.is_set)
    except (ValueError, OSError) as exc:
        log.error("cannot export: %s", exc)
        return 2
    finally:
        stop.restore()
    log.info("%s: %d messages, %.1f s of data in %.1f s (%s); fleet file %s/fleet.yaml", summary["out"],
             sum(summary["messages"].values()), summary["data_s"], summary["wall_s"],
             ", ".join(f"{topic} {n}" for topic, n in summary["messages"].items()), summary["out"])
    return 130 if summary["interrupted"] else 0
