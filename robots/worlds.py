"""Named simulated worlds (part of the interface: `random`, `paper000`, `grid196`, `cross`, `arena`, `office`).

A :class:`World` is a landmark map plus what a robot needs to move in it: the
sensor, the control noise, a trajectory kind with its parameters, the bounds,
and where robot i starts. Every random choice comes from the seed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from schemas.messages import SensorSpec

DEG = math.pi / 180.0


@dataclass(frozen=True)
class World:
    name: str
    landmarks: np.ndarray  # (L, 2)
    bounds: tuple[float, float, float, float]  # xmin, xmax, ymin, ymax the robots keep within
    sensor: SensorSpec
    control_std: tuple[float, float]  # σ_v (m/s), σ_ω (rad/s) of the odometry
    trajectory: str  # circle | waypoints | random_walk
    speed: float  # m/s
    turn_rate: float  # rad/s (circle: the constant rate; random walk: the largest rate)
    start_poses: Callable[[int], np.ndarray]  # robot index (0-based) -> (x, y, θ)
    waypoints: np.ndarray | None = None  # (K, 2) for the waypoints trajectory
    description: str = ""
    extra: dict = field(default_factory=dict)

    @property
    def landmark_ids(self) -> np.ndarray:
        return np.arange(self.landmarks.shape[0], dtype=np.int64)


def _sensor(max_range, fov, sigma_r, sigma_b, min_range=0.0, detection_probability=1.0, clutter_rate=0.0, offset=(0.0, 0.0)):
    return SensorSpec(
        min_range=min_range, max_range=max_range, fov=fov,
        noise_cov=np.diag([sigma_r**2, sigma_b**2]), offset=np.asarray(offset, float),
        detection_probability=detection_probability, clutter_rate=clutter_rate,
    )


PAPER000_CLUSTER = np.array([[2.9, 2.3], [2.6, 1.9], [2.4, 1.9], [2.5, 2.6], [2.7, 2.8]])


def _random(seed: int) -> World:
    rng = np.random.default_rng([seed, 1000])
    landmarks = rng.uniform(-15.0, 15.0, size=(60, 2))
    return World(
        name="random", landmarks=landmarks, bounds=(-12.0, 12.0, -12.0, 12.0),
        sensor=_sensor(8.0, 2 * math.pi / 3, 0.1, 2 * DEG), control_std=(0.05, 2 * DEG),
        trajectory="random_walk", speed=0.5, turn_rate=0.3,
        start_poses=lambda i: np.array([-8.0 + 4.0 * i, -8.0, math.pi / 2]),
        description="60 landmarks uniform in a 30 m square; bounded random walk",
    )


def _paper000(seed: int) -> World:
    """Paper 000's study: 12 features in 0-20 m (5 at the paper's clustered coordinates), a 5 m circle, 1°/step."""
    rng = np.random.default_rng([seed, 1000])
    landmarks = np.vstack([PAPER000_CLUSTER, rng.uniform(0.0, 20.0, size=(7, 2))])
    radius, step_deg, dt = 5.0, 1.0, 0.1
    turn = step_deg * DEG / dt
    centre = np.array([5.0, 5.0])
    return World(
        name="paper000", landmarks=landmarks, bounds=(0.0, 20.0, 0.0, 20.0),
        sensor=_sensor(10.0, math.pi, 0.02, 0.2 * DEG), control_std=(0.05, 1.0 * DEG),
        trajectory="circle", speed=radius * turn, turn_rate=turn,
        start_poses=lambda i: np.array([centre[0], centre[1] - radius, 0.0]),
        description="paper 000: 12 features, 5 clustered, circle of radius 5 m about (5, 5), 1°/step at 10 Hz",
        extra={"centre": centre, "radius": radius, "rate": 1.0 / dt},
    )


def _grid196(seed: int) -> World:
    """Paper 003's grid: 14 × 14 = 196 features at 3 m spacing in a 40 m square."""
    axis = 1.5 + 3.0 * np.arange(14)
    gx, gy = np.meshgrid(axis, axis)
    landmarks = np.stack([gx.ravel(), gy.ravel()], -1)
    return World(
        name="grid196", landmarks=landmarks, bounds=(1.0, 39.0, 1.0, 39.0),
        sensor=_sensor(5.0, math.pi, 0.05, 1.0 * DEG), control_std=(0.01, 0.5 * DEG),
        trajectory="random_walk", speed=0.2, turn_rate=0.1,
        start_poses=lambda i: np.array([1.0 + 2.0 * i, 1.0, math.pi / 4]),
        description="paper 003: 196 features, 3 m grid, 40 m square, 0.2 m/s, 0.1 rad/s, 180° FOV, 5 m range",
    )


def _cross(seed: int) -> World:
    """Paper 004: a symmetric cross-shaped area of about 15 m × 15 m, with an asymmetric room off one arm.

    The cross has four-fold rotational symmetry: reflectors line both walls of
    every arm. The east arm leads on into a small room whose reflectors break the
    symmetry; the robot tours the symmetric arms first and ends in that room.
    """
    half_width, arm = 1.5, 7.5
    wall = []
    for s in (2.5, 4.5, 6.5):
        for x, y in ((s, half_width), (s, -half_width)):
            for k in range(4):  # four-fold rotation
                c, sn = math.cos(k * math.pi / 2), math.sin(k * math.pi / 2)
                wall.append((c * x - sn * y, sn * x + c * y))
    symmetric = np.array(wall)
    room = np.array([[9.0, 2.5], [10.5, -1.0], [9.5, -2.8], [11.5, 1.5]])
    waypoints = np.array([[0.0, 5.5], [0.0, 0.0], [-5.5, 0.0], [0.0, 0.0], [0.0, -5.5], [0.0, 0.0], [10.0, 0.0]])
    return World(
        name="cross", landmarks=np.vstack([symmetric, room]), bounds=(-arm, arm + 4.0, -arm, arm),
        sensor=_sensor(6.0, 2 * math.pi, 0.05, 1.0 * DEG), control_std=(0.02, 1.0 * DEG),
        trajectory="waypoints", speed=0.5, turn_rate=0.8,
        start_poses=lambda i: np.array([0.0, 1.0 + 0.5 * i, math.pi / 2]),
        waypoints=waypoints,
        description="paper 004: four-fold symmetric cross (arms 3 m wide, 15 m across) plus an asymmetric room east",
        extra={"symmetric_landmarks": symmetric.shape[0]},
    )


