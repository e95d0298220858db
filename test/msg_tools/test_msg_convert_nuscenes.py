"""nuScenes -> rosbag2 on a tiny dataset in the real table schema, built around the real keyframe."""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from msg_tools import NUSCENES_CAMERAS, NUSCENES_TOPICS, DatasetError, read_camera_models, read_frames
from msg_tools.convert.nuscenes import convert_nuscenes, main
from msg_tools.geometry import matrix_to_quaternion, pose_from_parts

VERSION = "v1.0-mini"
LOGFILE = "n015-2018-07-24-11-22-45+0800"
# camera yaw in the vehicle frame (x forward, y left), nuScenes rig order
YAW = {"CAM_FRONT": 0, "CAM_FRONT_RIGHT": -55, "CAM_BACK_RIGHT": -110, "CAM_BACK": 180,
       "CAM_BACK_LEFT": 110, "CAM_FRONT_LEFT": 55}
OPTICAL = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])  # optical axes in vehicle axes


def _wxyz(R: np.ndarray) -> list[float]:
    x, y, z, w = matrix_to_quaternion(R)
    return [float(w), float(x), float(y), float(z)]


def _yaw(deg: float) -> np.ndarray:
    a = np.radians(deg)
    return np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])


def build_dataset(root: Path, sample_dir: Path) -> dict[str, object]:
    """Copy the real keyframe's 7 files under root/samples and write the 7 tables around them.

    Two scenes: scene-0001 (boston-seaport) uses the files at their real stamps;
    scene-0002 (singapore-onenorth) reuses them 40 s later. One LIDAR sweep that is
    not a keyframe must be ignored.
    """
    files = {}
    for path in sorted(sample_dir.iterdir()):
        channel = path.name.split("__")[1]
        rel_path = Path("samples") / channel / path.name
        (root / rel_path).parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(path, root / rel_path)
        files[channel] = (str(rel_path), int(path.name.split("__")[2].split(".")[0]))
    channels = [*NUSCENES_CAMERAS, "LIDAR_TOP"]
    sensors = [{"token": f"sensor-{c}", "channel": c, "modality": "lidar" if c == "LIDAR_TOP" else "camera"}
               for c in channels]
    calibrated, expected_extrinsics = [], {}
    for i, c in enumerate(channels):
        if c == "LIDAR_TOP":
            R, t, K = _yaw(-90), [0.94, 0.0, 1.84], []
        else:
            R = _yaw(YAW[c]) @ OPTICAL
            t = [1.5 * np.cos(np.radians(YAW[c])), 0.5 * np.sin(np.radians(YAW[c])), 1.55]
            f = 1266.4 if c != "CAM_BACK" else 809.2
            K = [[f, 0.0, 816.3 + i], [0.0, f, 491.5 - i], [0.0, 0.0, 1.0]]
        calibrated.append({"token": f"calib-{c}", "sensor_token": f"sensor-{c}", "translation": t,
                           "rotation": _wxyz(R), "camera_intrinsic": K})
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R, t
        expected_extrinsics[c] = (T, np.asarray(K))
    logs = [{"token": "log-boston", "logfile": LOGFILE, "vehicle": "n015", "date_captured": "2018-07-24",
             "location": "boston-seaport"},
            {"token": "log-sg", "logfile": "n008-x", "vehicle": "n008", "date_captured": "2018-08-01",
             "location": "singapore-onenorth"}]
    scenes, samples, sample_data, ego_poses, expected_poses = [], [], [], [], {}
    for k, (log, shift_us) in enumerate((("log-boston", 0), ("log-sg", 40_000_000))):
        scene, sample = f"scene-token-{k}", f"sample-token-{k}"
        lidar_us = files["LIDAR_TOP"][1] + shift_us
        scenes.append({"token": scene, "log_token": log, "nbr_samples": 1, "first_sample_token": sample,
                       "last_sample_token": sample, "name": f"scene-000{k + 1}", "description": "test"})
        samples.append({"token": sample, "timestamp": lidar_us, "prev": "", "next": "", "scene_token": scene})
        for c in channels:
            rel, us = files[c]
            us += shift_us
            ego_rot = _yaw(30.0 + k + (us - lidar_us) * 1e-6)
            ego_t = [600.0 + k * 10 + (us - lidar_us) * 1e-5, 1640.0, 0.0]
            ego_poses.append({"token": f"ego-{k}-{c}", "timestamp": us, "rotation": _wxyz(ego_rot),
                              "translation": ego_t})
            expected_poses[(k, c)] = pose_from_parts(ego_t, matrix_to_quaternion(ego_rot))
            is_camera = c != "LIDAR_TOP"
            sample_data.append({
                "token": f"sd-{k}-{c}", "sample_token": sample, "ego_pose_token": f"ego-{k}-{c}",
                "calibrated_sensor_token": f"calib-{c}", "timestamp": us, "fileformat": "jpg" if is_camera else "pcd",
                "is_key_frame": True, "height": 900 if is_camera else 0, "width": 1600 if is_camera else 0,
                "filename": rel, "prev": "", "next": "",
            })
    sample_data.append({  # a sweep between keyframes: not a keyframe, its file does not even exist
        "token": "sd-sweep", "sample_token": "sample-token-0", "ego_pose_token": "ego-0-LIDAR_TOP",
        "calibrated_sensor_token": "calib-LIDAR_TOP", "timestamp": files["LIDAR_TOP"][1] + 50_000,
        "fileformat": "pcd", "is_key_frame": False, "height": 0, "width": 0,
        "filename": "sweeps/LIDAR_TOP/missing.pcd.bin", "prev": "", "next": "",
    })
    tables = {"scene": scenes, "sample": samples, "sample_data": sample_data, "calibrated_sensor": calibrated,
              "ego_pose": ego_poses, "sensor": sensors, "log": logs}
    (root / VERSION).mkdir(parents=True)
    for name, rows in tables.items():
        (root / VERSION / f"{name}.json").write_text(json.dumps(rows, indent=1))
    return {"files": files, "extrinsics": expected_extrinsics, "poses": expected_poses}


