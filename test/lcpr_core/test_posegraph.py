"""Drifted odometry, loop constraints and what a GTSAM pose graph makes of them."""
from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import pytest

from lcpr_core.errors import LcprError, PoseGraphError
from lcpr_core.posegraph import (
    DriftModel,
    LoopConstraint,
    PoseGraphConfig,
    ate_rmse,
    drift_odometry,
    lidar_to_body,
    optimize_pose_graph,
    plot_trajectories,
    relative_pose_error,
    rotation_error_deg,
    to_gtsam_covariance,
    yaw_deg,
)
from trajectory_fixtures import pose, square_laps

# A verified ICP loop closure: 10 cm, 0.5 deg roll/pitch, 1 deg yaw (x, y, z, roll, pitch, yaw).
LOOP_COV = np.diag([0.1**2, 0.1**2, 0.05**2, math.radians(0.5) ** 2, math.radians(0.5) ** 2, math.radians(1.0) ** 2])


def straight(length_m: float, step_m: float = 1.0) -> np.ndarray:
    n = int(round(length_m / step_m)) + 1
    return np.stack([pose(i * step_m) for i in range(n)])


def true_loops(truth: np.ndarray, per_lap: int, *, every: int = 1) -> list[LoopConstraint]:
    """Each keyframe of a later lap matched to the same place one lap earlier, with its TRUE relative pose."""
    return [
        LoopConstraint(query=q, match=q - per_lap, match_T_query=np.linalg.inv(truth[q - per_lap]) @ truth[q],
                       covariance=LOOP_COV)
        for q in range(per_lap, len(truth), every)
    ]


# ============================================================================ drift
def test_drift_is_reproducible_for_a_seed_and_differs_across_seeds() -> None:
    truth = straight(100.0)
    a, cov_a = drift_odometry(truth, model=DriftModel(seed=3))
    b, cov_b = drift_odometry(truth, model=DriftModel(seed=3))
    c, _ = drift_odometry(truth, model=DriftModel(seed=4))
    np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(cov_a, cov_b)
    assert np.abs(a[-1, :3, 3] - c[-1, :3, 3]).max() > 1e-3


def test_drift_starts_at_the_truth_with_one_covariance_per_step_scaled_by_its_length() -> None:
    truth = np.stack([pose(0.0), pose(1.0), pose(3.0), pose(3.0)])  # steps of 1 m, 2 m, 0 m
    model = DriftModel()
    drifted, covs = drift_odometry(truth, model=model)
    assert drifted.shape == (4, 4, 4) and covs.shape == (3, 6, 6)
    np.testing.assert_array_equal(drifted[0], truth[0])
    sigmas = np.sqrt(np.diagonal(covs, axis1=1, axis2=2))  # (3, 6)
    assert sigmas[0, 0] == pytest.approx(model.translation_frac * 1.0)
    assert sigmas[1, 0] == pytest.approx(model.translation_frac * 2.0)
    assert sigmas[1, 5] == pytest.approx(math.radians(model.yaw_deg_per_m) * math.sqrt(2.0))  # heading random walk
    assert sigmas[2, 0] == pytest.approx(model.translation_frac * 0.01)  # standing still: a 1 cm step's noise
    for d in drifted:  # still rigid transforms
        np.testing.assert_allclose(d[:3, :3].T @ d[:3, :3], np.eye(3), atol=1e-12)


def test_drift_grows_with_distance() -> None:
    short, long_ = straight(50.0), straight(400.0)
    for seed in range(5):
        model = DriftModel(seed=seed)
        long_ate = ate_rmse(drift_odometry(long_, model=model)[0], long_)
        assert long_ate > ate_rmse(drift_odometry(short, model=model)[0], short)


def test_default_drift_ends_about_one_to_two_percent_of_a_few_hundred_metres_away() -> None:
    truth = straight(300.0)
    ends = [np.linalg.norm(drift_odometry(truth, model=DriftModel(seed=s))[0][-1, :3, 3] - truth[-1, :3, 3])
            for s in range(20)]
    assert 0.008 <= np.mean(ends) / 300.0 <= 0.022  # seed groups of 20 range over 1.0-1.9 %


