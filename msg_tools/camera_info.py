"""sensor_msgs/CameraInfo <-> :class:`~msg_tools.frames.CameraModel` (pinhole intrinsics)."""
from __future__ import annotations

from typing import Any

import numpy as np

from .build import build_message
from .errors import CameraInfoError
from .frames import CameraModel
from .types import StampLike, header_values


def intrinsics_matrix(values: Any) -> np.ndarray:
    """9 row-major values (CameraInfo ``k``) or a 3 x 3 matrix -> validated 3 x 3 float64 K."""
    K = np.asarray(values, dtype=np.float64)
    if K.size != 9:
        raise CameraInfoError(f"K needs 9 values (3 x 3), got {K.size}")
    K = K.reshape(3, 3)
    if not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0 or not np.allclose(K[2], [0.0, 0.0, 1.0]):
        raise CameraInfoError(
            f"K = {K.tolist()} is not a pinhole matrix; accepted: [[fx, s, cx], [0, fy, cy], [0, 0, 1]] with fx, fy > 0"
        )
    if K[1, 0] != 0.0:
        raise CameraInfoError(f"K[1][0] = {K[1, 0]}; a pinhole K has 0 there")
    return K


def camera_info_to_model(
    msg: Any, *, name: str, base_T_cam: np.ndarray | None = None, ignore_distortion: bool = False
) -> CameraModel:
    """A CameraInfo (rosbags or rclpy; ROS 1 style ``K``/``D`` also read) -> CameraModel.

    ``CameraModel`` is distortion-free, so non-zero distortion coefficients raise
    :class:`CameraInfoError` unless ``ignore_distortion=True``.
    """
    k = getattr(msg, "k", None)
    if k is None:
        k = getattr(msg, "K", None)
    if k is None:
        raise CameraInfoError(f"{type(msg).__name__} has no intrinsics field 'k' (or 'K')")
    K = intrinsics_matrix(k)
    d = getattr(msg, "d", getattr(msg, "D", ()))
    coefficients = np.asarray(list(d), dtype=np.float64)
    if coefficients.size and np.any(coefficients != 0.0) and not ignore_distortion:
        raise CameraInfoError(
            f"camera {name!r} has distortion {coefficients.tolist()} ({getattr(msg, 'distortion_model', '')!r}); "
            "CameraModel holds rectified pinhole cameras only: rectify first or pass ignore_distortion=True"
        )
    width, height = int(msg.width), int(msg.height)
    if width <= 0 or height <= 0:
        raise CameraInfoError(f"camera {name!r} has size {width} x {height}; accepted: positive width and height")
    pose = np.eye(4) if base_T_cam is None else np.asarray(base_T_cam, dtype=np.float64)
    if pose.shape != (4, 4):
        raise CameraInfoError(f"base_T_cam must be 4 x 4, got shape {pose.shape}")
    return CameraModel(name=name, frame_id=str(msg.header.frame_id), width=width, height=height, K=K, base_T_cam=pose)


def model_to_camera_info(model: CameraModel, *, stamp: StampLike, msg_type: type | None = None) -> Any:
    """CameraModel -> CameraInfo (plumb_bob, zero distortion, R = I, P = [K | 0]) in the model's frame."""
    K = intrinsics_matrix(model.K)
    P = np.zeros((3, 4))
    P[:, :3] = K
    values = {
        "header": header_values(frame_id=model.frame_id, stamp=stamp),
        "height": int(model.height),
        "width": int(model.width),
        "distortion_model": "plumb_bob",
        "d": np.zeros(5),
        "k": K.reshape(-1),
        "r": np.eye(3).reshape(-1),
        "p": P.reshape(-1),
    }
    return build_message("sensor_msgs/msg/CameraInfo", values, msg_type=msg_type)
