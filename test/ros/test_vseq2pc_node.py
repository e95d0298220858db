"""The vseq2pc node in this process (rclpy executor in a thread), driven over real DDS on loopback.

Drive: a short KITTI-like synthetic drive (citysim, 320 x 96 images, 2.5 m between
frames). The map pass publishes each frame's labelled 64-beam LiDAR cloud with odometry;
100 s later the camera pass publishes the same poses' depth + label images and CameraInfo.
The node runs the bundled trained weights (weights/vseq2pc_synth_*.pth), so each camera
sequence has to be told apart from the other scans of the street by the network: a
cross-modal revisit at the map's poses. (True revisits along other paths are measured on a
held-out drive by benchmarks/recipes/vseq2pc_train_synth.sh; see README.)
"""
from __future__ import annotations

import os
import random
import signal
import subprocess
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import rclpy
from nav_msgs.msg import Odometry
from rclpy.client import Client
from rclpy.context import Context
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.publisher import Publisher
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import CameraInfo, Image, PointCloud2
from std_srvs.srv import Trigger

from citysim import SynthConfig, SyntheticDrive
from lcpr_core.pretrained import default_vseq2pc_weights
from lcpr_core.vseq2pc.sequence import sequence_table
from msg_tools.camera_info import model_to_camera_info
from msg_tools.frames import CameraModel
from msg_tools.image import array_to_image
from msg_tools.pointcloud import array_to_pointcloud2
from msg_tools.transforms import pose_to_odometry
from ros_common import inputs
from ros_common.errors import ConfigError, MapLoadError
from ros_common.harness import OutputListener, spinning, wait_until
from vseq2pc_ros.config import NodeConfig
from vseq2pc_ros.node import Vseq2pcNode
from vseq2pc_ros.sync import SIZE_MISMATCH, TIME_JUMPED

REPO = Path(__file__).resolve().parents[2]
DOMAIN = random.randint(101, 200)
PREFIX = f"/v{random.randint(0, 10**6)}"
TOPICS = {"lidar_topic": f"{PREFIX}/points", "depth_topic": f"{PREFIX}/depth", "labels_topic": f"{PREFIX}/labels",
          "camera_info_topic": f"{PREFIX}/camera_info", "image_topic": "", "odom_topic": f"{PREFIX}/odom"}
FRAMES = 16  # 2.5 m apart: the first 9 or 10 frames become queries (15 m on)
MATCHED = 4  # of the 9 or 10 queries, whose best scan lies within 3 m (the paper's positives); seeded weights: 0
T0 = 1_700_000_000.0
DT = 0.25
REVISIT = 100.0  # s after the map pass
WAIT = 60.0
QOS = QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE)
LABEL_CLOUD = np.dtype([("x", np.float32), ("y", np.float32), ("z", np.float32), ("label", np.uint32)])


@dataclass
class Drive:
    poses: list[np.ndarray]
    depth: list[np.ndarray]  # float32 metres
    labels: list[np.ndarray]  # uint16
    clouds: list[np.ndarray]  # structured x, y, z, label: the labelled LiDAR scan
    info: CameraModel
    weights: tuple[Path, Path]  # sequence, descriptor


@pytest.fixture(scope="module")
def drive() -> Drive:
    weights = default_vseq2pc_weights()
    assert weights is not None, "weights/vseq2pc_synth_*.pth are missing from this checkout"
    return render(SynthConfig(rig="kitti", frames=FRAMES, route="grid", image_size=(320, 96), seed=0,
                              camera_drop=0.0, keyframe_spacing=2.5), (Path(weights[0]), Path(weights[1])))


