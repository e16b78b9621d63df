"""``fleetslam evaluate``: compare every live estimate with the truth; publish stats; write a report on exit.

Subscribes to the robots' truth (``{prefix}/robots/*/truth``), the true map
(``{prefix}/world/truth``, also asked for once at start for late joining), and
every estimate: ``central/estimate`` (poses and map), ``dslam/map``,
``dslam/pose/*`` and ``mcl/*/pose``. It keeps each estimator's trajectory per
robot, publishes the live figures (ATE per estimator and robot, map RMSE) in
the ``extra`` of its ServiceStats on ``{prefix}/eval/stats``, and on exit
writes the report folder (:mod:`services.evaluation.report`). The scoring and
plotting modules (scipy, matplotlib) are imported on first use, so that every
``fleetslam`` command, which imports this module for its flags, starts fast.

A robot that is stopped and started again replays its log from the start: a
new run, whose truth starts again at seq 0 and whose stamps go back. The
evaluator follows the robots' liveliness and recognises a new run as the
services do (:meth:`~schemas.streams.StreamTracker.leave`, then
:meth:`~schemas.streams.StreamTracker.new_run` on the truth's seq 0). The
run that ended is then set aside whole, its truth and every estimator's
trajectory of the robot together, under the label ``{robot}#run{n}`` (n = 1
for its first run), and scored as a robot of its own; the new run fills
fresh trajectories under the robot's id, so the old run's truth is never
compared with the new run's estimates. An estimator's stream of that robot
(D-SLAM and MCL go on with their seq numbers) may then go back in time once:
the tracker forgot the robot's streams, and it counts seq gaps only from the
first message it hears of a stream (the evaluator observes a running fleet).
An estimate of the old run that arrives after the new run began (central
publishes its whole state at a steady rate) lands in the new trajectory but
is dropped when the new run's estimates, earlier in time, follow it: a
trajectory that goes back in time keeps only its samples before that time.
A robot whose truth goes back to seq 0 while its token stays is not a new
run: those messages are refused as out of order.
"""

from __future__ import annotations

import argparse
import asyncio
import logging
import threading
import time
from collections import Counter
from importlib import import_module

import numpy as np
import zenoh

from schemas.codec import decode
from schemas.config import EvaluateSettings, add_settings_arguments, settings_from_args
from schemas.messages import Estimate, GroundTruth, MapEstimate, MclPose, PoseEstimate, WorldTruth
from schemas.streams import StreamTracker, Verdict
from services.mapfeed import MapFeed
from services.runtime import ServiceShell

log = logging.getLogger("fleetslam.evaluate")


class Series:
    """A trajectory in arrays of a fixed capacity (``limit`` samples, allocated and touched when it is created,
    so that its memory does not grow as it fills): when full, every other sample is dropped (the span stays, the
    resolution halves). Its stamps only go forward (:meth:`add`)."""

    def __init__(self, limit: int):
        self.limit = limit
        self.size = 0
        self.stamps = np.full(limit, np.nan)
        self.poses = np.full((limit, 3), np.nan)
        self.covs: np.ndarray | None = None  # allocated at the first sample that has a covariance

    def __len__(self) -> int:
        return self.size

    def add(self, stamp: float, pose: np.ndarray, cov: np.ndarray | None = None) -> None:
        """Append a sample; one at the stamp of the last replaces it, and one before the last drops the samples
        after it (they belong to an earlier run of the robot: see the module docstring)."""
        n = self.size
        if n and stamp < self.stamps[n - 1]:
            n = self.size = int(np.searchsorted(self.stamps[:n], stamp, side="left"))
        if cov is not None and self.covs is None:
            self.covs = np.full((self.limit, 3, 3), np.nan)
        if n and stamp == self.stamps[n - 1]:
            index = n - 1
        else:
            if n == self.limit:
                n = self.size = self._thin()
            index = n
            self.size = n + 1
            self.stamps[index] = stamp
        self.poses[index] = pose
        if self.covs is not None:
            self.covs[index] = np.nan if cov is None else cov

    def _thin(self) -> int:
        """Keep every other sample, in place; the samples kept."""
        kept = (self.size + 1) // 2
        self.stamps[:kept] = self.stamps[: self.size : 2]
        self.poses[:kept] = self.poses[: self.size : 2]
        if self.covs is not None:
            self.covs[:kept] = self.covs[: self.size : 2]
        return kept

    def trajectory(self):
        """A copy of the samples so far (the arrays go on filling while it is scored elsewhere)."""
        from services.evaluation.metrics import Trajectory

        n = self.size
        return Trajectory(self.stamps[:n].copy(), self.poses[:n].copy(),
                          None if self.covs is None else self.covs[:n].copy())


