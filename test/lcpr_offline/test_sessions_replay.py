"""A run relocalised in a prior map and two robots merged, on the real walk_loop (its start and its return)."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("gtsam")

from lcpr_core.detector import DetectorConfig  # noqa: E402
from lcpr_core.lcpr.config import ModelConfig  # noqa: E402
from lcpr_core.pretrained import default_weights  # noqa: E402
from lcpr_offline.fleet import Robot, fleet_replay  # noqa: E402
from lcpr_offline.relocalize import Step, build_prior, random_move, relocalize, scan_folder_steps  # noqa: E402


@pytest.fixture(scope="module")
def walk(shared: Path) -> list[Step]:
    folder = shared / "data" / "livox_hku" / "walk_loop"
    if not (folder / "Scans").is_dir():
        pytest.skip(f"{folder} not found")
    return scan_folder_steps(folder)


@pytest.fixture(scope="module")
def detector() -> DetectorConfig:
    weights = default_weights()
    if weights is None:
        pytest.skip("the bundled weights are not installed")
    return DetectorConfig(model=ModelConfig(weights=weights, threads=1))


@pytest.mark.slow
def test_the_return_of_a_walk_is_placed_in_the_map_its_start_left(walk: list[Step], detector: DetectorConfig,
                                                                   tmp_path: Path) -> None:
    prior = build_prior(walk[:60], detector=detector, folder=tmp_path, progress=False)  # the first 20 s
    result = relocalize(prior, walk[255:], detector=detector, move=random_move(3), progress=False)  # the return
    assert result.anchored_s is not None and result.frame_error_at_anchor is not None
    assert result.frame_error_at_anchor[0] < 0.5 and result.frame_error_at_anchor[1] < 3.0
    assert result.ate_m is not None and result.ate_m < 0.5
    assert result.inter_session["anchors"] == 1 and result.loops["within 0.5 m / 3 deg"] > 0


@pytest.mark.slow
def test_two_robots_walking_the_same_ground_at_once_are_merged_into_one_map(walk: list[Step],
                                                                            detector: DetectorConfig) -> None:
    first = walk[:60]
    second = walk[255:]
    start = second[0].reference @ np.linalg.inv(second[0].odometry)  # its odometry restarted, then moved
    second = [Step(s.stamp, s.points, start @ s.odometry, s.reference) for s in second]
    robots = [Robot("robot1", first), Robot("robot2", second, move=random_move(4))]
    result = fleet_replay(robots, detector=detector, progress=False)
    assert result.anchored_at_s["robot2"] is not None
    assert result.merged_ate_m is not None and result.merged_ate_m < 0.5
    loops = result.loops
    assert loops["within 0.5 m / 3 deg"] >= 0.98 * (loops["right"] + loops["wrong"]) > 0
    assert 0 < result.bytes_per_keyframe <= 32 * 1024
