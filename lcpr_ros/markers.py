"""RViz markers of loop candidates: a line from the query's position to each match's,
coloured from green (descriptor distance 0) to red (``match.max_distance``).

Only when poses are known: without odometry the node holds :class:`NoMarkers`.
"""
from __future__ import annotations

from typing import Protocol

import numpy as np
from geometry_msgs.msg import Point
from rclpy.publisher import Publisher
from std_msgs.msg import ColorRGBA
from visualization_msgs.msg import Marker, MarkerArray

from lcpr_core.detector import Result
from ros_common.stamps import NS_PER_S

NAMESPACE = "lcpr_loops"
LINE_WIDTH = 0.3  # m


class MarkerSink(Protocol):
    def publish(self, result: Result, query_pose: np.ndarray | None, frame_id: str, max_distance: float) -> None:
        """Show the result's candidates."""


class NoMarkers:
    """No poses, no markers."""

    def publish(self, result: Result, query_pose: np.ndarray | None, frame_id: str, max_distance: float) -> None:
        return None


def distance_colour(distance: float, max_distance: float) -> ColorRGBA:
    t = float(np.clip(distance / max_distance, 0.0, 1.0)) if max_distance > 0 else 1.0
    return ColorRGBA(r=t, g=1.0 - t, b=0.0, a=1.0)


def loop_markers(
    result: Result, query_pose: np.ndarray | None, frame_id: str, max_distance: float
) -> MarkerArray | None:
    """One LINE_LIST marker per query (id = query keyframe id), or None when nothing can be drawn."""
    if query_pose is None or result.keyframe_id is None:
        return None
    q = np.asarray(query_pose, dtype=np.float64)[:3, 3]
    marker = Marker(ns=NAMESPACE, id=int(result.keyframe_id), type=Marker.LINE_LIST, action=Marker.ADD)
    ns = round(result.stamp * NS_PER_S)
    marker.header.frame_id = frame_id
    marker.header.stamp.sec, marker.header.stamp.nanosec = divmod(ns, NS_PER_S)
    marker.pose.orientation.w = 1.0
    marker.scale.x = LINE_WIDTH
    points: list[Point] = []
    colours: list[ColorRGBA] = []
    for c in result.candidates:
        if c.match_position is None:
            continue
        colour = distance_colour(c.distance, max_distance)
        points += [Point(x=float(q[0]), y=float(q[1]), z=float(q[2])),
                   Point(x=float(c.match_position[0]), y=float(c.match_position[1]), z=float(c.match_position[2]))]
        colours += [colour, colour]
    if not points:
        return None
    marker.points, marker.colors = points, colours
    return MarkerArray(markers=[marker])


class LoopMarkers:
    def __init__(self, publisher: Publisher) -> None:
        self._publisher = publisher

    def publish(self, result: Result, query_pose: np.ndarray | None, frame_id: str, max_distance: float) -> None:
        msg = loop_markers(result, query_pose, frame_id, max_distance)
        if msg is not None:
            self._publisher.publish(msg)
