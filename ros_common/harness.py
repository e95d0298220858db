"""Driving a running ``lcpr`` node from another rclpy node: synthetic places, a frame
publisher and a listener for its outputs. Used by the tests and benchmarks/tools/node_soak.py.

A *place* is a deterministic set of six camera images and one cloud (seeded by its
number): publishing the same place again at a later stamp is an exact revisit.
"""
from __future__ import annotations

import signal
import subprocess
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import Vector3Stamped
from nav_msgs.msg import Odometry
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import CompressedImage, Image, PointCloud2
from std_msgs.msg import Float64MultiArray

from msg_tools.compressed import compressed_from_bytes, encode_image
from msg_tools.image import array_to_image
from msg_tools.pointcloud import array_to_pointcloud2, xyz_cloud
from msg_tools.transforms import pose_to_odometry

from .qos import CANDIDATE_QOS
from .stamps import NS_PER_S, stamp_ns
from .tables import parse_candidates

SMALL_IMAGE = (48, 128)  # height, width of synthetic camera images


@dataclass(frozen=True)
class Place:
    number: int
    jpegs: tuple[bytes, ...]  # one per camera
    rgb: tuple[np.ndarray, ...]
    cloud: np.ndarray  # structured x, y, z, intensity


def synthetic_place(number: int, *, cameras: int = 6, size: tuple[int, int] = SMALL_IMAGE,
                    points: int = 2000) -> Place:
    """Random-but-deterministic camera images and a cloud for place ``number``."""
    rng = np.random.default_rng(number)
    rgb = []
    for _ in range(cameras):
        coarse = rng.integers(0, 256, (size[0] // 8, size[1] // 8, 3), dtype=np.uint8)
        rgb.append(np.ascontiguousarray(np.kron(coarse, np.ones((8, 8, 1), np.uint8))))
    azimuth = rng.uniform(-np.pi, np.pi, points)
    distance = rng.uniform(3.0, 40.0, points)
    height = rng.uniform(-1.5, 3.0, points)
    xyz = np.stack([distance * np.cos(azimuth), distance * np.sin(azimuth), height], axis=1)
    cloud = xyz_cloud(xyz, intensity=rng.uniform(0, 255, points).astype(np.float32))
    return Place(number, tuple(encode_image(a, format="jpeg", quality=90) for a in rgb), tuple(rgb), cloud)


def pose_at_x(x: float) -> np.ndarray:
    pose = np.eye(4)
    pose[0, 3] = x
    return pose


SENSOR_PUB_QOS = QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE)


class FramePublisher:
    """Publishes places as camera images + cloud (+ odometry) with chosen header stamps."""

    def __init__(self, node: Node, camera_topics: Sequence[str], lidar_topic: str, *, compressed: bool = True,
                 odom_topic: str = "") -> None:
        self.node = node
        self.compressed = compressed
        image_type = CompressedImage if compressed else Image
        self.cameras = [node.create_publisher(image_type, t, SENSOR_PUB_QOS) for t in camera_topics]
        self.lidar = node.create_publisher(PointCloud2, lidar_topic, SENSOR_PUB_QOS)
        self.odom = node.create_publisher(Odometry, odom_topic, SENSOR_PUB_QOS) if odom_topic else None

    @property
    def publishers(self) -> list[Any]:
        return [*self.cameras, self.lidar, *([self.odom] if self.odom is not None else [])]

    def wait_for_subscribers(self, timeout: float = 20.0) -> None:
        deadline = time.monotonic() + timeout
        while any(p.get_subscription_count() < 1 for p in self.publishers):
            if time.monotonic() > deadline:
                missing = [p.topic_name for p in self.publishers if p.get_subscription_count() < 1]
                raise TimeoutError(f"no subscriber on {missing} after {timeout} s")
            time.sleep(0.05)

    def image_msg(self, place: Place, camera: int, stamp: float) -> Any:
        if self.compressed:
            return compressed_from_bytes(place.jpegs[camera], frame_id=f"cam{camera}", stamp=stamp,
                                         msg_type=CompressedImage)
        return array_to_image(place.rgb[camera], encoding="rgb8", frame_id=f"cam{camera}", stamp=stamp,
                              msg_type=Image)

    def cloud_msg(self, place: Place, stamp: float) -> PointCloud2:
        return array_to_pointcloud2(place.cloud, frame_id="lidar", stamp=stamp, msg_type=PointCloud2)

    def publish(self, place: Place, stamp: float, *, pose: np.ndarray | None = None,
                skip_cameras: Sequence[int] = ()) -> None:
        """Odometry first, then the images, then the cloud, all stamped ``stamp``."""
        if pose is not None and self.odom is not None:
            self.odom.publish(pose_to_odometry(pose, stamp=stamp, msg_type=Odometry))
        for k, pub in enumerate(self.cameras):
            if k not in skip_cameras:
                pub.publish(self.image_msg(place, k, stamp))
        self.lidar.publish(self.cloud_msg(place, stamp))


def interrupt(process: subprocess.Popen[Any], timeout: float = 60.0) -> None:
    """Ctrl-C a node process (it finishes its frame and saves), killing it if it has not stopped within ``timeout``."""
    if process.poll() is not None:
        return
    process.send_signal(signal.SIGINT)
    try:
        process.wait(timeout)
    except subprocess.TimeoutExpired:
        process.kill()


@contextmanager
def _spun(context: Context, *nodes: Node) -> Iterator[SingleThreadedExecutor]:
    """``nodes`` spun by one executor in a background thread until the block ends."""
    executor = SingleThreadedExecutor(context=context)
    for node in nodes:
        executor.add_node(node)
    thread = threading.Thread(target=executor.spin, daemon=True)
    thread.start()
    try:
        yield executor
    finally:
        executor.shutdown(timeout_sec=5)
        thread.join(5)


@contextmanager
def driver_node(name: str, domain: int) -> Iterator[Node]:
    """A node of its own context on ``domain``, spun in a background thread (a test's or benchmark's driver);
    on leaving, the executor stops and the context shuts down."""
    context = Context()
    rclpy.init(context=context, domain_id=domain)
    node = rclpy.create_node(name, context=context)
    try:
        with _spun(context, node):
            yield node
    finally:
        node.destroy_node()
        rclpy.try_shutdown(context=context)


@contextmanager
def spinning(context: Context, node: Any, driver: Node) -> Iterator[SingleThreadedExecutor]:
    """Spin a node under test (one with ``close()``) and a driver node in a background thread; on leaving,
    close the node (its worker finishes), stop the executor and shut ``context`` down."""
    try:
        with _spun(context, node, driver) as executor:
            try:
                yield executor
            finally:
                node.close()
    finally:
        node.destroy_node()
        driver.destroy_node()
        rclpy.try_shutdown(context=context)


def wait_until(condition: Callable[[], bool], timeout: float = 60.0, *, period: float = 0.02) -> bool:
    """Poll ``condition`` every ``period`` s: True once it holds, False after ``timeout`` s."""
    deadline = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > deadline:
            return False
        time.sleep(period)
    return True


@dataclass
class Outputs:
    loops: list[tuple[float, float]] = field(default_factory=list)
    candidates: list[list[dict[str, float]]] = field(default_factory=list)
    diagnostics: list[DiagnosticArray] = field(default_factory=list)
    received: list[float] = field(default_factory=list)  # monotonic time of each ~/candidates message
    ups: list[tuple[float, np.ndarray]] = field(default_factory=list)  # (stamp, up) of each ~/up message


class OutputListener:
    """Subscribes to a node's ``~/loop_closure``, ``~/candidates``, ``~/up`` and ``/diagnostics``."""

    def __init__(self, node: Node, target: str = "/lcpr", *, keep_diagnostics: int = 50) -> None:
        self.node = node
        self.target = target
        self.out = Outputs()
        self._cond = threading.Condition()
        self._keep = keep_diagnostics
        node.create_subscription(Float64MultiArray, f"{target}/loop_closure", self._on_loop, CANDIDATE_QOS)
        node.create_subscription(Float64MultiArray, f"{target}/candidates", self._on_candidates, CANDIDATE_QOS)
        node.create_subscription(Vector3Stamped, f"{target}/up", self._on_up, CANDIDATE_QOS)
        node.create_subscription(DiagnosticArray, "/diagnostics", self._on_diagnostics, 10)

    def _on_up(self, msg: Vector3Stamped) -> None:
        v = msg.vector
        with self._cond:
            self.out.ups.append((stamp_ns(msg.header) / NS_PER_S, np.array([v.x, v.y, v.z])))
            self._cond.notify_all()

    def _on_loop(self, msg: Float64MultiArray) -> None:
        with self._cond:
            self.out.loops.append((float(msg.data[0]), float(msg.data[1])))
            self._cond.notify_all()

    def _on_candidates(self, msg: Float64MultiArray) -> None:
        rows = parse_candidates(msg)
        with self._cond:
            self.out.candidates.append(rows)
            self.out.received.append(time.monotonic())
            self._cond.notify_all()

    def _on_diagnostics(self, msg: DiagnosticArray) -> None:
        if not any(s.name.startswith(self.target.strip("/").split("/")[-1] + ":") for s in msg.status):
            return
        with self._cond:
            self.out.diagnostics.append(msg)
            del self.out.diagnostics[: -self._keep]
            self._cond.notify_all()

    def clear(self) -> None:
        """Forget everything heard so far (a new node under test)."""
        with self._cond:
            self.out = Outputs()

    def wait_for_publishers(self, timeout: float = 20.0) -> None:
        deadline = time.monotonic() + timeout
        topics = [f"{self.target}/loop_closure", f"{self.target}/candidates"]
        while any(self.node.count_publishers(t) < 1 for t in topics):
            if time.monotonic() > deadline:
                raise TimeoutError(f"no publisher on {topics} after {timeout} s")
            time.sleep(0.05)

    def wait(self, predicate: Callable[[Outputs], object], timeout: float) -> bool:
        """Block until ``predicate(outputs)`` holds (True) or the timeout passes (False).

        A predicate that reads a message not yet heard (``o.candidates[-1]`` on an empty list)
        counts as not holding yet: outputs arrive over DDS after the node decided.
        """
        def holds() -> bool:
            try:
                return bool(predicate(self.out))
            except (IndexError, KeyError):
                return False

        with self._cond:
            return self._cond.wait_for(holds, timeout)

    def latest_values(self, status_suffix: str) -> dict[str, str]:
        """Key-values of the newest diagnostics status whose name ends with ``status_suffix``."""
        with self._cond:
            for msg in reversed(self.out.diagnostics):
                for status in msg.status:
                    if status.name.endswith(status_suffix):
                        return {kv.key: kv.value for kv in status.values}
        return {}


# -- bad input, one message per cause ------------------------------------------------------------------
def cloud_without_xyz(stamp: float) -> PointCloud2:
    cloud = np.zeros(10, dtype=[("a", np.float32), ("b", np.float32)])
    return array_to_pointcloud2(cloud, frame_id="lidar", stamp=stamp, msg_type=PointCloud2)


def truncated_cloud(place: Place, stamp: float) -> PointCloud2:
    msg = array_to_pointcloud2(place.cloud, frame_id="lidar", stamp=stamp, msg_type=PointCloud2)
    msg.data = bytes(msg.data)[: len(msg.data) // 2]
    return msg


def cloud_with_nan(place: Place, stamp: float, count: int = 100) -> PointCloud2:
    cloud = place.cloud.copy()
    cloud["x"][:count] = np.nan
    return array_to_pointcloud2(cloud, frame_id="lidar", stamp=stamp, msg_type=PointCloud2)


def image_with_unknown_encoding(stamp: float, *, compressed: bool) -> Any:
    if compressed:
        return compressed_from_raw(b"GIF89a" + bytes(64), stamp)
    return array_to_image(np.zeros((8, 8), np.float32), encoding="32FC1", frame_id="cam", stamp=stamp, msg_type=Image)


def image_of_wrong_size(stamp: float, *, compressed: bool) -> Any:
    if compressed:
        return compressed_from_raw(b"", stamp)
    msg = array_to_image(np.zeros((8, 8, 3), np.uint8), encoding="rgb8", frame_id="cam", stamp=stamp, msg_type=Image)
    msg.height = 64  # says 64 rows, carries 8
    return msg


def compressed_from_raw(data: bytes, stamp: float) -> CompressedImage:
    """A CompressedImage holding arbitrary bytes (compressed_from_bytes would refuse them)."""
    msg = compressed_from_bytes(encode_image(np.zeros((8, 8, 3), np.uint8)), frame_id="cam", stamp=stamp,
                                msg_type=CompressedImage)
    msg.format = "jpeg"
    msg.data = data
    return msg
