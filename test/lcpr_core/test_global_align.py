"""The global initial alignment (KISS-Matcher): a turned and shifted cloud is found again from no guess."""
from __future__ import annotations

import math
import re
import sys

import numpy as np
import pytest

from lcpr_core.errors import VerificationError
from lcpr_core.verification.global_align import GlobalAlignConfig, GlobalAlignment, global_alignment


def structured_scene(seed: int) -> np.ndarray:
    """N x 3 points on a street-like scene: ground, building walls, boxes and poles at seeded places."""
    rng = np.random.default_rng(seed)
    parts = [np.column_stack([rng.uniform(-30, 30, 6000), rng.uniform(-30, 30, 6000), rng.normal(0, 0.02, 6000)])]
    for _ in range(10):  # boxes: the four sides and the top
        cx, cy = rng.uniform(-25, 25, 2)
        sx, sy, sz = rng.uniform(1.5, 6.0), rng.uniform(1.5, 6.0), rng.uniform(1.0, 6.0)
        n = 600
        u, v = rng.uniform(-0.5, 0.5, n), rng.uniform(0, 1, n)
        side = rng.integers(0, 5, n)
        x = np.where(side == 0, -0.5, np.where(side == 1, 0.5, u)) * sx
        y = np.where(side == 2, -0.5, np.where(side == 3, 0.5, np.where(side < 2, u, rng.uniform(-0.5, 0.5, n)))) * sy
        z = np.where(side == 4, 1.0, v) * sz
        parts.append(np.column_stack([x + cx, y + cy, z]))
    for _ in range(15):  # poles
        cx, cy = rng.uniform(-28, 28, 2)
        a, h = rng.uniform(0, 2 * math.pi, 150), rng.uniform(0, rng.uniform(3, 8), 150)
        parts.append(np.column_stack([cx + 0.2 * np.cos(a), cy + 0.2 * np.sin(a), h]))
    return np.concatenate(parts)


def moved(points: np.ndarray, yaw_deg: float, shift: tuple[float, float, float]) -> tuple[np.ndarray, np.ndarray]:
    """(points seen from a sensor turned by yaw_deg and moved by shift, match_T_query mapping them back)."""
    c, s = math.cos(math.radians(yaw_deg)), math.sin(math.radians(yaw_deg))
    match_T_query = np.eye(4)
    match_T_query[:3, :3] = [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]
    match_T_query[:3, 3] = shift
    query_T_match = np.linalg.inv(match_T_query)
    return points @ query_T_match[:3, :3].T + query_T_match[:3, 3], match_T_query


def pose_errors(T: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    """(translation m, rotation deg) between two 4 x 4 poses."""
    cos = (np.trace(truth[:3, :3].T @ T[:3, :3]) - 1.0) / 2.0
    return float(np.linalg.norm(T[:3, 3] - truth[:3, 3])), math.degrees(math.acos(min(max(cos, -1.0), 1.0)))


def test_a_turned_and_shifted_cloud_is_found_again_from_no_guess():
    pytest.importorskip("kiss_matcher")
    match = structured_scene(0)
    query, truth = moved(structured_scene(0)[::-1], 137.0, (3.0, -2.0, 0.1))
    # the 60 m scene keeps ~6000 points at 0.8 m, more than a Livox view: no coarser voxel for it here
    found = global_alignment(query, match, config=GlobalAlignConfig(max_points=10000))
    assert isinstance(found, GlobalAlignment) and found.valid and found.inliers >= 5
    assert found.voxel == pytest.approx(0.8)
    err_m, err_deg = pose_errors(found.match_T_query, truth)
    assert err_m < 0.2 and err_deg < 2.0, (err_m, err_deg)
    assert found.match_T_query.shape == (4, 4) and found.match_T_query.dtype == np.float64
    assert found.seconds > 0.0


def test_a_large_cloud_is_aligned_at_a_coarser_voxel_still_close_enough_to_start_registration():
    pytest.importorskip("kiss_matcher")
    match = structured_scene(0)
    query, truth = moved(structured_scene(0)[::-1], 40.0, (3.0, -2.0, 0.1))
    found = global_alignment(query, match, config=GlobalAlignConfig(max_points=2000))
    assert found.voxel > 1.0 and found.valid
    err_m, err_deg = pose_errors(found.match_T_query, truth)
    assert err_m < 1.5 and err_deg < 10.0, (err_m, err_deg)  # the coarse stage's reach


def test_a_cloud_of_fewer_than_three_points_gives_no_valid_start():
    pytest.importorskip("kiss_matcher")
    found = global_alignment(np.zeros((2, 3)), structured_scene(1))
    assert not found.valid and found.inliers == 0 and np.array_equal(found.match_T_query, np.eye(4))


def test_points_that_are_not_n_by_three_are_refused_naming_the_argument():
    with pytest.raises(VerificationError, match="query_xyz of shape \\(5,\\)"):
        global_alignment(np.zeros(5), np.zeros((10, 3)))


@pytest.mark.parametrize(("field", "value"), [
    ("method", "ransac"), ("voxel", 0.0), ("voxel", -0.4), ("voxel", float("nan")), ("normal_gain", 0),
    ("fpfh_gain", 2.0), ("max_correspondences", 2), ("min_inliers", 2.5), ("use_quatro", "yes"),
])
def test_a_bad_setting_is_refused_naming_the_value(field: str, value: object):
    with pytest.raises(VerificationError, match=re.escape(f"global_align.{field}={value!r}")):
        GlobalAlignConfig(**{field: value})  # type: ignore[arg-type]


def test_without_kiss_matcher_the_error_says_how_to_install_it(monkeypatch: pytest.MonkeyPatch):
    monkeypatch.setitem(sys.modules, "kiss_matcher", None)  # import kiss_matcher now raises ImportError
    with pytest.raises(VerificationError, match="pip install kiss-matcher"):
        global_alignment(structured_scene(2), structured_scene(2))
