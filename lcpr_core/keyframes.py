"""The keyframe rule both methods use (LCPR's detector, VSeq2PC's scan map and camera frames).

A frame becomes a keyframe when it is at least ``min_interval`` seconds of header time after the
last keyframe and, when both poses are known and ``min_distance`` > 0, at least ``min_distance``
metres (3-D) away from it. The first frame, or the first after a reset, always is one.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lcpr_common.params import check_fields, param

from .errors import InvalidValueError

KEYFRAME, TOO_SOON, NOT_MOVED = "keyframe", "too soon", "not moved"


@dataclass(frozen=True)
class KeyframeConfig:
    min_interval: float = param(0.5, "s (header stamps) between keyframes", lo=0.0, hi=3600.0, dynamic=True)
    min_distance: float = param(0.0, "m travelled between keyframes when poses are known; 0 = off", lo=0.0, hi=1e6,
                                dynamic=True)

    def __post_init__(self) -> None:
        check_fields(self, error=InvalidValueError, prefix="KeyframeConfig.")


def keyframe_reason(stamp: float, position: np.ndarray | None, *, last_stamp: float | None,
                    last_position: np.ndarray | None, min_interval: float, min_distance: float) -> str:
    """``KEYFRAME``, or why not (``TOO_SOON``, ``NOT_MOVED``); stamps in seconds, positions (3,) in metres."""
    if last_stamp is not None and stamp - last_stamp < min_interval:
        return TOO_SOON
    if min_distance > 0 and position is not None and last_position is not None:
        if float(np.linalg.norm(np.asarray(position, np.float64) - last_position)) < min_distance:
            return NOT_MOVED
    return KEYFRAME


class KeyframeGate:
    """:func:`keyframe_reason` with the last keyframe's stamp and position kept."""

    def __init__(self) -> None:
        self.reset()

    def reset(self) -> None:
        """Forget the last keyframe (time jumped back: the next frame is one)."""
        self.last_stamp: float | None = None
        self.last_position: np.ndarray | None = None

    def decide(self, stamp: float, pose: np.ndarray | None, config: KeyframeConfig) -> str:
        """``KEYFRAME`` or why not, for a frame (``pose``: 4 x 4 or None); a keyframe becomes the last one."""
        position = None if pose is None else np.asarray(pose, np.float64)[:3, 3].copy()
        reason = keyframe_reason(stamp, position, last_stamp=self.last_stamp, last_position=self.last_position,
                                 min_interval=config.min_interval, min_distance=config.min_distance)
        if reason == KEYFRAME:
            self.last_stamp, self.last_position = stamp, position
        return reason
