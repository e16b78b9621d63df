"""Robot lifecycle inside the filter: a robot is waiting (known, no pose yet) or placed (a column of the particles).

A robot whose RobotInfo carries a start pose is placed at once; one without waits until a localizer
(MCL) places it. A placed robot that has not moved yet can be sent back to wait, and any robot can be
removed; the landmarks it mapped stay in the shared map.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from central.fastslam import noise_gain
from robots.gaussian import sqrt_psd, valid_placement
from robots.models import MotionModel, RangeBearingSensor, robot_models, wrap_angle
from schemas.messages import RobotInfo

if TYPE_CHECKING:
    from central.fastslam.core import FastSlam


@dataclass
class RobotState:
    """A placed robot: its column in the pose array, its models, its buffered controls and its clocks."""

    index: int
    info: RobotInfo
    model: MotionModel
    sensor: RangeBearingSensor
    controls: list = field(default_factory=list)
    dts: list = field(default_factory=list)
    covs: list = field(default_factory=list)
    pending_s: float = 0.0
    pending_memo: tuple | None = None  # ((controls buffered, pending_s), (Δ̄, Σ_Δ)): one integration per buffer state
    pose_time: float | None = None  # the time the particles' pose (with the buffered controls) holds at
    last_control: np.ndarray | None = None
    last_cov: np.ndarray | None = None
    last_odom_stamp: float = -np.inf
    last_scan_stamp: float = -np.inf
    last_match_stamp: float | None = None  # shared association: the last scan with a detection matched
    checked_cov: object = None  # the control covariance last validated (by identity), its scaled copy and its gain
    scaled_cov: np.ndarray | None = None
    scaled_gain: float | None = None
    drift: np.ndarray | None = None  # shared association: covariance of the dead reckoning, conditioned on matches
    blind: object = None  # a reacquire.BlindWindow while the robot re-acquires the map
    robot_checks: list = field(default_factory=list)  # (stamp, robot seen, explained): reacquire.contradicted
    odometry_noise: object = None  # robots.odometry_noise.OdometryNoiseGain: the gain on its odometry's covariance

    @property
    def robot_id(self) -> str:
        return self.info.robot_id


def add(slam: FastSlam, info: RobotInfo) -> bool:
    """Place a robot with a start pose, make one without wait; True when it was placed now.

    A robot already known is left as it is (robots republish their RobotInfo).
    """
    rid = info.robot_id
    if rid in slam.robots or rid in slam.waiting:
        return False
    if info.start_pose is None:
        slam.waiting[rid] = info
        return False
    cov = np.zeros((3, 3)) if info.start_pose_cov is None else np.asarray(info.start_pose_cov, float)
    take_in(slam, info, np.asarray(info.start_pose, float), cov)
    return True


def place(slam: FastSlam, robot_id: str, pose, cov, stamp: float | None) -> bool:
    """Place a waiting robot at ``pose`` ``(3,)``, spreading the particles by ``cov`` ``(3, 3)``.

    ``stamp`` is the time the pose holds at: later controls move the robot from there (without it, from
    its next control's start). Bad input is counted in ``slam.rejected`` and changes nothing.
    """
    pose, cov = np.asarray(pose, float), np.asarray(cov, float)
    if robot_id not in slam.waiting:
        slam.rejected["place_unknown_robot"] += 1
        return False
    if not valid_placement(pose, cov, stamp):
        slam.rejected["bad_placement"] += 1
        return False
    take_in(slam, slam.waiting.pop(robot_id), pose, cov)
    slam.robots[robot_id].pose_time = None if stamp is None else float(stamp)
    return True


def unplace(slam: FastSlam, robot_id: str) -> RobotInfo | None:
    """Send a placed robot that has not moved yet (no control or scan applied) back to wait; its RobotInfo,
    or None if it is unknown or has moved."""
    robot = slam.robots.get(robot_id)
    if robot is None or robot.pose_time is not None:
        return None
    slam.waiting[robot_id] = remove(slam, robot_id)
    return robot.info


def remove(slam: FastSlam, robot_id: str) -> RobotInfo | None:
    """Take a robot out, placed or waiting (the landmarks it mapped stay); its RobotInfo, or None if unknown."""
    if robot_id in slam.waiting:
        return slam.waiting.pop(robot_id)
    robot = slam.robots.pop(robot_id, None)
    if robot is None:
        return None
    keep = [i for i in range(slam.pose.shape[1]) if i != robot.index]
    slam.pose = slam.pose[:, keep]
    slam.turn_gain = slam.turn_gain[:, keep]
    for other in slam.robots.values():
        other.index = keep.index(other.index)
    return robot.info


def take_in(slam: FastSlam, info: RobotInfo, pose: np.ndarray, cov: np.ndarray) -> None:
    """Add the robot's column to every particle: one draw from N(pose, cov) each."""
    n = slam.pose.shape[0]
    start = pose + slam.rng.standard_normal((n, 3)) @ sqrt_psd(cov).T
    start[:, 2] = wrap_angle(start[:, 2])
    slam.pose = np.concatenate([slam.pose, start[:, None, :]], 1)
    gain = np.ones(n)
    if slam.config.turn_gain_std > 0.0:
        gain += slam.config.turn_gain_std * slam.rng.standard_normal(n)
    slam.turn_gain = np.concatenate([slam.turn_gain, gain[:, None]], 1)
    model, sensor = robot_models(info)
    slam.robots[info.robot_id] = RobotState(index=slam.pose.shape[1] - 1, info=info, model=model, sensor=sensor,
                                            odometry_noise=noise_gain.start(slam, model.name))


def placed(slam: FastSlam, robot_id: str) -> RobotState | None:
    """The placed robot an event is for, or None (counted: a waiting robot, or one never announced)."""
    robot = slam.robots.get(robot_id)
    if robot is None:
        slam.rejected["robot_not_placed" if robot_id in slam.waiting else "unknown_robot"] += 1
    return robot
