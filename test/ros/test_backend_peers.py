"""lcpr_backend given other robots' odometry (``peers``): each peer's odometry is a session of its own, and the
inter-robot loops of the detector's candidate rows place it in this robot's map; over real DDS."""
from __future__ import annotations

import math
import random
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any

import numpy as np
import pytest

pytest.importorskip("gtsam")
rclpy = pytest.importorskip("rclpy")

from diagnostic_msgs.msg import DiagnosticArray  # noqa: E402
from nav_msgs.msg import Odometry  # noqa: E402
from rclpy.context import Context  # noqa: E402
from rclpy.node import Node  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from std_msgs.msg import Float64MultiArray, String  # noqa: E402

from backend_ros.config import settings_from  # noqa: E402
from backend_ros.node import BackendNode  # noqa: E402
from msg_tools.geometry import matrix_to_quaternion  # noqa: E402
from msg_tools.transforms import pose_to_odometry  # noqa: E402
from ros_common.errors import ConfigError  # noqa: E402
from ros_common.harness import spinning, wait_until  # noqa: E402
from ros_common.qos import CANDIDATE_QOS, LATCHED_QOS, RELIABLE_INPUT_QOS  # noqa: E402
from ros_common.tables import COVARIANCE_COLUMNS, POSE_COLUMNS, SESSION_COLUMNS, sessions_msg, table_msg  # noqa: E402
from trajectory_fixtures import pose, quarter_lap_apart  # noqa: E402

T0, DT = 1_700_000_000.0, 0.1
LOOP_COV = np.diag([0.05**2] * 3 + [math.radians(0.5) ** 2] * 3)
MOVED = pose(80.0, 30.0, 0.0, yaw=-64.0)  # robot2's odometry frame in robot1's (the map)
COLUMNS = ("query_stamp", "match_stamp", "verified", *POSE_COLUMNS, *COVARIANCE_COLUMNS, *SESSION_COLUMNS)
TABLE = ["robot1", "robot2"]  # the detector's ~/sessions: code 0 robot1, code 1 robot2


class Fleet:
    """Two robots round one 40 m square at the same time: robot1 from a corner with exact odometry (the map),
    robot2 a quarter lap ahead, drifting, in an odometry frame moved by MOVED^-1."""

    def __init__(self) -> None:
        self.truth1, self.truth2, self.odom2 = quarter_lap_apart(moved=MOVED, seed=3)
        self.stamps = T0 + DT * np.arange(len(self.truth1))

    def loop_row(self, i: int) -> list[float]:
        """A verified row: robot2's pose ``i`` (query, code 1) against robot1's nearest earlier pose (code 0)."""
        j = int(np.argmin(np.linalg.norm(self.truth1[:i, :3, 3] - self.truth2[i, :3, 3], axis=1)))
        rel = np.linalg.inv(self.truth1[j]) @ self.truth2[i]
        cells = [self.stamps[i], self.stamps[j], 1.0, *rel[:3, 3], *matrix_to_quaternion(rel[:3, :3]),
                 *LOOP_COV.reshape(36), 1.0, 0.0]
        return [float(v) for v in cells]


@dataclass
class Ros:
    node: BackendNode
    odom: Any
    peer_odom: Any
    candidates: Any
    sessions: Any
    diagnostics: list[DiagnosticArray]


@contextmanager
def backend_with_a_peer() -> Iterator[Ros]:
    """The node as robot1's back end with peers ['/robot2'] (topics under a random prefix, a random domain)."""
    prefix = f"/p{random.randint(0, 10**6)}"
    context = Context()
    rclpy.init(context=context, domain_id=random.randint(1, 100))
    params = {"odom_topic": f"{prefix}/odom", "candidates_topic": f"{prefix}/candidates",
              "sessions_topic": f"{prefix}/sessions", "up_topic": "", "input_qos": "reliable",
              "session": "robot1", "peers": ["/robot2"], "diagnostics.period": 0.2}
    try:
        node = BackendNode(context=context, parameter_overrides=[Parameter(k, value=v) for k, v in params.items()])
    except Exception:
        rclpy.try_shutdown(context=context)
        raise
    driver: Node = rclpy.create_node("driver", context=context)
    with spinning(context, node, driver):
        diagnostics: list[DiagnosticArray] = []
        driver.create_subscription(DiagnosticArray, "/diagnostics", diagnostics.append, 10)
        odom = driver.create_publisher(Odometry, f"{prefix}/odom", RELIABLE_INPUT_QOS)
        peer_odom = driver.create_publisher(Odometry, f"/robot2{prefix}/odom", RELIABLE_INPUT_QOS)
        candidates = driver.create_publisher(Float64MultiArray, f"{prefix}/candidates", CANDIDATE_QOS)
        sessions = driver.create_publisher(String, f"{prefix}/sessions", LATCHED_QOS)
        assert wait_until(lambda: all(p.get_subscription_count() > 0 for p in (odom, peer_odom, candidates, sessions)),
                          20)
        yield Ros(node, odom, peer_odom, candidates, sessions, diagnostics)