# ============================================================================ pose graph
def test_loops_with_true_relative_poses_remove_most_of_the_drift() -> None:
    pytest.importorskip("gtsam")
    truth, per_lap = square_laps()  # 201 poses, 2 m steps, back at the start four times
    loops = true_loops(truth, per_lap)
    before, after = [], []
    for seed in range(5):
        drifted, covs = drift_odometry(truth, model=DriftModel(seed=seed))
        result = optimize_pose_graph(drifted, covs, loops)
        before.append(ate_rmse(drifted, truth))
        after.append(ate_rmse(result.optimized, truth))
        assert result.final_error < result.initial_error
        assert after[-1] < 0.7 * before[-1]  # every drive gains
        np.testing.assert_allclose(result.optimized[0], truth[0], atol=1e-2)  # anchored at the start
    pooled_before, pooled_after = np.sqrt(np.mean(np.square(before))), np.sqrt(np.mean(np.square(after)))
    assert pooled_after <= 0.3 * pooled_before, (before, after)


def test_a_wrong_loop_is_suppressed_by_the_robust_kernel_but_not_without_one() -> None:
    pytest.importorskip("gtsam")
    truth, per_lap = square_laps()
    drifted, covs = drift_odometry(truth, model=DriftModel(seed=0))
    loops = true_loops(truth, per_lap, every=5)
    query = 2 * per_lap + 12  # third lap, 24 m along the first side
    far = np.linalg.norm(truth[:per_lap, :3, 3] - truth[query, :3, 3], axis=1)
    match = int(np.argmin(np.abs(far - 30.0)))  # a first-lap keyframe 30 m away ...
    assert far[match] == pytest.approx(30.0, abs=1.0)
    # ... given the relative pose of the true revisit, as a false place match would be
    wrong = LoopConstraint(query=query, match=match, covariance=LOOP_COV,
                           match_T_query=np.linalg.inv(truth[query - 2 * per_lap]) @ truth[query])

    def ate(with_loops: list[LoopConstraint], robust: str = "cauchy") -> float:
        result = optimize_pose_graph(drifted, covs, with_loops, config=PoseGraphConfig(robust=robust))
        return ate_rmse(result.optimized, truth)

    clean, robust = ate(loops), ate([*loops, wrong])
    plain, huber = ate([*loops, wrong], "none"), ate([*loops, wrong], "huber")
    assert robust <= 1.5 * clean
    assert huber <= 1.5 * clean
    assert plain > 3.0 * robust
    assert plain > ate_rmse(drifted, truth)  # one unchecked wrong loop is worse than no loop closure at all


def test_without_loops_the_optimum_is_the_odometry() -> None:
    pytest.importorskip("gtsam")
    truth = straight(30.0)
    drifted, covs = drift_odometry(truth, model=DriftModel(seed=1))
    result = optimize_pose_graph(drifted, covs, [])
    np.testing.assert_allclose(result.optimized, drifted, atol=1e-6)
    assert result.final_error == pytest.approx(0.0, abs=1e-6)


def test_loop_covariance_is_converted_to_gtsam_tangent_order_and_frame() -> None:
    gtsam = pytest.importorskip("gtsam")
    rel = pose(3.0, -1.0, 0.5, yaw=100.0, roll=15.0, pitch=-10.0)
    a = np.random.default_rng(0).standard_normal((6, 6))
    cov_ros = (a @ a.T + np.eye(6)) * 1e-4  # correlated, small: first order holds
    samples = np.random.default_rng(1).multivariate_normal(np.zeros(6), cov_ros, size=20000)
    measured = gtsam.Pose3(rel)
    xi = np.empty_like(samples)
    for k, (dx, dy, dz, rx, ry, rz) in enumerate(samples):  # ROS perturbation: (Exp(dtheta) R, t + dt)
        perturbed = rel.copy()
        perturbed[:3, :3] = gtsam.Rot3.Expmap(np.array([rx, ry, rz])).matrix() @ rel[:3, :3]
        perturbed[:3, 3] += (dx, dy, dz)
        xi[k] = gtsam.Pose3.Logmap(measured.between(gtsam.Pose3(perturbed)))  # (rot, trans)
    expected = to_gtsam_covariance(cov_ros, rel[:3, :3])
    white = np.linalg.inv(np.linalg.cholesky(expected))
    np.testing.assert_allclose(white @ np.cov(xi.T) @ white.T, np.eye(6), atol=0.06)