@pytest.fixture
def dataset(tmp_path: Path, nuscenes_sample: Path) -> tuple[Path, dict[str, object]]:
    if not nuscenes_sample.is_dir():
        pytest.skip(f"{nuscenes_sample} not found")
    root = tmp_path / "nuscenes"
    return root, build_dataset(root, nuscenes_sample)


def test_a_converted_keyframe_keeps_its_jpeg_bytes_cloud_pose_and_calibration(
    dataset: tuple[Path, dict], tmp_path: Path
) -> None:
    root, expected = dataset
    bag = tmp_path / "boston"
    report = convert_nuscenes(root, bag, version=VERSION, locations=["boston-seaport"], storage="mcap")
    assert report.scenes == ["scene-0001"] and report.samples == 1 and report.missing_cameras == 0

    stream = read_frames(bag, topics=NUSCENES_TOPICS, slop=0.05)
    assert stream.stats.camera_missing == [0] * 6
    (frame,) = list(stream)
    lidar_rel, lidar_us = expected["files"]["LIDAR_TOP"]
    assert frame.extras["stamp_ns"] == lidar_us * 1000 and frame.lidar_frame_id == "LIDAR_TOP"
    for channel, image in zip(NUSCENES_CAMERAS, frame.cameras, strict=True):
        rel, us = expected["files"][channel]
        assert image is not None and image.frame_id == channel
        assert image.jpeg == (root / rel).read_bytes()
        assert round(image.stamp * 1e6) == us
    points = np.fromfile(root / lidar_rel, dtype=np.float32).reshape(-1, 5)
    assert frame.cloud.dtype.names == ("x", "y", "z", "intensity", "ring")
    for column, name in enumerate(("x", "y", "z", "intensity")):
        assert np.array_equal(frame.cloud[name], points[:, column])
    assert np.array_equal(frame.cloud["ring"], points[:, 4].astype(np.uint16))
    assert frame.pose is not None
    assert np.allclose(frame.pose, expected["poses"][(0, "LIDAR_TOP")], atol=1e-9)

    models = read_camera_models(bag, topics=NUSCENES_TOPICS)
    for channel, model in zip(NUSCENES_CAMERAS, models, strict=True):
        T, K = expected["extrinsics"][channel]
        assert model is not None and model.name == channel and (model.width, model.height) == (1600, 900)
        assert np.allclose(model.K, K) and np.allclose(model.base_T_cam, T, atol=1e-9)


def test_scenes_are_chosen_by_name_and_unknown_names_are_refused(dataset: tuple[Path, dict], tmp_path: Path) -> None:
    root, _expected = dataset
    report = convert_nuscenes(root, tmp_path / "both", version=VERSION, scenes=["scene-0002", "scene-0001"])
    assert report.scenes == ["scene-0001", "scene-0002"]  # ordered by time
    frames = list(read_frames(tmp_path / "both", topics=NUSCENES_TOPICS))
    assert len(frames) == 2 and frames[1].stamp - frames[0].stamp == pytest.approx(40.0)
    with pytest.raises(DatasetError, match=r"unknown scene\(s\) \['scene-9999'\]; this version has scene-0001"):
        convert_nuscenes(root, tmp_path / "x", version=VERSION, scenes=["scene-9999"])
    with pytest.raises(DatasetError, match="accepted: \\['boston-seaport', 'singapore-onenorth'\\]"):
        convert_nuscenes(root, tmp_path / "x", version=VERSION, locations=["mars"])
    assert not (tmp_path / "x").exists()


def test_the_command_line_prints_a_summary(dataset: tuple[Path, dict], tmp_path: Path,
                                          capsys: pytest.CaptureFixture[str]) -> None:
    root, _expected = dataset
    out = tmp_path / "cli"
    assert main(["--dataroot", str(root), "--version", VERSION, "--scene", "scene-0001", "--out", str(out),
                 "--no-progress"]) == 0
    printed = capsys.readouterr().out
    assert "samples:  1 written" in printed and "/LIDAR_TOP/points" in printed and "/tf_static" in printed
    assert main(["--dataroot", str(root), "--version", "v9", "--scene", "scene-0001", "--out", str(out)]) == 2
    assert "no nuScenes version folder" in capsys.readouterr().err
