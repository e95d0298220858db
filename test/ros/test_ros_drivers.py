"""Driver-shaped messages through the lcpr node over DDS: camera-native encodings and LiDAR layouts are used."""
from __future__ import annotations

import random
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np
import pytest
import rclpy
from rclpy.context import Context
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.publisher import Publisher
from sensor_msgs.msg import Image, PointCloud2

from camera_encodings import mosaic, nv21, packed_yuv422
from driver_layouts import LAYOUTS, driver_cloud
from lcpr_ros.node import LcprNode
from msg_tools import array_to_image
from ros_common.harness import SENSOR_PUB_QOS, spinning, synthetic_place, wait_until

PREFIX = f"/d{random.randint(0, 10**6)}"
CAMERAS = [f"{PREFIX}/CAM_{k}/image_raw" for k in range(6)]
LIDAR = f"{PREFIX}/points"
T0 = 1_700_000_000.0


@dataclass
class Ros:
    node: LcprNode
    driver: Node
    cameras: list[Publisher]
    lidar: Publisher


@pytest.fixture()
def ros() -> Iterator[Ros]:
    """A node of its own for every test (fresh map, counters and topics): each passes alone and in any order."""
    context = Context()
    rclpy.init(context=context, domain_id=random.randint(101, 200))
    values = {"model.image_size": [32, 96], "model.lidar": "velodyne_vlp16", "model.range_size": [8, 256],
              "model.weights": "seeded", "model.width": 0.25, "camera_topics": CAMERAS, "lidar_topic": LIDAR,
              "odom_topic": "",
              "sync.camera_timeout": 5.0, "keyframe.min_interval": 0.0, "verify.enabled": False}
    node = LcprNode(context=context, parameter_overrides=[Parameter(k, value=v) for k, v in values.items()])
    driver = rclpy.create_node("camera_driver", context=context)
    with spinning(context, node, driver):
        cameras = [driver.create_publisher(Image, t, SENSOR_PUB_QOS) for t in CAMERAS]
        lidar = driver.create_publisher(PointCloud2, LIDAR, SENSOR_PUB_QOS)
        assert wait_until(lambda: all(p.get_subscription_count() for p in [*cameras, lidar]), 20)
        yield Ros(node, driver, cameras, lidar)


def as_encoding(rgb: np.ndarray, encoding: str, stamp: float) -> Image:
    raw = {"rgb8": lambda a: a, "bayer_rggb8": lambda a: mosaic(a, "rggb"), "bayer_gbrg8": lambda a: mosaic(a, "gbrg"),
           "yuv422": lambda a: packed_yuv422(a, "UYVY"), "yuv422_yuy2": lambda a: packed_yuv422(a, "YUYV"),
           "nv21": nv21}[encoding](rgb)
    return array_to_image(raw, encoding=encoding, frame_id="cam", stamp=stamp, msg_type=Image)


def publish(ros: Ros, rgb: tuple[np.ndarray, ...], encoding: str, cloud: PointCloud2, stamp: float) -> None:
    before = sum(ros.node.decisions.snapshot().values())
    for k, pub in enumerate(ros.cameras):
        pub.publish(as_encoding(rgb[k], encoding, stamp))
    ros.lidar.publish(cloud)
    assert wait_until(lambda: sum(ros.node.decisions.snapshot().values()) > before, 60), (encoding, stamp)


@pytest.fixture()
def seen(monkeypatch: pytest.MonkeyPatch) -> dict[str, list]:
    """What the node's conversions returned for each message it took in (its camera images and cloud points)."""
    import lcpr_ros.node as node_module

    record: dict[str, list] = {"images": [], "points": []}
    camera_input, cloud_points = node_module.camera_input, node_module.cloud_points

    def spy_camera(payload, **kw):
        out = camera_input(payload, **kw)
        record["images"].append(np.asarray(out))
        return out

    def spy_cloud(msg):
        out = cloud_points(msg)
        record["points"].append(out[0])
        return out
    monkeypatch.setattr(node_module, "camera_input", spy_camera)
    monkeypatch.setattr(node_module, "cloud_points", spy_cloud)
    return record


@pytest.mark.parametrize("encoding", ["bayer_rggb8", "bayer_gbrg8", "yuv422", "yuv422_yuy2", "nv21", "rgb8"])
def test_camera_native_encodings_reach_the_model_as_the_rgb_they_encode(ros: Ros, seen: dict, encoding: str) -> None:
    """Six images in a camera-native encoding over DDS, with a cloud laid out as an Ouster OS1-64 publishes it:
    the frame is taken, nothing is dropped, each image the node decodes matches the RGB it encodes and the
    cloud's points are exactly its returns (a third of the beams publish the no-return zero point)."""
    stamp = T0 + 10.0 * len(ros.node.detector.map)
    place = synthetic_place(0)  # colours constant over 8 x 8 blocks: inside them demosaicing is exact
    xyz = np.stack([place.cloud[a] for a in "xyz"], axis=1).astype(np.float64)
    usable = len(xyz) // 64 * 64
    valid = np.ones(usable, bool)
    valid[::3] = False
    cloud = driver_cloud(LAYOUTS["ouster_os1_64"], xyz[:usable], valid, stamp=stamp, rclpy_types=True)
    publish(ros, place.rgb, encoding, cloud, stamp)
    assert not ros.node.drops.snapshot(), ros.node.drops.snapshot()
    assert len(seen["images"]) == 6 and len(seen["points"]) == 1
    rows, cols = np.mgrid[0:place.rgb[0].shape[0], 0:place.rgb[0].shape[1]]
    inside = (rows % 8 >= 2) & (rows % 8 <= 5) & (cols % 8 >= 2) & (cols % 8 <= 5)  # away from block edges
    for got, sent in zip(seen["images"], place.rgb, strict=True):
        assert got.shape == sent.shape
        assert np.abs(got[inside].astype(int) - sent[inside]).max() <= 3, encoding
    assert np.allclose(seen["points"][0], xyz[:usable][valid], atol=1e-5)