def test_an_identity_rotation_only_swaps_translation_and_rotation_blocks() -> None:
    cov = np.diag([1.0, 2.0, 3.0, 4.0, 5.0, 6.0])
    np.testing.assert_allclose(to_gtsam_covariance(cov, np.eye(3)), np.diag([4.0, 5.0, 6.0, 1.0, 2.0, 3.0]))


# ============================================================================ errors and helpers
def test_ate_is_the_rms_position_difference_and_alignment_removes_a_rigid_offset() -> None:
    truth = straight(10.0)
    shifted = truth.copy()
    shifted[:, 1, 3] += 2.0
    assert ate_rmse(shifted, truth) == pytest.approx(2.0)
    assert ate_rmse(truth[:, :3, 3], truth) == 0.0  # positions work too
    moved = np.stack([pose(5.0, -3.0, 1.0, yaw=37.0) @ p for p in truth])
    assert ate_rmse(moved, truth) > 1.0
    assert ate_rmse(moved, truth, align=True) == pytest.approx(0.0, abs=1e-9)


def test_relative_pose_error_of_identical_poses_is_zero() -> None:
    rel = pose(4.0, 1.0, 0.2, yaw=30.0, roll=2.0)
    assert relative_pose_error(rel, rel) == pytest.approx((0.0, 0.0), abs=1e-9)
    assert rotation_error_deg(rel, rel) == pytest.approx(0.0, abs=1e-6)


def test_relative_pose_error_reports_metres_and_yaw_degrees() -> None:
    trans, yaw = relative_pose_error(pose(3.0, 4.0, yaw=10.0), pose(0.0, 0.0, yaw=-5.0))
    assert trans == pytest.approx(5.0)
    assert yaw == pytest.approx(15.0)
    assert yaw_deg(pose(yaw=170.0) @ pose(yaw=20.0)) == pytest.approx(-170.0)
    assert rotation_error_deg(pose(roll=3.0), pose()) == pytest.approx(3.0)


def test_lidar_to_body_round_trips_a_known_extrinsic() -> None:
    body_T_lidar = pose(1.2, 0.0, 1.8, yaw=90.0, pitch=2.0)  # roof LiDAR, mounted sideways
    world_T_match, world_T_query = pose(10.0, 5.0, yaw=20.0), pose(13.0, 6.0, yaw=35.0)
    body_rel = np.linalg.inv(world_T_match) @ world_T_query
    lidar_rel = np.linalg.inv(world_T_match @ body_T_lidar) @ (world_T_query @ body_T_lidar)
    np.testing.assert_allclose(lidar_to_body(lidar_rel, body_T_lidar), body_rel, atol=1e-12)
    np.testing.assert_allclose(lidar_to_body(body_rel, np.eye(4)), body_rel, atol=1e-12)


def test_plot_is_written_as_png_without_leftovers(tmp_path: Path) -> None:
    truth, per_lap = square_laps(laps=2)
    drifted, _ = drift_odometry(truth, model=DriftModel(seed=2))
    loops = true_loops(truth, per_lap, every=10)
    out = tmp_path / "plots" / "posegraph.png"
    plot_trajectories(truth, drifted, truth, out, loops=[*loops[:2], (per_lap + 5, 5)], title="square")
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert [p.name for p in out.parent.iterdir()] == ["posegraph.png"]


# ============================================================================ bad input
def _graph_inputs(n: int = 5) -> tuple[np.ndarray, np.ndarray]:
    return drift_odometry(straight(n - 1.0), model=DriftModel(seed=0))


def test_missing_gtsam_names_the_install_command(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "gtsam", None)  # import gtsam -> ImportError
    with pytest.raises(PoseGraphError, match="pip install gtsam"):
        optimize_pose_graph(*_graph_inputs(), [])


