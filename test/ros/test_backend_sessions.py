"""lcpr_backend against a prior map (prior_graph): this run's odometry as its own session, candidate rows naming
sessions by the detector's ~/sessions table, ~/localized once loops place the run in the map; over real DDS."""
from __future__ import annotations

import math
import random
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
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
from std_msgs.msg import Bool, Float64MultiArray, String  # noqa: E402

from backend_ros.node import BackendNode  # noqa: E402
from lcpr_core.backend import PoseGraphBackend  # noqa: E402
from msg_tools.geometry import matrix_to_quaternion  # noqa: E402
from msg_tools.transforms import odometry_to_pose, pose_to_odometry  # noqa: E402
from ros_common.errors import ConfigError, MapLoadError  # noqa: E402
from ros_common.harness import spinning, wait_until  # noqa: E402
from ros_common.qos import CANDIDATE_QOS, LATCHED_QOS, RELIABLE_INPUT_QOS  # noqa: E402
from ros_common.tables import COVARIANCE_COLUMNS, POSE_COLUMNS, SESSION_COLUMNS, sessions_msg, table_msg  # noqa: E402
from trajectory_fixtures import pose, quarter_lap_apart, square_laps  # noqa: E402

T_PRIOR, T_RUN = 1_700_000_000.0, 1_700_090_000.0  # the prior's stamps, this run's (a day later)
DT = 0.1
LOOP_COV = np.diag([0.05**2] * 3 + [math.radians(0.5) ** 2] * 3)
MOVED = pose(130.0, -45.0, 0.0, yaw=117.0)  # this run's odometry frame in the prior map's
COLUMNS = ("query_stamp", "match_stamp", "verified", *POSE_COLUMNS, *COVARIANCE_COLUMNS, *SESSION_COLUMNS)


class Drives:
    """Yesterday's drive round a 40 m square (the prior map, session "a", its odometry exact) and today's from
    another corner, drifting, in an odometry frame moved by MOVED^-1."""

    def __init__(self) -> None:
        self.truth_a, self.truth_b, self.odom_b = quarter_lap_apart(moved=MOVED, seed=2)
        self.stamps_a = T_PRIOR + DT * np.arange(len(self.truth_a))
        self.stamps_b = T_RUN + DT * np.arange(len(self.truth_b))

    def save_prior(self, path: Path, session: str = "a") -> Path:
        g = PoseGraphBackend()
        for t, p in zip(self.stamps_a, self.truth_a, strict=True):
            g.add_odometry(float(t), p, session=session)
        g.save(path)
        return path

    def loop_row(self, i: int, codes: tuple[float, float]) -> list[float]:
        """A verified row: this run's pose ``i`` (query) against the prior's nearest pose (match)."""
        j = int(np.argmin(np.linalg.norm(self.truth_a[:, :3, 3] - self.truth_b[i, :3, 3], axis=1)))
        rel = np.linalg.inv(self.truth_a[j]) @ self.truth_b[i]
        cells = [float(self.stamps_b[i]), float(self.stamps_a[j]), 1.0, *rel[:3, 3], *matrix_to_quaternion(rel[:3, :3]),
                 *LOOP_COV.reshape(36), *codes]
        return [float(v) for v in cells]


@dataclass
class Ros:
    node: BackendNode
    driver: Node
    odom: Any
    candidates: Any
    sessions: Any
    localized: list[bool]
    corrected: list[Odometry]
    diagnostics: list[DiagnosticArray]


@contextmanager
def backend_node(params: dict[str, Any]) -> Iterator[Ros]:
    """The node with the topics of one test (a random prefix and domain) and ``params``, and a driver."""
    prefix = f"/s{random.randint(0, 10**6)}"
    context = Context()
    rclpy.init(context=context, domain_id=random.randint(1, 100))
    topics = {"odom_topic": f"{prefix}/odom", "candidates_topic": f"{prefix}/candidates",
              "sessions_topic": f"{prefix}/sessions", "up_topic": "", "input_qos": "reliable",
              "diagnostics.period": 0.2, "path_period": 0.2}
    try:
        node = BackendNode(context=context, parameter_overrides=[Parameter(k, value=v) for k, v in
                                                                 {**topics, **params}.items()])
    except Exception:
        rclpy.try_shutdown(context=context)
        raise
    driver = rclpy.create_node("driver", context=context)
    with spinning(context, node, driver):
        localized: list[bool] = []
        corrected: list[Odometry] = []
        diagnostics: list[DiagnosticArray] = []
        driver.create_subscription(Bool, "/lcpr_backend/localized", lambda m: localized.append(bool(m.data)),
                                   LATCHED_QOS)
        driver.create_subscription(Odometry, "/lcpr_backend/odometry", corrected.append, 100)
        driver.create_subscription(DiagnosticArray, "/diagnostics", diagnostics.append, 10)
        odom = driver.create_publisher(Odometry, f"{prefix}/odom", RELIABLE_INPUT_QOS)
        candidates = driver.create_publisher(Float64MultiArray, f"{prefix}/candidates", CANDIDATE_QOS)
        sessions = driver.create_publisher(String, f"{prefix}/sessions", LATCHED_QOS)
        assert wait_until(lambda: odom.get_subscription_count() > 0 and candidates.get_subscription_count() > 0
                          and sessions.get_subscription_count() > 0, 20)
        yield Ros(node, driver, odom, candidates, sessions, localized, corrected, diagnostics)


