"""Camera models and static transforms stored in a rosbag2 (CameraInfo topics and /tf_static)."""
from __future__ import annotations

import os
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from ..camera_info import camera_info_to_model
from ..errors import BagError
from ..frames import CameraModel, Topics
from ..transforms import BASE_FRAME, read_transforms
from ..types import typestore
from .open import check_topic, open_bag, topic_types


@dataclass
class StaticTransforms:
    """parent_T_child of every static transform pair (first message wins), with chaining."""

    edges: dict[tuple[str, str], np.ndarray] = field(default_factory=dict)

    def lookup(self, parent: str, child: str) -> np.ndarray | None:
        """parent_T_child by chaining edges in either direction, or None when not connected."""
        if parent == child:
            return np.eye(4)
        graph: dict[str, list[tuple[str, np.ndarray]]] = {}
        for (a, b), T in self.edges.items():
            graph.setdefault(a, []).append((b, T))
            graph.setdefault(b, []).append((a, np.linalg.inv(T)))
        seen = {parent}
        queue: deque[tuple[str, np.ndarray]] = deque([(parent, np.eye(4))])
        while queue:
            node, T = queue.popleft()
            for nxt, step in graph.get(node, []):
                if nxt in seen:
                    continue
                if nxt == child:
                    return T @ step
                seen.add(nxt)
                queue.append((nxt, T @ step))
        return None


def read_static_transforms(bag_path: str | os.PathLike[str], *, topic: str = "/tf_static") -> StaticTransforms:
    """Every transform on ``topic`` (the first message naming a parent/child pair wins)."""
    out = StaticTransforms()
    with open_bag(bag_path) as reader:
        if not check_topic(topic_types(reader), topic, ("tf2_msgs/msg/TFMessage",), required=False):
            return out
        connections = [c for c in reader.connections if c.topic == topic]
        for connection, _ns, raw in reader.messages(connections=connections):
            for parent, child, T in read_transforms(typestore().deserialize_cdr(raw, connection.msgtype)):
                out.edges.setdefault((parent, child), T)
    return out


def read_camera_models(
    bag_path: str | os.PathLike[str],
    *,
    topics: Topics,
    names: tuple[str, ...] | None = None,
    base_frame: str = BASE_FRAME,
    require_transforms: bool = True,
) -> list[CameraModel | None]:
    """The first CameraInfo of each ``topics.camera_info`` topic as a CameraModel (None if absent).

    ``base_T_cam`` comes from ``topics.tf_static`` (``base_frame`` -> the CameraInfo's
    frame); without such a transform, :class:`BagError` unless ``require_transforms``
    is False (identity is used then). Names default to the camera topics' first path part.
    """
    static = read_static_transforms(bag_path, topic=topics.tf_static)
    found: dict[str, object] = {}
    with open_bag(bag_path) as reader:
        types = topic_types(reader)
        present = [t for t in topics.camera_info
                   if check_topic(types, t, ("sensor_msgs/msg/CameraInfo",), required=False)]
        connections = [c for c in reader.connections if c.topic in present]
        for connection, _ns, raw in reader.messages(connections=connections):
            if connection.topic not in found:
                found[connection.topic] = typestore().deserialize_cdr(raw, connection.msgtype)
            if len(found) == len(present):
                break
    models: list[CameraModel | None] = []
    for index, topic in enumerate(topics.camera_info):
        msg = found.get(topic)
        if msg is None:
            models.append(None)
            continue
        name = names[index] if names is not None else _camera_name(topics, index)
        frame_id = str(msg.header.frame_id)  # type: ignore[attr-defined]
        pose = static.lookup(base_frame, frame_id)
        if pose is None:
            if require_transforms:
                raise BagError(
                    f"no {topics.tf_static} transform links {base_frame!r} to camera frame {frame_id!r}; "
                    f"known pairs: {sorted(static.edges)}; pass require_transforms=False to use identity"
                )
            pose = np.eye(4)
        models.append(camera_info_to_model(msg, name=name, base_T_cam=pose))
    return models


def _camera_name(topics: Topics, index: int) -> str:
    source = topics.cameras[index] if index < len(topics.cameras) else topics.camera_info[index]
    parts = [p for p in source.split("/") if p]
    return parts[0] if parts else f"camera{index}"
