"""rmw_zenoh's wire format as services/ros2/rmw_zenoh.py writes it, checked against zenoh-ros2-sdk's parsers (an
independent implementation), and the ROS 2 output messages of services/ros2/outputs.py."""

from __future__ import annotations

import math

import numpy as np
import pytest

from robots.models import se2_compose, wrap_angle
from services.ros2.core import typestore_for
from services.ros2.outputs import ELLIPSE_SCALE, ellipse, landmark_markers, map_to_odom, odometry_message, \
    pose_covariance_6x6, transform_message
from services.ros2.rmw_zenoh import Attachment, dds_type_name, mangle, topic_key, topic_subscription_key

sdk_attachment = pytest.importorskip("zenoh_ros2_sdk.attachment")
sdk_discovery = pytest.importorskip("zenoh_ros2_sdk.discovery")
sdk_utils = pytest.importorskip("zenoh_ros2_sdk.utils")


def test_an_attachment_is_33_bytes_that_the_independent_parser_reads_back():
    ours = Attachment(sequence=41, stamp_ns=1_700_000_000_123_456_789, gid=bytes(range(16)))
    packed = ours.pack()
    assert len(packed) == 33
    theirs = sdk_attachment.Attachment.from_bytes(packed)
    assert (theirs.sequence_id, theirs.timestamp_ns, theirs.gid) == (41, ours.stamp_ns, ours.gid)
    assert Attachment.unpack(theirs.to_bytes()) == ours


@pytest.mark.parametrize("data", [b"", b"\x00" * 16, b"\x00" * 17 + b"\x10" + b"\x00" * 15, b"\x00" * 16 + b"\x02abc"])
def test_an_attachment_of_another_layout_is_refused_with_a_reason(data):
    with pytest.raises(ValueError, match="^bad_attachment"):
        Attachment.unpack(data)


def test_keys_and_type_names_are_the_ones_the_independent_implementation_builds():
    assert dds_type_name("nav_msgs/msg/Odometry") == sdk_utils.ros2_to_dds_type("nav_msgs/msg/Odometry") \
        == "nav_msgs::msg::dds_::Odometry_"
    assert topic_key(0, "/robot1/odom", "nav_msgs/msg/Odometry", "RIHS01_ab") == \
        "0/robot1/odom/nav_msgs::msg::dds_::Odometry_/RIHS01_ab"
    assert topic_subscription_key(3, "/tf", "tf2_msgs/msg/TFMessage").endswith("/tf/tf2_msgs::msg::dds_::TFMessage_/*")
    assert mangle("/") == mangle("") == "%" and mangle("/robot1/odom") == sdk_utils.mangle_name("/robot1/odom")


def test_our_graph_tokens_parse_as_ros_graph_entities_in_the_independent_parser(zsession):
    from services.ros2.rmw_zenoh import RosNode

    node = RosNode(zsession, "fleetslam", "/", domain_id=7)
    try:
        key = node.endpoint_token_key("MP", "/r1/fleetslam/odom", "nav_msgs/msg/Odometry", "RIHS01_00")
        parsed = sdk_discovery._parse_liveliness_keyexpr(key)
        assert parsed is not None, key
        assert (parsed["domain_id"], parsed["kind"], parsed["node_name"], parsed["qualified_name"],
                parsed["dds_type"], parsed["type_hash"]) == (7, "MP", "fleetslam", "/r1/fleetslam/odom",
                                                             "nav_msgs::msg::dds_::Odometry_", "RIHS01_00")
        assert parsed["session_id"] == str(zsession.info.zid())
    finally:
        node.undeclare()


def test_map_to_odom_composed_with_the_odometry_pose_gives_the_fused_pose():
    rng = np.random.default_rng(3)
    for _ in range(50):
        fused = np.array([*rng.uniform(-20, 20, 2), rng.uniform(-math.pi, math.pi)])
        odom = np.array([*rng.uniform(-20, 20, 2), rng.uniform(-math.pi, math.pi)])
        back = se2_compose(map_to_odom(fused, odom), odom)
        assert np.allclose(back[:2], fused[:2]) and abs(wrap_angle(back[2] - fused[2])) < 1e-12


def test_a_landmark_ellipse_has_the_95_percent_diameters_along_the_covariances_axes():
    angle = 0.4
    rotation = np.array([[math.cos(angle), -math.sin(angle)], [math.sin(angle), math.cos(angle)]])
    cov = rotation @ np.diag([0.09, 0.01]) @ rotation.T
    major, minor, found = ellipse(cov)
    assert major == pytest.approx(2 * ELLIPSE_SCALE * 0.3) and minor == pytest.approx(2 * ELLIPSE_SCALE * 0.1)
    assert math.cos(2 * (found - angle)) == pytest.approx(1.0)  # the axis, either way along it


def test_the_planar_covariance_lands_on_x_y_and_yaw_of_the_6x6():
    cov3 = np.array([[1.0, 0.1, 0.2], [0.1, 2.0, 0.3], [0.2, 0.3, 3.0]])
    full = pose_covariance_6x6(cov3).reshape(6, 6)
    assert np.array_equal(full[np.ix_([0, 1, 5], [0, 1, 5])], cov3)
    assert full[2, 2] > 1e3 and full[0, 2] == 0.0


@pytest.mark.parametrize("distro", ["humble", "jazzy"])
def test_the_output_messages_serialize_and_read_back_in_each_distribution(distro):
    store = typestore_for(distro)
    means, covs = np.array([[1.0, 2.0], [3.0, -4.0]]), np.array([np.diag([0.04, 0.01])] * 2)
    markers = store.deserialize_cdr(store.serialize_cdr(
        landmark_markers(store, means, covs, 12.25, "map", "central", (1, 0, 0, 1)),
        "visualization_msgs/msg/MarkerArray"), "visualization_msgs/msg/MarkerArray")
    assert [m.action for m in markers.markers] == [3, 0, 0]  # DELETEALL, then one ADD per landmark
    assert [(m.pose.position.x, m.pose.position.y) for m in markers.markers[1:]] == [(1.0, 2.0), (3.0, -4.0)]
    assert (markers.markers[1].header.stamp.sec, markers.markers[1].header.stamp.nanosec) == (12, 250_000_000)
    odometry = store.deserialize_cdr(store.serialize_cdr(
        odometry_message(store, np.array([1.0, 2.0, 0.5]), np.eye(3) * 0.01, 3.5, "map", "r1/base_link"),
        "nav_msgs/msg/Odometry"), "nav_msgs/msg/Odometry")
    assert odometry.child_frame_id == "r1/base_link"
    assert 2 * math.atan2(odometry.pose.pose.orientation.z, odometry.pose.pose.orientation.w) == pytest.approx(0.5)
    tf = store.deserialize_cdr(store.serialize_cdr(transform_message(store, np.array([1.0, 0.0, 0.1]), 3.5, "map",
                                                                     "r1/odom"), "tf2_msgs/msg/TFMessage"),
                               "tf2_msgs/msg/TFMessage")
    assert tf.transforms[0].child_frame_id == "r1/odom" and tf.transforms[0].header.frame_id == "map"