def render(config: SynthConfig, weights: tuple[Path, Path]) -> Drive:
    synth = SyntheticDrive(config)
    out = Drive([], [], [], [], synth.rig.cameras[0], weights)
    for i in range(FRAMES):
        frame = synth.frame(i)
        image = frame.cameras[0]
        assert image is not None and image.depth is not None and image.labels is not None
        out.poses.append(synth.pose(i))
        out.depth.append(image.depth.astype(np.float32))
        out.labels.append(image.labels.astype(np.uint16))
        cloud = np.zeros(len(frame.cloud), LABEL_CLOUD)
        assert LABEL_CLOUD.names is not None
        for name in LABEL_CLOUD.names:
            cloud[name] = frame.cloud[name]
        out.clouds.append(cloud)
    return out


def params(drive: Drive, **extra: object) -> list[Parameter]:
    values: dict[str, object] = {
        **TOPICS, "input_qos": "reliable", "model.sequence": str(drive.weights[0]),
        "model.descriptor": str(drive.weights[1]), "model.threads": 1, "sync.max_wait": 5.0,
        "worker.max_waiting": 64, "diagnostics.period": 0.2, "match.top_k": 3, **extra,
    }
    return [Parameter(name, value=value) for name, value in values.items()]


@dataclass
class Ros:
    context: Context
    node: Vseq2pcNode
    driver: Node
    listener: OutputListener
    pubs: dict[str, Publisher]
    map_path: Path
    info: CameraModel

    def odom(self, pose: np.ndarray, stamp: float) -> None:
        self.pubs["odom"].publish(pose_to_odometry(pose, stamp=stamp, msg_type=Odometry))

    def cloud(self, msg: PointCloud2) -> None:
        self.pubs["cloud"].publish(msg)

    def camera(self, depth: Image, labels: Image, stamp: float) -> None:
        self.pubs["info"].publish(model_to_camera_info(self.info, stamp=stamp, msg_type=CameraInfo))
        self.pubs["depth"].publish(depth)
        self.pubs["labels"].publish(labels)


def cloud_msg(cloud: np.ndarray, stamp: float) -> PointCloud2:
    return array_to_pointcloud2(cloud, frame_id="velodyne", stamp=stamp, msg_type=PointCloud2)


def depth_msg(depth: np.ndarray, stamp: float, encoding: str = "32FC1") -> Image:
    return array_to_image(depth, encoding=encoding, frame_id="camera_left", stamp=stamp, msg_type=Image)


def labels_msg(labels: np.ndarray, stamp: float) -> Image:
    return array_to_image(labels, encoding="mono16", frame_id="camera_left", stamp=stamp, msg_type=Image)


@pytest.fixture(scope="module")
def exact_drive() -> Drive:
    """The same route with exact depth to any range (projected LiDAR, stereo, RGB-D) and the weights for it."""
    weights = default_vseq2pc_weights(depth="exact")
    assert weights is not None, "weights/vseq2pc_synth_exact_*.pth are missing from this checkout"
    return render(SynthConfig(rig="kitti", frames=FRAMES, route="grid", image_size=(320, 96), seed=0,
                              camera_drop=0.0, keyframe_spacing=2.5, depth_noise=0.0, depth_range=0.0),
                  (Path(weights[0]), Path(weights[1])))


@contextmanager
def started(drive: Drive, map_path: Path, **extra: object) -> Iterator[Ros]:
    """A node of its own (its own context and domain) with a driver publishing its inputs, spinning."""
    context = Context()
    rclpy.init(context=context, domain_id=random.randint(1, 200))
    node = Vseq2pcNode(context=context, parameter_overrides=params(drive, **{"map.path": str(map_path), **extra}))
    driver = rclpy.create_node("vdriver", context=context)
    with spinning(context, node, driver):
        pubs = {"odom": driver.create_publisher(Odometry, TOPICS["odom_topic"], QOS),
                "cloud": driver.create_publisher(PointCloud2, TOPICS["lidar_topic"], QOS),
                "depth": driver.create_publisher(Image, TOPICS["depth_topic"], QOS),
                "labels": driver.create_publisher(Image, TOPICS["labels_topic"], QOS),
                "info": driver.create_publisher(CameraInfo, TOPICS["camera_info_topic"], QOS)}
        listener = OutputListener(driver, "/vseq2pc")
        assert wait_until(lambda: all(p.get_subscription_count() >= 1 for p in pubs.values()), 20)
        listener.wait_for_publishers()
        yield Ros(context, node, driver, listener, pubs, map_path, drive.info)


