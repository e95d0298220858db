"""QoS of both nodes' subscriptions and outputs (one home for the rule; rclpy only, no node code)."""
from __future__ import annotations

from collections.abc import Callable
from typing import Any

from rclpy.event_handler import SubscriptionEventCallbacks
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data

from .config import INPUT_QOS

__all__ = ["CANDIDATE_QOS", "INPUT_QOS", "LATCHED_QOS", "QOS_ADAPTED", "RELIABLE_INPUT_QOS", "SensorSubscription",
           "input_qos_profile", "keyframes_qos"]

QOS_ADAPTED = "input: re-subscribed best effort"  # the warning's cause (counted once per node)

#: Sensor subscriptions that must not lose a message (bag replay).
RELIABLE_INPUT_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10, reliability=ReliabilityPolicy.RELIABLE)
#: Candidate and loop topics: every candidate must arrive.
CANDIDATE_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100, reliability=ReliabilityPolicy.RELIABLE,
                           durability=DurabilityPolicy.VOLATILE)


#: ``~/sessions``: the latest table for every subscriber, a late one included.
LATCHED_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL)


def keyframes_qos(depth: int) -> QoSProfile:
    """``~/keyframes`` (and a peer's subscription to it): reliable and transient local, the last ``depth`` kept,
    so that a peer started late is sent the keyframes it missed."""
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth, reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.TRANSIENT_LOCAL)


def input_qos_profile(name: str) -> QoSProfile:
    """The subscription profile of an ``input_qos`` value (checked by the node configs)."""
    if name == "reliable":
        return RELIABLE_INPUT_QOS
    if name == "sensor_data":
        return qos_profile_sensor_data
    best = getattr(ReliabilityPolicy, "BEST_AVAILABLE", None)
    if best is None:  # a system rclpy older than Iron: the live-sensor profile is the safe side
        return qos_profile_sensor_data
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10, reliability=best,
                      durability=DurabilityPolicy.VOLATILE)


class SensorSubscription:
    """A sensor subscription with an ``input_qos`` profile that adapts once to a best-effort driver.

    best_available is resolved when the subscription is created: with no publisher on the
    topic yet (the node started before its drivers) it becomes reliable, and a best-effort
    driver that appears later could never be heard. On that incompatibility the subscription
    is re-created best effort (reliable publishers such as ``ros2 bag play`` still match it)
    and ``warn`` is called once with the topic named.
    """

    def __init__(self, node: Node, msg_type: type, topic: str, callback: Callable[[Any], None], input_qos: str,
                 warn: Callable[[str], None]) -> None:
        self._node, self._type, self._topic, self._callback, self._warn = node, msg_type, topic, callback, warn
        self.adapted = False
        events = None
        if input_qos == "best_available":
            events = SubscriptionEventCallbacks(incompatible_qos=self._on_incompatible)
        self.subscription = node.create_subscription(msg_type, topic, callback, input_qos_profile(input_qos),
                                                     event_callbacks=events)
        self._timer: Any = None

    def _on_incompatible(self, info: Any) -> None:
        if self.adapted:
            return
        self.adapted = True
        self._warn(f"{self._topic}: a publisher offers QoS this reliable subscription cannot match (policy "
                   f"{getattr(info, 'last_policy_kind', '?')}); re-subscribing best effort")
        self._timer = self._node.create_timer(0.01, self._swap)  # not inside the event callback itself

    def _swap(self) -> None:
        self._node.destroy_timer(self._timer)
        self._node.destroy_subscription(self.subscription)
        self.subscription = self._node.create_subscription(self._type, self._topic, self._callback,
                                                           qos_profile_sensor_data)
