"""Scan Context: the polar max-height grid, ring keys, shift-aware distance and the time-excluding matcher."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from lcpr_core.errors import InputShapeError
from lcpr_core.scan_context import (
    ScanContextConfig,
    ScanContextMatcher,
    rank_database,
    ring_key,
    sc_distance,
    scan_context,
)


def street(seed: int, n: int = 4000) -> np.ndarray:
    """A place: walls and poles at random spots around the sensor, heights up to 8 m."""
    rng = np.random.default_rng(seed)
    centres = rng.uniform(-60, 60, size=(40, 2))
    heights = rng.uniform(0.5, 8.0, size=40)
    which = rng.integers(0, 40, n)
    xy = centres[which] + rng.normal(scale=1.5, size=(n, 2))
    z = rng.uniform(0, 1, n) * heights[which] - 2.0  # sensor 2 m above the ground
    return np.c_[xy, z, rng.random(n)]  # x, y, z, intensity


def rotate(points: np.ndarray, degrees: float) -> np.ndarray:
    c, s = np.cos(np.radians(degrees)), np.sin(np.radians(degrees))
    out = points.copy()
    out[:, 0], out[:, 1] = c * points[:, 0] - s * points[:, 1], s * points[:, 0] + c * points[:, 1]
    return out


def test_a_point_lands_in_its_ring_and_sector_with_its_height_above_ground() -> None:
    # 5 m away at 3 degrees: ring 5 / 4 m = 1, sector 3 / 6 deg = 0; 10 m at 93 degrees: ring 2, sector 15
    pts = np.array([[5 * np.cos(np.radians(3)), 5 * np.sin(np.radians(3)), 1.0],
                    [10 * np.cos(np.radians(93)), 10 * np.sin(np.radians(93)), -0.5]])
    sc = scan_context(pts)
    assert sc.shape == (20, 60) and sc.dtype == np.float32
    assert sc[1, 0] == pytest.approx(3.0) and sc[2, 15] == pytest.approx(1.5)
    assert np.count_nonzero(sc) == 2


def test_each_bin_keeps_its_highest_point_and_points_out_of_range_are_left_out() -> None:
    pts = np.array([[1.0, 0.1, 3.0], [1.2, 0.1, 0.5], [1.1, 0.1, -1.0],  # one bin: max 3 + 2 = 5
                    [85.0, 0.0, 9.0], [np.nan, 1.0, 1.0], [2.0, 0.0, -7.0]])  # too far, NaN, under the ground
    sc = scan_context(pts)
    assert sc[0, 0] == pytest.approx(5.0) and np.count_nonzero(sc) == 1
    assert not scan_context(np.zeros((0, 3))).any()
    near = scan_context(pts, config=ScanContextConfig(min_range=1.15))
    assert near[0, 0] == pytest.approx(2.5)  # only the 1.2 m point (z 0.5 -> 2.5) is kept


def test_the_lidar_height_is_configurable() -> None:
    pts = np.array([[3.0, 0.0, 0.0]])
    assert scan_context(pts, config=ScanContextConfig(lidar_height=1.84))[0, 0] == pytest.approx(1.84)


def test_ring_keys_are_occupancy_ratios_or_mean_heights() -> None:
    sc = np.array([[0.0, 2.0, 4.0, 0.0], [1.0, 1.0, 1.0, 1.0]])
    assert ring_key(sc).tolist() == [0.5, 1.0]
    assert ring_key(sc, kind="mean").tolist() == [1.5, 1.0]
    with pytest.raises(ValueError, match="'median'.*occupancy, mean"):
        ring_key(sc, kind="median")


def test_a_hand_made_distance_averages_column_cosines_over_columns_occupied_in_both() -> None:
    a = np.array([[1.0, 0.0, 1.0], [0.0, 1.0, 1.0]])  # columns (1,0) (0,1) (1,1)
    b = np.array([[1.0, 1.0, 0.0], [0.0, 1.0, 0.0]])  # columns (1,0) (1,1) (0,0)
    # shift 0: cos 1, 1/sqrt2, (b empty)          -> 1 - (1 + 1/sqrt2) / 2 = 0.146
    # shift 1: (b empty), cos 0, cos 1            -> 1 - 1/2            = 0.5
    # shift 2: cos 1/sqrt2, (b empty), 1/sqrt2    -> 1 - 1/sqrt2        = 0.293
    d, s = sc_distance(a, b)
    assert s == 0 and d == pytest.approx(1 - (1 + 1 / np.sqrt(2)) / 2)
    d_back, s_back = sc_distance(b, a)  # the other way round the shift is undone
    assert s_back == 0 and d_back == pytest.approx(d)
    assert sc_distance(np.roll(a, 1, axis=1), b) == pytest.approx((d, 1))


def test_identical_contexts_are_at_distance_zero_and_disjoint_columns_at_one() -> None:
    a = np.array([[1.0, 0.0], [2.0, 0.0]])
    assert sc_distance(a, a) == (pytest.approx(0.0, abs=1e-12), 0)
    assert sc_distance(np.zeros((2, 2)), a) == (1.0, 0)


@pytest.mark.parametrize("degrees", [6.0, 36.0, 90.0, 180.0, 294.0])
def test_a_yaw_rotated_cloud_matches_itself_with_the_shift_of_the_rotation(degrees: float) -> None:
    cloud = street(1)
    d, s = sc_distance(scan_context(rotate(cloud, degrees)), scan_context(cloud))
    assert d < 1e-3
    assert s == round(degrees / 6) % 60


def test_different_places_are_farther_apart_than_a_turned_copy() -> None:
    cloud = street(1)
    turned, _ = sc_distance(scan_context(rotate(cloud, 47.0)), scan_context(cloud))  # not a whole sector
    others = [sc_distance(scan_context(street(seed)), scan_context(cloud))[0] for seed in range(2, 7)]
    assert turned < 0.1 < min(others)


def test_shapes_and_configs_that_do_not_fit_are_refused_naming_them() -> None:
    with pytest.raises(InputShapeError, match=r"\(5, 2\)"):
        scan_context(np.zeros((5, 2)))
    with pytest.raises(InputShapeError, match=r"\(20, 60\) and \(20, 30\)"):
        sc_distance(np.zeros((20, 60)), np.zeros((20, 30)))
    with pytest.raises(ValueError, match="num_sectors=0"):
        ScanContextConfig(num_sectors=0)
    with pytest.raises(ValueError, match="ring_key='max'; accepted: occupancy, mean"):
        ScanContextConfig(ring_key="max")
    with pytest.raises(ValueError, match="min_range=90"):
        ScanContextConfig(min_range=90.0)


def test_the_matcher_leaves_out_entries_newer_than_the_exclusion_window() -> None:
    matcher = ScanContextMatcher(ScanContextConfig(exclude_recent_s=30.0))
    place = scan_context(street(3))
    assert matcher.process(street(3), stamp=0.0, position=np.zeros(3)).matches == []
    assert matcher.search(place, stamp=29.9) == []
    hit = matcher.search(place, stamp=30.0)  # exactly 30 s older: allowed, as in the detector
    assert [m.id for m in hit] == [0] and hit[0].distance < 1e-6 and hit[0].position == (0.0, 0.0, 0.0)
    assert len(matcher.search(place)) == 1  # without a stamp nothing is excluded


def test_the_matcher_ranks_the_revisited_place_first_among_many() -> None:
    matcher = ScanContextMatcher()
    for i in range(30):
        matcher.process(street(100 + i), stamp=float(i), position=np.array([10.0 * i, 0, 0]))
    result = matcher.process(rotate(street(117), 120.0), stamp=100.0)
    assert result.id == 30 and len(matcher) == 31
    best = result.matches[0]
    assert best.id == 17 and best.shift == 20 and best.rank == 0 and best.stamp == 17.0
    assert len(result.matches) == 10  # the ring-key candidates, ranked by full distance
    assert [m.distance for m in result.matches] == sorted(m.distance for m in result.matches)
    assert set(result.timings) == {"describe", "search", "add"}


def test_a_database_is_ranked_per_query_with_padding_when_short() -> None:
    db = np.stack([scan_context(street(s)) for s in (1, 2, 3)])
    queries = np.stack([scan_context(rotate(street(2), 30.0)), scan_context(street(3))])
    ids, dist = rank_database(queries, db, k=5)
    assert ids[:, 0].tolist() == [1, 2] and (ids[:, 3:] == -1).all() and np.isinf(dist[:, 3:]).all()
    assert (np.diff(dist[:, :3], axis=1) >= 0).all()


def test_real_kitti_scans_grow_apart_as_the_car_drives_on(shared: Path) -> None:
    kitti = shared / "data" / "kitti00"
    scans = {i: np.fromfile(kitti / f"{i:06d}.bin", np.float32).reshape(-1, 4) for i in (0, 1, 5, 15)}
    sc = {i: scan_context(p) for i, p in scans.items()}
    d1, d5, d15 = (sc_distance(sc[i], sc[0])[0] for i in (1, 5, 15))
    assert d1 < d5 < d15
    assert sc_distance(scan_context(rotate(scans[0].astype(np.float64), 90.0)), sc[0]) == (
        pytest.approx(0, abs=1e-6), 15
    )
