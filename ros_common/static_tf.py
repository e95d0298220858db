"""Static transforms from /tf_static, where a sourced ROS 2 provides tf2_msgs (the PyPI wheels carry none).

The nodes need one mount: where the LiDAR (the clouds' frame) sits in the odometry's child frame. A
robot's URDF already publishes it on /tf_static; reading it there spares the user from copying it into
parameters, and a wrong copy would stitch submaps crooked. :class:`StaticExtrinsic` keeps every
transform heard and answers the chain between two frames.
"""
from __future__ import annotations

import importlib
from typing import Any

import numpy as np
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

from msg_tools.bags.calibration import StaticTransforms
from msg_tools.transforms import read_transforms

#: /tf_static is latched: a late subscriber still gets every mount published at start.
STATIC_QOS = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)


def tf_message_type() -> type | None:
    """tf2_msgs/TFMessage, or None: the ROS 2 wheels of the ros extra carry no tf2_msgs; a sourced ROS 2 does."""
    try:
        module = importlib.import_module("tf2_msgs.msg")
    except ImportError:
        return None
    found: type = module.TFMessage
    return found


class StaticExtrinsic:
    """Every static transform heard (the first of each parent/child pair wins, as tf2's static buffer)."""

    def __init__(self) -> None:
        self._known = StaticTransforms()

    def offer(self, msg: Any) -> int:
        """Take a tf2_msgs/TFMessage; returns how many new parent/child pairs it added."""
        before = len(self._known.edges)
        for parent, child, T in read_transforms(msg):
            if parent and child and np.isfinite(T).all():
                self._known.edges.setdefault((parent, child), T)
        return len(self._known.edges) - before

    def lookup(self, parent: str, child: str) -> np.ndarray | None:
        """parent_T_child (4 x 4) through any chain of the transforms heard, or None when none links them."""
        if not parent or not child:
            return None
        return self._known.lookup(parent, child)
