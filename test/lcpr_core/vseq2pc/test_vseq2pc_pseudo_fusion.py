"""Depth-scale fusion of a pseudo-cloud's frames: each frame's smooth depth error corrected against the others.

Scene: a straight street (facades 8 m either side, the ground 1.7 m below the vehicle origin, a wall across it
40 m on) seen by a forward camera from 12 vehicle poses 1.5 m apart; depth by ray casting, the network-like error
made by citysim's depth model (a smooth relative error per frame, independent between frames).
"""
from __future__ import annotations

import numpy as np
import pytest

from citysim.depthnet import estimated_depth
from lcpr_core.errors import InvalidValueError
from lcpr_core.vseq2pc.pseudo_cloud import PseudoCloudConfig, accumulate, frame_cloud

K = np.array([[200.0, 0.0, 160.0], [0.0, 200.0, 48.0], [0.0, 0.0, 1.0]])
LIDAR_T_CAM = np.array([[0.0, 0.0, 1.0, 0.27], [-1.0, 0.0, 0.0, 0.06], [0.0, -1.0, 0.0, -0.08], [0, 0, 0, 1.0]])
PLANES = ((np.array([0.0, 1.0, 0.0]), 8.0), (np.array([0.0, 1.0, 0.0]), -8.0), (np.array([0.0, 0.0, 1.0]), -1.7),
          (np.array([1.0, 0.0, 0.0]), 40.0))  # n . x = d in the world (the first vehicle frame)


def render(world_T_base: np.ndarray, shape: tuple[int, int] = (96, 320)) -> np.ndarray:
    """H x W exact depth along the optical axis of the scene's nearest plane."""
    T = world_T_base @ LIDAR_T_CAM
    v, u = np.mgrid[0:shape[0], 0:shape[1]]
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones(shape)], axis=-1) @ T[:3, :3].T
    depth = np.full(shape, np.inf)
    for n, d in PLANES:
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (d - n @ T[:3, 3]) / (rays @ n)  # optical depth: rays have optical z = 1
        depth = np.where((t > 0) & (t < depth), t, depth)
    return np.where(np.isfinite(depth), depth, 0.0).astype(np.float32)


def scene_error(points: np.ndarray) -> float:
    """Mean distance (m) of points (query = world frame) to the nearest plane of the scene."""
    return float(np.min([np.abs(points @ n - d) for n, d in PLANES], axis=0).mean())


def frames(noise: float, seed: int = 0) -> list[tuple[np.ndarray, np.ndarray]]:
    rng = np.random.default_rng(seed)
    out = []
    for i in range(12):
        pose = np.eye(4)
        pose[0, 3] = 1.5 * i
        depth = estimated_depth(render(pose), max_depth=0.0, noise=noise, rng=rng)
        out.append((frame_cloud(depth, K, LIDAR_T_CAM), pose))
    return out


@pytest.mark.parametrize("noise", [0.05, 0.1])
def test_fusing_frames_brings_network_like_depth_closer_to_the_surfaces(noise: float) -> None:
    seen = frames(noise)
    stacked = accumulate(seen, query_pose=np.eye(4))
    fused = accumulate(seen, query_pose=np.eye(4), config=PseudoCloudConfig(fuse=True), lidar_T_cam=LIDAR_T_CAM)
    assert len(fused) == len(stacked)
    assert scene_error(fused) < 0.8 * scene_error(stacked)


def test_fusing_frames_of_exact_depth_leaves_them_where_they_are() -> None:
    seen = frames(0.0)
    stacked = accumulate(seen, query_pose=np.eye(4))
    fused = accumulate(seen, query_pose=np.eye(4), config=PseudoCloudConfig(fuse=True), lidar_T_cam=LIDAR_T_CAM)
    assert float(np.linalg.norm(fused - stacked, axis=1).mean()) < 0.03


def test_without_the_camera_extrinsics_frames_are_stacked_as_they_are() -> None:
    seen = frames(0.1)
    np.testing.assert_array_equal(accumulate(seen, query_pose=np.eye(4), config=PseudoCloudConfig(fuse=True)),
                                  accumulate(seen, query_pose=np.eye(4)))


@pytest.mark.parametrize("bad", [{"fuse_radius": 0.0}, {"fuse_cell": -1.0}, {"fuse_iterations": 0}])
def test_a_fusion_setting_out_of_range_is_refused_by_name(bad: dict[str, float]) -> None:
    with pytest.raises(InvalidValueError, match=next(iter(bad))):
        PseudoCloudConfig(**bad)  # type: ignore[arg-type]
