"""The lcpr node in this process (rclpy executor in a thread), driven over real DDS on loopback.

Every test gets a node of its own (fresh map, counters and topics, its own DDS domain) and
builds the history it needs with :func:`visit_places`: each passes alone and in any order.
"""
from __future__ import annotations

import random
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import rclpy
from nav_msgs.msg import Odometry
from rcl_interfaces.msg import Parameter as ParameterMsg
from rcl_interfaces.msg import ParameterType, ParameterValue
from rcl_interfaces.srv import SetParameters
from rclpy.client import Client
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from std_srvs.srv import Trigger
from visualization_msgs.msg import Marker, MarkerArray

from lcpr_core.descriptor_map import DescriptorMap
from lcpr_ros.node import CANDIDATE_QOS, LcprNode
from ros_common import inputs
from ros_common.errors import ConfigError, MapLoadError
from ros_common.harness import (
    FramePublisher,
    OutputListener,
    Place,
    cloud_with_nan,
    cloud_without_xyz,
    compressed_from_raw,
    image_of_wrong_size,
    image_with_unknown_encoding,
    pose_at_x,
    spinning,
    synthetic_place,
    truncated_cloud,
    wait_until,
)

T0 = 1_700_000_000.0  # epoch-like header stamps
WAIT = 60.0  # s: generous bound for one frame on a loaded 2-core machine


@dataclass(frozen=True)
class Topics:
    prefix: str

    @property
    def cameras(self) -> list[str]:
        return [f"{self.prefix}/CAM_{k}/image/compressed" for k in range(6)]

    @property
    def lidar(self) -> str:
        return f"{self.prefix}/LIDAR_TOP/points"

    @property
    def odom(self) -> str:
        return f"{self.prefix}/odom"


def small_model(topics: Topics, **extra: object) -> list[Parameter]:
    """A tiny model (32 x 96 images, 8 x 256 range image, quarter width): well under a second per frame."""
    values: dict[str, object] = {
        "model.image_size": [32, 96], "model.lidar": "velodyne_vlp16", "model.range_size": [8, 256],
        "model.width": 0.25, "model.weights": "seeded",
        "camera_topics": topics.cameras, "lidar_topic": topics.lidar, "odom_topic": topics.odom,
        "diagnostics.period": 0.2, "sync.camera_timeout": 5.0, **extra,
    }
    return [Parameter(name, value=value) for name, value in values.items()]


@dataclass
class Ros:
    topics: Topics
    context: Context
    node: LcprNode
    driver: Node
    pub: FramePublisher
    listener: OutputListener
    markers: list[MarkerArray]
    map_path: Path
    places: list[Place]
    ids: dict[int, int]  # place number -> keyframe id of its first visit
    executor: SingleThreadedExecutor

    def processed(self) -> int:
        return sum(self.node.decisions.snapshot().values())

    def feed(self, place: Place, stamp: float, *, x: float | None = None, skip: tuple[int, ...] = ()) -> None:
        """Publish one frame and wait until the detector has decided on it."""
        before = self.processed()
        self.pub.publish(place, stamp, pose=None if x is None else pose_at_x(x), skip_cameras=skip)
        assert wait_until(lambda: self.processed() > before), f"frame {stamp} was not processed"


@pytest.fixture()
def ros(tmp_path: Path) -> Iterator[Ros]:
    topics = Topics(f"/t{random.randint(0, 10**6)}")
    context = Context()
    rclpy.init(context=context, domain_id=random.randint(1, 100))
    map_path = tmp_path / "lcpr_map.npz"
    node = LcprNode(context=context, parameter_overrides=small_model(topics, **{"map.path": str(map_path)}))
    driver = rclpy.create_node("driver", context=context)
    with spinning(context, node, driver) as executor:
        markers: list[MarkerArray] = []
        driver.create_subscription(MarkerArray, "/lcpr/markers", markers.append, CANDIDATE_QOS)
        pub = FramePublisher(driver, topics.cameras, topics.lidar, odom_topic=topics.odom)
        listener = OutputListener(driver)
        pub.wait_for_subscribers()
        listener.wait_for_publishers()
        yield Ros(topics, context, node, driver, pub, listener, markers, map_path,
                  [synthetic_place(i) for i in range(3)], {}, executor)