def publish(ros: Ros, publisher: Any, stamps: np.ndarray, poses: np.ndarray) -> None:
    """Odometry messages on ``publisher``, five at a time (a reliable keep-last-10 reader loses none)."""
    topic = publisher.topic_name
    sent = ros.node.rates.totals.get(topic, 0)
    for k, (t, p) in enumerate(zip(stamps, poses, strict=True)):
        publisher.publish(pose_to_odometry(p, stamp=float(t), frame_id="odom", msg_type=Odometry))
        if k % 5 == 4:
            def received(count: int = sent + k + 1) -> bool:
                return ros.node.rates.totals.get(topic, 0) >= count
            assert wait_until(received, 10, period=0.002)
    assert wait_until(lambda: ros.node.rates.totals.get(topic, 0) == sent + len(stamps), 10)


def diagnosed(ros: Ros, key: str, value: str) -> bool:
    return any(kv.key == key and kv.value == value for d in ros.diagnostics for s in d.status for kv in s.values)


def test_a_peers_session_is_named_after_its_namespace_unless_peer_sessions_names_it() -> None:
    assert settings_from({"peers": ["/robot2", "/site/robot3/"]}).peer_odometry() == (
        ("robot2", "/robot2/odom"), ("robot3", "/site/robot3/odom"))
    cfg = settings_from({"peers": ["/r2"], "peer_sessions": ["north"], "odom_topic": "/lio/odometry"})
    assert cfg.peer_odometry() == (("north", "/r2/lio/odometry"),)
    with pytest.raises(ConfigError, match=r"peer_sessions=\['a'\] names 1 sessions for 2 peers"):
        settings_from({"peers": ["/r2", "/r3"], "peer_sessions": ["a"]})
    with pytest.raises(ConfigError, match=r"session='robot2' and the peers' sessions \['robot2'\] repeat a name"):
        settings_from({"session": "robot2", "peers": ["/robot2"]})
    with pytest.raises(ConfigError, match=r"peers=\['robot2'\]; give each robot's namespace from the root"):
        settings_from({"peers": ["robot2"]})


def test_a_peers_odometry_makes_its_own_session_after_this_robots_first_odometry() -> None:
    fleet = Fleet()
    with backend_with_a_peer() as ros:
        publish(ros, ros.peer_odom, fleet.stamps[:20], fleet.odom2[:20])  # before robot1's first: it waits
        assert wait_until(lambda: len(ros.node._early) == 20, 10)
        assert ros.node.backend.sessions == []
        publish(ros, ros.odom, fleet.stamps[:30], fleet.truth1[:30])
        publish(ros, ros.peer_odom, fleet.stamps[20:30], fleet.odom2[20:30])
        assert wait_until(lambda: ros.node._stats.odometry == 60, 20), ros.node._stats
        backend = ros.node.backend
        assert backend.sessions == ["robot1", "robot2"]  # robot1's frame is the map
        assert backend.anchored("robot1") and not backend.anchored("robot2")
        assert len(backend.trajectory("robot2")[0]) > 1 and not ros.node._early
        assert wait_until(lambda: diagnosed(ros, "peer sessions anchored", "none yet")
                          and diagnosed(ros, "peer sessions not anchored", "robot2"), 10)


def test_loops_between_this_robots_session_and_a_peers_anchor_the_peer() -> None:
    fleet = Fleet()
    n = len(fleet.stamps)
    with backend_with_a_peer() as ros:
        ros.sessions.publish(sessions_msg(TABLE))
        publish(ros, ros.odom, fleet.stamps[:120], fleet.truth1[:120])
        publish(ros, ros.peer_odom, fleet.stamps[:100], fleet.odom2[:100])
        # robot2 drives where robot1 drove before it; the last loop waits for robot2's odometry of its stamp
        rows = [fleet.loop_row(i) for i in (20, 40, 60, 80, 105)]
        ros.candidates.publish(table_msg(rows, COLUMNS))
        # robot2's stamp 105 is ahead of its odometry: that loop waits
        assert wait_until(lambda: ros.node._stats.inter_session.get("anchors") == 1 and len(ros.node._pending) == 1,
                          20), ros.node._stats
        assert ros.node.backend.anchored("robot2")
        publish(ros, ros.peer_odom, fleet.stamps[100:n], fleet.odom2[100:n])
        assert wait_until(lambda: not ros.node._pending and ros.node._stats.inter_session.get("accepted", 0) >= 3,
                          20), ros.node._stats
        stamps, traj = ros.node.backend.trajectory("robot2")
        truth = fleet.truth2[np.searchsorted(fleet.stamps, stamps)]
        assert np.sqrt(np.mean(np.sum((traj[:, :3, 3] - truth[:, :3, 3]) ** 2, axis=1))) < 1.0
        assert ros.node._stats.refused == {}
        assert wait_until(lambda: diagnosed(ros, "peer sessions anchored", "robot2")
                          and diagnosed(ros, "peer sessions not anchored", "none"), 10)
