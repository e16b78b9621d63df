"""The fleet as a Rerun scene: pure functions and one stateful :class:`Scene`, from decoded messages (or an offline
run) to :class:`Record` s (entity path, archetype, times). No Zenoh, no I/O, no clock: the caller passes ``now``
(any monotonic seconds: wall time live, data time offline) for the throttles and logs the records itself.

Entity layout (every robot in its own fixed colour, each source in a shade of it)::

    world/truth/landmarks                    Points2D (static)       true landmarks (WorldTruth, data set)
    world/robots/{rid}/{source}/pose         Arrows2D                current pose (Points2D when the heading is unknown)
    world/robots/{rid}/{source}/path/{k}     LineStrips2D            trajectory, in segments of path_segment_points
    world/robots/{rid}/mcl/hypotheses        Arrows2D                MCL hypotheses; thickness and opacity by weight
    world/map/{source}/landmarks             Points2D                estimated landmarks (labels: ids)
    world/map/{source}/ellipses              LineStrips2D            their covariance ellipses (ellipse_confidence)
    stats/{service}/{instance}/latency_ms    Scalars [median, p99]   ServiceStats latency

``source`` is ``truth``, ``central`` (FastSLAM), ``dslam``, ``mcl`` live, or the estimator's name offline.
Times: timeline ``stamp`` (the data's clock: a duration, or a Unix timestamp for data stamped after 2001) and,
live, ``wall`` (arrival time).
"""

from __future__ import annotations

import math
import zlib
from dataclasses import dataclass, field
from typing import Callable, Iterable, Iterator

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from robots.gaussian import ellipse_outlines
from schemas.messages import Estimate, GroundTruth, MapEstimate, MclPose, PoseEstimate, RobotInfo, ServiceStats, WorldTruth
from services.viz.config import VizConfig

PALETTE = (
    (31, 119, 180), (255, 127, 14), (44, 160, 44), (214, 39, 40), (148, 103, 189),
    (140, 86, 75), (227, 119, 194), (188, 189, 34), (23, 190, 207),
)
MAP_COLOURS = {"truth": (150, 150, 150), "central": (30, 30, 30), "dslam": (0, 120, 120)}
OTHER_MAP_COLOUR = (30, 30, 30)
SOURCE_SHADES = {"truth": ("white", 0.45), "central": ("white", 0.0), "dslam": ("black", 0.4), "mcl": ("white", 0.2)}
EPOCH_STAMP = 1e9  # stamps past this (2001-09-09) are Unix times: the stamp timeline is then a timestamp
DEFAULT_ARROW_M = 0.5


@dataclass(frozen=True)
class Record:
    """One log call: ``archetype`` at ``path`` at data time ``stamp`` and arrival time ``wall`` (either may be None)."""

    path: str
    archetype: object
    stamp: float | None = None
    wall: float | None = None
    static: bool = False


def time_arguments(record: Record) -> list[tuple[str, dict]]:
    """``[(timeline, set_time keyword arguments)]`` of a record."""
    times = []
    if record.stamp is not None:
        kind = "timestamp" if record.stamp >= EPOCH_STAMP else "duration"
        times.append(("stamp", {kind: record.stamp}))
    if record.wall is not None:
        times.append(("wall", {"timestamp": record.wall}))
    return times


def robot_colour(robot_id: str) -> tuple[int, int, int]:
    """A robot's fixed colour: ``r3`` (any id ending in a number n) is palette entry n-1, others by CRC32 of the id."""
    digits = len(robot_id) - len(robot_id.rstrip("0123456789"))
    index = int(robot_id[-digits:]) - 1 if digits else zlib.crc32(robot_id.encode())
    return PALETTE[index % len(PALETTE)]


def source_colour(robot_id: str, source: str) -> tuple[int, int, int]:
    """The robot's colour shaded for a source: truth lighter, D-SLAM darker, MCL a little lighter."""
    towards, amount = SOURCE_SHADES.get(source, ("black", 0.2))
    target = 255 if towards == "white" else 0
    return tuple(int(round(c + (target - c) * amount)) for c in robot_colour(robot_id))


def map_colour(source: str) -> tuple[int, int, int]:
    return MAP_COLOURS.get(source, OTHER_MAP_COLOUR)


def robot_path(robot_id: str, source: str, leaf: str) -> str:
    return f"world/robots/{robot_id}/{rr.escape_entity_path_part(source)}/{leaf}"


