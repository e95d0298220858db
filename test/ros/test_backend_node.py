"""The lcpr_backend node in this process (rclpy executor in a thread), driven over real DDS on loopback."""
from __future__ import annotations

import math
import random
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest

pytest.importorskip("gtsam")
rclpy = pytest.importorskip("rclpy")

from diagnostic_msgs.msg import DiagnosticArray  # noqa: E402
from geometry_msgs.msg import TransformStamped, Vector3Stamped  # noqa: E402
from nav_msgs.msg import Odometry  # noqa: E402
from nav_msgs.msg import Path as PathMsg  # noqa: E402
from rclpy.context import Context  # noqa: E402
from rclpy.node import Node  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from std_msgs.msg import Float64MultiArray  # noqa: E402
from std_srvs.srv import Trigger  # noqa: E402

from backend_ros.config import BackendNodeConfig, LidarMount, settings_from, yaml_text  # noqa: E402
from backend_ros.node import BackendNode, TFMessage  # noqa: E402
from lcpr_core.backend import PoseGraphBackend  # noqa: E402
from lcpr_core.detector import Result  # noqa: E402
from lcpr_core.posegraph import DriftModel, ate_rmse, drift_odometry  # noqa: E402
from lcpr_ros.outputs import CANDIDATE_COLUMNS, up_msg  # noqa: E402
from msg_tools.geometry import matrix_to_quaternion  # noqa: E402
from msg_tools.transforms import odometry_to_pose, pose_to_odometry  # noqa: E402
from ros_common.errors import ConfigError  # noqa: E402
from ros_common.harness import spinning, wait_until  # noqa: E402
from ros_common.qos import CANDIDATE_QOS, RELIABLE_INPUT_QOS  # noqa: E402
from ros_common.tables import table_msg  # noqa: E402
from trajectory_fixtures import square_laps  # noqa: E402

T0 = 1_700_000_000.0
DT = 0.1
LOOP_COV = np.diag([0.05**2] * 3 + [math.radians(0.5) ** 2] * 3)
MOUNT = LidarMount(xyz=(0.94, 0.0, 1.84), rpy=(0.0, 0.0, -math.pi / 2))


@dataclass
class Ros:
    node: BackendNode
    driver: Node
    odom: Any
    candidates: Any
    paths: list[PathMsg]
    corrected: list[Odometry]
    diagnostics: list[DiagnosticArray]
    graph_path: Path


@pytest.fixture()
def ros(tmp_path: Path) -> Iterator[Ros]:
    prefix = f"/b{random.randint(0, 10**6)}"
    context = Context()
    rclpy.init(context=context, domain_id=random.randint(1, 100))
    graph_path = tmp_path / "graph.npz"
    params = {"odom_topic": f"{prefix}/odom", "candidates_topic": f"{prefix}/candidates", "up_topic": f"{prefix}/up",
              "input_qos": "reliable",
              "graph.path": str(graph_path), "lidar.xyz": list(MOUNT.xyz), "lidar.rpy": list(MOUNT.rpy),
              "diagnostics.period": 0.2, "path_period": 0.2}
    node = BackendNode(context=context, parameter_overrides=[Parameter(k, value=v) for k, v in params.items()])
    driver = rclpy.create_node("driver", context=context)
    with spinning(context, node, driver):
        paths: list[PathMsg] = []
        corrected: list[Odometry] = []
        diagnostics: list[DiagnosticArray] = []
        driver.create_subscription(PathMsg, "/lcpr_backend/path", paths.append, CANDIDATE_QOS)
        driver.create_subscription(Odometry, "/lcpr_backend/odometry", corrected.append, 100)
        driver.create_subscription(DiagnosticArray, "/diagnostics", diagnostics.append, 10)
        odom = driver.create_publisher(Odometry, f"{prefix}/odom", RELIABLE_INPUT_QOS)
        candidates = driver.create_publisher(Float64MultiArray, f"{prefix}/candidates", CANDIDATE_QOS)
        assert wait_until(lambda: odom.get_subscription_count() > 0 and candidates.get_subscription_count() > 0, 20)
        yield Ros(node, driver, odom, candidates, paths, corrected, diagnostics, graph_path)


