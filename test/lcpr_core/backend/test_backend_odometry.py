"""KISS-ICP odometry (lcpr_core.backend.lidar_odometry): clouds of a known motion in, the base frame's poses out."""
from __future__ import annotations

import math

import numpy as np
import pytest

pytest.importorskip("kiss_icp")

from lcpr_core.backend.lidar_odometry import KissConfig, KissOdometry, run_kiss_icp  # noqa: E402
from lcpr_core.errors import InvalidValueError  # noqa: E402
from trajectory_fixtures import pose  # noqa: E402

# the LiDAR 1 m ahead of and 2 m above the base, turned 90 deg (as the synthetic nuScenes rig's)
BASE_T_LIDAR = pose(1.0, 0.0, 2.0, yaw=-90.0)


def street(seed: int = 0) -> np.ndarray:
    """A static scene: ground, two building rows with irregular facades, and poles (N, 3)."""
    rng = np.random.default_rng(seed)
    parts = [np.c_[rng.uniform(-30, 90, 8000), rng.uniform(-12, 12, 8000), np.zeros(8000)]]
    for side in (-12.0, 12.0):
        x = rng.uniform(-30, 90, 6000)
        depth = side + np.sign(side) * 2.0 * (np.floor(x / 7.0) % 2)  # setbacks every 7 m: x is observable
        parts.append(np.c_[x, depth, rng.uniform(0, 10, 6000)])
    for px in np.arange(-25.0, 90.0, 9.0):
        parts.append(np.c_[px + rng.normal(0, 0.1, 300), 8.0 + rng.normal(0, 0.1, 300), rng.uniform(0, 5, 300)])
    return np.concatenate(parts)


def scans(world: np.ndarray, world_T_lidar: np.ndarray) -> list[np.ndarray]:
    """The scene seen from each LiDAR pose (points within 60 m), in the LiDAR frame."""
    out = []
    for T in world_T_lidar:
        local = (world - T[:3, 3]) @ T[:3, :3]
        out.append(local[np.linalg.norm(local, axis=1) < 60.0])
    return out


def test_kiss_icp_follows_a_drive_and_reports_the_base_frame_from_its_start() -> None:
    truth = np.stack([pose(1.5 * k, 0.2 * math.sin(k / 5.0), yaw=2.0 * math.sin(k / 6.0)) for k in range(20)])
    start = pose(100.0, 50.0, 3.0, yaw=30.0)  # the odometry starts where the vehicle is known to be
    world_T_base = start @ truth
    clouds = scans(_moved(street(), start), world_T_base @ BASE_T_LIDAR)
    poses = run_kiss_icp(clouds, stamps=[10.0 + 0.1 * k for k in range(len(clouds))], base_T_lidar=BASE_T_LIDAR,
                         world_T_base0=world_T_base[0])
    assert poses.shape == (20, 4, 4)
    np.testing.assert_allclose(poses[0], world_T_base[0], atol=1e-9)
    err = np.linalg.norm(poses[:, :3, 3] - world_T_base[:, :3, 3], axis=1)
    assert err.max() < 0.2, err
    yaw_err = np.degrees(np.arccos(np.clip((np.trace(np.swapaxes(poses[:, :3, :3], 1, 2) @ world_T_base[:, :3, :3],
                                                       axis1=1, axis2=2) - 1) / 2, -1, 1)))
    assert yaw_err.max() < 1.0


def _moved(points: np.ndarray, T: np.ndarray) -> np.ndarray:
    return points @ T[:3, :3].T + T[:3, 3]


def test_clouds_out_of_order_or_without_points_are_refused_naming_the_value() -> None:
    odom = KissOdometry(KissConfig(), base_T_lidar=BASE_T_LIDAR)
    cloud = scans(street(), (pose(0.0) @ BASE_T_LIDAR)[None])[0]
    odom.register(cloud, 5.0)
    with pytest.raises(InvalidValueError, match=r"stamp 4\.0 is not after the previous cloud's 5\.0"):
        odom.register(cloud, 4.0)
    with pytest.raises(InvalidValueError, match=r"points of shape \(5,\); expected \(N, >=3\)"):
        odom.register(np.zeros(5), 6.0)
    with pytest.raises(InvalidValueError, match=r"a cloud of 0 finite points at stamp 6\.0"):
        odom.register(np.full((50, 3), np.nan), 6.0)
    with pytest.raises(InvalidValueError, match=r"KissConfig\.min_range=60\.0 is not below max_range=50\.0"):
        KissConfig(min_range=60.0, max_range=50.0)
    assert odom.frames == 1


def test_the_kiss_icp_node_turns_clouds_into_odometry_of_the_base_frame() -> None:
    import random
    import time

    rclpy = pytest.importorskip("rclpy")
    from nav_msgs.msg import Odometry
    from rclpy.context import Context
    from rclpy.parameter import Parameter
    from sensor_msgs.msg import PointCloud2

    from backend_ros.kiss_icp_node import KissIcpNode
    from msg_tools.pointcloud import array_to_pointcloud2, xyz_cloud
    from msg_tools.transforms import odometry_to_pose
    from ros_common.harness import spinning, wait_until
    from ros_common.qos import RELIABLE_INPUT_QOS

    context = Context()
    rclpy.init(context=context, domain_id=random.randint(1, 100))
    topic = f"/k{random.randint(0, 10**6)}/points"
    params = {"lidar_topic": topic, "input_qos": "reliable", "lidar.xyz": [1.0, 0.0, 2.0],
              "lidar.rpy": [0.0, 0.0, -math.pi / 2]}
    node = KissIcpNode(context=context, parameter_overrides=[Parameter(k, value=v) for k, v in params.items()])
    driver = rclpy.create_node("driver", context=context)
    with spinning(context, node, driver):
        got: list[Odometry] = []
        driver.create_subscription(Odometry, "/lcpr_kiss_icp/odometry", got.append, 10)
        pub = driver.create_publisher(PointCloud2, topic, RELIABLE_INPUT_QOS)
        assert wait_until(lambda: pub.get_subscription_count() > 0, 20)
        truth = np.stack([pose(1.5 * k) for k in range(6)])
        for k, cloud in enumerate(scans(street(), truth @ BASE_T_LIDAR)):
            pub.publish(array_to_pointcloud2(xyz_cloud(cloud.astype(np.float32)), frame_id="lidar",
                                             stamp=100.0 + 0.1 * k, msg_type=PointCloud2))
            def registered(count: int = k + 1) -> bool:
                return len(got) == count
            assert wait_until(registered, 30), f"cloud {k} was not registered"
            time.sleep(0.01)
    last = got[-1]
    assert (last.header.frame_id, last.child_frame_id) == ("odom", "base_link")
    assert last.header.stamp.sec == 100 and abs(last.header.stamp.nanosec - 5e8) < 1e3
    np.testing.assert_allclose(odometry_to_pose(last)[:3, 3], truth[-1, :3, 3], atol=0.2)
