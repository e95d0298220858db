"""The up direction from a scan's walls (lcpr_core.up): synthetic streets with a known tilt, real scans, bad input."""
from __future__ import annotations

import math

import numpy as np
import pytest

pytest.importorskip("small_gicp")

from lcpr_common.shared_data import shared_path  # noqa: E402
from lcpr_core.errors import InvalidValueError  # noqa: E402
from lcpr_core.up import UpConfig, estimate_up  # noqa: E402
from trajectory_fixtures import pose  # noqa: E402


def street(rng: np.random.Generator, *, walls: tuple[str, ...] = ("n", "s", "e", "w"), ground: bool = True
           ) -> np.ndarray:
    """Points of vertical walls 12 m around a LiDAR 1.8 m above flat ground (level frame), 2 cm of noise."""
    parts = []
    u = rng.uniform(-30.0, 30.0, 6000)
    h = rng.uniform(-1.8, 6.0, 6000)
    for side in walls:
        x, y = {"n": (u, np.full_like(u, 12.0)), "s": (u, np.full_like(u, -12.0)),
                "e": (np.full_like(u, 12.0), u), "w": (np.full_like(u, -12.0), u)}[side]
        parts.append(np.stack([x, y, h], axis=1))
    if ground:
        g = rng.uniform(-11.0, 11.0, (8000, 2))
        parts.append(np.column_stack([g, np.full(len(g), -1.8)]))
    pts = np.concatenate(parts)
    return pts + rng.normal(0.0, 0.02, pts.shape)


def angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    return math.degrees(math.acos(float(np.clip(a @ b / np.linalg.norm(a) / np.linalg.norm(b), -1.0, 1.0))))


@pytest.mark.parametrize("roll, pitch", [(0.0, 0.0), (3.0, -2.0), (-8.0, 5.0)])
def test_the_up_of_a_tilted_scan_is_found_from_its_walls(roll: float, pitch: float) -> None:
    rng = np.random.default_rng(0)
    world_R_lidar = pose(roll=roll, pitch=pitch, yaw=20.0)[:3, :3]
    scan = street(rng) @ world_R_lidar  # the points in the tilted LiDAR's frame: R^T p
    found = estimate_up(scan)
    assert found is not None
    truth = world_R_lidar.T @ np.array([0.0, 0.0, 1.0])
    assert angle_deg(found.up, truth) < 0.1
    assert found.walls > 1000 and found.spread > 0.5 and found.residual_deg < 2.0


def test_walls_of_one_direction_or_no_walls_give_no_up() -> None:
    rng = np.random.default_rng(1)
    wide = UpConfig(min_fov_deg=0.0)  # the corridor test is about the walls, not the field of view
    assert estimate_up(street(rng, walls=("n", "s")), config=wide) is None  # a corridor: one tilt unseen
    assert estimate_up(street(rng, walls=()), config=wide) is None  # flat ground only
    assert estimate_up(np.zeros((0, 3))) is None


def test_a_narrow_field_of_view_gives_no_up_unless_allowed() -> None:
    scan = street(np.random.default_rng(2))
    ahead = scan[np.abs(np.degrees(np.arctan2(scan[:, 1], scan[:, 0]))) < 35.0]  # a 70 deg Livox-like view
    assert estimate_up(ahead) is None
    assert estimate_up(ahead, config=UpConfig(min_fov_deg=0.0)) is not None


def test_the_prior_up_picks_the_walls_of_a_strongly_tilted_sensor() -> None:
    rng = np.random.default_rng(3)
    world_R_lidar = pose(pitch=40.0)[:3, :3]  # beyond max_tilt_deg from the LiDAR's own z
    scan = street(rng) @ world_R_lidar
    truth = world_R_lidar.T @ np.array([0.0, 0.0, 1.0])
    guided = estimate_up(scan, prior_up=world_R_lidar.T @ pose(pitch=3.0)[:3, :3] @ np.array([0.0, 0.0, 1.0]))
    assert guided is not None and angle_deg(guided.up, truth) < 0.1


@pytest.mark.parametrize("make, message", [
    (lambda: estimate_up(np.zeros((10, 2))), r"xyz of shape \(10, 2\); expected N x 3"),
    (lambda: estimate_up(np.zeros((10, 3)), prior_up=np.zeros(3)), r"prior_up=array.*expected a finite non-zero"),
    (lambda: UpConfig(voxel=-1.0), r"up\.voxel=-1\.0; accepted: 0 <= voxel <= 5"),
    (lambda: UpConfig(neighbours=2), r"up\.neighbours=2; accepted: an integer 3\.\.200"),
    (lambda: UpConfig(max_tilt_deg=90.0), r"up\.max_tilt_deg=90\.0; accepted: 0 < max_tilt_deg < 90"),
    (lambda: UpConfig(min_range=5.0, max_range=2.0), r"up\.max_range=2\.0 <= up\.min_range=5\.0"),
    (lambda: UpConfig(enabled="yes"), r"up\.enabled='yes'; expected true or false"),  # type: ignore[arg-type]
])
def test_bad_input_and_options_are_refused_naming_the_value(make: object, message: str) -> None:
    with pytest.raises(InvalidValueError, match=message):
        make()  # type: ignore[operator]


def test_real_spinning_scans_agree_on_their_up() -> None:
    """Four real KITTI-00 HDL-64 scans within 15 frames of one another: the car hardly tilts between them."""
    folder = shared_path("data", "kitti00")
    files = sorted(folder.glob("*.bin")) if folder.is_dir() else []
    if len(files) < 4:
        pytest.skip("../shared/data/kitti00 is not here")
    ups = []
    for f in files[:4]:
        found = estimate_up(np.fromfile(f, np.float32).reshape(-1, 4)[:, :3])
        assert found is not None and found.walls > 1000
        ups.append(found.up)
    assert max(angle_deg(a, b) for a in ups for b in ups) < 1.5  # 1.1 measured (a starting car pitches too)
    assert all(angle_deg(u, np.array([0.0, 0.0, 1.0])) < 3.0 for u in ups)  # a level-mounted LiDAR on a road
