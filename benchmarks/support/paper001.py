"""The simulated worlds of the experiments of Howard, "Multi-robot simultaneous localization and mapping using
particle filters" (its Fig. 2, 13 and 14), for the benchmarks and tests (the worlds keep their names
``paper001-*``, paper 001 of the project's reading list).

The paper gives only some numbers: two beacons at (4, 6.8) less than 20 cm apart
with 15 cm range noise; four beacons 1-1.5 m apart; two robots in a larger area
of the same kind. Everything else here (anchor beacons, circle, bearing noise,
speeds) is our choice, stated in each function.
"""

from __future__ import annotations

import math

import numpy as np

from robots.worlds import World, _sensor

DEG = math.pi / 180.0
#: beacons that anchor localization around the ambiguous ones (well separated: 4-5 m apart)
ANCHORS = np.array([[0.0, 0.0], [8.0, 0.0], [0.0, 8.0], [8.0, 8.0], [-1.5, 4.0], [9.5, 4.0]])


def two_beacons(separation: float = 0.18, range_std: float = 0.15, bearing_std_deg: float = 1.0) -> World:
    """Fig. 2-3: two beacons at (4, 6.8) ``separation`` apart (along x), 15 cm range noise, plus six anchors.

    The robot drives a circle of radius 5 m about (4, 4) at 0.5 m/s (63 s a lap), a 180° laser of 8 m range.
    """
    pair = np.array([[4.0 - separation / 2, 6.8], [4.0 + separation / 2, 6.8]])
    return _circle_world("paper001-two-beacons", np.vstack([pair, ANCHORS]), range_std, bearing_std_deg,
                         f"two beacons {separation * 100:.0f} cm apart at (4, 6.8) + 6 anchors")


def four_beacons(range_std: float = 0.15, bearing_std_deg: float = 1.0) -> World:
    """Fig. 13: four beacons 1-1.5 m apart (a 1.2 m × 1.4 m quadrilateral about (4, 6.5)), plus six anchors."""
    quad = np.array([[3.4, 5.8], [4.6, 5.9], [4.5, 7.3], [3.3, 7.1]])
    return _circle_world("paper001-four-beacons", np.vstack([quad, ANCHORS]), range_std, bearing_std_deg,
                         "four beacons 1-1.5 m apart + 6 anchors")


def two_robots(range_std: float = 0.15, bearing_std_deg: float = 1.0) -> World:
    """Fig. 14: the same kind of world, larger (24 m × 16 m, 18 beacons), two robots on their own circles.

    Robot 0 circles about (4, 4), robot 1 about (12, 4): each sees the beacons between the circles,
    so a shared map helps both.
    """
    gx, gy = np.meshgrid(np.arange(-2.0, 19.0, 4.0), np.arange(-2.0, 11.0, 4.0))
    rng = np.random.default_rng(1)
    landmarks = np.stack([gx.ravel(), gy.ravel()], -1) + rng.uniform(-0.7, 0.7, (gx.size, 2))
    starts = [np.array([4.0, -1.0, 0.0]), np.array([12.0, 9.0, math.pi])]
    return World(
        name="paper001-two-robots", landmarks=landmarks, bounds=(-3.0, 19.0, -3.0, 11.0),
        sensor=_sensor(6.0, math.pi, range_std, bearing_std_deg * DEG), control_std=(0.05, 3.0 * DEG),
        trajectory="circle", speed=0.5, turn_rate=0.1, start_poses=lambda i: starts[i % 2],
        description="paper 001 Fig. 14: two robots on circles of radius 5 m in a 24 m × 16 m beacon field",
    )


def _circle_world(name: str, landmarks: np.ndarray, range_std: float, bearing_std_deg: float, text: str) -> World:
    return World(
        name=name, landmarks=landmarks, bounds=(-2.0, 10.0, -2.0, 10.0),
        sensor=_sensor(8.0, math.pi, range_std, bearing_std_deg * DEG), control_std=(0.05, 2.0 * DEG),
        trajectory="circle", speed=0.5, turn_rate=0.1, start_poses=lambda i: np.array([4.0, -1.0, 0.0]),
        description=f"paper 001: {text}; circle of radius 5 m about (4, 4)",
    )