def visit_places(ros: Ros) -> None:
    """First visits of places 0, 1, 2 at T0, T0 + 1 and T0 + 2 (x = 0, 10, 20 m); ``ros.ids`` their keyframes."""
    for i, place in enumerate(ros.places):
        ros.feed(place, T0 + i, x=10.0 * i)
        ros.ids[i] = len(ros.node.detector.map) - 1


def test_an_exact_revisit_more_than_30_s_later_is_matched_to_the_right_frame(ros: Ros) -> None:
    visit_places(ros)
    assert ros.listener.out.loops == []  # everything is within 30 s: excluded
    assert ros.node.verify_time.count == 0  # no candidates: no verification time counted
    ros.feed(ros.places[1], T0 + 40.0, x=10.5)
    assert ros.listener.wait(lambda o: o.loops and o.candidates, 10)
    assert wait_until(lambda: ros.node.verify_time.count == 1, 5)
    assert ros.listener.out.loops == [(pytest.approx(T0 + 40.0), pytest.approx(T0 + 1.0))]
    rows = ros.listener.out.candidates[-1]
    assert rows[0]["match_id"] == ros.ids[1] and rows[0]["rank"] == 0
    assert rows[0]["distance"] == pytest.approx(0.0, abs=1e-4)
    assert rows[0]["query_stamp"] == pytest.approx(T0 + 40.0) and rows[0]["match_stamp"] == pytest.approx(T0 + 1.0)
    assert rows[0]["query_id"] == len(ros.node.detector.map) - 1 and rows[0]["degraded"] == 0
    assert [r["rank"] for r in rows] == list(range(len(rows)))
    assert all(a["distance"] <= b["distance"] for a, b in zip(rows, rows[1:], strict=False))


def test_markers_join_the_query_and_the_matched_position_coloured_by_distance(ros: Ros) -> None:
    visit_places(ros)
    ros.feed(ros.places[1], T0 + 40.0, x=10.5)
    assert wait_until(lambda: bool(ros.markers), 10), ros.node.detector.map.poses
    (marker,) = ros.markers[-1].markers
    assert marker.type == Marker.LINE_LIST and marker.header.frame_id == "map"
    start, end = marker.points[0], marker.points[1]
    assert (start.x, end.x) == (pytest.approx(10.5), pytest.approx(10.0))
    assert marker.colors[0].g == pytest.approx(1.0, abs=1e-3)  # distance ~0 -> green
    assert marker.header.stamp.sec == int(T0 + 40)


