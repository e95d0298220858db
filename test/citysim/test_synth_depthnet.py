"""The KITTI rig's depth images look like a monocular depth network's: limited range, smooth error."""
from __future__ import annotations

import numpy as np
import pytest

from citysim import cli
from citysim.depthnet import estimated_depth, smooth_field
from citysim.drive import SynthConfig, SyntheticDrive
from citysim.lidar import LidarNoise


def test_the_error_field_has_unit_variance_everywhere_and_is_smooth() -> None:
    fields = np.stack([smooth_field((64, 96), cell=16, rng=np.random.default_rng(s)) for s in range(400)])
    std = fields.std(axis=0)  # per pixel, over the draws
    assert 0.85 < std.min() and std.max() < 1.15  # also between lattice points, where bilinear would shrink it
    neighbours = np.corrcoef(fields[:, 30, 40], fields[:, 30, 41])[0, 1]
    far = np.corrcoef(fields[:, 30, 40], fields[:, 30, 88])[0, 1]
    assert neighbours > 0.9 and abs(far) < 0.2


def test_depth_beyond_the_range_is_gone_and_the_rest_carries_the_relative_error() -> None:
    exact = np.tile(np.linspace(1.0, 60.0, 240, dtype=np.float32), (80, 1))
    exact[:10] = 0.0  # sky
    got = estimated_depth(exact, max_depth=25.0, noise=0.1, rng=np.random.default_rng(1))
    assert got.dtype == np.float32 and got.shape == exact.shape
    assert (got[exact > 25.0] == 0).all() and (got[:10] == 0).all()
    kept = (exact > 0) & (exact <= 25.0)
    assert (got[kept] > 0).all()
    ratio = got[kept] / exact[kept] - 1.0
    assert 0.03 < ratio.std() < 0.2 and abs(np.median(ratio)) < 0.1


def test_no_range_and_no_noise_keep_the_exact_depth() -> None:
    exact = np.random.default_rng(0).uniform(0.0, 90.0, (20, 30)).astype(np.float32)
    np.testing.assert_array_equal(estimated_depth(exact, max_depth=0.0, noise=0.0, rng=np.random.default_rng(0)),
                                  exact)


def test_kitti_drives_publish_network_like_depth_by_default_and_exact_depth_on_request() -> None:
    default = SyntheticDrive(SynthConfig(rig="kitti", frames=3, seed=2, image_size=(310, 94),
                                         lidar_noise=LidarNoise.off(), pixel_noise=False, camera_drop=0.0))
    full = default.with_config(depth_range=0.0, depth_noise=0.0)
    a, b = default.frame(1).cameras[0], full.frame(1).cameras[0]
    assert a is not None and b is not None and a.depth is not None and b.depth is not None
    assert b.depth.max() > 40.0 and a.depth.max() < 25.0 * 1.6
    near = (b.depth > 0) & (b.depth < 20.0)
    assert (a.depth[near] > 0).all() and not np.array_equal(a.depth[near], b.depth[near])
    np.testing.assert_array_equal(a.labels, b.labels)  # the segmenter is not the depth network
    again = default.frame(1).cameras[0]
    assert again is not None and again.depth is not None
    np.testing.assert_array_equal(again.depth, a.depth)  # deterministic per frame


@pytest.mark.parametrize("changes, message", [
    (dict(depth_range=-1.0), "depth_range=-1.0"),
    (dict(depth_noise=1.5), "depth_noise=1.5"),
])
def test_bad_depth_options_name_the_value(changes: dict[str, float], message: str) -> None:
    with pytest.raises(ValueError, match=message):
        SynthConfig(rig="kitti", **changes)  # type: ignore[arg-type]


def test_the_cli_passes_the_depth_options_and_no_noise_zeroes_the_depth_error() -> None:
    parser = cli.build_parser()
    config = cli.config_from_args(parser.parse_args(["--out", "x", "--depth-range", "30", "--depth-noise", "0.2"]))
    assert (config.depth_range, config.depth_noise) == (30.0, 0.2)
    config = cli.config_from_args(parser.parse_args(["--out", "x", "--no-noise"]))
    assert config.depth_noise == 0.0 and config.depth_range == 25.0
