"""Two lcpr nodes of two robots in one process, each subscribed to the other's ``~/keyframes``: a place both
robots see comes out on ``~/candidates`` of each, its sessions named through ``~/sessions``."""
from __future__ import annotations

import random
import threading
from typing import Any

import pytest
import rclpy
from rclpy.context import Context
from std_msgs.msg import String, UInt8MultiArray
from test_ros_node import T0, WAIT, Topics, small_model

from lcpr_ros.node import LcprNode
from lcpr_ros.outputs import parse_sessions, row_sessions
from ros_common import inputs
from ros_common.harness import FramePublisher, OutputListener, spinning, synthetic_place, wait_until
from ros_common.qos import LATCHED_QOS, keyframes_qos

EVERY_CAMERA = tuple(range(6))


def robot(context: Context, name: str, topics: Topics, peer: str) -> LcprNode:
    return LcprNode(context=context, namespace=f"/{name}", parameter_overrides=small_model(
        topics, lidar_only=True, session=name, peers=[f"/{peer}"], odom_topic=""))


class Sessions:
    """The latest ``~/sessions`` table of one node."""

    def __init__(self, driver: Any, target: str) -> None:
        self.names: list[str] = []
        self._lock = threading.Lock()
        driver.create_subscription(String, f"{target}/sessions", self._on, LATCHED_QOS)

    def _on(self, msg: String) -> None:
        with self._lock:
            self.names = parse_sessions(msg)


def test_a_place_two_robots_see_is_matched_by_each_with_both_sessions_named() -> None:
    context = Context()
    rclpy.init(context=context, domain_id=random.randint(1, 100))
    prefix = f"/t{random.randint(0, 10**6)}"
    one_topics, two_topics = Topics(f"{prefix}/r1"), Topics(f"{prefix}/r2")
    one = robot(context, "robot1", one_topics, "robot2")
    two = robot(context, "robot2", two_topics, "robot1")
    driver = rclpy.create_node("driver", context=context)
    places = [synthetic_place(i) for i in range(3)]
    with spinning(context, one, driver) as executor:
        executor.add_node(two)
        try:
            pubs = [FramePublisher(driver, t.cameras, t.lidar) for t in (one_topics, two_topics)]
            listeners = [OutputListener(driver, f"/{n}/lcpr") for n in ("robot1", "robot2")]
            tables = [Sessions(driver, f"/{n}/lcpr") for n in ("robot1", "robot2")]
            for pub in pubs:
                assert wait_until(lambda pub=pub: bool(pub.lidar.get_subscription_count() == 1), 20)  # type: ignore[misc]
            for listener in listeners:
                listener.wait_for_publishers()
            assert wait_until(lambda: two.count_publishers("/robot1/lcpr/keyframes") == 1
                              and one.count_publishers("/robot2/lcpr/keyframes") == 1, 20)

            def taken(node: LcprNode, reason: str) -> int:
                return node.decisions.snapshot().get(reason, 0)

            # robot1 sees places 0 and 1; robot2, on its own clock, sees place 2 then place 0
            for k, place in enumerate(places[:2]):
                pubs[0].publish(place, T0 + k, skip_cameras=EVERY_CAMERA)
                assert wait_until(lambda k=k: taken(one, "keyframe") > k, WAIT)  # type: ignore[misc]
            for k, place in enumerate((places[2], places[0])):
                pubs[1].publish(place, 5000.0 + k, skip_cameras=EVERY_CAMERA)
                assert wait_until(lambda k=k: taken(two, "keyframe") > k, WAIT)  # type: ignore[misc]
            # each took the other's keyframes as peer keyframes
            assert wait_until(lambda: taken(one, "peer keyframe") == 2 and taken(two, "peer keyframe") == 2, WAIT)

            def inter_robot(k: int) -> list[dict[str, float]]:
                names = tables[k].names
                return [row for rows in listeners[k].out.candidates for row in rows
                        if row["verified"] == 1 and set(row_sessions(row, names)) == {"robot1", "robot2"}]

            assert wait_until(lambda: bool(inter_robot(0)) and bool(inter_robot(1)), 10)
            for k in (0, 1):
                (row,) = inter_robot(k)  # the one pair, found once on each robot
                query, match = row_sessions(row, tables[k].names)
                assert query is not None and match is not None
                stamps = {"robot1": pytest.approx(T0), "robot2": pytest.approx(5001.0)}
                assert (row["query_stamp"], row["match_stamp"]) == (stamps[query], stamps[match])
            # robot1 took robot2's place-0 keyframe after its own: robot2's is the query there; robot2 the other way
            assert row_sessions(inter_robot(0)[0], tables[0].names) == ("robot2", "robot1")
            assert row_sessions(inter_robot(1)[0], tables[1].names) == ("robot2", "robot1")
            # a peer's loop never reaches ~/loop_closure (its stamps are another robot's clock)
            assert all(5000.0 not in pair and 5001.0 not in pair for pair in listeners[0].out.loops)
            assert listeners[1].out.loops == []
            # a subscriber that starts late is sent every keyframe published before it (transient local)
            late: list[Any] = []
            driver.create_subscription(UInt8MultiArray, "/robot1/lcpr/keyframes",
                                       lambda m: late.append(inputs.peer_keyframe(m)), keyframes_qos(256))
            assert wait_until(lambda: len(late) == 2, 20)
            assert [(kf.session, kf.stamp) for kf in late] == [("robot1", T0), ("robot1", T0 + 1)]
            # a bad message on a peer topic is refused and counted, nothing stored changes
            bad = driver.create_publisher(UInt8MultiArray, "/robot2/lcpr/keyframes", keyframes_qos(10))
            assert wait_until(lambda: one.count_publishers("/robot2/lcpr/keyframes") == 2, 20)
            size = len(one.detector.map)
            bad.publish(UInt8MultiArray(data=b"not a keyframe"))
            assert wait_until(lambda: one.drops.snapshot().get(inputs.PEER_UNREADABLE, 0) == 1, 20)
            assert len(one.detector.map) == size
        finally:
            executor.remove_node(two)
            two.close()
            two.destroy_node()