def test_bad_input_is_dropped_counted_and_warned_once_per_cause_and_the_map_is_kept(ros: Ros) -> None:
    visit_places(ros)
    node, pub, place = ros.node, ros.pub, ros.places[2]
    size_before = len(node.detector.map)
    logged_before = node.warnings.logged
    t = T0 + 50.0
    assert pub.odom is not None
    for repeat in range(2):  # every cause twice: still one warning each
        t += 1.0
        pub.lidar.publish(cloud_without_xyz(t))
        pub.lidar.publish(truncated_cloud(place, t + 0.1))
        pub.cameras[0].publish(image_with_unknown_encoding(t, compressed=True))
        pub.cameras[1].publish(image_of_wrong_size(t, compressed=True))
        bad_pose = Odometry()
        bad_pose.header.stamp.sec = int(t)
        bad_pose.pose.pose.orientation.w = 0.0  # a zero quaternion
        pub.odom.publish(bad_pose)
        # sensor-data QoS keeps the last 5 messages per topic: the next round waits until this one is counted
        dropped_causes = (inputs.CLOUD_NO_XYZ, inputs.CLOUD_TRUNCATED, inputs.IMAGE_ENCODING, inputs.IMAGE_SIZE,
                          inputs.ODOM_BAD)

        def counted(repeat: int = repeat, causes: tuple[str, ...] = dropped_causes) -> bool:
            return all(node.drops[k] >= repeat + 1 for k in causes)
        assert wait_until(counted, 10), node.drops.snapshot()
    expected = {cause: 2 for cause in dropped_causes}
    assert wait_until(lambda: all(node.drops[k] >= n for k, n in expected.items()), 10), node.drops.snapshot()

    # a good frame, then the same stamp again (duplicate) and an older one (out of order), camera and cloud
    t += 1.0
    ros.feed(place, t, x=20.0)
    pub.publish(place, t)
    pub.publish(place, t - 0.5)
    assert wait_until(lambda: node.drops["cloud: duplicate stamp"] == 1 and node.drops["cloud: out of order"] == 1
                      and node.drops["image: duplicate stamp"] == 6 and node.drops["image: out of order"] == 6, 10)

    # NaN points are removed and the cloud used; a JPEG that does not decode leaves its camera empty
    t += 1.0
    pub.cameras[0].publish(compressed_from_raw(b"\xff\xd8\xff" + bytes(100), t))
    ros.feed(place, t, x=20.0, skip=(0,))
    t += 1.0
    before = ros.processed()
    for k, cam in enumerate(pub.cameras):
        cam.publish(pub.image_msg(place, k, t))
    pub.lidar.publish(cloud_with_nan(place, t, count=100))
    assert wait_until(lambda: ros.processed() > before)
    assert node.drops[inputs.IMAGE_DECODE] == 1
    assert node.fixes[inputs.CLOUD_NAN] == 100

    causes = set(node.warnings.causes)
    assert set(expected) | {inputs.IMAGE_DECODE, inputs.CLOUD_NAN, "cloud: duplicate stamp",
                            "image: out of order"} <= causes
    assert node.warnings.logged == len(causes)  # never twice for one cause
    assert node.warnings.logged > logged_before and node.warnings.suppressed > 0

    # the node is still up and its map holds every good keyframe, none of the bad input
    assert len(node.detector.map) == size_before + 3
    health = node.health()
    assert health.drops[inputs.CLOUD_TRUNCATED] == 2 and health.fixes[inputs.CLOUD_NAN] == 100
    assert wait_until(lambda: ros.listener.latest_values("inputs").get(f"dropped {inputs.CLOUD_NO_XYZ}") == "2", 5)
    values = ros.listener.latest_values("inputs")
    assert values[f"dropped {inputs.IMAGE_ENCODING}"] == "2" and inputs.CLOUD_TRUNCATED in values["warnings"]
    ros.feed(ros.places[0], t + 1.0, x=0.0)
    assert ros.listener.wait(lambda o: o.loops and o.loops[-1][0] == pytest.approx(t + 1.0), 10)
    assert ros.listener.out.loops[-1][1] == pytest.approx(T0)  # still matched to place 0's first visit


def test_a_camera_that_stops_degrades_frames_instead_of_stopping_them(ros: Ros) -> None:
    visit_places(ros)
    t = T0 + 70.0
    ros.feed(ros.places[0], t, x=0.0)
    ros.feed(ros.places[0], t + 3.0, x=0.0, skip=(3,))  # camera 3 late: the frame waits max_wait, then goes
    ros.feed(ros.places[0], t + 6.0, x=0.0, skip=(3,))  # silent > sync.camera_timeout: stopped
    assert ros.node.sync.stopped_cameras() == (3,)
    assert f"camera stopped: {ros.topics.cameras[3]}" in ros.node.warnings.causes
    assert ros.listener.wait(
        lambda o: o.candidates and o.candidates[-1][0]["query_stamp"] == pytest.approx(t + 6.0), 10)
    assert ros.listener.out.candidates[-1][0]["degraded"] == 1
    assert wait_until(lambda: ros.listener.latest_values("inputs").get("stopped cameras") == ros.topics.cameras[3], 5)


def call(node: Node, client: Client, request: Any, timeout: float = 20.0) -> Any:
    assert client.wait_for_service(timeout_sec=timeout)
    future = client.call_async(request)
    assert wait_until(future.done, timeout)
    return future.result()


