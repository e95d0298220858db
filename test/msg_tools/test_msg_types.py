"""Stamps, message building and pose messages."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from msg_tools.errors import MessageError, StampError
from msg_tools.geometry import interpolate_pose, matrix_to_quaternion, pose_from_parts, quaternion_to_matrix
from msg_tools.transforms import odometry_to_pose, pose_to_odometry, read_transforms, transforms_message
from msg_tools.types import Stamp, as_stamp, sec_to_stamp, stamp_to_ns, stamp_to_sec


@settings(max_examples=200, deadline=None)
@given(st.floats(min_value=2.0**23, max_value=2.0**31 - 1, allow_nan=False))
def test_an_epoch_float_stamp_survives_the_trip_through_sec_and_nanosec(t: float) -> None:
    stamp = sec_to_stamp(t)
    assert 0 <= stamp.nanosec < 1_000_000_000
    assert stamp_to_sec(stamp) == t


@settings(max_examples=200, deadline=None)
@given(st.floats(min_value=0.0, max_value=2.0**31 - 1, allow_nan=False))
def test_any_float_stamp_is_rounded_to_the_nearest_nanosecond(t: float) -> None:
    from fractions import Fraction

    assert abs(Fraction(sec_to_stamp(t).ns, 10**9) - Fraction(t)) <= Fraction(1, 2 * 10**9)


def test_integer_nanoseconds_are_kept_exactly() -> None:
    stamp = Stamp.from_ns(1532402927647951000)
    assert (stamp.sec, stamp.nanosec) == (1532402927, 647951000)
    assert stamp_to_ns(stamp) == 1532402927647951000
    assert as_stamp(stamp) is stamp


def test_out_of_range_stamps_are_refused() -> None:
    with pytest.raises(StampError, match="not finite"):
        sec_to_stamp(float("nan"))
    with pytest.raises(StampError, match="int32 range"):
        sec_to_stamp(2.0**40)
    with pytest.raises(StampError, match="cannot use str"):
        as_stamp("now")  # type: ignore[arg-type]


def test_quaternions_and_matrices_agree() -> None:
    rng = np.random.default_rng(4)
    for q in rng.normal(size=(200, 4)):
        R = quaternion_to_matrix(q)
        assert np.allclose(R @ R.T, np.eye(3)) and np.allclose(quaternion_to_matrix(matrix_to_quaternion(R)), R)


def test_an_odometry_message_carries_the_pose() -> None:
    pose = pose_from_parts([1.0, -2.0, 0.5], [0.1, 0.2, 0.3, 0.9])
    msg = pose_to_odometry(pose, stamp=3.0)
    assert (msg.header.frame_id, msg.child_frame_id) == ("map", "base_link")
    assert np.allclose(odometry_to_pose(msg), pose)


def test_static_transforms_roundtrip() -> None:
    T = pose_from_parts([0.3, 0.0, 1.2], [0.5, -0.5, 0.5, -0.5])
    (parent, child, back), = read_transforms(transforms_message([("base_link", "cam", T)], stamp=1.0))
    assert (parent, child) == ("base_link", "cam") and np.allclose(back, T)


def test_half_way_between_two_poses_is_half_the_motion() -> None:
    a = pose_from_parts([0, 0, 0], [0, 0, 0, 1])
    b = pose_from_parts([2, 0, 0], [0, 0, np.sin(np.pi / 4), np.cos(np.pi / 4)])  # 90 degrees about z
    mid = interpolate_pose(a, b, 0.5)
    assert np.allclose(mid[:3, 3], [1, 0, 0])
    assert np.allclose(mid[:3, :3], quaternion_to_matrix([0, 0, np.sin(np.pi / 8), np.cos(np.pi / 8)]))


def test_a_foreign_class_that_is_no_message_is_refused() -> None:
    from msg_tools import array_to_image

    with pytest.raises(MessageError, match="neither a rosbags message class nor"):
        array_to_image(np.zeros((1, 1), np.uint8), encoding="mono8", frame_id="c", stamp=0.0, msg_type=dict)
