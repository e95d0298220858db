"""lcpr_replay publishes a rosbag2 over DDS with the original header stamps and bytes."""
from __future__ import annotations

import os
import random
import subprocess
import sys
import time
from collections.abc import Iterator
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import rclpy
from rclpy.context import Context
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import CompressedImage, PointCloud2

from lcpr_ros.replay import message_class, replay, shared_memory_profile
from msg_tools.bags import BagWriter
from msg_tools.compressed import compressed_from_bytes
from msg_tools.frames import CameraModel
from msg_tools.pointcloud import array_to_pointcloud2, xyz_cloud
from msg_tools.types import Stamp
from ros_common.harness import driver_node, synthetic_place

REPO = Path(__file__).resolve().parents[2]
DOMAIN = random.randint(1, 100)
PREFIX = f"/r{random.randint(0, 10**6)}"
CAMERA = f"{PREFIX}/CAM_FRONT/image/compressed"
LIDAR = f"{PREFIX}/LIDAR_TOP/points"
STAMPS = [Stamp(1_532_402_927, 123_456_789 + 200_000_000 * i) for i in range(4)]  # exact, spans 0.6 s
RELIABLE = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
RIG = [f"{PREFIX}/CAM_{k}/image/compressed" for k in range(6)]  # six cameras, published before each big cloud
RIG_LIDAR = f"{PREFIX}/rig/points"
RIG_STAMPS = [Stamp(1_700_000_000, 250_000_000 * i) for i in range(4)]


