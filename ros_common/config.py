"""Settings the nodes share (input QoS, the map file, /diagnostics) and the validation helpers their
config dataclasses use: every ``__post_init__`` refuses a bad value with a ValueError naming it.

Each field is declared with :func:`lcpr_common.params.param` (description, range or choices, run-time
flag): the one source of its ROS parameter's descriptor, params-file entry and reference row.
"""
from __future__ import annotations

from dataclasses import dataclass

from lcpr_common.params import check_fields, param

#: ``input_qos`` values (profiles: ros_common.qos). best_available (rclpy >= Iron) matches each
#: publisher: reliable with reliable publishers such as ``ros2 bag play`` (a replay loses
#: nothing), best effort with drivers that publish best effort.
INPUT_QOS: tuple[str, ...] = ("best_available", "sensor_data", "reliable")


def input_qos_param(description: str = "QoS of the sensor subscriptions: best_available (the default: reliable "
                                       "with reliable publishers such as ros2 bag play, best effort with "
                                       "best-effort drivers), sensor_data (best effort) or reliable") -> str:
    """A node config's ``input_qos`` field (default best_available, one of :data:`INPUT_QOS`)."""
    return param("best_available", description, choices=INPUT_QOS)


def check_node_fields(config: object, prefix: str = "") -> None:
    """:func:`lcpr_common.params.check_fields` for a node's own config: a ValueError names the bad value."""
    check_fields(config, error=ValueError, prefix=prefix)


def require(ok: bool, message: str) -> None:
    """Raise ValueError(message) unless ``ok``."""
    if not ok:
        raise ValueError(message)


@dataclass(frozen=True)
class MapFileConfig:
    path: str = param("", "map file (.npz; lcpr_node: descriptors, vseq2pc_node: scans), loaded at start when it "
                          "exists and saved on ~/save_map and at shutdown; empty = in memory only")
    save_on_shutdown: bool = param(True, "save the map to map.path when the node stops (Ctrl-C, SIGTERM)")


@dataclass(frozen=True)
class DiagnosticsConfig:
    period: float = param(1.0, "s between /diagnostics messages", lo=0.05, hi=3600.0)
    window: int = param(200, "latest items (frames, scans) in the latency percentiles", lo=1, hi=100000)

    def __post_init__(self) -> None:
        check_node_fields(self)
