"""LCPR training augmentations (lcpr_core.lcpr.training.augment): yaw by camera slots, lighting, a missing camera,
a quarter of the LiDAR occluded, a narrower or sparser LiDAR."""
from __future__ import annotations

import numpy as np
import pytest

from lcpr_core.errors import InvalidValueError
from lcpr_core.lcpr.preprocess.range_image import NO_RETURN, range_image
from lcpr_core.lcpr.preprocess.turn import SLOT_YAWS_DEG, range_columns, turn_frame
from lcpr_core.lcpr.training.augment import (
    LIDAR_QUARTERS,
    AugmentConfig,
    augment,
    narrow_fov,
    occlude_lidar,
    sparsify,
    turn,
)
from lcpr_core.points import rotate_z


def cloud(seed: int = 0, n: int = 20000) -> np.ndarray:
    rng = np.random.default_rng(seed)
    azimuth = rng.uniform(-np.pi, np.pi, n)
    dist = rng.uniform(3.0, 60.0, n)
    return np.c_[dist * np.cos(azimuth), dist * np.sin(azimuth), rng.uniform(-2.0, 3.0, n)]


@pytest.mark.parametrize("k", range(1, 6))
def test_rolling_the_range_image_is_the_cloud_turned_by_the_slot_angle(k: int) -> None:
    points = cloud(k)
    yaw = SLOT_YAWS_DEG[k - 1]
    rolled = np.roll(range_image(points, width=288), range_columns(yaw, 288), axis=-1)
    turned = range_image(rotate_z(points, -yaw), width=288)
    assert np.mean(np.isclose(rolled, turned)) > 0.99  # pixel borders may round the other way


def test_turning_by_one_slot_shows_the_front_left_camera_in_front() -> None:
    images = np.arange(6, dtype=np.uint8).reshape(6, 1, 1, 1) * np.ones((6, 2, 2, 3), np.uint8)
    cameras = np.array([True, True, True, True, True, False])
    ranges = np.zeros((4, 288), np.float32)
    ranges[:, 0] = 1.0
    out_images, out_cameras, out_ranges = turn(images, cameras, ranges, 1)
    assert out_images[:, 0, 0, 0].tolist() == [5, 0, 1, 2, 3, 4] and out_cameras.tolist()[0] is False
    assert np.flatnonzero(out_ranges[0]).tolist() == [44]  # 55 deg of 288 columns


def test_a_raw_frame_turned_by_k_slots_matches_the_cached_inputs_turned_alike() -> None:
    points = cloud(7)
    images, turned_points = turn_frame(list("ABCDEF"), points, 2)
    assert images == list("EFABCD")
    cached = np.roll(range_image(points, width=288), range_columns(SLOT_YAWS_DEG[1], 288), axis=-1)
    assert np.mean(np.isclose(range_image(turned_points, width=288), cached)) > 0.99
    full, same = turn_frame(list("ABCDEF"), points, 6)
    assert full == list("ABCDEF") and np.allclose(same, points)


def test_probability_zero_changes_nothing_and_one_applies_each_augmentation() -> None:
    rng = np.random.default_rng(0)
    images = rng.integers(0, 256, (8, 6, 4, 4, 3), dtype=np.uint8)
    cameras = np.ones((8, 6), bool)
    ranges = rng.uniform(1, 50, (8, 4, 288)).astype(np.float32)
    same = augment(images, cameras, ranges, AugmentConfig(), rng)
    originals: tuple[np.ndarray, ...] = (images, cameras, ranges)
    assert all(np.array_equal(a, b) for a, b in zip(same, originals, strict=True))
    dropped = augment(images, cameras, ranges, AugmentConfig(camera_drop=1.0), rng)[1]
    assert (dropped.sum(axis=1) == 5).all()
    dark = augment(images, cameras, ranges, AugmentConfig(lighting=1.0, brightness=(0.5, 0.5)), rng)[0]
    assert np.allclose(dark, np.clip(images * 0.5 + 0.5, 0, 255).astype(np.uint8))
    yawed = augment(images, cameras, ranges, AugmentConfig(yaw=1.0), rng)
    assert not np.array_equal(yawed[2], ranges) and np.array_equal(np.sort(yawed[2], axis=-1), np.sort(ranges, axis=-1))
    assert np.array_equal(images, images.copy())  # the inputs are not changed in place


def test_a_lidar_sector_wraps_round_the_range_image_edge_and_covers_a_quarter() -> None:
    ranges = np.ones((16, 288), np.float32)
    out = occlude_lidar(ranges, "columns", start=250)
    blank = out == NO_RETURN
    assert blank.mean() == pytest.approx(0.25) and blank.all(axis=0).sum() == 72
    assert blank[:, 250:].all() and blank[:, :34].all() and not blank[:, 34:250].any()
    assert (ranges == 1).all()  # a copy
    top = occlude_lidar(ranges, "top rows")
    assert (top[:4] == NO_RETURN).all() and (top[4:] == 1).all()


