"""The nodes' intake (ros_common.inputs), fed seeded random malformed messages: only InputRejected comes out.

Every message is tried as a rosbags message and, copied field by field, as the rclpy message a node's
subscription hands over. What is accepted is what a node can use: finite points, labels beside them,
JPEG/PNG bytes, images that convert, finite poses. See ``message_fuzz`` for the messages and the
settings (1,000 seeded examples per test).
"""
from __future__ import annotations

from collections.abc import Callable, Iterator
from typing import Any, TypeVar

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from message_fuzz import FUZZ, as_rclpy, camera_infos, compressed_images, images, odometries, point_clouds
from ros_common import inputs
from ros_common.errors import InputRejected
from ros_common.poses import OdometryBuffer

pytest.importorskip("sensor_msgs.msg")

T = TypeVar("T")
REASONS = {value for name, value in vars(inputs).items() if name.isupper() and isinstance(value, str)}


def both_kinds(msg: Any) -> Iterator[Any]:
    yield msg
    copy = as_rclpy(msg)
    if copy is not None:
        yield copy


def accepted(intake: Callable[[Any], T], msg: Any) -> T | None:
    """``intake``'s result, or None where it refused the message with a reason of its own."""
    try:
        return intake(msg)
    except InputRejected as err:
        assert err.reason in REASONS or err.reason.startswith("odometry: "), err.reason
        return None


@FUZZ
@given(point_clouds())
def test_clouds_are_taken_as_finite_points_or_refused_with_a_reason(msg: Any) -> None:
    for message in both_kinds(msg):
        taken = accepted(inputs.cloud_points, message)
        if taken is not None:
            points, removed = taken
            assert points.dtype == np.float32 and points.ndim == 2 and points.shape[1] == 3
            assert np.isfinite(points).all() and removed >= 0
        labelled = accepted(inputs.labelled_cloud, message)
        if labelled is not None:
            points, labels, removed = labelled
            assert labels.dtype == np.uint32 and len(labels) == len(points) and np.isfinite(points).all()
            assert taken is not None and np.array_equal(points, taken[0]) and removed == taken[1]


@FUZZ
@given(st.one_of(compressed_images(), images(), images(("rgb8", "bayer_rggb8", "yuv422", "nv21", "mono16"))))
def test_camera_images_are_taken_and_convert_or_are_refused_with_a_reason(msg: Any) -> None:
    intake = inputs.compressed_payload if hasattr(msg, "format") else inputs.raw_payload
    for message in both_kinds(msg):
        payload = accepted(intake, message)
        if payload is None:
            continue
        if isinstance(payload, bytes):
            assert payload and accepted(inputs.camera_input, payload) == payload
            continue
        rgb = inputs.camera_input(payload)  # a raw image once taken always converts
        assert isinstance(rgb, np.ndarray) and rgb.shape == (message.height, message.width, 3)


@FUZZ
@given(st.one_of(images(("32FC1", "16UC1")), images(("mono8", "mono16", "16UC1", "32SC1")), images()))
def test_depth_and_label_images_are_taken_or_refused_with_a_reason(msg: Any) -> None:
    for message in both_kinds(msg):
        depth = accepted(inputs.depth_image, message)
        if depth is not None:
            assert depth.shape == (message.height, message.width) and depth.dtype == np.float32
            assert np.isfinite(depth).all() and (depth >= 0).all()
        labels = accepted(inputs.label_image, message)
        if labels is not None:
            assert labels.shape == (message.height, message.width) and labels.dtype == np.uint32


@FUZZ
@given(camera_infos())
def test_camera_infos_are_taken_as_intrinsics_or_refused_with_a_reason(msg: Any) -> None:
    for message in both_kinds(msg):
        taken = accepted(inputs.intrinsics, message)
        if taken is not None:
            K, width, height = taken
            assert K.shape == (3, 3) and np.isfinite(K).all() and width > 0 and height > 0


@FUZZ
@given(st.lists(odometries(), min_size=1, max_size=3))
def test_odometry_is_taken_as_finite_poses_or_refused_with_a_reason(messages: list[Any]) -> None:
    buffer = OdometryBuffer(slop=0.05, max_gap=1.0, jump_back=1.0)
    for msg in messages:
        for message in both_kinds(msg):
            pose = accepted(inputs.odometry_pose, message)
            if pose is not None:
                assert pose.shape == (4, 4) and np.isfinite(pose).all()
            accepted(lambda m: inputs.offer_odometry(buffer, m), message)
