"""KISS-ICP on a synthetic drive's own LiDAR (lcpr_offline.drive_odometry): the dense drive and its stream."""
from __future__ import annotations

import numpy as np
import pytest

from citysim import SynthConfig, SyntheticDrive
from lcpr_core.errors import InvalidValueError

pytest.importorskip("kiss_icp")


@pytest.fixture(scope="module")
def drive() -> SyntheticDrive:
    return SyntheticDrive(SynthConfig(rig="nuscenes", frames=4, seed=7, image_size=(64, 32)))  # 15 m, 5 m apart


def test_the_dense_drive_holds_every_keyframe_of_the_drive_at_the_same_stamp_and_pose(drive: SyntheticDrive) -> None:
    from lcpr_offline.drive_odometry import dense_drive

    dense = dense_drive(drive, spacing=1.0)
    assert len(dense) == 16 and dense.world is drive.world and dense.path is drive.path
    for k in range(len(drive)):
        assert dense.keyframes.stamps[5 * k] == pytest.approx(drive.keyframes.stamps[k], abs=1e-9)
        np.testing.assert_allclose(dense.pose(5 * k), drive.pose(k), atol=1e-9)
    with pytest.raises(InvalidValueError, match="spacing=0"):
        dense_drive(drive, spacing=0)


def test_kiss_icp_follows_the_dense_drive_and_the_node_s_loops_attach_to_its_keyframes(drive: SyntheticDrive) -> None:
    from lcpr_core.backend.replay import trajectory_error
    from lcpr_offline.drive_odometry import dense_drive, record_drive

    dense = dense_drive(drive, spacing=1.0)
    stream = record_drive(dense, every=5, progress=False)
    assert stream.keyframes.tolist() == [0, 5, 10, 15] and len(stream.loops) == 0
    np.testing.assert_allclose(stream.odometry[0], drive.pose(0), atol=1e-9)  # started at the true first pose
    assert trajectory_error(stream.odometry, stream.truth).rmse < 0.5  # 15 m of city: KISS-ICP keeps up
    loop = (float(drive.keyframes.stamps[3]) + 1e-7, float(drive.keyframes.stamps[0]), np.eye(4), None)
    ghost = (float(drive.keyframes.stamps[3]) + 0.3, float(drive.keyframes.stamps[0]), np.eye(4), None)
    with_loops, skipped = stream.with_loops([loop, ghost])
    assert skipped == 1 and with_loops.loops.tolist() == [[15, 0]]
    assert np.isnan(with_loops.loop_cov[0]).all()  # no covariance: the back end's default
    with pytest.raises(InvalidValueError, match="every=0"):
        record_drive(dense, every=0)
