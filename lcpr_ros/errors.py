"""lcpr_ros's exceptions are the shared ROS layer's (:mod:`ros_common.errors`), importable from here too."""
from __future__ import annotations

from ros_common.errors import ConfigError, InputRejected, MapLoadError, NodeError

LcprRosError = NodeError  # the base class's name before the ROS layer was shared

__all__ = ["ConfigError", "InputRejected", "LcprRosError", "MapLoadError", "NodeError"]