def test_pose_graph_error_is_an_lcpr_error() -> None:
    assert issubclass(PoseGraphError, LcprError)


@pytest.mark.parametrize(
    ("call", "message"),
    [
        (lambda: drift_odometry(np.zeros((5, 3, 3))), r"truth of shape \(5, 3, 3\); expected \(N, 4, 4\)"),
        (lambda: drift_odometry(np.stack([np.eye(4), np.full((4, 4), np.nan)])), "truth holds NaN or inf at pose 1"),
        (lambda: drift_odometry(np.zeros((0, 4, 4))), r"truth of shape \(0, 4, 4\) is empty"),
        (lambda: drift_odometry(np.stack([np.eye(4), 2 * np.eye(4)])), "truth pose 1 is not a rigid transform"),
        (lambda: DriftModel(translation_frac=-0.01), r"translation_frac=-0.01; expected a finite number > 0"),
        (lambda: DriftModel(yaw_deg_per_m=float("nan")), r"yaw_deg_per_m=nan"),
        (lambda: DriftModel(seed=-1), r"seed=-1; expected an integer >= 0"),
        (lambda: PoseGraphConfig(robust="tukey"), r"robust='tukey'; expected one of none, huber, cauchy"),
        (lambda: PoseGraphConfig(robust_param=0.0), r"robust_param=0.0; expected a finite number > 0"),
        (lambda: PoseGraphConfig(prior_sigma=float("inf")), r"prior_sigma=inf"),
        (lambda: LoopConstraint(3, 3, np.eye(4), LOOP_COV), "query = match = 3"),
        (lambda: LoopConstraint(-1, 0, np.eye(4), LOOP_COV), r"query=-1; expected a trajectory index >= 0"),
        (lambda: LoopConstraint(3, 0, np.eye(3), LOOP_COV), r"match_T_query of shape \(3, 3\); expected \(4, 4\)"),
        (lambda: LoopConstraint(3, 0, np.eye(4), np.diag([1.0, 1, 1, 1, 1, -1])),
         "covariance with eigenvalues .* not positive definite"),
        (lambda: LoopConstraint(3, 0, np.eye(4), np.full((6, 6), np.nan)), "covariance holds NaN or inf"),
        (lambda: optimize_pose_graph(*_graph_inputs(), [LoopConstraint(7, 0, np.eye(4), LOOP_COV)]),
         r"loops\[0\].query=7; expected an index into the 5 poses \(0..4\)"),
        (lambda: optimize_pose_graph(_graph_inputs()[0], _graph_inputs()[1][:2], []),
         r"step_covariances of shape \(2, 6, 6\); expected \(4, 6, 6\)"),
        # a wrong type on purpose: the refusal at run time is what is tested
        (lambda: optimize_pose_graph(*_graph_inputs(), [(3, 0)]),  # type: ignore[list-item]
         r"loops\[0\] is a tuple; expected a LoopConstraint"),
        (lambda: ate_rmse(straight(3.0), straight(4.0)), "estimate of 4 and truth of 5 poses"),
        (lambda: lidar_to_body(np.eye(4), np.eye(3)), r"body_T_lidar of shape \(3, 3\)"),
    ],
)
def test_bad_input_is_refused_naming_the_value(call, message: str) -> None:
    with pytest.raises(PoseGraphError, match=message):
        call()


def test_a_stream_drifted_step_by_step_is_the_chain_drift_odometry_makes() -> None:
    from lcpr_core.posegraph import drift_step

    truth = np.stack([np.eye(4)] * 30)
    truth[:, 0, 3] = np.arange(30) * 1.5
    model = DriftModel(seed=4)
    chain, _ = drift_odometry(truth, model=model)
    rng = np.random.default_rng(model.seed)
    streamed = [truth[0]]
    for i in range(1, len(truth)):
        streamed.append(streamed[-1] @ drift_step(np.linalg.inv(truth[i - 1]) @ truth[i], model=model, rng=rng)[0])
    np.testing.assert_allclose(np.stack(streamed), chain, atol=1e-12)