def map_path(source: str, leaf: str) -> str:
    return f"world/map/{rr.escape_entity_path_part(source)}/{leaf}"


def stats_path(service: str, instance: str) -> str:
    return f"stats/{rr.escape_entity_path_part(service)}/{rr.escape_entity_path_part(instance)}/latency_ms"


def covariance_ellipses(means: np.ndarray, covs: np.ndarray, confidence: float, vertices: int) -> np.ndarray:
    """Closed polygons ``(L, vertices + 1, 2)`` of each landmark's ``confidence`` ellipse."""
    return ellipse_outlines(np.asarray(means, float).reshape(-1, 2), np.asarray(covs, float).reshape(-1, 2, 2),
                            confidence, vertices + 1)


def pose_archetype(poses: np.ndarray, colour, arrow_m: float, labels: list[str] | None = None,
                   show_labels: bool = False):
    """Arrows2D (position, heading) of poses ``(n, 3)``; Points2D when a heading is unknown (NaN)."""
    poses = np.asarray(poses, float).reshape(-1, 3)
    if not np.all(np.isfinite(poses[:, 2])):
        return rr.Points2D(poses[:, :2], colors=[colour], radii=rr.Radius.ui_points(4.0), labels=labels,
                           show_labels=show_labels, draw_order=30.0)
    vectors = arrow_m * np.stack([np.cos(poses[:, 2]), np.sin(poses[:, 2])], axis=-1)
    return rr.Arrows2D(origins=poses[:, :2], vectors=vectors, colors=[colour], radii=rr.Radius.ui_points(1.5),
                       labels=labels, show_labels=show_labels, draw_order=30.0)


def hypotheses_archetype(means: np.ndarray, weights: np.ndarray, colour, arrow_m: float):
    """Arrows2D of MCL hypotheses: thicker and more opaque with weight, labelled with it."""
    means = np.asarray(means, float).reshape(-1, 3)
    weights = np.clip(np.asarray(weights, float).reshape(-1), 0.0, 1.0)
    vectors = arrow_m * np.stack([np.cos(means[:, 2]), np.sin(means[:, 2])], axis=-1)
    colours = np.column_stack([np.tile(colour, (len(weights), 1)), 60 + 195 * weights]).astype(np.uint8)
    return rr.Arrows2D(origins=means[:, :2], vectors=vectors, colors=colours,
                       radii=rr.Radius.ui_points(0.75 + 3.0 * weights), labels=[f"{w:.2f}" for w in weights],
                       show_labels=True, draw_order=25.0)


def landmark_records(source: str, means: np.ndarray, ids: np.ndarray | None, stamp: float | None,
                     wall: float | None) -> list[Record]:
    """The estimated landmarks of one map source as Points2D labelled with their ids."""
    means = np.asarray(means, float).reshape(-1, 2)
    labels = None if ids is None else [str(int(i)) for i in np.asarray(ids).reshape(-1)]
    points = rr.Points2D(means, colors=[map_colour(source)], radii=rr.Radius.ui_points(3.0), labels=labels,
                         show_labels=False, draw_order=20.0)
    return [Record(map_path(source, "landmarks"), points, stamp, wall)]


def ellipse_records(source: str, means: np.ndarray, covs: np.ndarray, config: VizConfig, stamp: float | None,
                    wall: float | None) -> list[Record]:
    """The covariance ellipses of one map source as LineStrips2D."""
    polygons = covariance_ellipses(means, covs, config.ellipse_confidence, config.ellipse_vertices)
    strips = rr.LineStrips2D(list(polygons), colors=[map_colour(source)], radii=rr.Radius.ui_points(0.6),
                             draw_order=10.0)
    return [Record(map_path(source, "ellipses"), strips, stamp, wall)]


def true_landmark_records(landmarks: np.ndarray, ids: np.ndarray | None) -> list[Record]:
    """The true landmarks, static (they do not move)."""
    labels = None if ids is None else [str(int(i)) for i in np.asarray(ids).reshape(-1)]
    points = rr.Points2D(np.asarray(landmarks, float).reshape(-1, 2), colors=[map_colour("truth")],
                         radii=rr.Radius.ui_points(6.0), labels=labels, show_labels=False, draw_order=5.0)
    return [Record("world/truth/landmarks", points, static=True)]


