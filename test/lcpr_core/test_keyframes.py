"""The keyframe rule LCPR's detector and both of VSeq2PC's streams share (lcpr_core.keyframes)."""
from __future__ import annotations

import numpy as np

from lcpr_core.keyframes import KEYFRAME, NOT_MOVED, TOO_SOON, KeyframeConfig, KeyframeGate, keyframe_reason


def pose_at(x: float, y: float = 0.0, z: float = 0.0) -> np.ndarray:
    pose = np.eye(4)
    pose[:3, 3] = (x, y, z)
    return pose


def test_the_first_frame_is_a_keyframe_and_a_later_one_waits_for_the_interval() -> None:
    gate = KeyframeGate()
    assert gate.decide(10.0, None, KeyframeConfig(min_interval=0.5, min_distance=0.0)) == KEYFRAME
    assert gate.decide(10.4, None, KeyframeConfig(min_interval=0.5, min_distance=0.0)) == TOO_SOON
    assert gate.decide(10.5, None, KeyframeConfig(min_interval=0.5, min_distance=0.0)) == KEYFRAME


def test_distance_is_measured_in_three_dimensions_from_the_last_keyframe() -> None:
    def reason(position: np.ndarray | None) -> str:
        return keyframe_reason(1.0, position, last_stamp=0.0, last_position=np.zeros(3), min_interval=0.0,
                               min_distance=2.0)

    assert reason(np.array([1.0, 1.0, 0.0])) == NOT_MOVED  # 1.41 m
    assert reason(np.array([1.0, 1.0, 1.5])) == KEYFRAME  # 2.06 m: height counts
    assert reason(None) == KEYFRAME  # no pose: time alone decides


def test_a_rejected_frame_does_not_move_the_reference() -> None:
    gate = KeyframeGate()
    assert gate.decide(0.0, pose_at(0), KeyframeConfig(min_interval=0.0, min_distance=5.0)) == KEYFRAME
    assert gate.decide(1.0, pose_at(3), KeyframeConfig(min_interval=0.0, min_distance=5.0)) == NOT_MOVED
    # 5 m from the kept one, not 2
    assert gate.decide(2.0, pose_at(5), KeyframeConfig(min_interval=0.0, min_distance=5.0)) == KEYFRAME


def test_after_a_reset_the_next_frame_is_a_keyframe_whatever_its_stamp() -> None:
    gate = KeyframeGate()
    assert gate.decide(100.0, pose_at(0), KeyframeConfig(min_interval=1.0, min_distance=1.0)) == KEYFRAME
    assert keyframe_reason(50.0, None, last_stamp=gate.last_stamp, last_position=gate.last_position,
                           min_interval=1.0, min_distance=0.0) == TOO_SOON  # time went back
    gate.reset()
    assert gate.decide(50.0, pose_at(0), KeyframeConfig(min_interval=1.0, min_distance=1.0)) == KEYFRAME
