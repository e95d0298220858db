"""Range-limited camera depth for the VSeq2PC depth study (lcpr_core.vseq2pc.depth_range)."""
from __future__ import annotations

import numpy as np
import pytest

from lcpr_core.vseq2pc.depth_range import coverage, limited_depth
from lcpr_core.vseq2pc.preprocess import MAX_RANGE, ROAD_CHANNEL

AHEAD = 45  # of the 90 camera sectors: straight ahead (sector 180)
BUILDING = 5


def feature(channel: int, sector: int, metres: float) -> np.ndarray:
    f = np.zeros((1, 12, 90), np.float32)
    f[0, channel, sector] = metres / MAX_RANGE
    return f


def test_without_noise_what_lies_within_the_depth_limit_is_unchanged() -> None:
    f = feature(BUILDING, AHEAD, 20.0)
    out = limited_depth(f, max_depth=25.0, noise=0.0, rng=np.random.default_rng(0))
    assert np.array_equal(out, f)


def test_a_class_seen_only_beyond_the_depth_limit_is_gone() -> None:
    out = limited_depth(feature(BUILDING, AHEAD, 40.0), max_depth=25.0, noise=0.0, rng=np.random.default_rng(0))
    assert not out.any()


def test_the_limit_is_depth_along_the_optical_axis_not_range() -> None:
    edge = 0  # 44.5 deg off the axis: 30 m of range is 21.4 m of depth
    out = limited_depth(feature(BUILDING, edge, 30.0), max_depth=25.0, noise=0.0, rng=np.random.default_rng(0))
    assert out[0, BUILDING, edge] * MAX_RANGE == pytest.approx(30.0)


def test_road_seen_beyond_the_limit_ends_at_the_limit() -> None:
    out = limited_depth(feature(ROAD_CHANNEL, AHEAD, 45.0), max_depth=25.0, noise=0.0, rng=np.random.default_rng(0))
    assert out[0, ROAD_CHANNEL, AHEAD] * MAX_RANGE == pytest.approx(25.0 / np.cos(np.deg2rad(0.5)))


def test_noise_changes_seen_cells_only_and_is_seeded() -> None:
    f = feature(BUILDING, AHEAD, 10.0)
    a = limited_depth(f, max_depth=25.0, noise=0.1, rng=np.random.default_rng(3))
    b = limited_depth(f, max_depth=25.0, noise=0.1, rng=np.random.default_rng(3))
    assert np.array_equal(a, b) and np.count_nonzero(a) == 1 and a[0, BUILDING, AHEAD] != f[0, BUILDING, AHEAD]


def test_coverage_counts_the_lidar_cells_a_camera_frame_holds_and_their_range_error() -> None:
    lidar = np.zeros((1, 12, 360), np.float32)
    lidar[0, BUILDING, 135 + AHEAD] = 20.0 / MAX_RANGE
    lidar[0, ROAD_CHANNEL, 135 + AHEAD] = 30.0 / MAX_RANGE
    camera = feature(BUILDING, AHEAD, 21.0)
    share, error = coverage(camera, lidar)
    assert share == pytest.approx(0.5) and error == pytest.approx(1.0, abs=1e-5)
