"""Simulated robots in a named world: controllers, noisy odometry and scans, truth.

:func:`simulate` produces the same :class:`~robots.dataset.Dataset` as a log
loader, so the robot process publishes a simulation exactly as it replays a
real log, and ``fleetslam run --dataset sim:WORLD`` feeds the same data to an
estimator offline. Same seed, same data: the world comes from ``seed``,
robot i's motion, sensor noise and sightings of other robots from three
streams of ``(seed, i)``, so a robot simulated alone equals the same robot in a fleet.

:func:`simulate_laser` is opt-in and separate: the raw planar laser scans a robot at given poses would
take of the world's landmarks, as poles, in front of the walls around the world (:func:`robots.worlds.world_walls`),
to test a landmark extractor (:mod:`robots.features`) against known truth. It leaves :func:`simulate` unchanged.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from robots.dataset import Dataset, RobotLog
from robots.models import RangeBearingSensor, UnicycleModel, in_field_of_view, wrap_angle
from robots.worlds import World, make_world, world_walls
from schemas.messages import RobotInfo


def _controller(world: World, trajectory: str, rng: np.random.Generator):
    """A function (pose, t, dt) -> true (v, ω) for the chosen trajectory."""
    if trajectory == "circle":
        return lambda pose, t, dt: (world.speed, world.turn_rate)

    if trajectory == "waypoints":
        if world.waypoints is None:
            raise ValueError(f"world {world.name!r} has no waypoints")
        state = {"next": 0}

        def follow(pose, t, dt):
            target = world.waypoints[state["next"] % len(world.waypoints)]
            delta = target - pose[:2]
            if np.hypot(*delta) < 0.3:
                state["next"] += 1
                target = world.waypoints[state["next"] % len(world.waypoints)]
                delta = target - pose[:2]
            heading_error = float(wrap_angle(math.atan2(delta[1], delta[0]) - pose[2]))
            w = float(np.clip(2.0 * heading_error, -world.turn_rate, world.turn_rate))
            v = world.speed * max(0.0, math.cos(heading_error)) ** 2
            return v, w

        return follow

    if trajectory == "random_walk":
        xmin, xmax, ymin, ymax = world.bounds
        centre = np.array([(xmin + xmax) / 2, (ymin + ymax) / 2])
        margin = max(1.0, world.speed / max(world.turn_rate, 1e-3))
        state = {"w": 0.0, "until": 0.0}

        def wander(pose, t, dt):
            near_edge = not (xmin + margin < pose[0] < xmax - margin and ymin + margin < pose[1] < ymax - margin)
            if near_edge:
                to_centre = centre - pose[:2]
                error = float(wrap_angle(math.atan2(to_centre[1], to_centre[0]) - pose[2]))
                if abs(error) > 0.3:
                    return world.speed, math.copysign(world.turn_rate, error)
            if t >= state["until"]:
                state["w"] = float(rng.choice([-1.0, 0.0, 0.0, 1.0])) * world.turn_rate
                state["until"] = t + float(rng.uniform(1.0, 5.0))
            return world.speed, state["w"]

        return wander

    raise ValueError(f"unknown trajectory {trajectory!r}")


def robot_info(world: World, robot_id: str, start_pose: np.ndarray | None, rate: float, odom_factor: int,
               detection_probability: float, clutter_rate: float) -> RobotInfo:
    sensor = world.sensor.model_copy(update={"detection_probability": detection_probability, "clutter_rate": clutter_rate})
    return RobotInfo(
        robot_id=robot_id, stamp=0.0, motion_model="unicycle", sensor=sensor,
        start_pose=start_pose, start_pose_cov=None if start_pose is None else np.diag([1e-6, 1e-6, 1e-8]),
        source=f"sim:{world.name}", odom_rate_hz=rate * odom_factor, scan_rate_hz=rate,
    )


def simulate(
    world: str | World,
    robots: int = 1,
    seed: int = 0,
    duration: float = 60.0,
    rate: float = 10.0,
    odom_factor: int = 1,
    trajectory: str = "auto",
    detection_probability: float | None = None,
    clutter_rate: float | None = None,
    unknown_start: bool | list[bool] = False,
    robot_ids: list[str] | None = None,
    robot_detections: bool = True,
) -> Dataset:
    """Simulate ``robots`` robots in a world for ``duration`` seconds of robot time.

    Scans come at ``rate`` Hz (the first at t = 0), odometry ``odom_factor``
    times as often. Odometry carries the true control plus Gaussian noise of the
    world's ``control_std``; detections get Gaussian noise of the sensor's
    covariance, are kept with the detection probability, and Poisson clutter is
    added uniformly over the field of view. Robots see each other too; with ``robot_detections`` False they do not
    (no robot detection is drawn, every other draw stays the same), so each robot's data depends on its own streams
    only: a large fleet can be simulated a chunk of robots at a time, at a cost linear, not quadratic, in its size.
    """
    world = make_world(world, seed) if isinstance(world, str) else world
    ids = robot_ids or [f"r{i + 1}" for i in range(robots)]
    unknown = unknown_start if isinstance(unknown_start, list) else [unknown_start] * len(ids)
    p_detect = world.sensor.detection_probability if detection_probability is None else detection_probability
    clutter = world.sensor.clutter_rate if clutter_rate is None else clutter_rate
    sensor = RangeBearingSensor(tuple(world.sensor.offset))
    sensor_chol = np.linalg.cholesky(world.sensor.noise_cov)
    control_cov = np.diag(np.square(world.control_std))
    control_chol = np.linalg.cholesky(control_cov)
    motion = UnicycleModel()
    dt = 1.0 / (rate * odom_factor)
    steps = int(round(duration * rate * odom_factor))
    trajectory_kind = world.trajectory if trajectory == "auto" else trajectory
    n = len(ids)
    indices = [int(rid[1:]) - 1 if rid[1:].isdigit() else i for i, rid in enumerate(ids)]
    rngs = [np.random.default_rng([seed, idx, 0]) for idx in indices]
    sensor_rngs = [np.random.default_rng([seed, idx, 1]) for idx in indices]
    mutual_rngs = [np.random.default_rng([seed, idx, 2]) for idx in indices]
    controllers = [_controller(world, trajectory_kind, rngs[i]) for i in range(n)]
    poses = np.array([world.start_poses(idx) for idx in indices], float)

    truth = [[poses[i].copy()] for i in range(n)]
    controls = [[] for _ in range(n)]
    scans: list[list[tuple]] = [[] for _ in range(n)]

    def scan_all(poses_now: np.ndarray) -> None:
        for i in range(n):
            rng = sensor_rngs[i]
            predicted = sensor.observe(poses_now[i], world.landmarks)
            visible = in_field_of_view(predicted, world.sensor.max_range, world.sensor.fov, world.sensor.min_range)
            visible &= rng.random(visible.shape[0]) < p_detect
            z = predicted[visible] + rng.standard_normal((int(visible.sum()), 2)) @ sensor_chol.T
            lm_ids = world.landmark_ids[visible]
            n_clutter = rng.poisson(clutter)
            fake = np.stack([
                rng.uniform(max(world.sensor.min_range, 0.1), world.sensor.max_range, n_clutter),
                rng.uniform(-world.sensor.fov / 2, world.sensor.fov / 2, n_clutter),
            ], -1)
            z = np.vstack([z, fake])
            lm_ids = np.concatenate([lm_ids, np.full(n_clutter, -1, np.int64)])
            order = rng.permutation(z.shape[0])
            z, lm_ids = z[order], lm_ids[order]
            z[:, 0] = np.abs(z[:, 0])
            z[:, 1] = wrap_angle(z[:, 1])
            others = [j for j in range(n) if j != i] if robot_detections else []
            seen_ids, seen_z = [], np.zeros((0, 2))
            if others:
                rz = sensor.observe(poses_now[i], poses_now[others, :2])
                rvis = in_field_of_view(rz, world.sensor.max_range, world.sensor.fov, world.sensor.min_range)
                seen_ids = [ids[others[k]] for k in np.flatnonzero(rvis)]
                seen_z = rz[rvis] + mutual_rngs[i].standard_normal((int(rvis.sum()), 2)) @ sensor_chol.T
                seen_z[:, 0] = np.abs(seen_z[:, 0])
                seen_z[:, 1] = wrap_angle(seen_z[:, 1])
            scans[i].append((z, lm_ids, seen_ids, seen_z))

    scan_all(poses)
    for k in range(1, steps + 1):
        t = k * dt
        for i in range(n):
            v, w = controllers[i](poses[i], t, dt)
            true_u = np.array([v, w])
            poses[i] = motion.step(poses[i], true_u, dt)
            controls[i].append(true_u + control_chol @ rngs[i].standard_normal(2))
            truth[i].append(poses[i].copy())
        if k % odom_factor == 0:
            scan_all(poses)

    logs = {}
    for i, rid in enumerate(ids):
        start = truth[i][0]
        info = robot_info(world, rid, None if unknown[i] else start, rate, odom_factor, p_detect, clutter)
        counts = np.array([len(s[0]) for s in scans[i]])
        robot_counts = np.array([len(s[2]) for s in scans[i]])
        det = np.vstack([s[0] for s in scans[i]]) if counts.sum() else np.zeros((0, 2))
        robot_det = np.vstack([s[3] for s in scans[i]]) if robot_counts.sum() else np.zeros((0, 2))
        logs[rid] = RobotLog(
            info=info,
            odom_stamp=dt * np.arange(1, steps + 1),
            odom_dt=np.full(steps, dt),
            odom_control=np.array(controls[i]).reshape(steps, 2),
            odom_cov=control_cov,
            scan_stamp=dt * odom_factor * np.arange(len(scans[i])),
            scan_offsets=np.concatenate([[0], np.cumsum(counts)]).astype(np.int64),
            det_range=det[:, 0].copy(),
            det_bearing=det[:, 1].copy(),
            det_id=np.concatenate([s[1] for s in scans[i]]).astype(np.int64),
            scan_cov=world.sensor.noise_cov,
            truth_stamp=dt * np.arange(steps + 1),
            truth_pose=np.array(truth[i]),
            robot_det_offsets=np.concatenate([[0], np.cumsum(robot_counts)]).astype(np.int64),
            robot_det_ids=[r for s in scans[i] for r in s[2]],
            robot_det_range=robot_det[:, 0].copy(),
            robot_det_bearing=robot_det[:, 1].copy(),
        )
    return Dataset(name=f"sim:{world.name}", robots=logs, landmarks=world.landmarks.copy(),
                   landmark_ids=world.landmark_ids, meta={"world": world.name, "seed": seed, "description": world.description})


@dataclass(frozen=True)
class LaserConfig:
    """A simulated planar laser (a SICK-like 2D lidar) and the poles it sees."""

    beams: int = 361  # beams, evenly spread over the field of view, first at −fov/2
    fov: float = math.pi  # rad, the laser's field of view, centred on the robot's heading
    max_range: float = 30.0  # m: a farther hit, or none, reads +inf (no return)
    range_std: float = 0.02  # m: Gaussian range noise of every return
    pole_radius: float = 0.1  # m: each landmark of the world is a pole (a disc) of this radius
    wall_margin: float = 2.0  # m: the walls lie this far outside the world's bounds and landmarks


@dataclass
class LaserScans:
    """Scans of :func:`simulate_laser`: ranges and the beam angles, and which pole each beam hit (the truth)."""

    ranges: np.ndarray  # (S, B) m; +inf where nothing is within max_range
    angle_min: float  # rad, the angle of beam 0 in the laser frame (x along the robot's heading)
    angle_increment: float  # rad between neighbouring beams
    pole: np.ndarray  # (S, B) the landmark whose pole the beam hit, −1 for a wall or no return


def _ray_distances(origins: np.ndarray, directions: np.ndarray, centres: np.ndarray, radius: float,
                   walls: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distance along each ray ``(S, B)`` to the first pole (a disc at each of ``centres``) or wall it meets, and the
    index of that pole (−1: a wall or nothing)."""
    relative = centres[None, None] - origins[:, None, None]  # (S, 1, L, 2)
    along = np.sum(directions[:, :, None] * relative, axis=-1)  # (S, B, L): distance to the point nearest the centre
    off_axis_sq = np.sum(relative**2, axis=-1) - along**2
    half_chord_sq = radius**2 - off_axis_sq
    with np.errstate(invalid="ignore"):
        entry = along - np.sqrt(half_chord_sq)
    entry = np.where((half_chord_sq >= 0) & (entry > 0), entry, np.inf)
    pole_distance = entry.min(axis=-1, initial=np.inf)
    pole_index = np.where(np.isfinite(pole_distance), entry.argmin(axis=-1) if centres.size else -1, -1)

    start, span = walls[:, 0], walls[:, 1] - walls[:, 0]  # (W, 2)
    to_start = start[None, None] - origins[:, None, None]  # (S, 1, W, 2)

    def cross(a, b):
        return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]

    denominator = cross(directions[:, :, None], span[None, None])  # (S, B, W)
    with np.errstate(divide="ignore", invalid="ignore"):
        distance = cross(to_start, span[None, None]) / denominator
        fraction = cross(to_start, directions[:, :, None]) / denominator
    hit = (denominator != 0) & (distance > 0) & (fraction >= 0) & (fraction <= 1)
    wall_distance = np.where(hit, distance, np.inf).min(axis=-1, initial=np.inf)
    return np.minimum(pole_distance, wall_distance), np.where(pole_distance < wall_distance, pole_index, -1)