class Evaluator(ServiceShell):
    """Collects truth and estimates; scores them live and at the end."""

    name = "eval"

    def __init__(self, settings: EvaluateSettings):
        super().__init__(settings)
        self.settings: EvaluateSettings = settings
        self.tick_period_s = settings.stats_period_s
        self.tracker = StreamTracker(missing_before_join=False)  # an observer: it counts the gaps after it joined
        self.runs_ended: Counter = Counter()  # robot id -> runs of it set aside (new runs recognised)
        self.missing_in_earlier_runs = 0  # seq gaps of the streams the tracker forgot at a new run
        self.truth: dict[str, Series] = {}
        self.estimates: dict[str, dict[str, Series]] = {}
        self.maps: dict[str, tuple[np.ndarray, np.ndarray | None]] = {}
        self.world: WorldTruth | None = None
        self.report_paths: list[str] = []
        self.mcl_unlocalized: set[str] = set()  # robots MCL reported on but has not localized (yet)
        self.central_feed = MapFeed(self, Estimate, self.keys.central_state, "central_state")
        self.dslam_feed = MapFeed(self, MapEstimate, self.keys.dslam_state, "dslam_state")

    def setup(self, session: zenoh.Session) -> None:
        prefix = self.settings.prefix
        self.subscribe(self.keys.all_robot_stream("truth"), "truth")
        self.subscribe(self.keys.world_truth, "world")
        self.subscribe(self.keys.central_estimate, "central")
        self.subscribe(self.keys.dslam_map, "dslam_map")
        self.subscribe(f"{prefix}/dslam/pose/*", "dslam_pose")
        self.subscribe(f"{prefix}/mcl/*/pose", "mcl")
        self._declared.append(
            session.liveliness().declare_subscriber(self.keys.alive_any, self._on_liveliness, history=True)
        )
        session.get(self.keys.world_truth, self._on_world_reply)
        # the report's plotting (matplotlib, about a second) is imported now, beside the fleet, not after SIGTERM
        threading.Thread(target=import_module, args=("services.evaluation.report",), daemon=True).start()

    def _on_liveliness(self, sample: zenoh.Sample) -> None:
        if sample.kind == zenoh.SampleKind.DELETE:
            self.enqueue("gone", str(sample.key_expr), b"")

    def _on_world_reply(self, reply: zenoh.Reply) -> None:
        if reply.ok is not None:
            self.enqueue("world", str(reply.ok.key_expr), reply.ok.payload.to_bytes())

    def _series(self, estimator: str, robot_id: str) -> Series:
        return self.estimates.setdefault(estimator, {}).setdefault(robot_id, Series(self.settings.max_samples))

    def new_run(self, robot_id: str, missing: int) -> None:
        """A robot that left started again at seq 0 (the tracker forgot its streams, which had ``missing``
        messages): set its run that ended aside (see the module docstring)."""
        self.runs_ended[robot_id] += 1
        self.missing_in_earlier_runs += missing
        label = f"{robot_id}#run{self.runs_ended[robot_id]}"
        for series in (self.truth, *self.estimates.values()):
            if robot_id in series:
                series[label] = series.pop(robot_id)
        if robot_id in self.mcl_unlocalized:
            self.mcl_unlocalized.remove(robot_id)
            self.mcl_unlocalized.add(label)
        log.info("robot %s started a new run; its run that ended is scored as %s", robot_id, label)

    def _central_map(self, message: Estimate | None) -> None:
        if message is not None:
            self.maps["central"] = (message.landmarks, message.landmark_covs)

    def _dslam_map(self, message: MapEstimate | None) -> None:
        if message is not None:
            self.maps["dslam"] = (message.landmarks, message.landmark_covariances())

    def _accept(self, robot_id: str, stream: str, seq: int, stamp: float, key: str) -> bool:
        verdict = self.tracker.check(robot_id, stream, seq, stamp)
        if verdict is not Verdict.ACCEPT:
            self.reject(verdict.value, f"{key} seq {seq}")
            return False
        return True

    async def handle(self, tag: str, key: str, payload: bytes) -> None:
        if tag == "gone":
            parsed = self.keys.parse_robot_key(key)
            if parsed is not None:
                self.tracker.leave(parsed[0])
        elif tag == "truth":
            message = decode(payload, GroundTruth)
            if not self.key_names_robot(key, message.robot_id, 1):
                return
            if message.seq == 0:  # perhaps a new run: keep its robot's seq gaps before the tracker forgets them
                missing = self.tracker.missing(message.robot_id)
                if self.tracker.new_run(message.robot_id, "truth", message.seq):
                    self.new_run(message.robot_id, missing)
            if self._accept(message.robot_id, "truth", message.seq, message.stamp, key):
                pose = message.pose if message.heading_known else np.array([*message.pose[:2], np.nan])
                self.truth.setdefault(message.robot_id, Series(self.settings.max_samples)).add(message.stamp, pose)
        elif tag == "world":
            self.world = decode(payload, WorldTruth)
        elif tag == "central":
            message = decode(payload, Estimate)
            if self._accept("central", "estimate", message.seq, message.stamp, key):
                for robot in message.robots:
                    self._series("central", robot.robot_id).add(robot.stamp, robot.pose, robot.cov)
                self._central_map(self.central_feed.take(message))
        elif tag == self.central_feed.reply_tag:
            self._central_map(self.central_feed.take(decode(payload, Estimate), reply=True))
        elif tag in ("dslam_map", self.dslam_feed.reply_tag):
            message = decode(payload, MapEstimate)
            if tag == self.dslam_feed.reply_tag or self._accept("dslam", "map", message.seq, message.stamp, key):
                self._dslam_map(self.dslam_feed.take(message, reply=tag == self.dslam_feed.reply_tag))
        elif tag == "dslam_pose":
            message = decode(payload, PoseEstimate)
            if self.key_names_robot(key, message.robot_id, 2) and self._accept(message.robot_id, "dslam_pose",
                                                                              message.seq, message.stamp, key):
                self._series("dslam", message.robot_id).add(message.stamp, message.pose, message.cov)
        elif tag == "mcl":
            message = decode(payload, MclPose)
            if self.key_names_robot(key, message.robot_id, 1) and self._accept(message.robot_id, "mcl", message.seq,
                                                                              message.stamp, key):
                if message.localized:  # before that the best pose is a guess: scoring it would say nothing
                    self.mcl_unlocalized.discard(message.robot_id)
                    self._series("mcl", message.robot_id).add(message.stamp, message.best_pose, message.best_cov)
                elif not self.estimates.get("mcl", {}).get(message.robot_id):
                    self.mcl_unlocalized.add(message.robot_id)

    @property
    def truth_offset(self) -> tuple[float, float]:
        return self.settings.truth_offset_x, self.settings.truth_offset_y

    @property
    def true_landmarks(self) -> np.ndarray | None:
        return None if self.world is None else self.world.landmarks

    def collected(self) -> tuple[dict, dict]:
        """(truth per robot, trajectories per estimator and robot) received so far."""
        truth = {rid: series.trajectory() for rid, series in self.truth.items() if len(series)}
        trajectories = {name: {rid: s.trajectory() for rid, s in robots.items() if len(s)}
                        for name, robots in self.estimates.items()}
        return truth, trajectories

    def score(self) -> tuple[dict, dict]:
        """Score everything received so far: (metrics, curves)."""
        return self._scorer()()

    def _scorer(self):
        """A scoring of a copy of everything received so far, to run in any thread: the loop goes on filling."""
        from services.evaluation.metrics import score_estimates

        truth, trajectories = self.collected()
        maps, true_landmarks = dict(self.maps), self.true_landmarks
        s = self.settings
        return lambda: score_estimates(trajectories, truth, maps, true_landmarks, self.truth_offset, s.map_cutoff_m,
                                       s.rpe_delta_s, s.max_gap_s)

    async def tick(self) -> None:
        """Score in a worker thread, so that messages are handled meanwhile; publish the figures in ``extra``."""
        metrics, _ = await asyncio.to_thread(self._scorer())
        restarts = sum(self.runs_ended.values())
        extra: dict[str, float] = {"robots_with_truth": float(len(self.truth) - restarts),  # not the runs set aside
                                   "robot_restarts": float(restarts)}
        for name, entry in metrics["summary"].items():
            for rid, value in entry["ate_rmse_m"].items():
                if value is not None:
                    extra[f"{name}.{rid}.ate_m"] = float(value)
            if entry.get("map_rmse_m") is not None:
                extra[f"{name}.map_rmse_m"] = float(entry["map_rmse_m"])
            if entry["landmarks"] and entry["landmarks"].get("matched") is not None:
                extra[f"{name}.landmarks_matched"] = float(entry["landmarks"]["matched"])
        self.extra = extra

    def on_stop(self) -> None:
        started = time.perf_counter()
        from services.evaluation.report import write_report

        imported = time.perf_counter()
        metrics, curves = self.score()
        scored = time.perf_counter()
        metrics["messages_in"] = dict(self.messages_in)
        metrics["rejected"] = dict(self.rejected)
        metrics["missing"] = self.tracker.missing() + self.missing_in_earlier_runs
        metrics["robot_restarts"] = dict(self.runs_ended)
        metrics["truth_offset"] = list(self.truth_offset)
        metrics["mcl_never_localized"] = sorted(self.mcl_unlocalized)
        truth, trajectories = self.collected()
        title = self.world.world if self.world is not None else "live fleet"
        written = write_report(self.settings.out, metrics, curves, truth, trajectories, self.maps,
                               self.true_landmarks, title, self.truth_offset)
        self.report_paths = [str(p) for p in written]
        log.info("evaluation report in %s (%d files; import %.2f s, scoring %.2f s, writing %.2f s)", self.settings.out,
                 len(written), imported - started, scored - imported, time.perf_counter() - scored)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_settings_arguments(parser, EvaluateSettings)


def main(args: argparse.Namespace) -> int:
    return Evaluator(settings_from_args(EvaluateSettings, args)).serve()