def test_the_save_map_service_saves_every_keyframe_and_answers_with_count_and_path(ros: Ros) -> None:
    visit_places(ros)
    client: Client = ros.driver.create_client(Trigger, "/lcpr/save_map")
    response = call(ros.driver, client, Trigger.Request())
    count = len(ros.node.detector.map)
    assert response.success and response.message == f"saved {count} places to {ros.map_path}"
    saved = DescriptorMap.load(ros.map_path)
    assert len(saved) == count and saved.ids.tolist() == ros.node.detector.map.ids.tolist()


def test_parameters_set_at_run_time_are_validated_over_the_parameter_service(ros: Ros) -> None:
    visit_places(ros)
    client: Client = ros.driver.create_client(SetParameters, "/lcpr/set_parameters")

    def set_one(name: str, value: ParameterValue) -> Any:
        request = SetParameters.Request(parameters=[ParameterMsg(name=name, value=value)])
        return call(ros.driver, client, request).results[0]

    def integer(v: int) -> ParameterValue:
        return ParameterValue(type=ParameterType.PARAMETER_INTEGER, integer_value=v)

    refused = set_one("match.top_k", integer(0))
    assert not refused.successful and "out of range" in refused.reason
    refused = set_one("sync.min_cameras", integer(9))
    assert not refused.successful and "sync.min_cameras=9" in refused.reason
    refused = set_one("model.weights", ParameterValue(type=ParameterType.PARAMETER_STRING, string_value="x.pth"))
    assert not refused.successful and "read-only" in refused.reason
    accepted = set_one("match.top_k", integer(1))
    assert accepted.successful
    ros.feed(ros.places[2], T0 + 90.0, x=20.0)
    assert ros.listener.wait(lambda o: o.candidates[-1][0]["query_stamp"] == pytest.approx(T0 + 90.0), 10)
    (best,) = ros.listener.out.candidates[-1]  # top_k = 1 applied to the next frame
    assert best["distance"] == pytest.approx(0.0, abs=1e-4)  # place 2 was seen at T0 + 2
    assert best["match_stamp"] == pytest.approx(T0 + 2.0)


def test_a_second_session_loads_the_saved_map_keeps_its_ids_and_adds_new_places(ros: Ros) -> None:
    visit_places(ros)
    ros.feed(ros.places[1], T0 + 40.0, x=10.5)
    ros.node.save_map()
    saved = DescriptorMap.load(ros.map_path)
    lidar = f"{ros.topics.prefix}/second/points"
    second = LcprNode(context=ros.context, namespace="/second",
                      parameter_overrides=small_model(ros.topics, **{"map.path": str(ros.map_path),
                                                                     "session": "second", "lidar_topic": lidar}))
    ros.executor.add_node(second)
    try:
        assert len(second.detector.map) == len(saved)
        assert second.detector.map.ids.tolist() == saved.ids.tolist()
        assert second.detector.map.sources == saved.sources
        pub = FramePublisher(ros.driver, ros.topics.cameras, lidar, odom_topic=ros.topics.odom)
        listener = OutputListener(ros.driver, "/second/lcpr")
        pub.wait_for_subscribers()
        listener.wait_for_publishers()
        pub.publish(ros.places[1], T0 + 200.0, pose=pose_at_x(10.0))
        assert listener.wait(lambda o: bool(o.candidates), WAIT)
        (row, *_) = listener.out.candidates[-1]
        assert row["query_id"] == int(saved.ids.max()) + 1  # new places continue the ids
        assert row["distance"] == pytest.approx(0.0, abs=1e-4)  # place 1, seen in the first session
        assert row["match_stamp"] in (pytest.approx(T0 + 1.0), pytest.approx(T0 + 40.0))
        assert second.detector.map.sources[-1] == "second"
    finally:
        ros.executor.remove_node(second)
        second.close()
        second.destroy_node()


