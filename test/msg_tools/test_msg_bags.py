"""rosbag2 writing and synchronised reading, on small bags made in tmp_path (sqlite3 and mcap)."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from msg_tools import (
    BagError,
    BagTopicError,
    BagWriter,
    CameraImage,
    CameraModel,
    SensorFrame,
    Topics,
    array_to_pointcloud2,
    bag_summary,
    read_camera_models,
    read_frames,
    xyz_cloud,
)
from msg_tools.compressed import encode_image
from msg_tools.geometry import pose_from_parts

TOPICS = Topics(
    cameras=("/front/image/compressed", "/left/image"),
    camera_info=("/front/camera_info", "/left/camera_info"),
    depth=("/front/depth", "/left/depth"),
    labels=("/front/labels", "/left/labels"),
    lidar="/points",
)
K = np.array([[40.0, 0.0, 16.0], [0.0, 40.0, 12.0], [0.0, 0.0, 1.0]])


def _models() -> list[CameraModel]:
    left = pose_from_parts([0.5, 0.3, 1.6], [0.5, -0.5, 0.5, -0.5])
    return [CameraModel("front", "front_optical", 32, 24, K, pose_from_parts([1.0, 0, 1.5], [-0.5, 0.5, -0.5, 0.5])),
            CameraModel("left", "left_optical", 32, 24, K, left)]


def _frames(count: int = 3) -> list[SensorFrame]:
    rng = np.random.default_rng(7)
    frames = []
    for i in range(count):
        t = 1_700_000_000.0 + 0.1 * i
        front = CameraImage(t + 0.004, "front_optical",
                            jpeg=encode_image(rng.integers(0, 255, (24, 32, 3), dtype=np.uint8), format="jpeg"))
        labels = rng.integers(0, 70_000 if i == 1 else 260, (24, 32)).astype(np.uint32)  # frame 1 needs 32 bits
        left = CameraImage(t - 0.006, "left_optical", rgb=rng.integers(0, 255, (24, 32, 3), dtype=np.uint8),
                           depth=rng.random((24, 32), dtype=np.float32) * 50, labels=labels)
        cloud = xyz_cloud(rng.normal(size=(50, 3)) * 10, intensity=rng.random(50).astype(np.float32),
                          ring=rng.integers(0, 32, 50).astype(np.uint16))
        pose = pose_from_parts([2.0 * i, 0.5 * i, 0.0], [0.0, 0.0, np.sin(0.1 * i), np.cos(0.1 * i)])
        frames.append(SensorFrame(t, [front, left], cloud, "velodyne", pose))
    return frames


def _write(path: Path, frames: list[SensorFrame], storage: str = "sqlite3") -> None:
    with BagWriter(path, storage=storage) as writer:  # type: ignore[arg-type]
        writer.write_static_transforms(_models(), "velodyne", pose_from_parts([0, 0, 1.8], [0, 0, 0, 1]))
        for frame in frames:
            writer.write_frame(frame, topics=TOPICS, cameras=_models())


@pytest.mark.parametrize("storage", ["sqlite3", "mcap"])
def test_three_written_frames_read_back_equal(tmp_path: Path, storage: str) -> None:
    frames = _frames()
    bag = tmp_path / "run"
    _write(bag, frames, storage)
    stream = read_frames(bag, topics=TOPICS)
    assert len(stream) == 3 and stream.stats.dropped_clouds == 0 and stream.stats.camera_missing == [0, 0]
    back = list(stream)
    assert len(back) == 3
    for sent, got in zip(frames, back, strict=True):
        assert got.stamp == sent.stamp and got.lidar_frame_id == "velodyne"
        assert got.cloud.dtype == sent.cloud.dtype and np.array_equal(got.cloud, sent.cloud)
        assert got.pose is not None and sent.pose is not None
        assert np.allclose(got.pose, sent.pose, atol=1e-12)
        front, left = got.cameras
        assert front is not None and left is not None and sent.cameras[0] is not None and sent.cameras[1] is not None
        assert left.rgb is not None and left.depth is not None and left.labels is not None
        assert sent.cameras[1].rgb is not None and sent.cameras[1].depth is not None
        assert sent.cameras[1].labels is not None
        assert front.jpeg == sent.cameras[0].jpeg and front.stamp == sent.cameras[0].stamp
        assert front.frame_id == "front_optical"
        assert np.array_equal(left.rgb, sent.cameras[1].rgb)
        assert np.array_equal(left.depth, sent.cameras[1].depth)
        assert np.array_equal(left.labels, sent.cameras[1].labels)
    assert back[0].cameras[1] is not None and back[1].cameras[1] is not None
    assert back[0].cameras[1].labels is not None and back[1].cameras[1].labels is not None
    assert back[1].cameras[1].labels.dtype == np.uint32 and back[0].cameras[1].labels.dtype == np.uint16

    models = read_camera_models(bag, topics=TOPICS)
    for want, model in zip(_models(), models, strict=True):
        assert model is not None and model.frame_id == want.frame_id and np.array_equal(model.K, want.K)
        assert np.allclose(model.base_T_cam, want.base_T_cam, atol=1e-12)


def test_a_bag_summary_counts_every_topic(tmp_path: Path) -> None:
    _write(tmp_path / "bag", _frames(), "mcap")
    summary = bag_summary(tmp_path / "bag")
    counts = {t.name: (t.msgtype, t.count) for t in summary.topics}
    assert counts["/points"] == ("sensor_msgs/msg/PointCloud2", 3)
    assert counts["/front/image/compressed"] == ("sensor_msgs/msg/CompressedImage", 3)
    assert counts["/tf_static"] == ("tf2_msgs/msg/TFMessage", 1)
    assert summary.storage == "mcap" and summary.message_count == sum(c for _t, c in counts.values())
    assert summary.duration == pytest.approx(0.2 + 0.004 + 0.006, abs=1e-6)
    assert "/odom" in summary.format()


def test_images_outside_the_slop_are_counted_not_used(tmp_path: Path) -> None:
    topics = Topics(cameras=("/a/image", "/b/image"), lidar="/points")
    cloud = xyz_cloud(np.zeros((2, 3)))
    pixels = np.zeros((2, 2, 3), np.uint8)
    with BagWriter(tmp_path / "bag") as w:
        for t in (10.0, 11.0, 12.0, 13.0):
            w.write_cloud("/points", cloud, frame_id="l", stamp=t)
        w.write_cloud("/points", cloud, frame_id="l", stamp=13.0)  # duplicate stamp
        late = array_to_pointcloud2(cloud, frame_id="l", stamp=12.5)
        w.write("/points", late, stamp=13.1)  # logged after 13.0 with an earlier header stamp: out of order
        w.write_image("/a/image", pixels, encoding="rgb8", frame_id="a", stamp=10.03)
        w.write_image("/b/image", pixels, encoding="rgb8", frame_id="b", stamp=10.2)  # beyond slop
        w.write_image("/a/image", pixels, encoding="rgb8", frame_id="a", stamp=11.0)
        w.write_image("/b/image", pixels, encoding="rgb8", frame_id="b", stamp=10.98)
        w.write_image("/b/image", pixels, encoding="rgb8", frame_id="b", stamp=10.98)  # duplicate image
        w.write_image("/a/image", pixels, encoding="rgb8", frame_id="a", stamp=13.05)  # just outside 0.04
    stream = read_frames(tmp_path / "bag", topics=topics, slop=0.04)
    stats = stream.stats
    assert stats.clouds == 6 and stats.duplicate_clouds == 1 and stats.out_of_order_clouds == 1
    assert stats.no_camera == 2  # 12.0 and 13.0 have no image within 0.04 s
    assert stats.camera_missing == [0, 1] and stats.duplicate_images == [0, 1]
    assert not stats.odometry_topic and stats.no_pose == 2
    frames = list(stream)
    assert [f.stamp for f in frames] == [10.0, 11.0]
    assert frames[0].cameras[0] is not None and frames[1].cameras[1] is not None
    assert frames[0].cameras[1] is None and frames[0].cameras[0].stamp == 10.03
    assert frames[1].cameras[1].stamp == 10.98
    assert len(list(read_frames(tmp_path / "bag", topics=topics, slop=0.06, min_cameras=2))) == 1


def test_odometry_is_interpolated_to_the_cloud_stamp(tmp_path: Path) -> None:
    topics = Topics(cameras=(), lidar="/points")
    a = pose_from_parts([0, 0, 0], [0, 0, 0, 1])
    b = pose_from_parts([4, 2, 0], [0, 0, np.sin(np.pi / 4), np.cos(np.pi / 4)])
    with BagWriter(tmp_path / "bag") as w:
        w.write_odometry("/odom", a, stamp=100.0)
        w.write_cloud("/points", xyz_cloud(np.zeros((1, 3))), frame_id="l", stamp=100.25)
        w.write_odometry("/odom", b, stamp=101.0)
        w.write_cloud("/points", xyz_cloud(np.zeros((1, 3))), frame_id="l", stamp=101.03)
        w.write_cloud("/points", xyz_cloud(np.zeros((1, 3))), frame_id="l", stamp=105.0)
    stream = read_frames(tmp_path / "bag", topics=topics, slop=0.05)
    frames = list(stream)
    assert frames[0].pose is not None and frames[1].pose is not None
    assert np.allclose(frames[0].pose[:3, 3], [1.0, 0.5, 0.0])
    yaw = np.arctan2(frames[0].pose[1, 0], frames[0].pose[0, 0])
    assert yaw == pytest.approx(np.pi / 8)
    assert np.allclose(frames[1].pose, b)  # nearest within the slop after the last odometry
    assert frames[2].pose is None and stream.stats.no_pose == 1


def test_a_failed_write_leaves_no_bag_and_existing_bags_are_kept(tmp_path: Path) -> None:
    bag = tmp_path / "bag"
    with pytest.raises(RuntimeError):
        with BagWriter(bag) as w:
            w.write_cloud("/points", xyz_cloud(np.zeros((1, 3))), frame_id="l", stamp=1.0)
            raise RuntimeError("interrupted")
    assert not bag.exists() and list(tmp_path.iterdir()) == []
    _write(bag, _frames(1))
    with pytest.raises(BagError, match="exists already"):
        BagWriter(bag).open()
    _write_over = BagWriter(bag, overwrite=True)
    with _write_over as w:
        w.write_cloud("/points", xyz_cloud(np.zeros((1, 3))), frame_id="l", stamp=1.0)
    assert bag_summary(bag).message_count == 1 and sorted(p.name for p in tmp_path.iterdir()) == ["bag"]


def test_topics_missing_or_of_the_wrong_type_are_named(tmp_path: Path) -> None:
    _write(tmp_path / "bag", _frames(1))
    with pytest.raises(BagTopicError, match="topic /nope is not in the bag"):
        read_frames(tmp_path / "bag", topics=Topics(cameras=(), lidar="/nope"))
    with pytest.raises(BagTopicError, match="/odom carries nav_msgs/msg/Odometry; accepted: sensor_msgs/msg/Image"):
        read_frames(tmp_path / "bag", topics=Topics(cameras=("/odom",), lidar="/points"))
    with BagWriter(tmp_path / "other") as w:
        w.write_cloud("/points", xyz_cloud(np.zeros((1, 3))), frame_id="l", stamp=1.0)
        with pytest.raises(BagTopicError, match="already carries sensor_msgs/msg/PointCloud2"):
            w.write_image("/points", np.zeros((1, 1), np.uint8), encoding="mono8", frame_id="c", stamp=1.0)


def test_an_organised_cloud_is_flattened_with_its_shape_kept(tmp_path: Path) -> None:
    cloud = np.zeros((2, 3), dtype=[("x", "f4"), ("y", "f4"), ("z", "f4")])
    cloud["x"] = np.arange(6).reshape(2, 3)
    with BagWriter(tmp_path / "bag") as w:
        w.write_cloud("/points", cloud, frame_id="l", stamp=1.0)
    (frame,) = read_frames(tmp_path / "bag", topics=Topics(cameras=(), lidar="/points"))
    assert frame.cloud.shape == (6,) and frame.extras["cloud_shape"] == (2, 3)
    assert frame.xyz[:, 0].tolist() == [0, 1, 2, 3, 4, 5]


def test_frames_stream_out_before_the_bag_is_read_to_the_end(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from msg_tools.types import typestore

    frames = _frames(40)
    _write(tmp_path / "bag", frames)
    store = typestore()
    decoded: list[str] = []
    original = store.deserialize_cdr

    def counting(raw: bytes, msgtype: str) -> object:
        decoded.append(msgtype)
        return original(raw, msgtype)

    monkeypatch.setattr(store, "deserialize_cdr", counting)
    with read_frames(tmp_path / "bag", topics=TOPICS) as stream:
        indexed = len(decoded)  # the first pass deserialises odometry only
        assert set(decoded) == {"nav_msgs/msg/Odometry"} and indexed == 40
        first = next(stream)
        assert first.stamp == frames[0].stamp
        assert len(decoded) - indexed <= 12  # the first frame's parts and little more
    assert len(decoded) - indexed <= 12  # closing stopped reading
