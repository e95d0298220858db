"""Local submaps: neighbours stitched by the odometry, the query's past only, and a narrow-field revisit that
one scan cannot verify."""
from __future__ import annotations

import dataclasses
import json
import math
import re
from typing import Any, cast

import numpy as np
import pytest
from test_map_clouds import KeyedDescriber
from test_verification import pose, pose_error, scene, view

from lcpr_core.descriptor_map import SCHEMA_VERSION, DescriptorMap, MapConfig
from lcpr_core.detector import DetectorConfig, Frame, LoopDetector, MatchConfig
from lcpr_core.errors import MapError, VerificationError
from lcpr_core.lcpr.describer import Describer
from lcpr_core.verification import SubmapConfig, VerifierConfig, build_submap
from lcpr_core.verification.submap import azimuth_coverage_deg, neighbour_rows, stitch

DIM = 16
EXTRINSIC = SubmapConfig(lidar_xyz=(0.3, -0.1, 1.0), lidar_rpy=(0.05, 0.1, 0.5))


def sparse_world(n: int = 60, seed: int = 0) -> np.ndarray:
    """n world points at least 1.5 m apart (each alone in its voxel, so stitching keeps it where it is)."""
    rng = np.random.default_rng(seed)
    out: list[np.ndarray] = []
    while len(out) < n:
        p = rng.uniform([-20, -20, 0], [20, 20, 5])
        if all(np.linalg.norm(p - q) > 1.5 for q in out):
            out.append(p)
    return np.array(out)


def seen_from(points: np.ndarray, world_T_lidar: np.ndarray) -> np.ndarray:
    inv = np.linalg.inv(world_T_lidar)
    return (points @ inv[:3, :3].T + inv[:3, 3]).astype(np.float32)


