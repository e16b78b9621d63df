"""fleetslam's estimates as ROS 2 messages (pure: numbers in, rosbags message objects out).

- a robot's fused pose as ``nav_msgs/msg/Odometry`` in the map frame, its 3×3 covariance in the 6×6 pose
  covariance (x, y, yaw);
- the ``map → odom`` transform of a robot (``tf2_msgs/msg/TFMessage``): the fused pose composed with the inverse
  of the robot's own odometry pose at the same time, as REP-105 has a localisation node publish it;
- a landmark map as ``visualization_msgs/msg/MarkerArray``: a DELETEALL first (so landmarks merged away
  disappear), then one flat cylinder per landmark whose footprint is the 95 % ellipse of its position (diameters
  2·√(χ²₂(0.95)·λ) from the covariance's eigenvalues λ).
"""

from __future__ import annotations

import math

import numpy as np

from robots.models import se2_compose, se2_inverse
from services.ros2.core import make_header, new_message, stamp_to_ns, yaw_quaternion

ELLIPSE_SCALE = math.sqrt(5.991464547107979)  # √χ²₂(0.95): semi-axes of the 95 % ellipse, in σ
MIN_DIAMETER_M = 0.02  # a marker never thinner than this (RViz draws nothing for a zero scale)
LANDMARK_HEIGHT_M = 0.05
UNOBSERVED_VARIANCE = 1e6  # z, roll and pitch of a planar pose, as planar ROS drivers report them


def pose_covariance_6x6(cov3: np.ndarray) -> np.ndarray:
    """A planar (x, y, θ) covariance in ROS's row-major 6×6 (x, y, z, roll, pitch, yaw) layout."""
    full = np.diag([0.0, 0.0, UNOBSERVED_VARIANCE, UNOBSERVED_VARIANCE, UNOBSERVED_VARIANCE, 0.0])
    index = [0, 1, 5]
    full[np.ix_(index, index)] = cov3
    return full.ravel()


def _pose(typestore, x: float, y: float, yaw: float, z: float = 0.0):
    return new_message(typestore, "geometry_msgs/msg/Pose",
                       position=new_message(typestore, "geometry_msgs/msg/Point", x=float(x), y=float(y), z=z),
                       orientation=yaw_quaternion(typestore, float(yaw)))


def odometry_message(typestore, pose: np.ndarray, cov: np.ndarray, stamp: float, frame_id: str, child_frame_id: str):
    """A fused pose as ``nav_msgs/msg/Odometry`` (pose only; the twist is left zero)."""
    return new_message(
        typestore, "nav_msgs/msg/Odometry", header=make_header(typestore, stamp_to_ns(stamp), frame_id),
        child_frame_id=child_frame_id,
        pose=new_message(typestore, "geometry_msgs/msg/PoseWithCovariance", pose=_pose(typestore, *pose[:3]),
                         covariance=pose_covariance_6x6(np.asarray(cov, float))))


def map_to_odom(fused: np.ndarray, odom: np.ndarray) -> np.ndarray:
    """The transform T with T ⊕ odom = fused: where the robot's odometry frame lies in the map."""
    return se2_compose(np.asarray(fused, float), se2_inverse(np.asarray(odom, float)))


def transform_message(typestore, transform: np.ndarray, stamp: float, frame_id: str, child_frame_id: str):
    """One planar transform as a ``tf2_msgs/msg/TFMessage`` holding one ``TransformStamped``."""
    stamped = new_message(
        typestore, "geometry_msgs/msg/TransformStamped", header=make_header(typestore, stamp_to_ns(stamp), frame_id),
        child_frame_id=child_frame_id,
        transform=new_message(
            typestore, "geometry_msgs/msg/Transform",
            translation=new_message(typestore, "geometry_msgs/msg/Vector3", x=float(transform[0]),
                                    y=float(transform[1])),
            rotation=yaw_quaternion(typestore, float(transform[2]))))
    return new_message(typestore, "tf2_msgs/msg/TFMessage", transforms=[stamped])


def ellipse(cov: np.ndarray) -> tuple[float, float, float]:
    """(major diameter, minor diameter, angle of the major axis) of the 95 % ellipse of a 2×2 covariance."""
    values, vectors = np.linalg.eigh(0.5 * (cov + cov.T))
    values = np.clip(values, 0.0, None)
    major, minor = (max(2 * ELLIPSE_SCALE * math.sqrt(v), MIN_DIAMETER_M) for v in values[::-1])
    return major, minor, math.atan2(vectors[1, 1], vectors[0, 1])


def landmark_markers(typestore, means: np.ndarray, covs: np.ndarray, stamp: float, frame_id: str, namespace: str,
                     color: tuple[float, float, float, float]):
    """A map as ``visualization_msgs/msg/MarkerArray``: DELETEALL of ``namespace``, then a flat cylinder per
    landmark (id = its index), its footprint the landmark's 95 % ellipse."""
    header = make_header(typestore, stamp_to_ns(stamp), frame_id)
    Marker = typestore.types["visualization_msgs/msg/Marker"]
    rgba = new_message(typestore, "std_msgs/msg/ColorRGBA", r=color[0], g=color[1], b=color[2], a=color[3])

    def marker(index: int, action: int, pose=None, scale=(0.0, 0.0, 0.0)):
        return new_message(typestore, "visualization_msgs/msg/Marker", header=header, ns=namespace, id=index,
                           type=Marker.CYLINDER, action=action, pose=pose or _pose(typestore, 0.0, 0.0, 0.0),
                           scale=new_message(typestore, "geometry_msgs/msg/Vector3", x=scale[0], y=scale[1],
                                             z=scale[2]),
                           color=rgba)

    markers = [marker(0, Marker.DELETEALL)]
    for index, (mean, cov) in enumerate(zip(np.asarray(means, float), np.asarray(covs, float))):
        major, minor, angle = ellipse(cov)
        markers.append(marker(index, Marker.ADD, _pose(typestore, mean[0], mean[1], angle, LANDMARK_HEIGHT_M / 2),
                              (major, minor, LANDMARK_HEIGHT_M)))
    return new_message(typestore, "visualization_msgs/msg/MarkerArray", markers=markers)