def test_invalid_parameters_or_an_unusable_map_file_refuse_to_build_the_node(ros: Ros, tmp_path: Path) -> None:
    visit_places(ros)
    ros.node.save_map()
    with pytest.raises(ConfigError, match="match.top_k"):
        LcprNode(context=ros.context, namespace="/bad1",
                 parameter_overrides=small_model(ros.topics, **{"match.top_k": 0}))
    with pytest.raises(ConfigError, match="image_size"):
        LcprNode(context=ros.context, namespace="/bad2",
                 parameter_overrides=small_model(ros.topics, **{"model.image_size": [30, 90]}))
    corrupt = tmp_path / "corrupt.npz"
    corrupt.write_bytes(b"PK\x03\x04 definitely not a map")
    with pytest.raises(MapLoadError, match="refusing to start"):
        LcprNode(context=ros.context, namespace="/bad3",
                 parameter_overrides=small_model(ros.topics, **{"map.path": str(corrupt)}))
    assert corrupt.read_bytes() == b"PK\x03\x04 definitely not a map"
    other = tmp_path / "other.npz"
    DescriptorMap.load(ros.map_path).save(other)
    with pytest.raises(MapLoadError, match="512-d"):
        LcprNode(context=ros.context, namespace="/bad4",
                 parameter_overrides=small_model(ros.topics, **{"map.path": str(other), "map.dim": 512}))
    assert np.array_equal(DescriptorMap.load(other).ids, DescriptorMap.load(ros.map_path).ids)


def test_a_verified_loop_carries_its_relative_pose_and_covariance_on_candidates(ros: Ros) -> None:
    ros.feed(ros.places[2], T0 + 10_000.0, x=500.0)
    ros.feed(ros.places[2], T0 + 10_040.0, x=500.2)
    assert ros.listener.wait(lambda o: o.loops and o.loops[-1][0] == pytest.approx(T0 + 10_040.0), 10)
    rows = [r for r in ros.listener.out.candidates[-1] if r["match_stamp"] == ros.listener.out.loops[-1][1]]
    assert rows and rows[0]["verified"] == 1.0 and 0.5 < rows[0]["fitness"] <= 1.0
    assert abs(rows[0]["tx"]) < 0.05 and abs(rows[0]["ty"]) < 0.05 and rows[0]["qw"] == pytest.approx(1.0, abs=1e-3)
    cov = np.array([rows[0][f"cov_{i}"] for i in range(36)]).reshape(6, 6)
    assert np.allclose(cov, cov.T) and (np.linalg.eigvalsh(cov) > 0).all()
    assert wait_until(lambda: int(ros.listener.latest_values("detector").get("candidates verified", 0)) >= 1, 10)
    assert ros.listener.latest_values("detector")["inference path"] in ("fp32", "bf16", "onnx")  # what auto chose


def test_a_lidar_only_node_subscribes_no_camera_and_closes_loops_from_clouds_alone(tmp_path: Path) -> None:
    topics = Topics(f"/t{random.randint(0, 10**6)}")
    context = Context()
    rclpy.init(context=context, domain_id=random.randint(1, 100))
    node = LcprNode(context=context, parameter_overrides=small_model(topics, lidar_only=True))
    driver = rclpy.create_node("driver", context=context)
    try:
        with spinning(context, node, driver):
            pub = FramePublisher(driver, topics.cameras, topics.lidar)
            listener = OutputListener(driver)
            assert wait_until(lambda: pub.lidar.get_subscription_count() == 1, 20)
            assert all(cam.get_subscription_count() == 0 for cam in pub.cameras)
            listener.wait_for_publishers()
            places = [synthetic_place(i) for i in range(2)]
            everything = tuple(range(6))

            def decided() -> int:
                return sum(node.decisions.snapshot().values())

            for n, (stamp, place) in enumerate(((T0, places[0]), (T0 + 1.0, places[1]), (T0 + 40.0, places[0]))):
                pub.publish(place, stamp, skip_cameras=everything)

                def done(before: int = n) -> bool:
                    return decided() > before
                assert wait_until(done, WAIT), f"frame {stamp} was not processed"
            assert listener.wait(lambda o: bool(o.loops), 10)
            assert listener.out.loops == [(pytest.approx(T0 + 40.0), pytest.approx(T0))]
            assert listener.out.candidates[-1][0]["degraded"] == 1  # every camera slot was empty
    finally:
        node.close()
        node.destroy_node()
        driver.destroy_node()
        rclpy.try_shutdown(context=context)