@pytest.fixture()
def ros(request: pytest.FixtureRequest, drive: Drive, tmp_path_factory: pytest.TempPathFactory) -> Iterator[Ros]:
    """A node of its own for every test (fresh map and counters): each passes alone and in any order.
    A test parametrised indirectly with a dict of parameters starts the node with them too."""
    extra: dict[str, object] = dict(getattr(request, "param", {}))
    with started(drive, tmp_path_factory.mktemp("map") / "vseq2pc_map.npz", **extra) as made:
        yield made


def publish_map_pass(ros: Ros, drive: Drive, start: float = T0) -> None:
    """The LiDAR drive, one scan after the other: each waits until the node has added the last."""
    size = len(ros.node.map)
    for i in range(FRAMES):
        ros.odom(drive.poses[i], start + i * DT)
        ros.cloud(cloud_msg(drive.clouds[i], start + i * DT))

        def added(i: int = i) -> bool:
            return len(ros.node.map) == size + i + 1
        assert wait_until(added, WAIT), ros.node.health()


def camera_frames_handled(ros: Ros) -> int:
    return sum(n for k, n in ros.node.decisions.snapshot().items() if k.startswith("camera frames"))


def publish_camera_pass(ros: Ros, drive: Drive, start: float) -> None:
    """The camera drive along the same route: each frame waits until the node has taken the last."""
    handled = camera_frames_handled(ros)
    for i in range(FRAMES):
        stamp = start + i * DT
        ros.odom(drive.poses[i], stamp)
        ros.camera(depth_msg(drive.depth[i], stamp), labels_msg(drive.labels[i], stamp), stamp)

        def taken(i: int = i) -> bool:
            return camera_frames_handled(ros) == handled + i + 1
        assert wait_until(taken, WAIT), ros.node.health()


@pytest.mark.parametrize("ros", [{"verify.enabled": False}], indirect=True)
def test_camera_sequences_revisiting_the_map_are_matched_to_the_scans_at_their_poses(ros: Ros, drive: Drive) -> None:
    publish_map_pass(ros, drive)
    publish_camera_pass(ros, drive, T0 + REVISIT)
    xy = np.array([p[:2, 3] for p in drive.poses])
    queries = int((sequence_table(xy)[:, 0] >= 0).sum())  # frames with a frame 15 m further on
    assert queries >= 8
    assert ros.listener.wait(lambda o: len(o.loops) >= queries and len(o.candidates) >= queries, WAIT), \
        (queries, ros.listener.out.loops, ros.node.health())
    best = []
    for q, rows in enumerate(ros.listener.out.candidates[:queries]):
        assert len(rows) == 3 and [r["rank"] for r in rows] == [0, 1, 2]
        assert all(r["verified"] == 0.0 and np.isnan(r["tx"]) and np.isnan(r["cov_0"]) for r in rows)
        assert {"query_stamp", "match_stamp", "distance", "probability"} <= set(rows[0])
        assert rows[0]["query_id"] == q and rows[0]["distance"] == pytest.approx(1.0 - rows[0]["probability"])
        assert all(a["distance"] <= b["distance"] for a, b in zip(rows, rows[1:], strict=False))
        best.append(int(rows[0]["match_id"]))
    for q, (query_stamp, match_stamp) in enumerate(ros.listener.out.loops[:queries]):
        assert query_stamp == pytest.approx(T0 + REVISIT + q * DT)
        assert match_stamp == pytest.approx(T0 + best[q] * DT)
    off = np.hypot(*(xy[best] - xy[:queries]).T)
    assert (off < 3.0).sum() >= MATCHED, f"best scan this far from each query: {np.round(off, 1)} m"
    assert wait_until(lambda: ros.listener.latest_values(": detector").get("loops") == str(queries), 10)


