"""Poses of bag frames for ground truth (msg_tools.ground_truth)."""
from __future__ import annotations

import numpy as np
import pytest

from msg_tools import SensorFrame, TrajectoryError, poses_from_frames, xyz_cloud


def test_poses_come_out_of_frames_in_order() -> None:
    cloud = xyz_cloud(np.zeros((1, 3)))
    poses = [np.eye(4) for _ in range(3)]
    for i, pose in enumerate(poses):
        pose[0, 3] = i
    frames = [SensorFrame(float(i), [], cloud, pose=poses[i] if i != 1 else None) for i in range(3)]
    with pytest.raises(TrajectoryError, match="frame 1 .* has no pose"):
        poses_from_frames(frames)
    got, stamps, indices = poses_from_frames(frames, skip_missing=True)
    assert got[:, 0, 3].tolist() == [0.0, 2.0] and stamps.tolist() == [0.0, 2.0] and indices.tolist() == [0, 2]
