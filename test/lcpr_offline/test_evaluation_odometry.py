"""lcpr_eval --odometry kiss-icp: the detector on KISS-ICP's poses, the back end's ATE before and after, backend.png."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from lcpr_core.errors import InvalidValueError

pytest.importorskip("kiss_icp")
pytest.importorskip("gtsam")

RADIUS_M = 10.0  # the circle driven
FRAMES = 80  # 1 m apart: a lap and a quarter, so the last 17 frames revisit the first
SMALL = ["--seeded", "--image-size", "32", "96", "--lidar", "velodyne_vlp16", "--threads", "1", "--quiet",
         "--warmup", "1", "--lidar-only", "--no-scan-context", "--keyframe-interval", "7",  # 12 keyframes
         "--precision", "fp32"]  # no timing race between the inference paths at start


def write_circle_bag(path: Path) -> None:
    """A LiDAR-only bag: clouds every 1 m (1 s) around a circle among poles on flat ground, with odometry."""
    from msg_tools import NUSCENES_TOPICS, BagWriter, SensorFrame, xyz_cloud

    rng = np.random.default_rng(0)
    poles = rng.uniform(-45, 45, size=(160, 2))
    poles = poles[np.abs(np.hypot(*poles.T) - RADIUS_M) > 4]  # keep the road clear
    step = 1.0 / RADIUS_M  # rad per frame: 1 m of arc
    with BagWriter(path) as writer:
        for i in range(FRAMES):
            angle = step * i
            yaw = angle + np.pi / 2
            pose = np.eye(4)
            pose[:2, :2] = [[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]]
            pose[:2, 3] = RADIUS_M * np.cos(angle), RADIUS_M * np.sin(angle)
            noise = np.random.default_rng(i)
            k = noise.integers(0, len(poles), 2500)
            pole_pts = np.c_[poles[k] + noise.normal(scale=0.15, size=(2500, 2)), noise.uniform(0, 6, 2500)]
            ground = np.c_[pose[:2, 3] + noise.uniform(-30, 30, size=(2500, 2)), np.zeros(2500)]
            world = np.r_[pole_pts, ground]
            local = (world[:, :2] - pose[:2, 3]) @ pose[:2, :2]  # world -> vehicle frame
            cloud = xyz_cloud(np.c_[local, world[:, 2] - 1.8], intensity=noise.random(len(world)).astype(np.float32))
            writer.write_frame(SensorFrame(1_700_000_000.0 + i, [], cloud, "lidar", pose),
                               topics=NUSCENES_TOPICS)


def test_the_odometry_option_defaults_to_the_bag_s_and_takes_kiss_icp_by_name(tmp_path: Path) -> None:
    from lcpr_ros.evaluate import options_from_args, parse_args

    bag = str(tmp_path / "bag")
    assert options_from_args(parse_args([bag])).odometry == "bag"
    assert options_from_args(parse_args([bag, "--odometry", "kiss-icp"])).odometry == "kiss-icp"
    with pytest.raises(SystemExit):
        parse_args([bag, "--odometry", "wheels"])


def test_evaluation_options_refuse_an_odometry_they_do_not_know_naming_it() -> None:
    from lcpr_offline.lcpr_evaluate import EvalOptions

    with pytest.raises(InvalidValueError, match=r"odometry='wheels'; accepted: bag, kiss-icp"):
        EvalOptions(odometry="wheels")


@pytest.fixture(scope="module")
def circle_bag(tmp_path_factory: pytest.TempPathFactory) -> Path:
    bag = tmp_path_factory.mktemp("bags") / "circle"
    write_circle_bag(bag)
    return bag


@pytest.mark.slow  # 80 KISS-ICP registrations and every candidate verified
def test_lcpr_eval_with_kiss_icp_odometry_reports_the_ate_before_and_after_and_draws_it(
        circle_bag: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from lcpr_ros.evaluate import main

    assert main([str(circle_bag), "--out", str(tmp_path), "--odometry", "kiss-icp", *SMALL]) == 0
    assert "back end: KISS-ICP odometry ATE" in capsys.readouterr().out
    assert (tmp_path / "backend.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    report = json.loads((tmp_path / "report.json").read_text())
    backend = report["backend"]
    assert report["settings"]["odometry"] == "kiss-icp" and report["counts"]["backend"] == "run"
    assert backend["odometry"] == "KISS-ICP" and backend["frames"] == FRAMES
    assert backend["keyframes"] == report["counts"]["keyframes"]
    # KISS-ICP follows this easy circle closely (started at the bag's first pose); the back end keeps it so
    assert 0.0 <= backend["ate_odometry"]["rmse"] < 1.0
    assert 0.0 <= backend["ate_backend"]["rmse"] <= backend["ate_odometry"]["rmse"] + 0.05


def test_lcpr_eval_without_the_option_runs_no_back_end(circle_bag: Path, tmp_path: Path) -> None:
    from lcpr_ros.evaluate import main

    assert main([str(circle_bag), "--out", str(tmp_path), "--limit", "6", *SMALL]) == 0
    report = json.loads((tmp_path / "report.json").read_text())
    assert report["backend"] is None and "backend" not in report["counts"]
    assert not (tmp_path / "backend.png").exists()
