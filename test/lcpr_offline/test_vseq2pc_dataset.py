"""Feature caches from a synthetic KITTI-like bag: camera and LiDAR features of a frame agree."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from citysim import SynthConfig, SyntheticDrive, write_bag
from citysim.lidar import LidarNoise
from lcpr_core.vseq2pc.dataset import FeatureCache
from lcpr_offline.vseq2pc_cache import build_cache, main


@pytest.fixture(scope="module")
def bag(tmp_path_factory: pytest.TempPathFactory) -> Path:
    drive = SyntheticDrive(SynthConfig(rig="kitti", frames=4, seed=3, image_size=(310, 94), camera_drop=0.0,
                                       lidar_noise=LidarNoise.off(), pixel_noise=False, depth_range=0.0,
                                       depth_noise=0.0))  # exact depth: the features must agree
    out = tmp_path_factory.mktemp("bags") / "kitti.bag"
    write_bag(drive, out)
    return out


def test_a_bag_becomes_a_cache_whose_camera_sees_what_the_lidar_sees(bag: Path, tmp_path: Path) -> None:
    cache = build_cache(bag)
    assert len(cache) == 4 and cache.camera_valid.all()
    assert cache.camera.shape == (4, 12, 90) and cache.lidar.shape == (4, 12, 360)
    np.testing.assert_allclose(np.diff(cache.positions[:, 0]) ** 2 + np.diff(cache.positions[:, 1]) ** 2, 1.0,
                               atol=1e-3)  # KITTI rig keyframes: 1 m apart
    forward = cache.lidar[:, :, 135:225]
    both = (cache.camera > 0) & (forward > 0)
    assert both.sum() > 0.5 * (cache.camera > 0).sum()  # what the camera labels, the LiDAR mostly sees too
    building = both[:, 5]  # buildings: the nearest range per sector agrees to well under a metre
    if building.any():
        assert np.median(np.abs(cache.camera[:, 5][building] - forward[:, 5][building])) * 50 < 0.5
    cache.save(tmp_path / "c.npz")
    back = FeatureCache.load(tmp_path / "c.npz")
    np.testing.assert_array_equal(back.camera, cache.camera)
    np.testing.assert_array_equal(back.poses, cache.poses)


def test_the_cache_command_writes_a_file_and_names_bad_input(bag: Path, tmp_path: Path, capsys) -> None:
    assert main([str(bag), "--out", str(tmp_path / "c.npz"), "--no-progress"]) == 0
    assert "4 frames" in capsys.readouterr().out
    assert main([str(tmp_path / "nope.bag"), "--out", str(tmp_path / "x.npz"), "--no-progress"]) == 2
    assert "vseq2pc_cache: error" in capsys.readouterr().err
