"""KITTI odometry -> rosbag2 on a 4-scan sequence built in tmp_path from the real KITTI-00 scans."""
from __future__ import annotations

import shutil
from decimal import Decimal
from pathlib import Path
from typing import TypedDict

import numpy as np
import pytest
from PIL import Image as PILImage

from msg_tools import KITTI_TOPICS, DatasetError, read_camera_models, read_frames
from msg_tools.convert.baginfo import main as baginfo_main
from msg_tools.convert.kitti import convert_kitti, main
from msg_tools.geometry import invert_pose

SCANS = ("000000", "000001", "000005", "000015")  # renamed 000000..000003 in the fixture
# calib.txt of KITTI odometry sequence 00 (P0, P1, P2 and Tr as published in the odometry devkit data).
CALIB_00 = """\
P0: 7.188560000000e+02 0.000000000000e+00 6.071928000000e+02 0.000000000000e+00 0.000000000000e+00 7.188560000000e+02 1.852157000000e+02 0.000000000000e+00 0.000000000000e+00 0.000000000000e+00 1.000000000000e+00 0.000000000000e+00
P1: 7.188560000000e+02 0.000000000000e+00 6.071928000000e+02 -3.861448000000e+02 0.000000000000e+00 7.188560000000e+02 1.852157000000e+02 0.000000000000e+00 0.000000000000e+00 0.000000000000e+00 1.000000000000e+00 0.000000000000e+00
P2: 7.188560000000e+02 0.000000000000e+00 6.071928000000e+02 4.538225000000e+01 0.000000000000e+00 7.188560000000e+02 1.852157000000e+02 -1.130887000000e-01 0.000000000000e+00 0.000000000000e+00 1.000000000000e+00 3.779761000000e-03
Tr: 4.276802385584e-04 -9.999672484946e-01 -8.084491683471e-03 -1.198459927713e-02 -7.210626507497e-03 8.081198471645e-03 -9.999413164504e-01 -5.403984729748e-02 9.999738645903e-01 4.859485810390e-04 -7.206933692422e-03 -2.921968648686e-01
"""  # noqa: E501 - the file's lines verbatim
WIDTH, HEIGHT = 1241, 376


def _tr() -> np.ndarray:
    values = [float(v) for v in CALIB_00.splitlines()[3].split()[1:]]
    return np.vstack([np.reshape(values, (3, 4)), [0, 0, 0, 1]])


class Expected(TypedDict):
    """What a converted sequence must hold, per scan."""

    images: list[np.ndarray]
    labels: list[np.ndarray]
    poses: np.ndarray
    times_ns: list[int]


def build_sequence(root: Path, kitti00: Path, *, labels: bool) -> Expected:
    (root / "velodyne").mkdir(parents=True)
    (root / "image_2").mkdir()
    pose_lines = (kitti00 / "poses.txt").read_text().splitlines()
    time_lines = (kitti00 / "times.txt").read_text().splitlines()
    rng = np.random.default_rng(0)
    images, label_arrays = [], []
    for new, old in enumerate(SCANS):
        stem = f"{new:06d}"
        shutil.copyfile(kitti00 / f"{old}.bin", root / "velodyne" / f"{stem}.bin")
        yy, xx = np.mgrid[0:HEIGHT, 0:WIDTH]
        rgb = np.stack([(xx + 40 * new) % 256, yy % 256, np.full_like(xx, 60 * new)], axis=2).astype(np.uint8)
        PILImage.fromarray(rgb).save(root / "image_2" / f"{stem}.png")
        images.append(rgb)
        if labels:
            (root / "labels").mkdir(exist_ok=True)
            count = (kitti00 / f"{old}.bin").stat().st_size // 16
            semantic = rng.choice([10, 40, 50, 70, 252], size=count).astype(np.uint32)
            instance = rng.integers(0, 3, size=count).astype(np.uint32)
            label = semantic | (instance << 16)
            label.astype("<u4").tofile(root / "labels" / f"{stem}.label")
            label_arrays.append(label)
    chosen = [int(s) for s in SCANS]
    (root / "poses.txt").write_text("\n".join(pose_lines[i] for i in chosen) + "\n")
    (root / "times.txt").write_text("\n".join(time_lines[i] for i in chosen) + "\n")
    (root / "calib.txt").write_text(CALIB_00)
    poses = np.tile(np.eye(4), (4, 1, 1))
    poses[:, :3, :] = np.array([[float(v) for v in pose_lines[i].split()] for i in chosen]).reshape(4, 3, 4)
    times_ns = [int(Decimal(time_lines[i].strip()) * 10**9) for i in chosen]
    return {"images": images, "labels": label_arrays, "poses": poses, "times_ns": times_ns}


@pytest.fixture
def kitti00(shared: Path) -> Path:
    folder = shared / "data" / "kitti00"
    if not folder.is_dir():
        pytest.skip(f"{folder} not found")
    return folder


