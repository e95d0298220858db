"""A folder of LiDAR scans with poses and times -> rosbag2 (msg_tools_scans2bag), on the real Livox and KITTI scans."""
from __future__ import annotations

import dataclasses
import shutil
from pathlib import Path

import numpy as np
import pytest

from msg_tools import NUSCENES_TOPICS, DatasetError, read_frames
from msg_tools.convert.scan_folder import read_kitti_poses
from msg_tools.convert.scans2bag import convert_scans, main

SCANS_ONLY = dataclasses.replace(NUSCENES_TOPICS, cameras=(), camera_info=(), depth=(), labels=(), lidar="/points",
                                 odom="/odom")


def frames(bag: Path) -> list:
    with read_frames(bag, topics=SCANS_ONLY, min_cameras=0) as stream:
        return list(stream)


@pytest.fixture()
def walk(shared: Path, tmp_path: Path) -> Path:
    """The first 6 keyframes of livox_hku/walk_loop, its files cut to match."""
    source = shared / "data" / "livox_hku" / "walk_loop"
    root = tmp_path / "walk"
    (root / "Scans").mkdir(parents=True)
    for path in sorted((source / "Scans").glob("*.pcd"))[:6]:
        shutil.copyfile(path, root / "Scans" / path.name)
    for name in ("optimized_poses.txt", "odom_poses.txt", "times.txt"):
        (root / name).write_text("\n".join((source / name).read_text().splitlines()[:6]) + "\n")
    return root


def test_a_livox_scan_folder_becomes_points_and_odometry_at_its_times(walk: Path, tmp_path: Path) -> None:
    report = convert_scans(walk, tmp_path / "bag")
    assert report.scans == 6 and report.poses.endswith("optimized_poses.txt")
    got = frames(tmp_path / "bag")
    stamps = np.loadtxt(walk / "times.txt")
    assert np.allclose([f.stamp for f in got], stamps, atol=1e-6)
    poses = read_kitti_poses(walk / "optimized_poses.txt")
    assert all(f.pose is not None and np.allclose(f.pose, p, atol=1e-6) for f, p in zip(got, poses, strict=True))
    assert len(got[0].xyz) > 1000 and got[0].lidar_frame_id == "lidar"


def test_kitti_scans_pick_their_pose_and_time_lines_by_name(shared: Path, tmp_path: Path) -> None:
    kitti = shared / "data" / "kitti00"
    assert main([str(kitti), "--out", str(tmp_path / "bag"), "--no-progress"]) == 0
    got = frames(tmp_path / "bag")
    times = np.loadtxt(kitti / "times.txt")
    assert np.allclose([f.stamp for f in got], times[[0, 1, 5, 15]], atol=1e-6)
    assert np.allclose(got[3].pose, read_kitti_poses(kitti / "poses.txt")[15], atol=1e-6)


def test_poses_that_do_not_match_the_scans_are_refused_with_both_counts(walk: Path, tmp_path: Path) -> None:
    lines = (walk / "optimized_poses.txt").read_text().splitlines()
    (walk / "optimized_poses.txt").write_text("\n".join(lines[:4]) + "\n")
    (walk / "Scans" / "000005.pcd").rename(walk / "Scans" / "last.pcd")
    with pytest.raises(DatasetError, match="6 scans but 4 lines"):
        convert_scans(walk, tmp_path / "bag")


def test_a_truncated_scan_is_named_or_left_out_when_asked(walk: Path, tmp_path: Path,
                                                          capsys: pytest.CaptureFixture[str]) -> None:
    bad = sorted((walk / "Scans").glob("*.pcd"))[2]
    bad.write_bytes(bad.read_bytes()[:300])
    assert main([str(walk), "--out", str(tmp_path / "bag"), "--no-progress"]) == 2
    assert bad.name in capsys.readouterr().err
    report = convert_scans(walk, tmp_path / "bag2", skip_bad=True)
    assert report.scans == 5 and report.skipped == [bad.name]
    assert len(frames(tmp_path / "bag2")) == 5


def test_a_folder_without_scans_says_where_it_looked(tmp_path: Path) -> None:
    with pytest.raises(DatasetError, match=r"Scans/\*\.pcd.*velodyne/\*\.bin"):
        convert_scans(tmp_path, tmp_path / "bag")


def test_without_a_pose_file_the_bag_has_points_only_and_times_default_to_10_hz(walk: Path, tmp_path: Path) -> None:
    for name in ("optimized_poses.txt", "odom_poses.txt", "times.txt"):
        (walk / name).unlink()
    report = convert_scans(walk, tmp_path / "bag")
    assert report.poses.startswith("none") and "0.1 s apart" in report.times
    got = frames(tmp_path / "bag")
    assert [f.pose for f in got] == [None] * 6
    assert np.allclose(np.diff([f.stamp for f in got]), 0.1)


def test_a_pose_file_named_without_a_path_is_the_folders_own(walk: Path, tmp_path: Path, monkeypatch) -> None:
    monkeypatch.chdir(tmp_path)  # no odom_poses.txt here: the name means the folder's
    report = convert_scans(walk, tmp_path / "bag", poses=Path("odom_poses.txt"))
    assert report.poses == str(walk / "odom_poses.txt")
    got = frames(tmp_path / "bag")
    assert np.allclose(got[2].pose, read_kitti_poses(walk / "odom_poses.txt")[2], atol=1e-6)


def test_a_pose_file_found_nowhere_names_both_places_it_looked(walk: Path, tmp_path: Path, monkeypatch) -> None:
    monkeypatch.chdir(tmp_path)
    with pytest.raises(DatasetError, match=r"--poses missing\.txt does not exist \(nor .*walk/missing\.txt\)"):
        convert_scans(walk, tmp_path / "bag", poses=Path("missing.txt"))