@pytest.mark.parametrize("consistency", [1, 2])
def test_with_exact_depth_loops_are_verified_ones_with_the_camera_pose_and_diagnostics_count_the_verdicts(
        exact_drive: Drive, tmp_path: Path, consistency: int) -> None:
    extra = {"model.sequence": "bundled-exact", "model.descriptor": "bundled-exact",
             "verify.min_fitness": 0.4, "verify.min_support": 2,  # 3 candidates a query (match.top_k)
             "verify.consistency": consistency, "verify.consistency_spacing": 4.0}  # frames 2.5 m apart
    with started(exact_drive, tmp_path / "m.npz", **extra) as ros:
        node, listener = ros.node, ros.listener
        publish_map_pass(ros, exact_drive)
        publish_camera_pass(ros, exact_drive, T0 + REVISIT)
        xy = np.array([p[:2, 3] for p in exact_drive.poses])
        queries = int((sequence_table(xy)[:, 0] >= 0).sum())
        assert wait_until(lambda: node.queries == queries, WAIT), node.health()
        assert listener.wait(lambda o: len(o.candidates) >= queries, WAIT)
        rows = [r for batch in listener.out.candidates for r in batch]
        loops = listener.out.loops
        # nearly every query: a verified loop; with the temporal gate the first two (no query 4 m before them) are
        # held back, then published late when the queries after them confirm them
        assert queries - 1 - 3 * (consistency - 1) <= len(loops) <= queries, (len(loops), queries)
        if consistency > 1:
            assert wait_until(lambda: int(listener.latest_values(": detector").get("rejected inconsistent", "0"))
                              >= 2, 10), listener.latest_values(": detector")
            assert wait_until(lambda: int(listener.latest_values(": detector").get("frames loops confirmed late", "0"))
                              >= 1, 10), listener.latest_values(": detector")
            assert len({q for q, _ in loops}) == len(loops)  # one loop per query, late or not
        by_query = {batch[0]["query_stamp"]: batch for batch in listener.out.candidates}  # a late batch: the latest
        seen: set[float] = set()
        late_rows = []  # a query's candidates again, with the loop confirmed late: not a new verdict
        for batch in listener.out.candidates:
            if batch[0]["query_stamp"] in seen:
                late_rows += batch
            seen.add(batch[0]["query_stamp"])
        for query_stamp, match_stamp in loops:
            best = max((r for r in by_query[query_stamp] if r["verified"] == 1.0), key=lambda r: r["fitness"])
            assert best["match_stamp"] == pytest.approx(match_stamp)
        lidar_T_cam = NodeConfig().extrinsics.lidar_T_cam()
        for r in rows:
            if r["verified"] != 1.0:
                continue
            q, m = int(r["query_id"]), int(r["match_id"])
            truth = np.linalg.inv(exact_drive.poses[m]) @ exact_drive.poses[q] @ lidar_T_cam
            assert np.linalg.norm(truth[:3, 3] - [r["tx"], r["ty"], r["tz"]]) < 0.3
            assert np.isfinite([r[f"cov_{i}"] for i in range(36)]).all() and r["cov_0"] > 0
        verified = sum(r["verified"] == 1.0 for r in rows) - sum(r["verified"] == 1.0 for r in late_rows)

        def counted() -> bool:
            values = listener.latest_values(": detector")
            return (values.get("candidates verified") == str(verified)
                    and values.get("candidates rejected") == str(len(rows) - len(late_rows) - verified))
        assert wait_until(counted, 10), listener.latest_values(": detector")