def publish_odometry(ros: Ros, stamps: np.ndarray, poses: np.ndarray) -> None:
    """Odometry messages, five at a time (a reliable keep-last-10 reader loses none), all in the graph."""
    topic, before = ros.node.settings.odom_topic, ros.node._stats.odometry
    sent = ros.node.rates.totals.get(topic, 0)
    for k, (t, p) in enumerate(zip(stamps, poses, strict=True)):
        ros.odom.publish(pose_to_odometry(p, stamp=float(t), frame_id="odom", msg_type=Odometry))
        if k % 5 == 4:
            def received(count: int = sent + k + 1) -> bool:
                return ros.node.rates.totals[topic] >= count
            assert wait_until(received, 10, period=0.002)
    assert wait_until(lambda: ros.node._stats.odometry == before + len(stamps), 30), ros.node._stats


def diagnosed(ros: Ros, key: str, value: str) -> bool:
    return any(kv.key == key and kv.value == value for d in ros.diagnostics for s in d.status for kv in s.values)


def waiting_for_names(ros: Ros) -> int:
    return sum(1 for item in list(ros.node._pending) if getattr(item, "sessions", "") is None)


def test_a_run_in_a_prior_map_is_localized_by_rows_naming_its_sessions_and_saved_with_the_prior(
        tmp_path: Path) -> None:
    drives = Drives()
    prior = drives.save_prior(tmp_path / "prior.npz")
    graph = tmp_path / "graph.npz"
    with backend_node({"prior_graph": str(prior), "graph.path": str(graph)}) as ros:
        assert wait_until(lambda: ros.localized == [False], 10), ros.localized  # latched, at start
        publish_odometry(ros, drives.stamps_b[:70], drives.odom_b[:70])
        # before it is placed: corrected within its own odometry frame, never claimed to be in the map
        assert wait_until(lambda: len(ros.corrected) == 70, 10)
        assert {m.header.frame_id for m in ros.corrected} == {"odom"}
        assert ros.node.backend.sessions == ["a", "session"] and not ros.node.backend.anchored("session")

        # rows before the table: they wait for it; "robot7" is a session the graph does not hold
        table = ["a", "robot7", "session"]
        rows = [drives.loop_row(i, (2.0, 0.0)) for i in range(10, 70, 10)]
        ros.candidates.publish(table_msg(rows + [drives.loop_row(65, (2.0, 1.0))], COLUMNS))
        assert wait_until(lambda: waiting_for_names(ros) == 7, 10), ros.node._pending
        assert ros.node._stats.inter_session.get("anchors", 0) == 0
        ros.sessions.publish(sessions_msg(table))

        assert wait_until(lambda: ros.localized == [False, True], 20), (ros.localized, ros.node._stats)
        stats = ros.node._stats
        assert stats.refused.get("loop session unknown") == 1 and stats.inter_session["anchors"] == 1
        assert waiting_for_names(ros) == 0

        publish_odometry(ros, drives.stamps_b[70:80], drives.odom_b[70:80])
        assert wait_until(lambda: bool(ros.corrected) and ros.corrected[-1].header.stamp.sec ==
                          int(drives.stamps_b[79]), 10)
        got = odometry_to_pose(ros.corrected[-1])
        assert ros.corrected[-1].header.frame_id == "map"
        # in the prior's map (its own frame is 130 m away); 20 m past the last loop, its drift is not corrected
        assert np.linalg.norm(got[:3, 3] - drives.truth_b[79, :3, 3]) < 1.5
        assert wait_until(lambda: diagnosed(ros, "localized", "true") and diagnosed(ros, "inter-session anchors", "1")
                          and diagnosed(ros, "refused loop session unknown", "1"), 10)
    saved = PoseGraphBackend.load(graph)
    assert saved.sessions == ["a", "session"] and saved.anchored("session")


