"""The submap mount taken from /tf_static: the LiDAR in the odometry's child frame, found through a chain."""
from __future__ import annotations

import math
import random
from collections.abc import Iterator
from types import SimpleNamespace

import numpy as np
import pytest
import rclpy
from geometry_msgs.msg import TransformStamped
from rclpy.context import Context
from rclpy.parameter import Parameter

from lcpr_core.geometry import pose_from_xyz_rpy
from lcpr_ros.node import LcprNode
from ros_common.static_tf import StaticExtrinsic


def transform(parent: str, child: str, xyz: tuple[float, float, float], yaw: float) -> TransformStamped:
    t = TransformStamped()
    t.header.frame_id, t.child_frame_id = parent, child
    t.transform.translation.x, t.transform.translation.y, t.transform.translation.z = xyz
    t.transform.rotation.z, t.transform.rotation.w = math.sin(yaw / 2), math.cos(yaw / 2)
    return t


def tf_message(*transforms: TransformStamped) -> SimpleNamespace:
    return SimpleNamespace(transforms=list(transforms))  # what read_transforms reads of a tf2_msgs/TFMessage


@pytest.fixture()
def node() -> Iterator[LcprNode]:
    context = Context()
    rclpy.init(context=context, domain_id=random.randint(101, 200))
    values = {"model.image_size": [32, 96], "model.lidar": "velodyne_vlp16", "model.range_size": [8, 256],
              "model.weights": "seeded", "model.width": 0.25, "lidar_only": True, "odom_topic": "/odom"}
    made = LcprNode(context=context, parameter_overrides=[Parameter(k, value=v) for k, v in values.items()])
    try:
        yield made
    finally:
        made.close()
        made.destroy_node()
        rclpy.shutdown(context=context)


def test_static_transforms_chain_in_either_direction_and_the_first_of_a_pair_wins() -> None:
    tf = StaticExtrinsic()
    assert tf.offer(tf_message(transform("base_link", "mount", (1.0, 0.0, 0.5), 0.0),
                               transform("lidar", "mount", (0.0, 0.2, 0.0), math.pi / 2))) == 2
    assert tf.offer(tf_message(transform("base_link", "mount", (9.0, 9.0, 9.0), 0.0))) == 0  # already known
    T = tf.lookup("base_link", "lidar")
    expected = pose_from_xyz_rpy((1.0, 0.0, 0.5), (0, 0, 0)) @ np.linalg.inv(
        pose_from_xyz_rpy((0.0, 0.2, 0.0), (0, 0, math.pi / 2)))
    assert T is not None and np.allclose(T, expected)
    assert tf.lookup("base_link", "camera") is None and tf.lookup("", "lidar") is None


def test_the_node_takes_the_submap_mount_from_tf_static_once_both_frames_are_known(node: LcprNode) -> None:
    node._on_tf_static(tf_message(transform("base_link", "livox_frame", (0.3, -0.1, 0.2), 0.25)))
    assert node._next_detector_config is None  # the frames are not known yet: nothing changes
    node._note_frame("base", "base_link")  # an odometry child_frame_id
    node._note_frame("lidar", "livox_frame")  # a cloud's header.frame_id
    pending = node._next_detector_config
    assert pending is not None and pending is node.settings.detector
    assert np.allclose(pending.submap.lidar_xyz, (0.3, -0.1, 0.2))
    assert np.allclose(pending.submap.lidar_rpy, (0.0, 0.0, 0.25))
    results = node.set_parameters([Parameter("submap.lidar_xyz", value=[5.0, 5.0, 5.0]),  # later changes ...
                                   Parameter("submap.travel_m", value=3.0)])
    assert all(r.successful for r in results)
    assert node.settings.detector.submap.travel_m == 3.0  # ... take effect ...
    assert np.allclose(node.settings.detector.submap.lidar_xyz, (0.3, -0.1, 0.2))  # ... but the heard mount stays
