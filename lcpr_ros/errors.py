"""Exceptions of lcpr_ros; every message says what is wrong and what is accepted."""
from __future__ import annotations


class LcprRosError(Exception):
    """Base class of every error raised by lcpr_ros."""


class ConfigError(LcprRosError, ValueError):
    """A parameter value (or a combination of them) is refused; the message gives the reason."""


class MapLoadError(LcprRosError):
    """The map file named by ``map.path`` exists but cannot be used; it is left untouched."""


class InputRejected(LcprRosError, ValueError):
    """A message cannot be used. ``reason`` is a short, stable cause (counted and warned once)."""

    def __init__(self, reason: str, detail: str) -> None:
        super().__init__(f"{reason}: {detail}")
        self.reason = reason
        self.detail = detail