def blueprint(with_stats: bool = True) -> rrb.Blueprint:
    """The fleet map (y up) beside, live, the services' latency; the time panel on the data's clock."""
    fleet = rrb.Spatial2DView(origin="/", contents="+ /world/**", name="fleet map")
    layout = rrb.Horizontal(fleet, rrb.TimeSeriesView(origin="stats", name="service latency (ms)"),
                            column_shares=[3, 1]) if with_stats else fleet
    return rrb.Blueprint(layout, rrb.TimePanel(timeline="stamp", state="collapsed"), rrb.SelectionPanel(state="collapsed"))


def world_frame_record() -> Record:
    """Flip y under ``world`` so the map reads with y up (a 2-D view draws y down; the view's origin is the root,
    above ``world``, so the flip applies); logged values keep their sign."""
    return Record("world", rr.Transform3D(scale=[1.0, -1.0, 1.0]), static=True)


@dataclass
class PathBuilder:
    """One trajectory as segments ``{base}/{k}``: the open segment is re-logged at most ``period_s`` apart; a full
    one (``segment_points``) is logged one last time and a new one starts at its last point."""

    base: str
    colour: tuple
    radius: float
    period_s: float
    segment_points: int
    min_step: float
    segment: int = 0
    points: list = field(default_factory=list)
    stamp: float | None = None
    wall: float | None = None
    last_log: float = -math.inf
    dirty: bool = False

    def add(self, xy, stamp: float | None, wall: float | None, now: float) -> list[Record]:
        xy = (float(xy[0]), float(xy[1]))
        if not all(map(math.isfinite, xy)):
            return []
        if self.points and math.dist(xy, self.points[-1]) < self.min_step:
            return []
        self.points.append(xy)
        self.stamp, self.wall, self.dirty = stamp, wall, True
        if len(self.points) >= self.segment_points:
            records = self._emit(now)
            self.segment += 1
            self.points = self.points[-1:]
            return records
        return self.flush(now)

    def flush(self, now: float, force: bool = False) -> list[Record]:
        if self.dirty and (force or now - self.last_log >= self.period_s):
            return self._emit(now)
        return []

    def restart(self) -> None:
        """Break the line (a new run of the robot): the next point opens a new segment."""
        if len(self.points) > 1:
            self.segment += 1
        self.points, self.dirty = [], False

    def _emit(self, now: float) -> list[Record]:
        if len(self.points) < 2:
            return []  # a single point draws nothing: the first line goes out as soon as there are two
        self.last_log, self.dirty = now, False
        strip = rr.LineStrips2D([np.asarray(self.points)], colors=[self.colour], radii=rr.Radius.ui_points(self.radius),
                                draw_order=15.0)
        return [Record(f"{self.base}/{self.segment}", strip, self.stamp, self.wall)]


class Throttle:
    """Latest wins: at most one item per key every ``period_s``; an item held back is built and logged by
    :meth:`flush` once its time comes (so the last map is never lost)."""

    def __init__(self, period_s: float):
        self.period_s = period_s
        self.last: dict[str, float] = {}
        self.pending: dict[str, Callable[[], list[Record]]] = {}

    def offer(self, key: str, now: float, make: Callable[[], list[Record]]) -> list[Record]:
        if now - self.last.get(key, -math.inf) >= self.period_s:
            self.last[key] = now
            self.pending.pop(key, None)
            return make()
        self.pending[key] = make
        return []

    def flush(self, now: float, force: bool = False) -> list[Record]:
        records = []
        for key in [k for k in self.pending if force or now - self.last[k] >= self.period_s]:
            self.last[key] = now
            records.extend(self.pending.pop(key)())
        return records