def candidate_row(query_stamp: float, match_stamp: float, match_T_query: np.ndarray, *, verified: bool = True,
                  covariance: np.ndarray | None = LOOP_COV) -> list[float]:
    values = {"query_stamp": query_stamp, "match_stamp": match_stamp, "query_id": 9.0, "match_id": 0.0,
              "distance": 0.3, "rank": 0.0, "degraded": 0.0, "verified": float(verified), "fitness": 0.8}
    q = matrix_to_quaternion(match_T_query[:3, :3])
    values.update(zip(("tx", "ty", "tz", "qx", "qy", "qz", "qw"), [*match_T_query[:3, 3], *q], strict=True))
    cov = np.full(36, math.nan) if covariance is None else covariance.reshape(36)
    values.update({f"cov_{i}": float(v) for i, v in enumerate(cov)})
    return [float(values.get(name, math.nan)) for name in CANDIDATE_COLUMNS]  # sessions: none named


def published(ros: Ros, stamps: np.ndarray, poses: np.ndarray) -> None:
    """Odometry messages, five at a time (a reliable keep-last-10 reader loses none), all in the graph."""
    topic = ros.node.settings.odom_topic
    for k, (t, pose) in enumerate(zip(stamps, poses, strict=True)):
        ros.odom.publish(pose_to_odometry(pose, stamp=float(t), frame_id="odom", msg_type=Odometry))
        if k % 5 == 4:
            def received(count: int = k + 1) -> bool:
                return ros.node.rates.totals[topic] >= count
            assert wait_until(received, 10, period=0.002)
    assert wait_until(lambda: ros.node._stats.odometry == len(stamps), 30), ros.node._stats


def stamp_of(msg: Any) -> float:
    return float(msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9)


def test_odometry_and_one_verified_candidate_row_come_back_as_a_corrected_path(ros: Ros) -> None:
    truth, _ = square_laps(side=30.0, step=0.5, laps=1)
    drifted, _ = drift_odometry(truth, model=DriftModel(seed=1, yaw_deg_per_m=0.3))
    stamps = T0 + DT * np.arange(len(truth))
    published(ros, stamps, drifted)
    assert wait_until(lambda: bool(ros.corrected) and stamp_of(ros.corrected[-1]) == pytest.approx(stamps[-1]), 10)
    np.testing.assert_allclose(odometry_to_pose(ros.corrected[-1]), drifted[-1], atol=1e-6)  # no loop yet
    assert ros.corrected[-1].header.frame_id == "map"

    lidar = truth @ MOUNT.matrix()
    q = len(truth) - 1
    rows = [candidate_row(stamps[q], stamps[0], np.linalg.inv(lidar[0]) @ lidar[q]),
            candidate_row(stamps[q], stamps[40], np.eye(4), verified=False)]  # unverified: ignored
    ros.candidates.publish(table_msg(rows, CANDIDATE_COLUMNS))
    assert wait_until(lambda: ros.node._stats.loops_accepted == 1, 20), ros.node._stats

    def closed() -> bool:  # a path published after the loop went in (one from before it may still arrive first)
        if not ros.paths or len(ros.paths[-1].poses) != ros.node._stats.nodes or ros.node.loops != 1:
            return False
        end = ros.paths[-1].poses[-1].pose.position
        return bool(np.linalg.norm(np.array([end.x, end.y]) - truth[q, :2, 3]) < 0.1)  # the loop closed the square
    assert wait_until(closed, 10)
    path = ros.paths[-1]
    assert path.header.frame_id == "map"
    nodes = np.array([[p.pose.position.x, p.pose.position.y, p.pose.position.z] for p in path.poses])
    node_stamps = np.array([stamp_of(p) for p in path.poses])
    idx = np.searchsorted(stamps, node_stamps - 1e-4)
    assert ate_rmse(nodes, truth[idx, :3, 3]) < 0.5 * ate_rmse(drifted[idx], truth[idx])

    # the next odometry message comes back with the new correction
    before = len(ros.corrected)
    step = drifted[-1].copy()
    step[0, 3] += 0.5
    ros.odom.publish(pose_to_odometry(step, stamp=float(stamps[-1] + DT), frame_id="odom", msg_type=Odometry))
    assert wait_until(lambda: len(ros.corrected) > before, 10)
    correction = ros.node.backend.map_T_odom(ros.node.settings.session)
    assert correction is not None
    np.testing.assert_allclose(odometry_to_pose(ros.corrected[-1]), correction @ step, atol=1e-6)

    def diagnosed() -> bool:
        return any(kv.key == "loops accepted" and kv.value == "1" for d in ros.diagnostics for s in d.status
                   for kv in s.values)
    assert wait_until(diagnosed, 10)


