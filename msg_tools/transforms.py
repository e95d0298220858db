"""nav_msgs/Odometry and tf2_msgs/TFMessage <-> 4 x 4 poses."""
from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from .build import build_message
from .geometry import check_pose, pose_from_parts, pose_to_parts
from .types import StampLike, header_values

MAP_FRAME = "map"
BASE_FRAME = "base_link"


def _xyz(v: np.ndarray) -> dict[str, float]:
    return {"x": float(v[0]), "y": float(v[1]), "z": float(v[2])}


def _xyzw(q: np.ndarray) -> dict[str, float]:
    return {"x": float(q[0]), "y": float(q[1]), "z": float(q[2]), "w": float(q[3])}


def pose_to_odometry(
    pose: np.ndarray,
    *,
    stamp: StampLike,
    frame_id: str = MAP_FRAME,
    child_frame_id: str = BASE_FRAME,
    msg_type: type | None = None,
) -> Any:
    """world_T_base (4 x 4) -> nav_msgs/Odometry (zero twist, zero covariance)."""
    translation, quaternion = pose_to_parts(check_pose(pose, what="odometry pose"))
    values = {
        "header": header_values(frame_id=frame_id, stamp=stamp),
        "child_frame_id": child_frame_id,
        "pose": {"pose": {"position": _xyz(translation), "orientation": _xyzw(quaternion)}},
    }
    return build_message("nav_msgs/msg/Odometry", values, msg_type=msg_type)


def odometry_to_pose(msg: Any) -> np.ndarray:
    """nav_msgs/Odometry (or anything with ``pose.pose``) -> 4 x 4 world_T_child."""
    pose = msg.pose.pose
    p, o = pose.position, pose.orientation
    return pose_from_parts(np.array([p.x, p.y, p.z]), np.array([o.x, o.y, o.z, o.w]))


def transform_to_matrix(transform: Any) -> np.ndarray:
    """geometry_msgs/Transform -> 4 x 4."""
    t, r = transform.translation, transform.rotation
    return pose_from_parts(np.array([t.x, t.y, t.z]), np.array([r.x, r.y, r.z, r.w]))


def transforms_message(
    transforms: Sequence[tuple[str, str, np.ndarray]], *, stamp: StampLike, msg_type: type | None = None
) -> Any:
    """[(parent, child, parent_T_child), ...] -> tf2_msgs/TFMessage."""
    items = []
    for parent, child, T in transforms:
        translation, quaternion = pose_to_parts(check_pose(T, what=f"transform {parent} -> {child}"))
        items.append({
            "header": header_values(frame_id=parent, stamp=stamp),
            "child_frame_id": child,
            "transform": {"translation": _xyz(translation), "rotation": _xyzw(quaternion)},
        })
    return build_message("tf2_msgs/msg/TFMessage", {"transforms": items}, msg_type=msg_type)


def read_transforms(msg: Any) -> list[tuple[str, str, np.ndarray]]:
    """tf2_msgs/TFMessage -> [(parent, child, parent_T_child), ...]."""
    return [
        (str(t.header.frame_id), str(t.child_frame_id), transform_to_matrix(t.transform)) for t in msg.transforms
    ]