def walk(n: int, *, step: float = 0.5, dt: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """(world_T_base (n, 4, 4), stamps (n,)) of keyframes ``step`` m apart along x, turning 10 deg each."""
    return np.stack([pose(step * i, 0.0, 10.0 * i) for i in range(n)]), np.arange(n, dtype=np.float64) * dt


# ---------------------------------------------------------------------- stitching
def test_stitching_puts_a_neighbours_points_where_the_odometry_and_the_extrinsic_say():
    world = sparse_world()
    poses = np.stack([pose(2.0, 1.0, 20.0, z=0.2), pose(4.5, -0.5, 65.0, pitch_deg=3.0)])
    ext = EXTRINSIC.base_T_lidar()
    clouds = [seen_from(world[:30], poses[0] @ ext), seen_from(world[30:], poses[1] @ ext)]
    stitched = stitch(clouds, poses, 0, config=EXTRINSIC)
    expected = seen_from(world, poses[0] @ ext)  # every point in the centre keyframe's LiDAR frame
    assert len(stitched) == len(world)
    nearest = np.linalg.norm(stitched[:, None] - expected[None], axis=-1).min(axis=1)
    assert nearest.max() <= 0.01  # the int16 centimetre grid


def test_the_extrinsic_matters_a_base_frame_stitch_would_misplace_the_points():
    world = sparse_world()
    poses = np.stack([pose(0.0, 0.0, 0.0), pose(1.0, 0.0, 90.0)])
    ext = EXTRINSIC.base_T_lidar()
    clouds = [np.zeros((0, 3), np.float32), seen_from(world, poses[1] @ ext)]
    wrong = stitch(clouds, poses, 0, config=SubmapConfig())  # identity extrinsic
    expected = seen_from(world, poses[0] @ ext)
    assert np.linalg.norm(wrong[:, None] - expected[None], axis=-1).min(axis=1).max() > 0.2


def test_a_stitched_cloud_is_voxelised_and_capped():
    dense = view(scene(1), pose(0.0, 0.0, 0.0), seed=1).astype(np.float32)
    poses, _ = walk(3)
    capped = stitch([dense, dense, dense], poses, 1, config=SubmapConfig(max_points=500))
    assert capped.shape == (500, 3) and capped.dtype == np.float32


# ---------------------------------------------------------------------- which neighbours
def test_the_match_takes_neighbours_on_both_sides_within_the_travel():
    poses, stamps = walk(11)  # 0.5 m apart
    assert neighbour_rows(poses, stamps, 5, config=SubmapConfig(travel_m=1.0), before_only=False) == (3, 4, 5, 6, 7)


def test_the_query_submap_never_uses_later_keyframes():
    poses, stamps = walk(11)
    cfg = SubmapConfig(mode="on", travel_m=10.0, max_keyframes=20)
    assert neighbour_rows(poses, stamps, 5, config=cfg, before_only=True) == (0, 1, 2, 3, 4, 5)
    asked: list[int] = []

    def cloud(row: int) -> np.ndarray:
        asked.append(row)
        return np.zeros((5, 3), np.float32) + row

    sub = build_submap(5, world_T_base=poses, stamps=stamps, cloud=cloud, config=cfg, before_only=True)
    assert sub is not None and sub.rows == (0, 1, 2, 3, 4, 5) and max(asked) == 5


def test_at_most_max_keyframes_are_stitched_the_nearest_by_path_first():
    poses, stamps = walk(11)
    rows = neighbour_rows(poses, stamps, 5, config=SubmapConfig(travel_m=10.0, max_keyframes=4), before_only=False)
    assert len(rows) == 4 and 5 in rows and set(rows) <= {3, 4, 5, 6, 7}


@pytest.mark.parametrize("change, expected", [
    ("unknown pose", (4, 5, 6, 7)),  # row 3 has no pose: the walk back stops before it
    ("time goes back", (5, 6, 7)),  # rows 0-4 are stamped after row 5: another run
    ("long gap", (4, 5, 6, 7)),  # 100 s between rows 3 and 4
    ("jump", (3, 4, 5, 6)),  # row 7 is 50 m on: beyond the travel
], ids=["unknown pose", "time goes back", "long gap", "jump"])
def test_the_walk_stops_where_the_run_or_the_odometry_breaks(change, expected):
    poses, stamps = walk(11)
    if change == "unknown pose":
        poses[3] = np.nan
    elif change == "time goes back":
        stamps[:5] += 100.0
    elif change == "long gap":
        stamps[4:] += 100.0
    else:
        poses[7:, 0, 3] += 50.0
    cfg = SubmapConfig(travel_m=1.0)
    assert neighbour_rows(poses, stamps, 5, config=cfg, before_only=False) == expected


def test_a_keyframe_without_a_full_pose_gets_no_submap():
    poses, stamps = walk(5)
    poses[2] = np.nan
    sub = build_submap(2, world_T_base=poses, stamps=stamps, cloud=lambda r: np.ones((4, 3), np.float32) * r,
                       config=SubmapConfig(mode="on"), before_only=False)
    assert sub is not None and sub.rows == (2,) and np.array_equal(sub.xyz, np.full((4, 3), 2.0, np.float32))


# ---------------------------------------------------------------------- when submaps apply
def narrow(xyz: np.ndarray, half_fov_deg: float = 35.0) -> np.ndarray:
    """The points within +-half_fov_deg of the LiDAR's x axis (a Livox Avia's ~70 deg field of view)."""
    return xyz[np.abs(np.degrees(np.arctan2(xyz[:, 1], xyz[:, 0]))) <= half_fov_deg]


def test_auto_turns_submaps_on_for_a_narrow_field_of_view_only():
    full = view(scene(1), pose(0.0, 0.0, 0.0), seed=1)
    assert azimuth_coverage_deg(full) >= 350.0
    assert 65.0 <= azimuth_coverage_deg(narrow(full)) <= 75.0
    auto = SubmapConfig()
    assert auto.mode == "auto" and auto.applies(narrow(full)) and not auto.applies(full)
    assert SubmapConfig(mode="on").applies(full) and not SubmapConfig(mode="off").applies(narrow(full))


@pytest.mark.parametrize("options, says", [
    ({"mode": "sometimes"}, "submap.mode='sometimes'; accepted: off, on, auto"),
    ({"travel_m": 0.0}, "submap.travel_m=0.0"),
    ({"travel_m": math.inf}, "submap.travel_m=inf"),
    ({"max_keyframes": 0}, "submap.max_keyframes=0"),
    ({"max_points": 10}, "submap.max_points=10"),
    ({"auto_fov_deg": 400.0}, "submap.auto_fov_deg=400.0"),
    ({"lidar_xyz": (1.0, 2.0)}, "submap.lidar_xyz=[1.0, 2.0]"),
], ids=["mode", "travel", "infinite travel", "keyframes", "points", "fov", "extrinsic"])
def test_a_bad_submap_setting_is_refused_naming_the_value(options, says):
    with pytest.raises(VerificationError, match=re.escape(says)):
        SubmapConfig(**options)


# ---------------------------------------------------------------------- the map keeps full poses
def test_the_map_keeps_full_poses_through_a_file_and_positions_only_stay_unknown(tmp_path):
    rng = np.random.default_rng(2)
    m = DescriptorMap(MapConfig(dim=DIM))
    poses, _ = walk(3)
    m.add(rng.normal(size=(3, DIM)).astype(np.float32), stamps=[0.0, 1.0, 2.0], poses=poses)
    m.add(rng.normal(size=DIM).astype(np.float32), stamps=3.0, poses=[7.0, 8.0, 9.0])  # a position only
    m.save(tmp_path / "map.npz")
    loaded = DescriptorMap.load(tmp_path / "map.npz")
    back = loaded.pose_matrices(slice(None))
    assert np.abs(back[:3] - poses).max() <= 1e-12
    assert np.isnan(back[3]).all() and loaded.poses[3].tolist() == [7.0, 8.0, 9.0]
    assert np.isnan(loaded.orientations[3]).all() and loaded.row_of(int(loaded.ids[2])) == 2
    with np.load(tmp_path / "map.npz") as npz:
        assert json.loads(str(npz["header"]))["schema_version"] == SCHEMA_VERSION == 3


def test_a_map_file_without_orientations_still_loads_and_its_keyframes_get_no_submap(tmp_path):
    """A schema-version-2 file (positions and clouds, no orientations), as maps were saved before."""
    n = 3
    header = {"format": "lcpr_core.descriptor_map", "schema_version": 2, "dim": DIM, "model": "lcpr",
              "index": "flat", "count": n, "sources": ["old"], "clouds": 0}
    with open(tmp_path / "v2.npz", "wb") as fh:
        np.savez(fh, header=np.array(json.dumps(header)), descriptors=np.ones((n, DIM), np.float32),
                 ids=np.arange(n, dtype=np.int64), stamps=np.arange(n, dtype=np.float64),
                 poses=np.arange(3.0 * n).reshape(n, 3), source_codes=np.zeros(n, np.int32),
                 cloud_ids=np.zeros(0, np.int64), cloud_counts=np.zeros(0, np.int64),
                 cloud_points=np.zeros((0, 3), np.int16))
    loaded = DescriptorMap.load(tmp_path / "v2.npz")
    assert len(loaded) == n and np.isnan(loaded.orientations).all() and np.isnan(loaded.pose_matrices([0, 2])).all()
    sub = build_submap(1, world_T_base=loaded.pose_matrices(slice(None)), stamps=loaded.stamps,
                       cloud=lambda r: np.ones((4, 3), np.float32), config=SubmapConfig(mode="on"), before_only=False)
    assert sub is not None and sub.rows == (1,)


def test_a_version_3_map_file_without_orientations_or_with_bad_ones_is_refused_naming_the_file(tmp_path):
    m = DescriptorMap(MapConfig(dim=DIM))
    m.add(np.ones((2, DIM), np.float32), stamps=[0.0, 1.0], poses=walk(2)[0])
    m.save(tmp_path / "good.npz")
    with np.load(tmp_path / "good.npz") as npz:
        arrays = {k: npz[k] for k in npz.files}
    for name, change, says in (("none.npz", None, "lacks orientations"),
                               ("bad.npz", np.full((2, 4), 0.5) * [1, 1, 1, 3], "neither unit quaternions")):
        bad = {k: v for k, v in arrays.items() if k != "orientations" or change is not None}
        if change is not None:
            bad["orientations"] = change
        with open(tmp_path / name, "wb") as fh:
            np.savez(fh, **bad)
        with pytest.raises(MapError, match=re.escape(str(tmp_path / name)) + ".*" + says):
            DescriptorMap.load(tmp_path / name)


def test_a_pose_that_is_not_rigid_is_refused_by_the_map_and_kept_as_a_position_by_the_detector():
    m = DescriptorMap(MapConfig(dim=DIM))
    sheared = np.eye(4)
    sheared[0, 1] = 0.5
    with pytest.raises(MapError, match=r"poses \[0\] are not rigid"):
        m.add(np.ones(DIM, np.float32), stamps=0.0, poses=sheared)
    from lcpr_core.lcpr.detector import _map_pose  # a private helper, tested where it lives
    kept = _map_pose(sheared)
    assert kept is not None and kept.shape == (1, 3)


# ---------------------------------------------------------------------- the detector
VERIFY = VerifierConfig(num_threads=1, processes=0)  # see test_verification.CONFIG; in-process: tests read its cache
FIRST_VISIT = [pose(0.3 * i, 0.0, 45.0 * i) for i in range(5)]  # walking on x while turning from 0 to 180 deg
RETURN = [pose(0.5, 0.8, 100.0), pose(0.6, 0.5, 50.0), pose(0.7, 0.3, 5.0)]  # back, turning the other way


def narrow_frame(t: float, key: str, world: np.ndarray, world_T_base: np.ndarray, seed: int) -> Frame:
    images = cast(Any, [key] * 6)  # not images: KeyedDescriber reads the key
    return Frame(stamp=t, images=images, points=narrow(view(world, world_T_base, seed=seed)), pose=world_T_base)


def narrow_revisit(submap: SubmapConfig, verify: VerifierConfig = VERIFY) -> tuple[LoopDetector, Any]:
    """A 70 deg sensor: the first visit turns through 180 deg; the return's last keyframe looks along x (as the
    first visit's first keyframe did) and its descriptor names the first visit's middle keyframe, which looked
    along y: a single scan of each shares nothing."""
    rng = np.random.default_rng(5)
    keys = [f"k{i}" for i in range(5)] + ["q0", "q1"]
    table = {k: (v / np.linalg.norm(v)).astype(np.float32) for k in keys for v in [rng.normal(size=256)]}
    det = LoopDetector(DetectorConfig(match=MatchConfig(max_distance=1.0), verify=verify, submap=submap),
                       describer=cast(Describer, KeyedDescriber(table)))
    world = scene(1)
    for i, T in enumerate(FIRST_VISIT):
        det.process(narrow_frame(0.5 * i, f"k{i}", world, T, seed=10 + i))
    for i, T in enumerate(RETURN[:2]):
        assert det.process(narrow_frame(40.0 + 0.5 * i, f"q{i}", world, T, seed=30 + i)).candidates == []
    result = det.process(narrow_frame(41.0, "k2", world, RETURN[2], seed=32))
    return det, result


MOUNT = (0.0, 0.0, 1.8)  # base_T_lidar: test_verification.view's sensor height above the base


def test_the_detector_with_submaps_verifies_a_narrow_field_revisit_that_a_single_scan_cannot():
    _, alone = narrow_revisit(SubmapConfig(mode="off", lidar_xyz=MOUNT))
    assert [c.match_id for c in alone.candidates] == [2] and alone.loop is None
    assert alone.candidates[0].verification == "low overlap"
    det, stitched = narrow_revisit(SubmapConfig(lidar_xyz=MOUNT))  # "auto": a 70 deg cloud is narrow
    loop = stitched.loop
    assert loop is not None and loop.match_id == 2 and loop.query_id == 7
    err_m, err_deg = pose_error(loop.match_T_query, np.linalg.inv(FIRST_VISIT[2]) @ RETURN[2])
    assert err_m <= 0.05 and err_deg <= 0.5, (err_m, err_deg)
    assert list(det._prepared) == [(det._token, 2, 0, 1, 2, 3, 4)]  # by its centre (its frame) and what it stitches


def test_verifying_over_worker_processes_gives_the_detector_the_same_loop_and_verdicts():
    _, here = narrow_revisit(SubmapConfig(lidar_xyz=MOUNT))
    det, over = narrow_revisit(SubmapConfig(lidar_xyz=MOUNT), verify=dataclasses.replace(VERIFY, processes=2))
    try:
        assert det._processes is not None and det._processes.fallbacks == 0 and not det._prepared
        assert over.loop is not None and here.loop is not None and over.loop.match_id == here.loop.match_id
        for a, b in zip(here.candidates, over.candidates, strict=True):
            assert (a.match_id, a.verified, a.verification, a.fitness) == (b.match_id, b.verified, b.verification,
                                                                          b.fitness)
            assert np.array_equal(a.match_T_query, b.match_T_query) and np.array_equal(a.covariance, b.covariance)
    finally:
        det.close()
    assert det._processes is None


def test_a_full_field_of_view_is_verified_scan_against_scan_under_auto():
    det = LoopDetector(DetectorConfig(verify=VERIFY), describer=cast(Describer, KeyedDescriber({})))
    world = scene(1)
    assert not det.config.submap.applies(view(world, pose(0.0, 0.0, 0.0), seed=1))
    assert det.config.submap.applies(narrow(view(world, pose(0.0, 0.0, 0.0), seed=1)))


def test_two_matches_that_stitch_the_same_keyframes_keep_their_own_frames():
    det, _ = narrow_revisit(SubmapConfig(lidar_xyz=MOUNT))
    refs = det._match_cloud(1, end=5), det._match_cloud(2, end=5)  # both stitch rows 0-4
    assert refs[0] is not None and refs[1] is not None and refs[0].key != refs[1].key
    around_1, around_2 = det._prepared_cloud(refs[0]), det._prepared_cloud(refs[1])
    assert around_1 is not around_2
    lidar = [T @ SubmapConfig(lidar_xyz=MOUNT).base_T_lidar() for T in FIRST_VISIT]
    two_T_one = np.linalg.inv(lidar[2]) @ lidar[1]
    sample = around_1.xyz[::10]

    def gap(points: np.ndarray) -> float:  # median distance to the nearest point of the second match's cloud
        return float(np.median(np.linalg.norm(points[:, None] - around_2.xyz[None], axis=-1).min(axis=1)))

    assert gap(sample @ two_T_one[:3, :3].T + two_T_one[:3, 3]) <= 0.15 < 0.5 <= gap(sample)  # one place, two frames