@pytest.mark.parametrize("ros", [{"verify.enabled": False}], indirect=True)
def test_a_camera_replay_that_jumps_back_in_time_starts_a_new_session_and_is_matched_again(
        ros: Ros, drive: Drive) -> None:
    publish_map_pass(ros, drive)
    publish_camera_pass(ros, drive, T0 + REVISIT)
    first = int((sequence_table(np.array([p[:2, 3] for p in drive.poses]))[:, 0] >= 0).sum())  # queries per pass
    assert ros.listener.wait(lambda o: len(o.loops) >= first, WAIT), ros.node.health()
    assert wait_until(lambda: ros.node.queries == first)  # the whole first pass is answered
    assert len(ros.listener.out.loops) == first
    logged = ros.node.warnings.logged
    replay = T0 + REVISIT - 50.0  # 54 s before the newest stamps: more than sync.jump_back (5 s)
    publish_camera_pass(ros, drive, replay)
    assert ros.listener.wait(lambda o: len(o.loops) >= 2 * first, WAIT), (first, ros.listener.out.loops)
    assert wait_until(lambda: ros.node.queries == 2 * first) and len(ros.listener.out.loops) == 2 * first
    again = ros.listener.out.loops[first:]
    assert [q for q, _ in again] == pytest.approx([replay + q * DT for q in range(len(again))])
    assert [m for _, m in again] == pytest.approx([m for _, m in ros.listener.out.loops[:first]])
    assert ros.node.fixes.snapshot()[TIME_JUMPED] == 2  # the depth and the label stream
    assert ros.node.warnings.logged - logged == 1 and TIME_JUMPED in ros.node.warnings.causes
    assert ros.node.drops.snapshot().get("depth: out of order", 0) == 0


