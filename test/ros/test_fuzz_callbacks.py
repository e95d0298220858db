"""Both nodes' input callbacks, fed seeded random malformed messages: each returns normally and counts its refusals.

The callbacks are called directly, as the executor would (no DDS, no spinning): whatever comes in, a
callback refuses it with a counted reason or takes it, and never lets an exception out into the executor.
Each test starts a node of its own. See ``message_fuzz`` for the messages and the settings
(1,000 seeded examples per test).
"""
from __future__ import annotations

import random
from collections.abc import Iterator
from typing import Any

import pytest
from hypothesis import assume, given
from hypothesis import strategies as st

from message_fuzz import FUZZ, as_rclpy, camera_infos, compressed_images, images, odometries, point_clouds

rclpy = pytest.importorskip("rclpy")

from rclpy.context import Context  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402

from lcpr_core.pretrained import default_vseq2pc_weights  # noqa: E402
from lcpr_ros.node import LcprNode  # noqa: E402
from vseq2pc_ros.node import Vseq2pcNode  # noqa: E402

CAMERAS = [f"/fuzz/CAM_{k}/image/compressed" if k % 2 else f"/fuzz/CAM_{k}/image" for k in range(6)]


def _started(node_class: type, values: dict[str, object]) -> Iterator[Any]:
    context = Context()
    rclpy.init(context=context, domain_id=random.randint(1, 200))
    node = node_class(context=context, parameter_overrides=[Parameter(k, value=v) for k, v in values.items()])
    try:
        yield node
    finally:
        node.close()
        node.destroy_node()
        rclpy.try_shutdown(context=context)


@pytest.fixture()
def lcpr_node() -> Iterator[LcprNode]:
    """A tiny seeded model (32 x 96 images, 8 x 256 range image): a frame it takes is decided in milliseconds."""
    yield from _started(LcprNode, {
        "model.image_size": [32, 96], "model.lidar": "velodyne_vlp16", "model.range_size": [8, 256],
        "model.width": 0.25, "model.weights": "seeded", "camera_topics": CAMERAS,
        "lidar_topic": "/fuzz/points", "odom_topic": "/fuzz/odom", "sync.camera_timeout": 5.0,
    })


@pytest.fixture()
def vseq2pc_node() -> Iterator[Vseq2pcNode]:
    weights = default_vseq2pc_weights()
    assert weights is not None, "weights/vseq2pc_synth_*.pth are missing from this checkout"
    yield from _started(Vseq2pcNode, {
        "lidar_topic": "/fuzz/points", "depth_topic": "/fuzz/depth", "labels_topic": "/fuzz/labels",
        "camera_info_topic": "/fuzz/camera_info", "image_topic": "", "odom_topic": "/fuzz/odom",
        "model.sequence": str(weights[0]), "model.descriptor": str(weights[1]), "model.threads": 1,
    })


def delivered(msg: Any) -> Any:
    """The message as a subscription hands it over (rclpy); messages no subscription can deliver (a field
    outside its type's range) are left out: the intake functions' own fuzz test takes those."""
    message = as_rclpy(msg)
    assume(message is not None)
    return message


MESSAGES = st.one_of(point_clouds(stamped=True), images(stamped=True), compressed_images(stamped=True),
                     odometries(stamped=True))
VSEQ2PC_MESSAGES = st.one_of(point_clouds(stamped=True), images(("32FC1", "16UC1", "mono16", "mono8"), stamped=True),
                             camera_infos(stamped=True), odometries(stamped=True))


def assert_both_sides_reached(node: LcprNode | Vseq2pcNode) -> None:
    """The fuzz reached both sides of the callbacks: refusals counted, and messages taken."""
    drops = node.drops.snapshot()
    assert any(reason.startswith("cloud: ") for reason in drops), drops
    assert any(reason.startswith(("image: ", "depth: ", "labels: ")) for reason in drops), drops
    assert node.poses.newest is not None, "no odometry message was taken"


def test_lcpr_node_callbacks_refuse_or_take_any_message_and_return(lcpr_node: LcprNode) -> None:
    @FUZZ
    @given(MESSAGES, st.integers(0, len(CAMERAS) - 1))
    def feed(msg: Any, camera: int) -> None:
        message = delivered(msg)
        kind = msg.__msgtype__
        if kind == "sensor_msgs/msg/PointCloud2":
            lcpr_node._on_cloud(message)
        elif kind == "nav_msgs/msg/Odometry":
            lcpr_node._on_odom(lcpr_node.poses, message)  # type: ignore[arg-type]  # the node's odometry buffer
        else:  # each camera subscription gets its own type: CompressedImage on the odd ones, Image on the even
            lcpr_node._on_image(2 * (camera // 2) + int(kind == "sensor_msgs/msg/CompressedImage"), message)

    feed()
    assert_both_sides_reached(lcpr_node)


def test_vseq2pc_node_callbacks_refuse_or_take_any_message_and_return(vseq2pc_node: Vseq2pcNode) -> None:
    @FUZZ
    @given(VSEQ2PC_MESSAGES, st.sampled_from(["depth", "labels"]))
    def feed(msg: Any, image_kind: str) -> None:
        message = delivered(msg)
        kind = msg.__msgtype__
        if kind == "sensor_msgs/msg/PointCloud2":
            vseq2pc_node._on_cloud(message)
        elif kind == "nav_msgs/msg/Odometry":
            vseq2pc_node._on_odom(message)
        elif kind == "sensor_msgs/msg/CameraInfo":
            vseq2pc_node._on_camera_info(message)
        else:
            vseq2pc_node._on_image(image_kind, message)

    feed()
    assert_both_sides_reached(vseq2pc_node)