@pytest.fixture(scope="module")
def bag(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("replay") / "bag"
    camera = CameraModel("CAM_FRONT", "cam", 128, 48, np.eye(3), np.eye(4))
    with BagWriter(path) as writer:
        for i, stamp in enumerate(STAMPS):
            place = synthetic_place(i)
            writer.write(CAMERA, compressed_from_bytes(place.jpegs[0], frame_id="cam", stamp=stamp))
            writer.write(LIDAR, array_to_pointcloud2(place.cloud, frame_id="lidar", stamp=stamp))
        writer.write_static_transforms([camera], "lidar", np.eye(4))  # tf2_msgs: not installed here
    return path


@pytest.fixture(scope="module")
def rig_bag(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A camera+LiDAR bag whose frames (six small JPEGs, then a 1.6 MB cloud) outgrow Fast DDS's default
    512 KiB shared-memory segment, like the demo's drives at small image sizes."""
    path = tmp_path_factory.mktemp("rig") / "bag"
    rng = np.random.default_rng(0)
    with BagWriter(path) as writer:
        for i, stamp in enumerate(RIG_STAMPS):
            place = synthetic_place(i)
            for topic, jpeg in zip(RIG, place.jpegs, strict=True):
                writer.write(topic, compressed_from_bytes(jpeg, frame_id="cam", stamp=stamp))
            cloud = xyz_cloud(rng.uniform(-50, 50, (100_000, 3)))
            writer.write(RIG_LIDAR, array_to_pointcloud2(cloud, frame_id="lidar", stamp=stamp))
    return path


@pytest.fixture(scope="module")
def ros() -> Iterator[tuple[Context, Node]]:
    with driver_node("replay_test", DOMAIN) as node:
        yield node.context, node


class Received:
    def __init__(self, node: Node) -> None:
        self.images: list[CompressedImage] = []
        self.clouds: list[PointCloud2] = []
        self._subs = [node.create_subscription(CompressedImage, CAMERA, self.images.append, RELIABLE),
                      node.create_subscription(PointCloud2, LIDAR, self.clouds.append, RELIABLE)]
        self._node = node

    def close(self) -> None:
        for sub in self._subs:
            self._node.destroy_subscription(sub)

    def wait(self, images: int, clouds: int, timeout: float = 20.0) -> bool:
        deadline = time.monotonic() + timeout
        while (len(self.images), len(self.clouds)) != (images, clouds):
            if time.monotonic() > deadline:
                return False
            time.sleep(0.02)
        return True


def stamp_of(msg: Any) -> Stamp:
    return Stamp(msg.header.stamp.sec, msg.header.stamp.nanosec)


def test_a_replayed_bag_arrives_with_its_original_header_stamps_and_bytes(ros: tuple[Context, Node],
                                                                          bag: Path) -> None:
    _, node = ros
    received = Received(node)
    publisher_node = rclpy.create_node("replayer", context=ros[0])
    try:
        stats = replay(publisher_node, bag, rate=0, wait_subscribers=10, log=lambda text: None)
        assert received.wait(4, 4)
    finally:
        publisher_node.destroy_node()
        received.close()
    assert stats.published == {CAMERA: 4, LIDAR: 4}
    assert stats.skipped == {"/tf_static": "tf2_msgs/msg/TFMessage is not installed"}
    assert [stamp_of(m) for m in received.clouds] == STAMPS
    assert [stamp_of(m) for m in received.images] == STAMPS
    assert bytes(received.images[2].data) == synthetic_place(2).jpegs[0]
    assert received.clouds[1].width == len(synthetic_place(1).cloud)


def test_the_rate_paces_publishing_by_the_bag_times(ros: tuple[Context, Node], bag: Path) -> None:
    publisher_node = rclpy.create_node("paced", context=ros[0])
    try:
        real_time = replay(publisher_node, bag, rate=1.0, log=lambda text: None)
        double = replay(publisher_node, bag, rate=2.0, log=lambda text: None)
    finally:
        publisher_node.destroy_node()
    assert 0.55 <= real_time.seconds < 3.0
    assert 0.25 <= double.seconds < real_time.seconds


def test_message_types_are_looked_up_from_their_names() -> None:
    assert message_class("sensor_msgs/msg/PointCloud2") is PointCloud2
    assert message_class("no_such_pkg/msg/Thing") is None


def run_replay(*args: str) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "ROS_DOMAIN_ID": str(DOMAIN),
           "PYTHONPATH": os.pathsep.join([str(REPO), *filter(None, [os.environ.get("PYTHONPATH")])])}
    return subprocess.run([sys.executable, "-m", "lcpr_ros.replay", *args], cwd=REPO, env=env, text=True,
                          capture_output=True, timeout=60)


def test_the_lcpr_replay_command_publishes_only_the_chosen_topics(ros: tuple[Context, Node], bag: Path) -> None:
    received = Received(ros[1])
    try:
        done = run_replay(str(bag), "--rate", "0", "--topics", LIDAR, "--no-progress", "--wait-subscribers", "10")
        assert done.returncode == 0, done.stderr
        assert received.wait(0, 4)
    finally:
        received.close()
    assert "published 4 messages on 1 topics" in done.stderr
    assert [stamp_of(m) for m in received.clouds] == STAMPS


def test_the_lcpr_replay_command_refuses_a_topic_the_bag_lacks(bag: Path) -> None:
    done = run_replay(str(bag), "--topics", "/nope", "--no-progress")
    assert done.returncode == 1
    assert "/nope" in done.stderr and "not in" in done.stderr


def test_images_published_just_before_a_large_cloud_arrive_with_it(ros: tuple[Context, Node], rig_bag: Path) -> None:
    """Fast DDS's default shared-memory segment recycled the images' buffers to send the cloud; reliable QoS
    then repaired them only at the next heartbeat (3 s), long after the node had given up on them."""
    node = ros[1]
    arrivals: dict[tuple[str, Stamp], float] = {}

    def on_message(topic: str, msg: object) -> None:
        arrivals[(topic, stamp_of(msg))] = time.monotonic()

    subs = [node.create_subscription(CompressedImage, topic, partial(on_message, topic), RELIABLE) for topic in RIG]
    subs.append(node.create_subscription(PointCloud2, RIG_LIDAR, partial(on_message, RIG_LIDAR), RELIABLE))
    try:
        done = run_replay(str(rig_bag), "--rate", "1", "--no-progress", "--wait-subscribers", "10")
        assert done.returncode == 0, done.stderr
        deadline = time.monotonic() + 10
        while len(arrivals) < 7 * len(RIG_STAMPS) and time.monotonic() < deadline:
            time.sleep(0.05)
    finally:
        for sub in subs:
            node.destroy_subscription(sub)
    assert len(arrivals) == 7 * len(RIG_STAMPS)
    late = {(topic, stamp): round(arrivals[(topic, stamp)] - arrivals[(RIG_LIDAR, stamp)], 2)
            for topic in RIG for stamp in RIG_STAMPS if arrivals[(topic, stamp)] - arrivals[(RIG_LIDAR, stamp)] > 0.2}
    assert not late, f"images later than their cloud by more than 0.2 s: {late}"


def test_the_replay_keeps_a_users_own_fast_dds_settings_and_restores_the_environment() -> None:
    environ: dict[str, str] = {}
    with shared_memory_profile(4096, environ=environ) as path:
        # Fast DDS 3.x (Kilted) reads the first variable, 2.x (Jazzy) the second: both point at the profile.
        assert path is not None
        assert environ["FASTDDS_DEFAULT_PROFILES_FILE"] == environ["FASTRTPS_DEFAULT_PROFILES_FILE"] == str(path)
        assert "<segment_size>4096</segment_size>" in path.read_text()
    assert environ == {} and not path.exists()
    for own in ({"FASTDDS_DEFAULT_PROFILES_FILE": "/etc/mine.xml"}, {"FASTRTPS_DEFAULT_PROFILES_FILE": "/etc/mine.xml"},
                {"FASTDDS_BUILTIN_TRANSPORTS": "UDPv4"},
                {"RMW_IMPLEMENTATION": "rmw_cyclonedds_cpp"}):
        environ = dict(own)
        with shared_memory_profile(environ=environ) as path:
            assert path is None and environ == own
