"""Poses of bag frames for ground truth: the trajectory :func:`lcpr_core.revisits.revisit_pairs` scores."""
from __future__ import annotations

from collections.abc import Iterable

import numpy as np

from .errors import TrajectoryError
from .frames import SensorFrame


def poses_from_frames(
    frames: Iterable[SensorFrame], *, skip_missing: bool = False
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(poses N x 4 x 4, stamps N, frame indices N) of frames with a pose.

    A frame without a pose raises :class:`TrajectoryError` unless ``skip_missing``.
    Positions for ground-truth revisits are ``poses[:, :3, 3]``.
    """
    poses, stamps, indices = [], [], []
    for index, frame in enumerate(frames):
        if frame.pose is None:
            if skip_missing:
                continue
            raise TrajectoryError(f"frame {index} (stamp {frame.stamp:.9f}) has no pose; pass skip_missing=True")
        pose = np.asarray(frame.pose, dtype=np.float64)
        if pose.shape != (4, 4):
            raise TrajectoryError(f"frame {index} has a pose of shape {pose.shape}; accepted: 4 x 4")
        poses.append(pose)
        stamps.append(frame.stamp)
        indices.append(index)
    return (
        np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4),
        np.asarray(stamps, dtype=np.float64),
        np.asarray(indices, dtype=np.int64),
    )