def test_bad_input_is_dropped_counted_warned_once_and_the_map_is_kept(ros: Ros, drive: Drive) -> None:
    size = len(ros.node.map)
    logged = ros.node.warnings.logged
    stamp = T0 + 500.0
    no_label = np.zeros(10, [("x", np.float32), ("y", np.float32), ("z", np.float32)])
    no_xyz = np.zeros(10, [("a", np.float32), ("label", np.uint32)])
    truncated = cloud_msg(drive.clouds[0], stamp)
    truncated.data = bytes(truncated.data)[: len(truncated.data) // 2]
    for k in range(2):  # twice: the second time is only counted
        ros.cloud(cloud_msg(no_label, stamp + k))
        ros.cloud(cloud_msg(no_xyz, stamp + k))
        ros.cloud(truncated)
        t = stamp + 10 + k
        ros.odom(drive.poses[0], t)
        ros.pubs["depth"].publish(depth_msg(drive.depth[0].astype(np.uint8), t, "mono8"))  # not a depth encoding
        ros.camera(depth_msg(drive.depth[0], t + 0.5), labels_msg(drive.labels[0][:24, :80].copy(), t + 0.5), t + 0.5)
    ros.odom(drive.poses[1], stamp + 20)
    ros.cloud(cloud_msg(drive.clouds[1], stamp + 20))  # a good cloud
    ros.cloud(cloud_msg(drive.clouds[2], stamp + 19))  # out of order
    causes = [inputs.CLOUD_NO_LABEL, inputs.CLOUD_NO_XYZ, inputs.CLOUD_TRUNCATED, inputs.DEPTH_ENCODING,
              SIZE_MISMATCH, "cloud: out of order"]
    expected = {cause: 1 if cause == "cloud: out of order" else 2 for cause in causes}
    assert wait_until(lambda: all(ros.node.drops[c] >= n for c, n in expected.items())), ros.node.drops.snapshot()
    assert wait_until(lambda: len(ros.node.map) == size + 1)  # the good cloud still goes in
    assert ros.node.warnings.logged - logged == len(causes)  # once per cause
    values = ros.listener
    assert wait_until(lambda: values.latest_values(": inputs").get(f"dropped {inputs.CLOUD_NO_LABEL}") == "2", 10)
    assert wait_until(lambda: values.latest_values(": detector").get("map size") == str(size + 1), 10)


def test_runtime_parameters_are_validated(ros: Ros) -> None:
    ok = ros.node.set_parameters([Parameter("match.top_k", value=5)])[0]
    assert ok.successful and ros.node.settings.match.top_k == 5
    bad = ros.node.set_parameters([Parameter("extrinsics.matrix", value=[1.0] * 16)])[0]
    assert not bad.successful and "rigid" in bad.reason
    bad = ros.node.set_parameters([Parameter("match.min_probability", value=2.0)])[0]
    assert not bad.successful
    assert ros.node.settings.match.top_k == 5 and ros.node.settings.extrinsics.format == "xyz_rpy"


def test_the_map_is_saved_loaded_by_a_second_node_and_bad_files_refuse_the_start(ros: Ros, drive: Drive,
                                                                                 tmp_path: Path) -> None:
    client: Client = ros.driver.create_client(Trigger, "/vseq2pc/save_map")
    assert client.wait_for_service(timeout_sec=10)
    future = client.call_async(Trigger.Request())
    assert wait_until(future.done, 20)
    saved = future.result()
    assert saved is not None
    assert saved.success, saved.message
    size = len(ros.node.map)
    second = Vseq2pcNode(context=ros.context, parameter_overrides=params(drive, **{
        "map.path": str(ros.map_path), "lidar_topic": f"{PREFIX}/other"}))
    try:
        assert len(second.map) == size
        assert np.allclose(second.map.db.stamps, ros.node.map.db.stamps)
    finally:
        second.close()
        second.destroy_node()
    original = ros.map_path.read_bytes()
    seeded = {"model.sequence": "seeded", "model.descriptor": "seeded"}  # random weights: another model
    with pytest.raises(MapLoadError, match="descriptor weights"):
        Vseq2pcNode(context=ros.context, parameter_overrides=[
            Parameter(n, value=v) for n, v in {**TOPICS, **seeded, "map.path": str(ros.map_path)}.items()])
    assert ros.map_path.read_bytes() == original
    corrupt = tmp_path / "corrupt.npz"
    corrupt.write_bytes(b"not a map")
    with pytest.raises(MapLoadError):
        Vseq2pcNode(context=ros.context, parameter_overrides=params(drive, **{"map.path": str(corrupt)}))
    assert corrupt.read_bytes() == b"not a map"
    with pytest.raises(ConfigError, match="model.sequence"):
        Vseq2pcNode(context=ros.context, parameter_overrides=[Parameter("model.sequence", value="x.pth")])


def test_main_stops_cleanly_on_sigterm_and_refuses_a_corrupt_map(tmp_path: Path) -> None:
    env = {**os.environ, "ROS_DOMAIN_ID": str(DOMAIN + 1), "PYTHONPATH": str(REPO)}
    corrupt = tmp_path / "bad.npz"
    corrupt.write_bytes(b"junk")
    cmd = [sys.executable, "-m", "vseq2pc_ros.node", "--ros-args", "-p", f"lidar_topic:={PREFIX}/m",
           "-p", "diagnostics.period:=0.5"]
    bad = subprocess.run([*cmd, "-p", f"map.path:={corrupt}"], env=env, capture_output=True, text=True, timeout=60)
    assert bad.returncode == 1 and "cannot start" in bad.stderr and corrupt.read_bytes() == b"junk"
    saved = tmp_path / "saved.npz"
    proc = subprocess.Popen([*cmd, "-p", f"map.path:={saved}"], env=env, stderr=subprocess.PIPE, text=True)
    try:
        lines: list[str] = []
        assert proc.stderr is not None
        for line in proc.stderr:
            lines.append(line)
            if "ready:" in line:
                break
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=30) == 0, "".join(lines)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert saved.exists()  # an empty map, saved at shutdown
