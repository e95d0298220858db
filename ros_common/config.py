"""Settings both nodes have (input QoS, the map file, /diagnostics) and the validation helpers their
config dataclasses use: every ``__post_init__`` refuses a bad value with a ValueError naming it."""
from __future__ import annotations

import math
from dataclasses import dataclass

from .params import ParamDoc

#: ``input_qos`` values (profiles: ros_common.qos). best_available (rclpy >= Iron) matches each
#: publisher: reliable with reliable publishers such as ``ros2 bag play`` (a replay loses
#: nothing), best effort with drivers that publish best effort.
INPUT_QOS: tuple[str, ...] = ("best_available", "sensor_data", "reliable")


def require(ok: bool, message: str) -> None:
    """Raise ValueError(message) unless ``ok``."""
    if not ok:
        raise ValueError(message)


def require_finite_non_negative(obj: object, *names: str) -> None:
    for name in names:
        value = getattr(obj, name)
        require(isinstance(value, (int, float)) and math.isfinite(value) and value >= 0,
                f"{name}={value!r}; it must be a finite number >= 0")


@dataclass(frozen=True)
class MapFileConfig:
    path: str = ""  # map file (.npz); "" = in memory only
    save_on_shutdown: bool = True


@dataclass(frozen=True)
class DiagnosticsConfig:
    period: float = 1.0  # s between /diagnostics messages (wall time)
    window: int = 200  # latest items in the latency percentiles

    def __post_init__(self) -> None:
        require(math.isfinite(self.period) and self.period > 0, f"period={self.period}; it must be > 0")
        require(self.window >= 1, f"window={self.window}; it must be >= 1")


#: Descriptions of the shared settings' parameters; each node's table adds its own (and may override).
SHARED_DOCS: dict[str, ParamDoc] = {
    "input_qos": ParamDoc("QoS of the sensor subscriptions: best_available (the default: reliable with reliable "
                          "publishers such as ros2 bag play, best effort with best-effort drivers), sensor_data "
                          "(best effort) or reliable", choices=INPUT_QOS),
    "map.save_on_shutdown": ParamDoc("save the map to map.path when the node stops (Ctrl-C, SIGTERM)"),
    "diagnostics.period": ParamDoc("s between /diagnostics messages", 0.05, 3600.0),
    "diagnostics.window": ParamDoc("latest items (frames, scans) in the latency percentiles", 1, 100000),
}