class Scene:
    """What the viewer shows, built up from messages: each method returns the records to log now."""

    def __init__(self, config: VizConfig | None = None):
        self.config = config or VizConfig()
        self.arrow_m: dict[str, float] = {}
        self.paths: dict[tuple[str, str], PathBuilder] = {}
        self.maps = Throttle(1.0 / self.config.map_hz)
        self.hypotheses = Throttle(1.0 / self.config.hypotheses_hz)
        self.series: set[str] = set()
        self.latest_stamp: float | None = None

    # ------------------------------------------------------------ building blocks (also used offline)
    def robot_pose(self, robot_id: str, source: str, pose, stamp: float | None, wall: float | None, now: float,
                   label: str | None = None) -> list[Record]:
        """A robot's pose from one source: its arrow, and a point of its trajectory."""
        pose = np.asarray(pose, float).reshape(3)
        if stamp is not None:
            self.latest_stamp = stamp if self.latest_stamp is None else max(self.latest_stamp, stamp)
        colour = source_colour(robot_id, source)
        text = label or f"{robot_id} {source}"
        records = [Record(robot_path(robot_id, source, "pose"),
                          pose_archetype(pose[None], colour, self.arrow_length(robot_id), [text],
                                         show_labels=source in ("truth", "central")), stamp, wall)]
        return records + self.path(robot_id, source).add(pose[:2], stamp, wall, now)

    def path(self, robot_id: str, source: str) -> PathBuilder:
        key = (robot_id, source)
        if key not in self.paths:
            self.paths[key] = PathBuilder(robot_path(robot_id, source, "path"), source_colour(robot_id, source),
                                          0.8 if source == "truth" else 1.2, 1.0 / self.config.path_hz,
                                          self.config.path_segment_points, self.config.path_min_step_m)
        return self.paths[key]

    def landmark_map(self, source: str, means, covs, ids, stamp: float | None, wall: float | None,
                     now: float) -> list[Record]:
        """An estimated map (throttled per source): landmarks, and ellipses of the covariances given (``covs``
        ``(L, 2, 2)`` for every landmark, or None)."""
        means = np.asarray(means, float).reshape(-1, 2)

        def make() -> list[Record]:
            records = landmark_records(source, means, ids, stamp, wall)
            if covs is not None:
                records += ellipse_records(source, means, covs, self.config, stamp, wall)
            return records

        return self.maps.offer(source, now, make)

    def arrow_length(self, robot_id: str) -> float:
        return self.arrow_m.get(robot_id, DEFAULT_ARROW_M)

    def flush(self, now: float, force: bool = False) -> list[Record]:
        """Records held back by a throttle whose time has come (all of them with ``force``, e.g. at the end)."""
        records = self.maps.flush(now, force) + self.hypotheses.flush(now, force)
        for builder in self.paths.values():
            records += builder.flush(now, force)
        return records

    def new_run(self, robot_id: str) -> None:
        """A robot started a new run: its trajectories break instead of jumping back to the start."""
        for (rid, _), builder in self.paths.items():
            if rid == robot_id:
                builder.restart()

    # ------------------------------------------------------------ messages (live)
    def robot_info(self, info: RobotInfo) -> list[Record]:
        """Remembers the robot's scale: pose arrows are ``arrow_fraction`` of its sensor range long."""
        self.arrow_m[info.robot_id] = self.config.arrow_fraction * info.sensor.max_range
        return []

    def ground_truth(self, message: GroundTruth, wall: float | None, now: float) -> list[Record]:
        pose = message.pose if message.heading_known else np.array([*message.pose[:2], np.nan])
        return self.robot_pose(message.robot_id, "truth", pose, message.stamp, wall, now, label=message.robot_id)

    def world_truth(self, message: WorldTruth) -> list[Record]:
        return true_landmark_records(message.landmarks, message.landmark_ids)

    def estimate(self, message: Estimate, wall: float | None, now: float) -> list[Record]:
        """The central FastSLAM estimate: every robot's pose, and the shared map with ellipses."""
        records = []
        for robot in message.robots:
            records += self.robot_pose(robot.robot_id, "central", robot.pose, robot.stamp, wall, now)
        return records + self.landmark_map("central", message.landmarks, message.landmark_covs, message.landmark_ids,
                                           message.stamp, wall, now)

    def map_estimate(self, message: MapEstimate, wall: float | None, now: float) -> list[Record]:
        """The D-SLAM map: every landmark, ellipses for those whose marginal covariance the message carries."""
        stamp = message.stamp
        means, ids = message.landmarks, message.landmark_ids
        row = {int(i): k for k, i in enumerate(ids.tolist())}
        known = [(row[int(i)], k) for k, i in enumerate(message.covariance_ids.tolist()) if int(i) in row]
        rows = np.array([r for r, _ in known], dtype=np.int64)
        covs = message.covariances[[k for _, k in known]] if known else np.zeros((0, 2, 2))

        def make() -> list[Record]:
            records = landmark_records("dslam", means, ids, stamp, wall)
            return records + ellipse_records("dslam", means[rows] if known else np.zeros((0, 2)), covs, self.config,
                                             stamp, wall)

        return self.maps.offer("dslam", now, make)

    def pose_estimate(self, message: PoseEstimate, wall: float | None, now: float) -> list[Record]:
        return self.robot_pose(message.robot_id, "dslam", message.pose, message.stamp, wall, now)

    def mcl_pose(self, message: MclPose, wall: float | None, now: float) -> list[Record]:
        """MCL's best pose (arrow, trajectory) and its hypotheses, weighted (throttled per robot)."""
        rid = message.robot_id
        state = "localized" if message.localized else "searching"
        records = self.robot_pose(rid, "mcl", message.best_pose, message.stamp, wall, now,
                                  label=f"{rid} mcl ({state})")
        means = np.array([h.mean for h in message.hypotheses]).reshape(-1, 3)
        weights = np.array([h.weight for h in message.hypotheses], float)
        colour, arrow_m, stamp = source_colour(rid, "mcl"), self.arrow_length(rid), message.stamp

        def make() -> list[Record]:
            return [Record(robot_path(rid, "mcl", "hypotheses"), hypotheses_archetype(means, weights, colour, arrow_m),
                           stamp, wall)]

        return records + self.hypotheses.offer(rid, now, make)

    def service_stats(self, message: ServiceStats, wall: float | None) -> list[Record]:
        """A service's latency (median, p99) as two series of one entity, in the service's colour (p99 lighter), on
        the data clock seen so far too."""
        path = stats_path(message.service, message.instance)
        records = []
        if path not in self.series:
            self.series.add(path)
            colour = PALETTE[zlib.crc32(message.service.encode()) % len(PALETTE)]
            lighter = tuple(int(c + (255 - c) * 0.5) for c in colour)
            names = [f"{message.service} median", f"{message.service} p99"]
            records.append(Record(path, rr.SeriesLines(names=names, colors=[colour, lighter]), static=True))
        scalars = rr.Scalars([message.latency_ms_median, message.latency_ms_p99])
        return records + [Record(path, scalars, self.latest_stamp, wall)]