def test_the_detectors_ups_are_taken_and_a_bad_one_is_counted(ros: Ros) -> None:
    truth, _ = square_laps(side=30.0, step=0.5, laps=1)
    stamps = T0 + DT * np.arange(len(truth))
    up_pub = ros.driver.create_publisher(Vector3Stamped, ros.node.settings.up_topic, CANDIDATE_QOS)
    assert wait_until(lambda: up_pub.get_subscription_count() > 0, 20)
    lidar = truth @ MOUNT.matrix()
    published(ros, stamps, truth)
    for i in range(0, len(truth), 20):
        up = lidar[i, :3, :3].T @ np.array([0.0, 0.0, 1.0])
        up_pub.publish(up_msg(Result(stamp=float(stamps[i]), keyframe_id=i, reason="keyframe", up=up), "lidar"))
    sent = len(range(0, len(truth), 20))
    assert wait_until(lambda: ros.node._stats.ups == sent, 20), ros.node._stats
    _, corrected = ros.node.backend.trajectory(ros.node.settings.session)
    np.testing.assert_allclose(corrected[:, :3, 3], truth[:, :3, 3], atol=0.02)  # true ups
    bad = Vector3Stamped()
    bad.header.stamp.sec = int(stamps[-1])
    up_pub.publish(bad)  # a zero vector
    assert wait_until(lambda: ros.node._stats.refused.get("up bad vector") == 1, 20), ros.node._stats
    assert ros.node._stats.ups == sent


def test_refused_inputs_are_counted_and_the_graph_is_saved_on_request(ros: Ros) -> None:
    stamps = T0 + DT * np.arange(30)
    poses = np.stack([np.eye(4)] * 30)
    poses[:, 0, 3] = 0.5 * np.arange(30)
    published(ros, stamps, poses)
    ros.odom.publish(pose_to_odometry(poses[3], stamp=float(stamps[3]), frame_id="odom", msg_type=Odometry))
    rows = [candidate_row(stamps[20], T0 - 100.0, np.eye(4)),  # older than the graph: refused by the back end
            candidate_row(stamps[25], stamps[0], np.eye(4)),  # 12.5 m off: rejected by the consistency check
            candidate_row(stamps[29] + 60.0, stamps[0], np.eye(4), covariance=None)]  # a minute ahead: dropped
    ros.candidates.publish(table_msg(rows, CANDIDATE_COLUMNS))
    bad = Float64MultiArray(data=[1.0, 2.0])  # no layout
    ros.candidates.publish(bad)

    def counted() -> bool:
        stats, drops = ros.node._stats, ros.node.drops.snapshot()
        return (stats.refused.get("loop stamp older than the graph") == 1 and stats.loops_rejected == 1
                and drops.get("odometry: out of order") == 1 and drops.get("loop: its odometry never came") == 1
                and drops.get("candidates: bad table") == 1)
    assert wait_until(counted, 20), (ros.node._stats, ros.node.drops.snapshot())

    client = ros.driver.create_client(Trigger, "/lcpr_backend/save_graph")
    assert client.wait_for_service(timeout_sec=20)
    future = client.call_async(Trigger.Request())
    assert wait_until(future.done, 20)
    response = future.result()
    nodes = ros.node._stats.nodes
    assert response.success and response.message == f"saved {nodes} graph nodes to {ros.graph_path}"
    loaded = PoseGraphBackend.load(ros.graph_path, ros.node.settings.backend())
    assert loaded.stats().nodes == nodes and loaded.stats().loops_rejected == 1


def test_the_map_to_odom_transform_is_published(ros: Ros) -> None:
    if TFMessage is not None:
        pytest.skip("tf2_msgs is installed: map -> odom goes to /tf")
    got: list[TransformStamped] = []
    ros.driver.create_subscription(TransformStamped, "/lcpr_backend/map_to_odom", got.append, 10)
    assert wait_until(lambda: ros.node.count_subscribers("/lcpr_backend/map_to_odom") > 0, 10)
    published(ros, T0 + DT * np.arange(3), np.stack([np.eye(4)] * 3))
    assert wait_until(lambda: len(got) >= 1 and stamp_of(got[-1]) == pytest.approx(T0 + 2 * DT), 10)
    assert (got[-1].header.frame_id, got[-1].child_frame_id) == ("map", "odom")