def test_lidar_occlusion_blanks_one_quarter_per_sample_and_leaves_the_cameras() -> None:
    rng = np.random.default_rng(1)
    images = rng.integers(0, 256, (30, 6, 2, 2, 3), dtype=np.uint8)
    cameras = np.ones((30, 6), bool)
    ranges = rng.uniform(1, 50, (30, 16, 288)).astype(np.float32)
    out_images, out_cameras, out = augment(images, cameras, ranges, AugmentConfig(lidar_occlusion=1.0), rng)
    assert np.array_equal(out_images, images) and out_cameras.all()
    blank = out == NO_RETURN
    assert np.allclose(blank.mean(axis=(1, 2)), 0.25)
    rows = blank.all(axis=2)  # whole rows blank: the top or the bottom quarter
    parts = {"top rows" if rows[b, 0] else "bottom rows" if rows[b, -1] else "columns" for b in range(30)}
    assert parts == set(LIDAR_QUARTERS)
    assert np.array_equal(out[~blank], ranges[~blank])


def test_bad_augmentation_settings_name_the_accepted_values() -> None:
    with pytest.raises(InvalidValueError, match=r"augment.yaw=1.5; expected a probability in \[0, 1\]"):
        AugmentConfig(yaw=1.5)
    with pytest.raises(InvalidValueError, match="expected 0 < low <= high"):
        AugmentConfig(brightness=(1.2, 0.5))
    with pytest.raises(InvalidValueError, match=r"augment.lidar_occlusion=-0.1; expected a probability"):
        AugmentConfig(lidar_occlusion=-0.1)
    with pytest.raises(InvalidValueError, match="'half'; expected one of 'columns', 'top rows', 'bottom rows'"):
        occlude_lidar(np.zeros((4, 8), np.float32), "half")
    with pytest.raises(InvalidValueError, match="needs the 6 nuScenes cameras"):
        augment(np.zeros((1, 4, 2, 2, 3), np.uint8), np.ones((1, 4), bool), np.zeros((1, 2, 8), np.float32),
                AugmentConfig(yaw=1.0), np.random.default_rng(0))


def test_a_narrower_field_of_view_blanks_whole_rows_at_both_ends_and_keeps_the_rest() -> None:
    ranges = np.ones((16, 288), np.float32)
    out = narrow_fov(ranges, 3, 5)
    assert (out[:3] == NO_RETURN).all() and (out[-5:] == NO_RETURN).all() and (out[3:11] == 1).all()
    assert (ranges == 1).all() and np.array_equal(narrow_fov(ranges, 0, 0), ranges)
    with pytest.raises(InvalidValueError, match="top=8, bottom=8; expected counts >= 0 leaving a row of the 16"):
        narrow_fov(ranges, 8, 8)


def test_sparse_lidar_drops_every_second_row_or_a_share_of_the_returns() -> None:
    rng = np.random.default_rng(3)
    ranges = np.ones((16, 288), np.float32)
    kinds = set()
    for _ in range(40):
        out = sparsify(ranges, rng, (0.2, 0.3))
        blank_rows = (out == NO_RETURN).all(axis=1)
        if blank_rows.sum() == 8:  # every second row, from row 0 or row 1
            assert blank_rows[::2].all() != blank_rows[1::2].all()
            kinds.add("rows")
        else:
            assert 0.15 < (out == NO_RETURN).mean() < 0.35 and not blank_rows.any()
            kinds.add("returns")
    assert kinds == {"rows", "returns"} and (ranges == 1).all()


def test_the_sensor_augmentations_touch_only_the_range_images_of_the_samples_drawn() -> None:
    rng = np.random.default_rng(4)
    images = rng.integers(0, 256, (20, 6, 2, 2, 3), dtype=np.uint8)
    cameras = np.ones((20, 6), bool)
    ranges = rng.uniform(1, 50, (20, 16, 288)).astype(np.float32)
    out_images, out_cameras, out = augment(images, cameras, ranges, AugmentConfig(lidar_fov=1.0, lidar_sparse=1.0),
                                           rng)
    assert np.array_equal(out_images, images) and out_cameras.all()
    assert ((out == NO_RETURN).mean(axis=(1, 2)) > 0).all()
    assert np.array_equal(out[out != NO_RETURN], ranges[out != NO_RETURN])
    with pytest.raises(InvalidValueError, match=r"augment.lidar_sparse=2; expected a probability in \[0, 1\]"):
        AugmentConfig(lidar_sparse=2)
    with pytest.raises(InvalidValueError, match=r"augment.sparse_share=\(0.5, 1.0\); expected 0 <= low <= high < 1"):
        AugmentConfig(sparse_share=(0.5, 1.0))
