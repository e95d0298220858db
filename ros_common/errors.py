"""Exceptions of the nodes' ROS layer (ros_common, lcpr_ros, vseq2pc_ros); every message says what is
wrong and what is accepted."""
from __future__ import annotations

from lcpr_common.errors import ProjectError


class NodeError(ProjectError):
    """Base class of every error the ROS layer raises."""


class ConfigError(NodeError, ValueError):
    """A parameter value (or a combination of them) is refused; the message gives the reason."""


class MapLoadError(NodeError):
    """The map file named by ``map.path`` exists but cannot be used; it is left untouched."""


class InputRejected(NodeError, ValueError):
    """A message cannot be used. ``reason`` is a short, stable cause (counted and warned once)."""

    def __init__(self, reason: str, detail: str) -> None:
        super().__init__(f"{reason}: {detail}")
        self.reason = reason
        self.detail = detail