def test_the_node_settings_refuse_bad_values_and_the_yaml_lists_every_parameter() -> None:
    with pytest.raises(ConfigError, match=r"loops: LoopPolicy\.gate=2\.0"):
        settings_from({"loops.gate": 2.0})
    with pytest.raises(ConfigError, match=r"lidar: xyz=\[1\.0\]; give 3 finite metres"):
        settings_from({"lidar.xyz": (1.0,)})
    text = yaml_text()
    for name in ("odom_topic", "candidates_topic", "keyframes:", "robust", "default_sigmas", "graph:"):
        assert name in text
    config = BackendNodeConfig(lidar=MOUNT)
    np.testing.assert_allclose(config.backend().base_T_lidar[:3, :3], [[0, 1, 0], [-1, 0, 0], [0, 0, 1]], atol=1e-12)


def test_the_launch_file_starts_odometry_detector_and_back_end_with_their_params_files() -> None:
    import xml.etree.ElementTree as ET

    from backend_ros import kiss_icp_node
    from backend_ros.config import all_leaves
    from lcpr_ros.params import all_leaves as detector_leaves

    repo = Path(__file__).resolve().parents[2]
    root = ET.parse(repo / "launch" / "lcpr_backend.launch.xml").getroot()
    nodes = {str(n.get("exec")): n for n in root.findall("node")}
    assert {e: n.get("name") for e, n in nodes.items()} == {
        "lcpr_kiss_icp": "lcpr_kiss_icp", "lcpr_node": "lcpr", "lcpr_backend": "lcpr_backend"}
    known = {"lcpr_kiss_icp": kiss_icp_node.all_leaves(), "lcpr_node": detector_leaves(),
             "lcpr_backend": all_leaves()}
    for exe, node in nodes.items():
        params = node.findall("param")
        (params_file,) = [p.get("from") for p in params if p.get("from")]
        assert (repo / "config" / Path(str(params_file)).name).is_file()
        assert {p.get("name") for p in params if p.get("name")} <= {leaf.name for leaf in known[exe]}
    assert (repo / "config" / "lcpr_backend.yaml").read_text() == yaml_text()
    assert (repo / "config" / "lcpr_kiss_icp.yaml").read_text() == kiss_icp_node.yaml_text()


def test_the_prior_map_launch_file_gives_both_nodes_one_session_name_and_the_back_end_the_prior() -> None:
    import xml.etree.ElementTree as ET

    from backend_ros.config import all_leaves
    from lcpr_ros.params import all_leaves as detector_leaves

    repo = Path(__file__).resolve().parents[2]
    root = ET.parse(repo / "launch" / "lcpr_prior_map.launch.xml").getroot()
    required = {str(a.get("name")) for a in root.findall("arg") if a.get("default") is None}
    assert required == {"map_path", "prior_graph", "session"}
    nodes = {str(n.get("exec")): n for n in root.findall("node")}
    assert {e: n.get("name") for e, n in nodes.items()} == {"lcpr_node": "lcpr", "lcpr_backend": "lcpr_backend"}
    known = {"lcpr_node": detector_leaves(), "lcpr_backend": all_leaves()}
    values = {}
    for exe, node in nodes.items():
        params = node.findall("param")
        (params_file,) = [p.get("from") for p in params if p.get("from")]
        assert (repo / "config" / Path(str(params_file)).name).is_file()
        values[exe] = {str(p.get("name")): p.get("value") for p in params if p.get("name")}
        assert set(values[exe]) <= {leaf.name for leaf in known[exe]}
    assert values["lcpr_node"]["session"] == values["lcpr_backend"]["session"] == "$(var session)"
    assert values["lcpr_node"]["map.path"] == "$(var map_path)"
    assert values["lcpr_backend"]["prior_graph"] == "$(var prior_graph)"
    assert values["lcpr_backend"]["sessions_topic"] == "/lcpr/sessions"  # the detector (node name lcpr)'s ~/sessions