def test_a_converted_sequence_reads_back_scans_images_labels_and_velodyne_poses(kitti00: Path, tmp_path: Path) -> None:
    seq = tmp_path / "00"
    expected = build_sequence(seq, kitti00, labels=True)
    report = convert_kitti(seq, tmp_path / "bag", start_time=1_317_000_000.0)
    assert report.scans == 4 and report.with_pose and report.with_labels

    stream = read_frames(tmp_path / "bag", topics=KITTI_TOPICS, slop=0.01)
    frames = list(stream)
    assert len(frames) == 4 and stream.stats.dropped_clouds == 0 and stream.stats.no_pose == 0
    Tr = _tr()
    for i, (frame, old) in enumerate(zip(frames, SCANS, strict=True)):
        assert frame.extras["stamp_ns"] == 1_317_000_000 * 10**9 + expected["times_ns"][i]
        points = np.fromfile(kitti00 / f"{old}.bin", dtype=np.float32).reshape(-1, 4)
        assert frame.lidar_frame_id == "velodyne"
        assert frame.cloud.dtype.names == ("x", "y", "z", "intensity", "label")
        assert np.array_equal(frame.xyz, points[:, :3].astype(np.float64))
        assert np.array_equal(frame.cloud["intensity"], points[:, 3])
        assert np.array_equal(frame.cloud["label"], expected["labels"][i])
        (camera,) = frame.cameras
        assert camera is not None and camera.rgb is not None and frame.pose is not None
        assert camera.frame_id == "camera_left" and np.array_equal(camera.rgb, expected["images"][i])
        want = invert_pose(Tr) @ expected["poses"][i] @ Tr
        assert np.allclose(frame.pose, want, atol=1e-9)
    assert frames[0].pose is not None and frames[3].pose is not None
    assert np.allclose(frames[0].pose, np.eye(4), atol=1e-6)  # map = the first scan's Velodyne frame
    assert frames[3].pose[0, 3] > 5.0  # KITTI-00 drives forward (Velodyne x) at the start

    (model,) = read_camera_models(tmp_path / "bag", topics=KITTI_TOPICS)
    assert model is not None and (model.width, model.height) == (WIDTH, HEIGHT)
    assert np.allclose(model.K, [[718.856, 0, 607.1928], [0, 718.856, 185.2157], [0, 0, 1.0]])
    # the camera looks along the Velodyne's x axis and sits about 0.27 m ahead of it, 0.06 m to the left
    assert np.allclose(model.base_T_cam[:3, 2], [1, 0, 0], atol=0.02)
    assert model.base_T_cam[0, 3] == pytest.approx(0.27, abs=0.02)


def test_depth_images_hold_projected_ranges(kitti00: Path, tmp_path: Path) -> None:
    seq = tmp_path / "00"
    build_sequence(seq, kitti00, labels=True)
    convert_kitti(seq, tmp_path / "bag", depth=True, limit=1, storage="mcap")
    (frame,) = list(read_frames(tmp_path / "bag", topics=KITTI_TOPICS))
    camera = frame.cameras[0]
    assert camera is not None and camera.depth is not None and camera.labels is not None
    assert camera.depth.shape == (HEIGHT, WIDTH) and camera.depth.dtype == np.float32
    hit = camera.depth > 0
    assert 5_000 < hit.sum() < 40_000 and camera.depth[hit].max() < 90.0
    assert np.array_equal(camera.labels > 0, hit)  # every projected point carries a label (semantic ids > 0)
    assert set(np.unique(camera.labels[hit] & 0xFFFF).tolist()) <= {10, 40, 50, 70, 252}


def test_a_sequence_without_poses_or_labels_still_converts(kitti00: Path, tmp_path: Path) -> None:
    seq = tmp_path / "00"
    build_sequence(seq, kitti00, labels=False)
    (seq / "poses.txt").unlink()
    report = convert_kitti(seq, tmp_path / "bag", limit=2)
    assert report.scans == 2 and not report.with_pose and not report.with_labels
    stream = read_frames(tmp_path / "bag", topics=KITTI_TOPICS)
    frames = list(stream)
    assert [f.pose for f in frames] == [None, None] and not stream.stats.odometry_topic
    assert frames[0].cloud.dtype.names == ("x", "y", "z", "intensity")


def test_inconsistent_sequences_are_refused_by_name(kitti00: Path, tmp_path: Path) -> None:
    seq = tmp_path / "00"
    build_sequence(seq, kitti00, labels=False)
    (seq / "times.txt").write_text("0.0\n0.1\n")
    with pytest.raises(DatasetError, match="times.txt has 2 lines for 4 scans"):
        convert_kitti(seq, tmp_path / "bag")
    (seq / "times.txt").write_text("0.0\n0.1\n0.2\n0.3\n")
    (seq / "calib.txt").write_text("P0: 1 2 3\n")
    with pytest.raises(DatasetError, match="needs a 'P2:' line of 12 numbers"):
        convert_kitti(seq, tmp_path / "bag")
    assert not (tmp_path / "bag").exists()


def test_the_command_lines_convert_and_describe(
    kitti00: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    seq = tmp_path / "00"
    build_sequence(seq, kitti00, labels=False)
    assert main([str(seq), "--out", str(tmp_path / "bag"), "--limit", "1", "--no-progress"]) == 0
    assert "scans:    1" in capsys.readouterr().out
    assert baginfo_main([str(tmp_path / "bag")]) == 0
    printed = capsys.readouterr().out
    assert "/kitti/velodyne/points" in printed and "sensor_msgs/msg/Image" in printed
    assert baginfo_main([str(tmp_path / "nothing")]) == 2
