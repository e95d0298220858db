"""lcpr_demo --odometry kiss-icp: KISS-ICP on the demo drive's own LiDAR, corrected with the node's verified rows."""
from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

pytest.importorskip("gtsam")
pytest.importorskip("kiss_icp")
pytest.importorskip("rclpy")

from lcpr_core.detector import Candidate  # noqa: E402
from lcpr_ros.demo import demo_drive, kiss_icp_backend, parse_args  # noqa: E402
from lcpr_ros.outputs import CANDIDATE_COLUMNS, _row  # noqa: E402


def row(drive, q: int, m: int, *, verified: bool, offset: float = 0.0) -> dict[str, float]:
    """A parsed ~/candidates row of keyframes q -> m at their true relative LiDAR pose."""
    ext = np.asarray(drive.rig.lidar.base_T_lidar)
    rel = np.linalg.inv(drive.pose(m) @ ext) @ drive.pose(q) @ ext
    c = Candidate(query_id=q, match_id=m, query_stamp=float(drive.keyframes.stamps[q]) + offset,
                  match_stamp=float(drive.keyframes.stamps[m]), distance=0.2, rank=0, match_position=None,
                  degraded=False, verified=verified, fitness=0.8, match_T_query=rel,
                  covariance=np.diag([0.02**2] * 3 + [np.radians(0.2) ** 2] * 3))
    return dict(zip(CANDIDATE_COLUMNS, _row(c), strict=True))


def test_the_demo_s_odometry_mode_defaults_to_the_seeded_drift() -> None:
    assert parse_args([]).odometry == "drift"
    assert parse_args(["--odometry", "kiss-icp"]).odometry == "kiss-icp"
    with pytest.raises(SystemExit):
        parse_args(["--odometry", "wheels"])


def test_kiss_icp_on_the_demo_drive_takes_the_node_s_verified_rows_as_loops_and_its_ups(tmp_path: Path) -> None:
    args = parse_args(["--frames", "4", "--image-size", "64x32", "--odometry", "kiss-icp", "--out", str(tmp_path)])
    drive = demo_drive(args)  # 4 keyframes 5 m apart: 16 LiDAR frames 1 m apart for KISS-ICP
    up = (drive.pose(1) @ drive.rig.lidar.base_T_lidar)[:3, :3].T @ np.array([0.0, 0.0, 1.0])
    out = SimpleNamespace(candidates=[[row(drive, 3, 0, verified=True), row(drive, 3, 1, verified=False)],
                                      [row(drive, 2, 0, verified=True, offset=0.3)]],  # a stamp no frame has
                          ups=[(float(drive.keyframes.stamps[1]), up)])  # the node's ~/up of keyframe 1
    evaluation, skipped = kiss_icp_backend(args, out)
    assert skipped == 1  # the row 0.3 s off every frame
    assert evaluation.stream.loops.tolist() == [[15, 0]]  # keyframe 3 is LiDAR frame 15; the unverified row left out
    np.testing.assert_allclose(evaluation.stream.ups[1], up)  # the stream's keyframes: every 5th LiDAR frame
    assert np.isnan(evaluation.stream.ups[[0, 2, 3]]).all()
    summary = evaluation.to_dict()
    assert summary["frames"] == 16 and summary["loops_accepted"] == 1
    assert summary["ate_backend"]["rmse"] <= summary["ate_odometry"]["rmse"] + 0.01