def simulate_laser(world: str | World, poses: np.ndarray, config: LaserConfig = LaserConfig(), seed: int = 0,
                   chunk: int = 32) -> LaserScans:
    """The scans a planar laser takes at ``poses`` ``(S, 3)`` (robot poses; the laser sits at the world's sensor
    offset, its x axis along the heading): each beam's range to the nearest pole or wall, plus Gaussian noise of
    ``config.range_std`` drawn from ``seed`` (same seed, same scans), +inf beyond ``config.max_range``. Rays are
    cast ``chunk`` scans at a time to bound the memory."""
    world = make_world(world, seed) if isinstance(world, str) else world
    poses = np.atleast_2d(np.asarray(poses, float))
    angle_min = -0.5 * config.fov
    angle_increment = config.fov / (config.beams - 1)
    beam_angles = angle_min + angle_increment * np.arange(config.beams)
    origins, _ = RangeBearingSensor(tuple(world.sensor.offset)).sensor_position(poses)
    walls = world_walls(world, config.wall_margin)
    ranges = np.empty((poses.shape[0], config.beams))
    pole = np.empty((poses.shape[0], config.beams), np.int64)
    for begin in range(0, poses.shape[0], chunk):
        part = slice(begin, begin + chunk)
        angles = poses[part, 2, None] + beam_angles
        directions = np.stack([np.cos(angles), np.sin(angles)], axis=-1)
        ranges[part], pole[part] = _ray_distances(origins[part], directions, world.landmarks, config.pole_radius, walls)
    noisy = ranges + config.range_std * np.random.default_rng([seed, 3]).standard_normal(ranges.shape)
    returned = noisy <= config.max_range
    return LaserScans(ranges=np.where(returned, noisy, np.inf), angle_min=angle_min, angle_increment=angle_increment,
                      pole=np.where(returned, pole, -1))