def test_with_the_default_input_qos_a_best_effort_driver_is_heard_too(ros: Ros) -> None:
    """input_qos best_available: a reliable subscriber would never connect to a best-effort driver."""
    from rclpy.qos import qos_profile_sensor_data

    assert ros.node.get_parameter("input_qos").value == "best_available"
    cameras = [ros.driver.create_publisher(Image, t, qos_profile_sensor_data) for t in CAMERAS]
    lidar = ros.driver.create_publisher(PointCloud2, LIDAR, qos_profile_sensor_data)
    try:
        assert wait_until(lambda: all(p.get_subscription_count() for p in [*cameras, lidar]), 20)
        best_effort = Ros(ros.node, ros.driver, cameras, lidar)
        place = synthetic_place(1)
        xyz = np.stack([place.cloud[a] for a in "xyz"], axis=1).astype(np.float64)
        stamp = T0 + 10.0 * len(ros.node.detector.map) + 5.0
        cloud = driver_cloud(LAYOUTS["velodyne_vlp16"], xyz, np.ones(len(xyz), bool), stamp=stamp, rclpy_types=True)
        before = len(ros.node.detector.map)
        publish(best_effort, place.rgb, "rgb8", cloud, stamp)
        assert len(ros.node.detector.map) == before + 1
        from ros_common.qos import QOS_ADAPTED

        assert QOS_ADAPTED in ros.node.warnings.causes  # said once, naming the topic
    finally:
        for p in [*cameras, lidar]:
            ros.driver.destroy_publisher(p)


def test_a_bag_played_again_starts_a_new_session_that_closes_loops_to_the_first_pass(ros: Ros) -> None:
    """Header time jumps back 60 s (ros2 bag play --loop, a simulator reset): no frame is refused as out of
    order, one warning names the cause, and the second pass of a place matches its first pass at once."""
    from lcpr_ros.sync import TIME_JUMPED

    first = T0 + 100_000.0
    places = [synthetic_place(2), synthetic_place(3)]
    ids = []
    for i, place in enumerate(places):
        xyz = np.stack([place.cloud[a] for a in "xyz"], axis=1).astype(np.float64)
        stamp = first + 60.0 * i
        publish(ros, place.rgb, "rgb8", driver_cloud(LAYOUTS["velodyne_vlp16"], xyz, np.ones(len(xyz), bool),
                                                     stamp=stamp, rclpy_types=True), stamp)
        ids.append(len(ros.node.detector.map) - 1)
    loops_before = ros.node.loops
    xyz = np.stack([places[0].cloud[a] for a in "xyz"], axis=1).astype(np.float64)
    replay = first  # the bag starts over: 60 s back, the first place again
    publish(ros, places[0].rgb, "rgb8", driver_cloud(LAYOUTS["velodyne_vlp16"], xyz, np.ones(len(xyz), bool),
                                                     stamp=replay, rclpy_types=True), replay)
    assert ros.node.fixes[TIME_JUMPED] == 1 and TIME_JUMPED in ros.node.warnings.causes
    assert not any("out of order" in k for k in ros.node.drops.snapshot()), ros.node.drops.snapshot()
    assert ros.node.decisions.snapshot().get("out of order", 0) == 0
    assert wait_until(lambda: ros.node.loops > loops_before, 10)
    assert len(ros.node.detector.map) == ids[-1] + 2  # the replayed frame is a keyframe of the new session


def test_100_mb_of_garbage_on_a_camera_topic_is_refused_and_the_node_goes_on(ros: Ros) -> None:
    """An Image whose fields are nonsense and whose data is 100 MB of random bytes."""
    from ros_common import inputs

    rng = np.random.default_rng(0)
    garbage = Image(encoding="\x93\x07garbage", height=0xFFFFFFFF, width=0xFFFFFFFF, step=7,
                    data=rng.integers(0, 256, 100 * 2**20, dtype=np.uint8).tobytes())
    garbage.header.stamp.sec = int(T0 + 200_000)
    size, dropped = len(ros.node.detector.map), ros.node.drops[inputs.IMAGE_ENCODING]
    ros.cameras[0].publish(garbage)
    assert wait_until(lambda: ros.node.drops[inputs.IMAGE_ENCODING] > dropped, 60)
    assert "garbage" in ros.node.warnings.causes or inputs.IMAGE_ENCODING in ros.node.warnings.causes
    place = synthetic_place(4)
    xyz = np.stack([place.cloud[a] for a in "xyz"], axis=1).astype(np.float64)
    stamp = T0 + 200_001.0
    publish(ros, place.rgb, "rgb8", driver_cloud(LAYOUTS["velodyne_vlp16"], xyz, np.ones(len(xyz), bool),
                                                 stamp=stamp, rclpy_types=True), stamp)
    assert len(ros.node.detector.map) == size + 1  # still up, the map kept and growing
