"""The ROS 2 side of tests/integration/test_ros2.py, played by zenoh-ros2-sdk: a Python implementation of rmw_zenoh
that is not ours (its own keys, attachments, graph tokens, type hashes and message classes, built from .msg text).

It publishes the robots of a simulated fleet as ROS 2 robots (nav_msgs/Odometry and geometry_msgs/PoseArray on
``/<robot>/odom`` and ``/<robot>/landmarks``), subscribes to what ``fleetslam ros2`` sends back (each robot's fused
pose, ``/tf``, ``/fleetslam/map``), lists the ROS graph's topics as ``ros2 topic list`` would, and writes what it
saw to a JSON file. With ``--abuse`` it also sends what a broken ROS node could: samples without an attachment,
CDR that is not the topic's type, a foreign type hash, a repeated sequence number, a stamp going backwards.

Run as a process of its own (the SDK keeps one Zenoh session per process).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import struct
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))

SDK_TYPES = ("nav_msgs/msg/Odometry", "geometry_msgs/msg/PoseArray", "geometry_msgs/msg/PoseStamped",
             "visualization_msgs/msg/MarkerArray",
             "tf2_msgs/msg/TFMessage")


def write_msg_files(folder: Path, typestore) -> None:
    """The .msg text of every type the SDK needs (and their fields' types), one file per type, as ROS installs them:
    the SDK reads these instead of fetching its definitions from GitHub."""
    rule = "=" * 80 + "\n"
    for msgtype in SDK_TYPES:
        text, _ = typestore.generate_msgdef(msgtype, ros_version=2)
        blocks = text.split(rule)
        named = [(msgtype, blocks[0])] + [tuple(b.split("\n", 1)) for b in blocks[1:]]
        for name, body in named:
            package, *_, type_name = name.removeprefix("MSG: ").split("/")
            path = folder / package / "msg" / f"{type_name}.msg"
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text(body)


def as_fields(message, sdk_types) -> dict:
    """A rosbags message of our typestore as keyword fields of the SDK's own class of the same type."""
    values = {}
    for item in dataclasses.fields(message):
        value = getattr(message, item.name)
        if dataclasses.is_dataclass(value):
            value = sdk_types[value.__msgtype__](**as_fields(value, sdk_types))
        elif isinstance(value, list):
            value = [sdk_types[v.__msgtype__](**as_fields(v, sdk_types)) if dataclasses.is_dataclass(v) else v
                     for v in value]
        values[item.name] = value
    return values


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--port", type=int, required=True)
    parser.add_argument("--fleet", required=True, help="fleet file fleetslam ros2 runs with")
    parser.add_argument("--dataset", default="sim:arena", help="sim:WORLD, or any data set spec (mrclam:PATH, ...)")
    parser.add_argument("--seed", type=int, default=0, help="seed of a simulated fleet")
    parser.add_argument("--duration", type=float, default=20.0, help="seconds of each robot's data from its start")
    parser.add_argument("--speedup", type=float, default=4.0)
    parser.add_argument("--out", required=True)
    parser.add_argument("--abuse", action="store_true")
    parser.add_argument("--settle-s", type=float, default=8.0,
                        help="longest wait, after the last message, for the fused poses at the last stamp")
    args = parser.parse_args()

    from robots.loaders import load_dataset
    from services.ros2.core import robot_log_messages, typestore_for
    from schemas.transport import Shutdown
    from services.ros2.fleet import load_fleet
    from tests.helpers import wait_until

    fleet = load_fleet(args.fleet)
    ours = typestore_for(fleet.ros_distro)
    folder = Path(tempfile.mkdtemp(prefix="ros2-side-msgs-"))
    write_msg_files(folder, ours)

    from zenoh_ros2_sdk import ROS2Publisher, ROS2Subscriber, message_registry
    from zenoh_ros2_sdk.discovery import get_topic_names_and_types

    message_registry.get_registry(str(folder))
    ids = [r.robot_id for r in fleet.robots]
    options = dict(seed=args.seed, duration=args.duration, robot_ids=ids) if args.dataset.startswith("sim:") else {}
    dataset = load_dataset(args.dataset, **options)
    seen: dict[str, list] = {}
    lock = threading.Lock()

    def keep(topic: str):
        def callback(msg) -> None:
            with lock:
                seen.setdefault(topic, []).append(msg)
        return callback

    outputs = {f"/{r.robot_id}/fleetslam/odom": "nav_msgs/msg/Odometry" for r in fleet.robots}
    outputs.update({"/fleetslam/map": "visualization_msgs/msg/MarkerArray", "/tf": "tf2_msgs/msg/TFMessage"})
    subscribers = [ROS2Subscriber(topic=t, msg_type=m, callback=keep(t), router_port=args.port, node_name="checker")
                   for t, m in outputs.items()]
    streams = []
    publishers = {}
    for entry in fleet.robots:
        log = dataset.robots[entry.robot_id]
        until_ns = (log.start_stamp + args.duration) * 1e9  # as `fleetslam robot --duration`: from its own start
        for topic, msgtype, stamp_ns, message in robot_log_messages(log, entry, ours):
            if topic not in publishers:
                publishers[topic] = ROS2Publisher(topic=topic, msg_type=msgtype, router_port=args.port,
                                                  node_name=f"{entry.robot_id}_driver")
            if stamp_ns <= until_ns:
                streams.append((stamp_ns, topic, message))
    streams.sort(key=lambda item: item[0])
    sdk_types = next(iter(publishers.values())).session_mgr.store.types
    wait_until(lambda: all(p.pub.matching_status.matching for p in publishers.values()), 30, 0.05,
               "the bridge's subscriptions to match every publisher")
    shutdown = Shutdown()
    sent: dict[str, int] = {}
    wall0, data0 = time.monotonic(), streams[0][0] * 1e-9
    for stamp_ns, topic, message in streams:
        due = wall0 + (stamp_ns * 1e-9 - data0) / args.speedup
        if (delay := due - time.monotonic()) > 0 and shutdown.wait(delay):
            break  # paced as the data's stamps say; Ctrl-C stops it
        publishers[topic].publish(**as_fields(message, sdk_types))
        sent[topic] = sent.get(topic, 0) + 1
    abused = abuse(publishers, streams, ours, sdk_types) if args.abuse else {}
    last_stamp = {rid: max(ns for ns, topic, _ in streams if topic == f"/{rid}/odom") * 1e-9 for rid in ids}

    def fused_to_the_end() -> bool:
        with lock:
            poses = {rid: seen.get(f"/{rid}/fleetslam/odom", []) for rid in ids}
            return all(poses[rid] and stamp_of(poses[rid][-1]) >= last_stamp[rid] - 1e-6 for rid in ids) \
                and all(seen.get(topic) for topic in ("/fleetslam/map", "/tf"))

    try:
        wait_until(fused_to_the_end, args.settle_s, 0.05, "every robot's fused pose at its last stamp, a map, /tf")
    except AssertionError:
        pass  # what came is reported; the caller judges it
    topics = get_topic_names_and_types(router_port=args.port, timeout=2.0)
    with lock:
        result = {
            "sent": sent, "abused": abused, "topics": [[name, types] for name, types in topics],
            "received": {topic: len(messages) for topic, messages in seen.items()},
            "last_pose": {topic.split("/")[1]: [messages[-1].pose.pose.position.x, messages[-1].pose.pose.position.y,
                                                stamp_of(messages[-1])]
                          for topic, messages in seen.items() if topic.endswith("/fleetslam/odom")},
            "last_map": {ns: [[m.pose.position.x, m.pose.position.y] for m in markers]
                         for ns, markers in last_maps(seen.get("/fleetslam/map", [])).items()},
            "tf_children": sorted({t.child_frame_id for msg in seen.get("/tf", []) for t in msg.transforms}),
        }
    Path(args.out).write_text(json.dumps(result))
    for entity in [*publishers.values(), *subscribers]:
        entity.close()
    os._exit(0)  # the SDK's session lives in a singleton with callbacks: leave without waiting on it


def stamp_of(message) -> float:
    return message.header.stamp.sec + message.header.stamp.nanosec * 1e-9


def last_maps(messages) -> dict[str, list]:
    """The landmarks (ADD markers) of the last MarkerArray of each namespace."""
    maps: dict[str, list] = {}
    for msg in messages:
        adds = [m for m in msg.markers if m.action == 0]
        if adds:
            maps[adds[0].ns] = adds
    return maps


def abuse(publishers, streams, ours, sdk_types) -> dict[str, int]:
    """Broken samples on the first robot's odometry key, each kind once: raw puts under a GID of their own (so the
    SDK publisher's sequence numbers are untouched), then one message of the run's start again through the SDK."""
    odom_topic = next(topic for _, topic, _ in streams if topic.endswith("/odom"))
    odom = publishers[odom_topic]
    key, session = odom.keyexpr, odom.session_mgr.session
    first = next(message for _, topic, message in streams if topic == odom_topic)
    good_cdr = bytes(ours.serialize_cdr(first, "nav_msgs/msg/Odometry"))
    gid = os.urandom(16)

    def attachment(sequence: int) -> bytes:
        return struct.pack("<qqB", sequence, time.time_ns(), len(gid)) + gid

    session.put(key, good_cdr)  # no attachment
    session.put(key, b"\x00\x01\x00\x00" + b"\xff" * 7, attachment=attachment(1))  # not an Odometry
    session.put(key.rsplit("/", 1)[0] + "/RIHS01_" + "0" * 64, good_cdr, attachment=attachment(2))  # foreign hash
    session.put(key, good_cdr, attachment=attachment(1))  # sequence number 1 again
    odom.publish(**as_fields(first, sdk_types))  # a message from the run's very start: its stamp goes backwards
    return {"no_attachment": 1, "bad_cdr": 1, "type_hash_mismatch": 1, "duplicate": 1, "time_backwards": 1}


if __name__ == "__main__":
    sys.exit(main())
