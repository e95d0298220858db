"""Structure features, LiDAR slices and camera back-projection follow the VSeq2PC spec."""
from __future__ import annotations

import numpy as np
import pytest

from lcpr_core import lidar_slices, structure_feature
from lcpr_core.vseq2pc.preprocess import (
    CLASSES,
    camera_feature,
    camera_points,
    cityscapes_to_semantickitti,
    sequence_indices,
)

BUILDING, ROAD, CAR = 5, 1, 0


def test_each_cell_keeps_the_nearest_point_but_road_keeps_the_farthest():
    pts = np.array([[10.0, 0, 0], [20.0, 0, 0], [5.0, 0, 0], [30.0, 0, 0]])
    labels = np.array([50, 50, 40, 40])
    f = structure_feature(pts, labels)
    assert f.shape == (12, 360) and f.dtype == np.float32
    assert f[BUILDING, 180] == pytest.approx(10 / 50)  # +x is sector 180
    assert f[ROAD, 180] == pytest.approx(30 / 50)
    assert np.count_nonzero(f) == 2


def test_sectors_ranges_instance_bits_and_ignored_classes():
    pts = np.array([[0.0, 10, 5], [0.0, -10, 0], [60.0, 0, 0], [10.0, 0, 0], [10.0, 0, 0]])
    labels = np.array([10 | (3 << 16), 252, 50, 0, 99])  # car with instance id, moving car, far, ignored
    f = structure_feature(pts, labels)
    assert f[CAR, 270] == pytest.approx(0.2)  # +y (left) -> atan2 = pi/2 -> sector 270; z ignored
    assert f[CAR, 90] == pytest.approx(0.2)
    assert np.count_nonzero(f) == 2  # > 50 m dropped, unlabelled/unknown ignored


def test_every_class_has_its_own_channel():
    for channel, (_, ids) in enumerate(CLASSES):
        for label in ids:
            f = structure_feature(np.array([[10.0, 0, 0]]), np.array([label]))
            assert np.argwhere(f > 0).tolist() == [[channel, 180]]


def test_slices_roll_each_window_to_the_front():
    f = np.zeros((12, 360), np.float32)
    f[:, :] = np.arange(360)[None, :]
    s = lidar_slices(f)
    assert s.shape == (8, 12, 360)
    for i in range(8):
        front = s[i, 0, 135:225]
        np.testing.assert_array_equal(front, (np.arange(135, 225) + 45 * i) % 360)
        assert not s[i, :, :135].any() and not s[i, :, 225:].any()


def test_a_camera_pixel_is_back_projected_into_the_lidar_frame():
    K = np.array([[100.0, 0, 50], [0, 100.0, 25], [0, 0, 1]])
    depth = np.zeros((50, 100), np.float32)
    labels = np.zeros((50, 100), np.uint16)
    depth[25, 50], labels[25, 50] = 20.0, 50  # the principal point, 20 m ahead
    depth[25, 60], labels[25, 60] = 10.0, 0  # no label: skipped
    lidar_T_cam = np.array([[0, 0, 1, 0.3], [-1, 0, 0, 0], [0, -1, 0, -0.1], [0, 0, 0, 1.0]])  # optical -> x fwd
    pts, lab = camera_points(depth, labels, K, lidar_T_cam)
    np.testing.assert_allclose(pts, [[20.3, 0.0, -0.1]])
    assert lab.tolist() == [50]
    feature = camera_feature(depth, labels, K, lidar_T_cam)
    assert feature.shape == (12, 90)
    assert feature[BUILDING, 45] == pytest.approx(20.3 / 50)


def test_cityscapes_train_ids_map_to_semantickitti_ids():
    np.testing.assert_array_equal(cityscapes_to_semantickitti(np.array([0, 1, 2, 8, 13, 10, 255])),
                                  [40, 48, 50, 70, 10, 0, 0])


def test_a_sequence_is_the_query_and_the_first_frames_5_10_15_m_on():
    positions = np.stack([np.arange(0, 40, 2.0), np.zeros(20)], axis=1)  # 2 m steps
    assert sequence_indices(positions, 0) == [0, 3, 5, 8]
    assert sequence_indices(positions, 3) == [3, 6, 8, 11]
    assert sequence_indices(positions, 15) is None  # only 8 m left
