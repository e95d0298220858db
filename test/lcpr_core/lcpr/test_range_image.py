"""range_image reproduces the released projection and takes options for other LiDARs."""
from __future__ import annotations

import numpy as np
import pytest

from lcpr_core import InputShapeError, range_image
from lcpr_core.lcpr.preprocess import PRESETS, lidar_preset


def test_the_reference_cloud_projects_to_the_reference_image_exactly(shared):
    ref = np.load(shared / "reference" / "lcpr" / "expected_seed0.npz")
    image = range_image(ref["points"])
    assert image.dtype == np.float32 and image.shape == (32, 1056)
    np.testing.assert_array_equal(image, ref["range_image"])


def test_a_single_point_lands_in_the_pixel_the_formula_gives():
    # nuScenes frame: x right, y forward. A point 10 m ahead, level -> yaw 0, pitch 0.
    image = range_image(np.array([[0.0, 10.0, 0.0]]))
    v, u = np.argwhere(image > 0)[0]
    assert u == 1056 // 2
    assert v == int(np.floor((1 - np.deg2rad(30) / np.deg2rad(40)) * 32))
    assert image[v, u] == pytest.approx(10.0)
    assert (image == -1).sum() == 32 * 1056 - 1


def test_the_nearest_point_of_a_pixel_wins_whatever_the_input_order():
    far, near = [0.0, 20.0, 0.0], [0.0, 10.0, 0.0]
    for cloud in ([far, near], [near, far]):
        image = range_image(np.array(cloud))
        assert image.max() == pytest.approx(10.0)


def test_ego_box_out_of_range_and_non_finite_points_are_dropped():
    cloud = np.array([
        [1.0, 1.5, 0.0],  # inside the 2 m ego box
        [0.0, 85.0, 0.0],  # beyond 80 m
        [np.nan, 5.0, 0.0],
        [np.inf, 5.0, 0.0],
    ])
    assert (range_image(cloud) == -1).all()


def test_options_override_the_preset():
    cloud = np.array([[10.0, 0.0, 0.0]])  # REP-103: ahead
    image = range_image(cloud, preset="kitti_hdl64e", height=16, width=360)
    assert image.shape == (16, 360)
    assert np.argwhere(image > 0)[0][1] == 180


def test_the_kitti_preset_puts_a_forward_point_in_the_middle_column():
    image = range_image(np.array([[10.0, 0.0, 0.0]]), preset="kitti_hdl64e")
    preset = lidar_preset("kitti_hdl64e")
    assert image.shape == (preset.height, preset.width)
    assert np.argwhere(image > 0)[0][1] == preset.width // 2


def test_bad_input_names_the_problem():
    with pytest.raises(InputShapeError, match=r"shape \(5, 2\)"):
        range_image(np.zeros((5, 2)))
    with pytest.raises(ValueError, match="accepted: " + ", ".join(sorted(PRESETS))):
        range_image(np.zeros((5, 3)), preset="hdl32")
    with pytest.raises(ValueError, match="fov_up_deg"):
        range_image(np.zeros((5, 3)), fov_up_deg=-40)