def test_rows_without_session_columns_or_with_nan_codes_are_this_runs_own_loops(tmp_path: Path) -> None:
    truth, _ = square_laps(side=30.0, step=0.5, laps=1)
    stamps = T_RUN + DT * np.arange(len(truth))
    with backend_node({"session": "today"}) as ros:
        assert wait_until(lambda: ros.localized == [True], 10)  # no prior: this run is the map
        publish_odometry(ros, stamps, truth)
        q = len(truth) - 1
        rel = np.linalg.inv(truth[0]) @ truth[q]
        row = [float(stamps[q]), float(stamps[0]), 1.0, *rel[:3, 3], *matrix_to_quaternion(rel[:3, :3]),
               *LOOP_COV.reshape(36)]
        ros.candidates.publish(table_msg([row], COLUMNS[:-2]))  # an older detector: no session columns
        ros.candidates.publish(table_msg([[*row, math.nan, math.nan]], COLUMNS))  # a detector that kept no table
        assert wait_until(lambda: ros.node._stats.loops_accepted + ros.node._stats.loops_redundant == 2, 20), \
            ros.node._stats
        assert ros.node.backend.sessions == ["today"] and ros.node.backend.session_loops()[0][::2] == ("today",
                                                                                                       "today")
        assert ros.corrected and ros.corrected[-1].header.frame_id == "map"


def test_a_row_whose_session_code_the_table_never_names_is_dropped_after_pending_s_and_counted(
        tmp_path: Path) -> None:
    stamps = T_RUN + DT * np.arange(40)
    poses = np.stack([pose(0.5 * i) for i in range(40)])
    with backend_node({"pending_s": 1.0}) as ros:
        ros.sessions.publish(sessions_msg(["session"]))
        publish_odometry(ros, stamps[:10], poses[:10])
        rel = np.linalg.inv(poses[0]) @ poses[9]
        row = [float(stamps[9]), float(stamps[0]), 1.0, *rel[:3, 3], *matrix_to_quaternion(rel[:3, :3]),
               *LOOP_COV.reshape(36), 0.0, 3.0]  # code 3: not in the table
        bad = [*row[:-2], 0.5, 0.0]  # no index at all
        ros.candidates.publish(table_msg([row, bad], COLUMNS))
        assert wait_until(lambda: waiting_for_names(ros) == 1, 10)
        publish_odometry(ros, stamps[10:40], poses[10:40])  # 3 s of odometry
        drops = ros.node.drops.snapshot
        assert wait_until(lambda: drops().get("loop: its session names never came") == 1
                          and drops().get("candidates: bad session code") == 1, 10), drops()
        assert waiting_for_names(ros) == 0 and ros.node._stats.loops_accepted == 0


def test_a_prior_holding_this_runs_session_name_refuses_the_start_naming_both(tmp_path: Path) -> None:
    prior = Drives().save_prior(tmp_path / "prior.npz", session="session")
    with pytest.raises(ConfigError, match=r"session='session' is a session of the prior map in prior_graph "
                                          rf"{prior}.*needs a session name of its own"):
        with backend_node({"prior_graph": str(prior)}):
            pass


def test_a_prior_graph_that_is_missing_or_not_a_graph_refuses_the_start_naming_it(tmp_path: Path) -> None:
    missing = tmp_path / "none.npz"
    with pytest.raises(MapLoadError, match=rf"prior_graph {missing} does not exist"):
        with backend_node({"prior_graph": str(missing)}):
            pass
    other = tmp_path / "other.npz"
    np.savez(other, x=np.zeros(3))
    with pytest.raises(MapLoadError, match=rf"prior_graph {other} cannot be used: .*schema"):
        with backend_node({"prior_graph": str(other)}):
            pass


def test_a_prior_graph_of_another_map_refuses_the_start_naming_both_files(tmp_path: Path) -> None:
    from lcpr_core.descriptor_map import DescriptorMap

    drives = Drives()
    prior = drives.save_prior(tmp_path / "prior.npz", session="a")

    def map_file(name: str, source: str, stamps: np.ndarray) -> Path:
        m = DescriptorMap()
        m.add(np.eye(256, dtype=np.float32)[: len(stamps)], stamps=stamps, sources=source)
        m.save(tmp_path / name)
        return tmp_path / name

    beside = map_file("beside.npz", "a", drives.stamps_a[[5, 50]])
    with backend_node({"prior_graph": str(prior), "prior_map": str(beside)}):
        pass  # the map the graph was saved beside: the start goes on
    other = map_file("other.npz", "monday", drives.stamps_a[[5, 50]])
    with pytest.raises(MapLoadError, match=rf"prior_map {other} holds sessions \['monday'\], none of them a session "
                                           r"of this graph \(a\).*give the map file the prior graph was saved beside"):
        with backend_node({"prior_graph": str(prior), "prior_map": str(other)}):
            pass
