"""Scoring published loops against ground truth, and the pose-graph proof, on hand-made drives."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from lcpr_core.errors import InputShapeError, LcprError
from lcpr_core.loop_report import (
    PoseGraphProof,
    PublishedLoop,
    covariance_lidar_to_body,
    loop_pose_right,
    pose_graph_proof,
    pose_right,
    score_loops,
    verified_loop_right,
)
from lcpr_core.posegraph import DriftModel, lidar_to_body
from trajectory_fixtures import pose, square_laps

# 10 cm, 0.5 deg roll/pitch, 1 deg yaw (x, y, z, roll, pitch, yaw)
LOOP_COV = np.diag([0.1**2, 0.1**2, 0.05**2, math.radians(0.5) ** 2, math.radians(0.5) ** 2, math.radians(1.0) ** 2])


def rel(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.linalg.inv(a) @ b


# ------------------------------------------------------------------ score_loops
def hand_drive() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """7 keyframes on the x axis; 3, 4 and 6 revisit 0, 1 and 2 (1 m off); 5 is a new place."""
    x = np.array([0.0, 10.0, 20.0, 1.0, 11.0, 50.0, 21.0])
    yaw = np.array([0.0, 0.0, 0.0, 180.0, 170.0, 0.0, 90.0])
    world_T_lidar = np.stack([pose(xi, 0.0, 0.5, yaw=y) for xi, y in zip(x, yaw, strict=True)])
    has_revisit = np.array([False, False, False, True, True, False, True])
    return world_T_lidar[:, :3, 3].copy(), world_T_lidar, has_revisit


def off_by(truth_rel: np.ndarray, shift: tuple[float, float, float], yaw_deg: float) -> np.ndarray:
    """An estimate ``shift`` metres and ``yaw_deg`` degrees away from ``truth_rel``."""
    est = truth_rel.copy()
    est[:3, :3] = truth_rel[:3, :3] @ pose(yaw=yaw_deg)[:3, :3]
    est[:3, 3] += shift
    return est


def test_score_loops_gives_the_hand_computed_precision_recall_and_pose_errors() -> None:
    positions, world_T_lidar, has_revisit = hand_drive()
    loops = [
        PublishedLoop(3, 0, off_by(rel(world_T_lidar[0], world_T_lidar[3]), (0.1, 0.0, 0.0), 1.0), LOOP_COV),
        PublishedLoop(4, 1, off_by(rel(world_T_lidar[1], world_T_lidar[4]), (0.0, 0.3, 0.0), -3.0), None),
        PublishedLoop(4, 1),  # the same revisit again, without a pose: closes nothing new, no error
        PublishedLoop(5, 2, off_by(rel(world_T_lidar[2], world_T_lidar[5]), (5.0, 0.0, 0.0), 40.0)),  # 30 m off
    ]
    score = score_loops(loops, positions=positions, world_T_lidar=world_T_lidar, has_revisit=has_revisit, radius=5.0)
    assert (score.loops, score.correct, score.closed, score.true_revisits, score.posed) == (4, 3, 2, 3, 2)
    assert score.precision == pytest.approx(0.75) and score.recall == pytest.approx(2 / 3)
    # errors (0.1 m, 1 deg) and (0.3 m, 3 deg); the wrong loop's are not counted
    assert score.trans_err_median == pytest.approx(0.2) and score.trans_err_p95 == pytest.approx(0.29)
    assert score.yaw_err_median == pytest.approx(2.0) and score.yaw_err_p95 == pytest.approx(2.9)
    data = score.to_dict()
    assert data["precision"] == pytest.approx(0.75) and data["closed"] == 2

    no_truth = score_loops(loops, positions=positions, world_T_lidar=None, has_revisit=has_revisit, radius=5.0)
    assert no_truth.correct == 3 and no_truth.trans_err_median is None and no_truth.posed == 0
    # a radius of 9 m: 5 -> 2 is still 30 m off, 4 -> 1 and 3 -> 0 stay correct
    assert score_loops(loops, positions=positions, world_T_lidar=None, has_revisit=has_revisit,
                       radius=9.0).correct == 3


def test_a_loop_beyond_the_radius_with_the_true_relative_pose_is_counted_as_a_valid_constraint() -> None:
    positions, world_T_lidar, has_revisit = hand_drive()
    true_far = PublishedLoop(5, 2, rel(world_T_lidar[2], world_T_lidar[5]))  # 30 m apart, pose exact
    wrong_far = PublishedLoop(5, 1, off_by(rel(world_T_lidar[1], world_T_lidar[5]), (1.0, 0.0, 0.0), 0.0))
    score = score_loops([true_far, wrong_far], positions=positions, world_T_lidar=world_T_lidar,
                        has_revisit=has_revisit, radius=5.0)
    assert (score.correct, score.wrong_with_true_pose) == (0, 1)


def test_verified_loops_fall_in_three_groups_by_pose_and_their_precision_counts_the_right_poses() -> None:
    positions, world_T_lidar, has_revisit = hand_drive()
    loops = [
        PublishedLoop(3, 0, rel(world_T_lidar[0], world_T_lidar[3])),  # 1 m apart, right pose
        PublishedLoop(5, 2, rel(world_T_lidar[2], world_T_lidar[5])),  # 30 m apart, right pose: a valid constraint
        PublishedLoop(6, 2, off_by(rel(world_T_lidar[2], world_T_lidar[6]), (1.0, 0.0, 0.0), 0.0)),  # 1 m, pose off
        PublishedLoop(4, 1),  # 1 m apart, no pose: in no group, and not right
    ]
    score = score_loops(loops, positions=positions, world_T_lidar=world_T_lidar, has_revisit=has_revisit, radius=5.0)
    assert (score.right_within_radius, score.right_beyond_radius, score.wrong_pose, score.unjudged) == (1, 1, 1, 1)
    assert score.precision_by_pose == pytest.approx(0.5) and score.headline_precision == pytest.approx(0.5)
    assert score.correct == 3 and score.precision == pytest.approx(0.75)  # the radius rule, kept beside it
    assert score.wrong_with_true_pose == 1
    data = score.to_dict()
    assert (data["right_within_radius"], data["right_beyond_radius"], data["wrong_pose"]) == (1, 1, 1)
    assert score.groups_text(5.0) == ("1 right pose within 5 m, 1 right pose beyond 5 m (a valid constraint), "
                                      "1 wrong pose, 1 without a pose to judge")
    right = verified_loop_right(loops, positions=positions, world_T_lidar=world_T_lidar, radius=5.0)
    assert right.tolist() == [True, True, False, False]


def test_loops_without_a_pose_to_judge_are_judged_by_the_radius_rule_alone() -> None:
    positions, world_T_lidar, has_revisit = hand_drive()
    loops = [PublishedLoop(3, 0), PublishedLoop(5, 2)]  # retrieval alone: no pose
    score = score_loops(loops, positions=positions, world_T_lidar=world_T_lidar, has_revisit=has_revisit, radius=5.0)
    assert score.precision_by_pose is None and not score.judged_by_pose and score.unjudged == 2
    assert score.headline_precision == pytest.approx(0.5) and score.groups_text(5.0) == "1 within 5 m, 1 beyond"
    posed = [PublishedLoop(3, 0, rel(world_T_lidar[0], world_T_lidar[3])), PublishedLoop(5, 2, np.eye(4))]
    no_truth = score_loops(posed, positions=positions, world_T_lidar=None, has_revisit=has_revisit, radius=5.0)
    assert no_truth.precision_by_pose is None and no_truth.headline_precision == pytest.approx(0.5)
    assert verified_loop_right(posed, positions=positions, world_T_lidar=None, radius=5.0).tolist() == [True, False]


def test_a_pose_is_right_within_the_tolerance_of_translation_and_of_the_whole_rotation_angle() -> None:
    truth = pose(2.0, 1.0, 0.0, yaw=30.0)
    assert pose_right(off_by(truth, (0.29, 0.0, 0.0), 1.9), truth)
    assert not pose_right(off_by(truth, (0.31, 0.0, 0.0), 0.0), truth)
    assert not pose_right(off_by(truth, (0.0, 0.0, 0.0), 2.1), truth)
    tilted = truth @ pose(pitch=3.0)  # the yaw is right, the sensor tilted: a pose graph would be bent by it
    assert not pose_right(tilted, truth)
    positions, world_T_lidar, _ = hand_drive()
    world_T_lidar[0] = np.nan  # keyframe 0's true pose is unknown: 3 -> 0 cannot be judged
    assert loop_pose_right([PublishedLoop(3, 0, np.eye(4)), PublishedLoop(5, 2, np.eye(4))], world_T_lidar) == [
        None, False]


def test_score_loops_without_loops_or_revisits_and_with_unknown_positions() -> None:
    positions, world_T_lidar, has_revisit = hand_drive()
    empty = score_loops([], positions=positions, world_T_lidar=world_T_lidar, has_revisit=has_revisit, radius=5.0)
    assert empty.loops == 0 and empty.precision is None and empty.recall == 0.0 and empty.yaw_err_p95 is None
    none = score_loops([PublishedLoop(3, 0)], positions=positions, world_T_lidar=None,
                       has_revisit=np.zeros(7, bool), radius=5.0)
    assert none.recall is None and none.precision == 1.0
    positions[0] = np.nan  # keyframe 0's position is unknown: 3 -> 0 cannot be correct
    assert score_loops([PublishedLoop(3, 0)], positions=positions, world_T_lidar=None, has_revisit=has_revisit,
                       radius=5.0).correct == 0


def test_score_loops_refuses_indices_and_shapes_it_cannot_use() -> None:
    positions, world_T_lidar, has_revisit = hand_drive()
    with pytest.raises(InputShapeError, match=r"loops\[0\].match=7"):
        score_loops([PublishedLoop(3, 7)], positions=positions, world_T_lidar=None, has_revisit=has_revisit,
                    radius=5.0)
    with pytest.raises(InputShapeError, match="has_revisit"):
        score_loops([], positions=positions, world_T_lidar=None, has_revisit=has_revisit[:3], radius=5.0)
    with pytest.raises(ValueError, match="radius=0"):
        score_loops([PublishedLoop(3, 0)], positions=positions, world_T_lidar=None, has_revisit=has_revisit,
                    radius=0)


# ------------------------------------------------------------------ covariance in the body frame
def test_the_covariance_follows_the_pose_from_the_lidar_to_the_body_frame() -> None:
    """Against finite differences of lidar_to_body under the (x, y, z, roll, pitch, yaw) convention."""
    from lcpr_core.geometry import so3_exp

    rng = np.random.default_rng(1)
    ext, x = pose(0.9, 0.1, 1.8, yaw=-90.0), pose(3.0, -2.0, 0.2, yaw=35.0)
    ext[:3, :3] = ext[:3, :3] @ so3_exp(np.array([0.02, -0.01, 0.0]))
    y = lidar_to_body(x, ext)
    jac = np.zeros((6, 6))
    eps = 1e-6
    for i in range(6):
        d = np.zeros(6)
        d[i] = eps
        xp = x.copy()
        xp[:3, :3] = so3_exp(d[3:]) @ x[:3, :3]
        xp[:3, 3] += d[:3]
        yp = lidar_to_body(xp, ext)
        r = yp[:3, :3] @ y[:3, :3].T
        dtheta = np.array([r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]]) / 2  # small-angle log
        jac[:, i] = np.r_[yp[:3, 3] - y[:3, 3], dtheta] / eps
    cov = np.diag(rng.uniform(0.1, 1.0, 6))
    np.testing.assert_allclose(covariance_lidar_to_body(cov, x, ext), jac @ cov @ jac.T, atol=1e-5)


# ------------------------------------------------------------------ the pose-graph proof
def test_true_loops_bring_the_drifted_square_back_to_the_truth(tmp_path: Path) -> None:
    pytest.importorskip("gtsam")
    truth, per_lap = square_laps()
    body_T_lidar = pose(0.94, 0.0, 1.84, yaw=90.0)  # a nuScenes-like mount: x right, y forward
    world_T_lidar = truth @ body_T_lidar
    # each keyframe of a later lap matched to the next keyframe one lap earlier (2 m ahead, around
    # corners also turned): a relative pose that only fits in the body frame after lidar_to_body
    loops = [PublishedLoop(q, q - per_lap + 1, rel(world_T_lidar[q - per_lap + 1], world_T_lidar[q]), LOOP_COV)
             for q in range(per_lap, len(truth) - 1)]
    loops.append(PublishedLoop(len(truth) - 1, 0))  # no pose: skipped
    png = tmp_path / "posegraph.png"
    proof = pose_graph_proof(truth, loops, body_T_lidar=body_T_lidar, plot=png, title="square")
    assert isinstance(proof, PoseGraphProof) and proof.drift == DriftModel(seed=0)
    assert proof.loops_used == len(loops) - 1 and proof.loops_skipped == 1
    assert proof.ate_drifted > 0.5, "the drift should be visible on 400 m"
    assert proof.ratio < 0.3 and proof.ratio == pytest.approx(proof.ate_corrected / proof.ate_drifted)
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    data = proof.to_dict()
    assert data["loops_used"] == proof.loops_used and data["drift"]["seed"] == 0 and data["poses"] == len(truth)

    # the same loops read as body-frame poses (the mount ignored) pull the graph the wrong way
    assert pose_graph_proof(truth, loops, body_T_lidar=np.eye(4)).ratio > 0.5
    # without loops the graph is the odometry: nothing gained
    alone = pose_graph_proof(truth, [], body_T_lidar=body_T_lidar)
    assert alone.loops_used == 0 and alone.ratio == pytest.approx(1.0, abs=1e-3)


def test_drift_before_the_first_revisit_stays_in_the_ate_from_the_first_pose_but_not_in_the_aligned_one() -> None:
    pytest.importorskip("gtsam")
    laps, per_lap = square_laps(laps=3)
    approach = np.stack([pose(-150.0 + 2.0 * i, 0.0) for i in range(75)])  # 150 m driven once, then the laps
    truth = np.concatenate([approach, laps])
    loops = [PublishedLoop(q, q - per_lap + 1, rel(truth[q - per_lap + 1], truth[q]), LOOP_COV)
             for q in range(len(approach) + per_lap, len(truth) - 1)]
    proof = pose_graph_proof(truth, loops, body_T_lidar=np.eye(4))
    # the heading drifted on the approach turns the laps as a whole: loops cannot see that
    assert proof.ratio > 0.7
    # the laps made consistent again: most of the aligned error is gone
    assert proof.ate_corrected_aligned < 0.5 * proof.ate_drifted_aligned
    assert proof.ate_drifted_aligned <= proof.ate_drifted and proof.ate_corrected_aligned <= proof.ate_corrected
    assert "aligned" in proof.text() and proof.to_dict()["ate_corrected_aligned"] == proof.ate_corrected_aligned


def test_pose_graph_proof_raises_the_library_error_for_bad_loops() -> None:
    pytest.importorskip("gtsam")
    truth, _ = square_laps(laps=1)
    with pytest.raises(LcprError, match="expected two different keyframes"):
        pose_graph_proof(truth, [PublishedLoop(3, 3, np.eye(4), LOOP_COV)], body_T_lidar=np.eye(4))
