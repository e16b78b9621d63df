"""``fleetslam viz``: the live fleet in Rerun; with no output flag it serves the web viewer on port 9090.

True and estimated trajectories, poses, maps with covariance ellipses, MCL hypotheses and the services' latency,
each robot in its own colour.

A thin shell: it subscribes the robots' info and truth, the world truth, the central estimate, the D-SLAM map and
poses, the MCL poses and every service's stats; decodes and checks each message (seq, stamp, robot id against the
key); hands it to :class:`~services.viz.scene.Scene`, whose records it logs. Outputs: ``--spawn`` (native viewer),
``--serve PORT`` (web viewer), ``--save FILE.rrd``; with none of them, the web viewer on port 9090.
"""

from __future__ import annotations

import argparse
import logging
import time

import zenoh

from schemas.codec import decode
from schemas.config import VizSettings, add_settings_arguments, settings_from_args
from schemas.messages import Estimate, GroundTruth, MapEstimate, MclPose, PoseEstimate, RobotInfo, ServiceStats, WorldTruth
from schemas.streams import StreamTracker, Verdict
from services.mapfeed import MapFeed
from services.runtime import ServiceShell

log = logging.getLogger("fleetslam.viz")

DEFAULT_WEB_PORT = 9090


class Viz(ServiceShell):
    """Feeds every fleet message to the scene and logs what it returns."""

    name = "viz"
    tick_period_s = 0.1

    def __init__(self, settings: VizSettings):
        from services.viz.config import VizConfig
        from services.viz.recording import open_recording
        from services.viz.scene import Scene, blueprint

        super().__init__(settings)
        self.settings: VizSettings = settings
        self.scene = Scene(settings.core(VizConfig))
        self.tracker = StreamTracker()
        self.central_feed = MapFeed(self, Estimate, self.keys.central_state, "central_state")
        self.dslam_feed = MapFeed(self, MapEstimate, self.keys.dslam_state, "dslam_state")
        self.logged = 0
        self.recording, self.notes = open_recording(self.outputs(), blueprint(), f"fleet {settings.prefix}")

    def outputs(self):
        from services.viz.recording import Outputs

        s = self.settings
        serve = s.serve if s.serve is not None or s.spawn or s.save else DEFAULT_WEB_PORT
        return Outputs(save=s.save, spawn=s.spawn, serve=serve, grpc_port=s.grpc_port, grpc_bind=s.grpc_bind)

    def setup(self, session: zenoh.Session) -> None:
        from services.viz.scene import world_frame_record

        for note in self.notes:
            log.info("viz: %s", note)
            print(f"viz: {note}", flush=True)
        self.log([world_frame_record()])
        keys, prefix = self.keys, self.settings.prefix
        for key, tag in ((keys.all_robot_stream("info"), "info"), (keys.all_robot_stream("truth"), "truth"),
                         (keys.world_truth, "world"), (keys.central_estimate, "central"), (keys.dslam_map, "dslam_map"),
                         (f"{prefix}/dslam/pose/*", "dslam_pose"), (f"{prefix}/mcl/*/pose", "mcl"),
                         (keys.all_stats, "stats")):
            self.subscribe(key, tag, recover=tag not in ("info", "world", "stats"))
        for key, tag in ((keys.world_truth, "world"), (keys.all_robot_stream("info"), "info")):
            session.get(key, self._replies(tag), timeout=self.settings.info_timeout_s)

    def _replies(self, tag: str):
        def on_reply(reply: zenoh.Reply) -> None:
            if reply.ok is not None:
                self.enqueue(tag, str(reply.ok.key_expr), reply.ok.payload.to_bytes())

        return on_reply

    def log(self, records) -> None:
        from services.viz.recording import log_records

        if self.recording is not None:
            self.logged += log_records(self.recording, records)
            self.extra["records_logged"] = float(self.logged)

    def _accept(self, key: str, robot_id: str, position: int | None, stream: str, seq: int, stamp: float) -> bool:
        """The message names the robot of its key (``position``, None for fleet-wide messages) and is in order;
        seq 0 again starts a new run of the stream's robot."""
        if position is not None and not self.key_names_robot(key, robot_id, position):
            return False
        if seq == 0 and self.tracker.received(robot_id, stream):
            self.tracker.forget(robot_id)
            self.scene.new_run(robot_id)
        verdict = self.tracker.check(robot_id, stream, seq, stamp)
        if verdict is not Verdict.ACCEPT:
            self.reject(verdict.value, f"{key} seq {seq}")
            return False
        return True

    async def handle(self, tag: str, key: str, payload: bytes) -> None:
        wall, now, scene = time.time(), time.monotonic(), self.scene
        if tag == "info":
            info = decode(payload, RobotInfo)
            if self.key_names_robot(key, info.robot_id, 1):
                self.log(scene.robot_info(info))
        elif tag == "truth":
            message = decode(payload, GroundTruth)
            if self._accept(key, message.robot_id, 1, "truth", message.seq, message.stamp):
                self.log(scene.ground_truth(message, wall, now))
        elif tag == "world":
            self.log(scene.world_truth(decode(payload, WorldTruth)))
        elif tag in ("central", self.central_feed.reply_tag):
            message, reply = decode(payload, Estimate), tag == self.central_feed.reply_tag
            if reply or self._accept(key, "central", None, "estimate", message.seq, message.stamp):
                whole = self.central_feed.take(message, reply=reply)
                if not reply and whole is not None:  # a reply brings the map only: its poses are not the stream's
                    self.log(scene.estimate(whole, wall, now))
                elif not reply:  # no whole map yet (one was asked for): the poses alone
                    self.log([record for robot in message.robots
                              for record in scene.robot_pose(robot.robot_id, "central", robot.pose, robot.stamp, wall,
                                                             now)])
        elif tag in ("dslam_map", self.dslam_feed.reply_tag):
            message, reply = decode(payload, MapEstimate), tag == self.dslam_feed.reply_tag
            if reply or self._accept(key, "dslam", None, "map", message.seq, message.stamp):
                whole = self.dslam_feed.take(message, reply=reply)
                if whole is not None:
                    self.log(scene.map_estimate(whole, wall, now))
        elif tag == "dslam_pose":
            message = decode(payload, PoseEstimate)
            if self._accept(key, message.robot_id, 2, "dslam_pose", message.seq, message.stamp):
                self.log(scene.pose_estimate(message, wall, now))
        elif tag == "mcl":
            message = decode(payload, MclPose)
            if self._accept(key, message.robot_id, 1, "mcl", message.seq, message.stamp):
                self.log(scene.mcl_pose(message, wall, now))
        elif tag == "stats":
            self.log(scene.service_stats(decode(payload, ServiceStats), wall))

    async def tick(self) -> None:
        self.log(self.scene.flush(time.monotonic()))

    def on_stop(self) -> None:
        from services.viz.recording import close_recording

        if self.recording is not None:
            self.log(self.scene.flush(time.monotonic(), force=True))
            close_recording(self.recording)
            self.recording = None
            log.info("viz: %d records logged", self.logged)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_settings_arguments(parser, VizSettings)


def main(args: argparse.Namespace) -> int:
    from services.viz import rerun_missing

    settings = settings_from_args(VizSettings, args)
    if missing := rerun_missing():
        log.error("viz: %s", missing)
        return 2
    try:
        viz = Viz(settings)
    except ValueError as exc:
        log.error("viz: %s", exc)
        return 2
    try:
        return viz.serve()
    finally:
        viz.on_stop()  # closes the recording when the router was never reached