# ------------------------------------------------------------ offline runs
def thin_by_time(stamps: np.ndarray, period_s: float) -> np.ndarray:
    """Indices of ``stamps`` (sorted) keeping at most one per ``period_s``, always the first and the last."""
    stamps = np.asarray(stamps, float)
    if stamps.size == 0:
        return np.zeros(0, dtype=np.int64)
    bins = np.floor((stamps - stamps[0]) / period_s)
    keep = np.flatnonzero(np.r_[True, np.diff(bins) > 0])
    return keep if keep[-1] == stamps.size - 1 else np.r_[keep, stamps.size - 1]


def clip_trajectory(trajectory, end: float):
    """The part of a :class:`services.evaluation.metrics.Trajectory` up to stamp ``end``."""
    keep = trajectory.stamps <= end
    covs = None if trajectory.covs is None else trajectory.covs[keep]
    return type(trajectory)(trajectory.stamps[keep], trajectory.poses[keep], covs)


def offline_records(run, truth: dict, infos: dict[str, RobotInfo], estimator: str, landmarks: np.ndarray | None,
                    landmark_ids: np.ndarray | None, period_s: float, config: VizConfig | None = None
                    ) -> Iterator[Record]:
    """An offline run (:class:`services.offline.OfflineRun`) on the data's clock: each robot's true and estimated
    trajectory (``truth``: robot id -> Trajectory), at most one pose per ``period_s`` of data, the true landmarks,
    and the final map with ellipses at the last data stamp. Paths are throttled in data time."""
    scene = Scene(config)
    for info in infos.values():
        scene.robot_info(info)
    yield world_frame_record()
    if landmarks is not None and len(landmarks):
        yield from true_landmark_records(landmarks, landmark_ids)
    sources: Iterable[tuple[str, dict]] = (("truth", truth), (estimator, run.trajectories))
    last = -math.inf
    for source, trajectories in sources:
        for rid, trajectory in trajectories.items():
            label = rid if source == "truth" else None
            keep = thin_by_time(trajectory.stamps, period_s)
            for stamp, pose in zip(trajectory.stamps[keep].tolist(), trajectory.poses[keep]):
                yield from scene.robot_pose(rid, source, pose, stamp, None, stamp, label=label)
                last = max(last, stamp)
            yield from scene.path(rid, source).flush(last, force=True)
    if math.isfinite(last) and len(run.map_means):
        yield from scene.landmark_map(estimator, run.map_means, run.map_covs, run.map_ids, last, None, last)