def _arena(seed: int) -> World:
    """Like MR.CLAM's arena: 15 landmarks in about 6 m × 10 m, five robots, a forward camera."""
    rng = np.random.default_rng([seed, 1000])
    gx, gy = np.meshgrid(np.linspace(-2.0, 4.0, 3), np.linspace(-4.0, 4.0, 5))
    landmarks = np.stack([gx.ravel(), gy.ravel()], -1) + rng.uniform(-0.4, 0.4, size=(15, 2))
    starts = np.array([[0.0, -2.5, 0.0], [2.0, 2.5, math.pi], [-1.0, 0.0, -math.pi / 2], [3.0, -1.0, math.pi / 2], [1.0, 3.5, 0.0]])
    return World(
        name="arena", landmarks=landmarks, bounds=(-3.0, 5.0, -5.0, 5.0),
        sensor=_sensor(6.0, 1.2, 0.08, 2.0 * DEG, min_range=0.3), control_std=(0.02, 2.0 * DEG),
        trajectory="random_walk", speed=0.3, turn_rate=0.5,
        start_poses=lambda i: starts[i % 5] + np.array([0.0, 0.3 * (i // 5), 0.0]),
        description="MR.CLAM-like: 15 landmarks, 8 m × 10 m arena, camera with 1.2 rad field of view, 6 m range",
    )


def _office(seed: int) -> World:
    """An office floor for global localization (paper 004 §6): symmetric structure, a few unique features.

    A 30 m corridor (2.5 m wide) with six 5 m × 6 m rooms on each side. Reflectors
    mark every wall junction and both frames of every door, all on a 5 m period
    along the corridor, so the structure alone repeats; three pieces of furniture
    per room (drawn from the seed) break the repetition — except that two rooms,
    north 2 and south 5, are furnished identically, a true local ambiguity.
    A laser-like sensor: 6 m range, 180° field of view.
    """
    rng = np.random.default_rng([seed, 1000])
    half, depth, width, rooms = 1.25, 6.0, 5.0, 6
    xs = width * np.arange(rooms + 1)
    corners = np.array([(x, y) for x in xs for y in (half, half + depth, -half, -half - depth)])
    doors = np.array([(x0 + d, y) for x0 in xs[:-1] for d in (1.5, 2.7) for y in (half, -half)])
    layouts = rng.uniform([0.7, 0.7], [width - 0.7, depth - 0.7], size=(2 * rooms, 3, 2))
    layouts[rooms + 4] = layouts[1]  # south room 5 furnished as north room 2
    furniture = []
    for k in range(2 * rooms):
        x0 = xs[k % rooms]
        inside = layouts[k]
        furniture.append(np.column_stack([x0 + inside[:, 0], half + inside[:, 1]]) if k < rooms
                         else np.column_stack([x0 + inside[:, 0], -half - inside[:, 1]]))
    landmarks = np.vstack([corners, doors, *furniture])
    return World(
        name="office", landmarks=landmarks, bounds=(0.7, float(xs[-1]) - 0.7, -half - depth + 0.7, half + depth - 0.7),
        sensor=_sensor(6.0, math.pi, 0.05, 1.0 * DEG), control_std=(0.02, 1.0 * DEG),
        trajectory="random_walk", speed=0.4, turn_rate=0.5,
        start_poses=lambda i: np.array([3.0 + 5.0 * (i % rooms), 0.0, 0.0]),
        description="office floor: 30 m corridor, 12 rooms, reflectors at junctions, doors and furniture (2 rooms alike)",
    )


def world_walls(world: World, margin: float = 2.0) -> np.ndarray:
    """Walls ``(4, 2, 2)`` (segments, each from one end to the other) of the rectangle ``margin`` m outside both the
    world's bounds and its landmarks: what a simulated laser sees behind the landmarks (the worlds hold no other
    structure)."""
    xmin, xmax, ymin, ymax = world.bounds
    if world.landmarks.size:
        xmin, ymin = np.minimum([xmin, ymin], world.landmarks.min(axis=0))
        xmax, ymax = np.maximum([xmax, ymax], world.landmarks.max(axis=0))
    xmin, ymin, xmax, ymax = xmin - margin, ymin - margin, xmax + margin, ymax + margin
    corners = np.array([[xmin, ymin], [xmax, ymin], [xmax, ymax], [xmin, ymax]], float)
    return np.stack([corners, np.roll(corners, -1, axis=0)], axis=1)


WORLDS: dict[str, Callable[[int], World]] = {
    "random": _random,
    "paper000": _paper000,
    "grid196": _grid196,
    "cross": _cross,
    "arena": _arena,
    "office": _office,
}


def make_world(name: str, seed: int = 0) -> World:
    """Build the named world (random parts drawn from ``seed``)."""
    try:
        return WORLDS[name](seed)
    except KeyError:
        raise ValueError(f"unknown world {name!r}; choose from {', '.join(WORLDS)}") from None
