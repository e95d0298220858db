"""A recorded drive replayed through the back end (lcpr_core.backend.replay): streams, false loops, ATE."""
from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("gtsam")

from lcpr_core.backend import BackendConfig, LoopPolicy  # noqa: E402
from lcpr_core.backend.replay import (  # noqa: E402
    FALSE_MIN_M,
    MIN_GAP_S,
    LoopStream,
    StreamRecorder,
    evaluate_backend,
    false_loops,
    replay,
    trajectory_error,
)
from lcpr_core.detector import Candidate, Result  # noqa: E402
from lcpr_core.errors import InvalidValueError  # noqa: E402
from lcpr_core.posegraph import DriftModel, drift_odometry  # noqa: E402
from trajectory_fixtures import pose, square_laps  # noqa: E402

T0 = 1_700_000_000.0
DT = 0.5  # s between frames: 2 m/s at 1 m steps, so a lap of 160 m lasts 80 s (> MIN_GAP_S)
EVERY = 4  # every 4th frame is a detector keyframe
EXT = pose(0.5, 0.0, 1.5, yaw=90.0)  # base_T_lidar: a turned LiDAR above and ahead of the base


def candidate(truth: np.ndarray, stamps: np.ndarray, q: int, m: int) -> Candidate:
    """A verified candidate whose match_T_query is the true one between the LiDAR frames of q and m."""
    lidar = truth @ EXT
    rel = np.linalg.inv(lidar[m]) @ lidar[q]
    return Candidate(query_id=q, match_id=m, query_stamp=float(stamps[q]), match_stamp=float(stamps[m]), distance=0.1,
                     rank=0, match_position=None, degraded=False, verified=True, fitness=0.9, match_T_query=rel,
                     covariance=np.diag([0.02**2] * 3 + [np.radians(0.2) ** 2] * 3), verification="accepted")


def recorded(*, laps: int = 2, seed: int = 3) -> tuple[LoopStream, int]:
    """(a stream of square laps with drifted odometry and true loops on every lap after the first, poses per lap)."""
    truth, per_lap = square_laps(side=40.0, step=1.0, laps=laps)
    drifted, _ = drift_odometry(truth, model=DriftModel(seed=seed))  # within the back end's model
    stamps = T0 + DT * np.arange(len(truth))
    rec = StreamRecorder(base_T_lidar=EXT)
    for i in range(len(truth)):
        rec.add_frame(float(stamps[i]), odometry=drifted[i], truth=truth[i])
        if i % EVERY:
            continue
        loops = [candidate(truth, stamps, i, i - per_lap)] if i >= per_lap else []
        rec.add_result(Result(stamp=float(stamps[i]), keyframe_id=i // EVERY, reason="keyframe", candidates=loops))
    return rec.stream(), per_lap


def test_true_loops_replayed_online_are_all_accepted_and_lower_the_ate() -> None:
    stream, per_lap = recorded()
    assert len(stream.loops) == (len(stream.stamps) - per_lap + EVERY - 1) // EVERY
    run = replay(stream)
    assert run.accepted.all() and run.injected == 0 and run.refused == []
    before, after = trajectory_error(stream.odometry, stream.truth), trajectory_error(run.trajectory, stream.truth)
    assert after.rmse < 0.5 * before.rmse  # the first lap's own drift is left: no loop sees it
    assert run.stats.loops_accepted == len(stream.loops)


def test_injected_false_loops_are_each_counted_as_rejected_or_down_weighted_and_barely_move_the_ate() -> None:
    stream, _ = recorded()
    clean = trajectory_error(replay(stream).trajectory, stream.truth).rmse
    for count in (5, 20):
        run = replay(stream, inject=count, seed=1)
        assert run.injected == count
        assert run.injected_rejected + run.injected_down_weighted == count
        assert trajectory_error(run.trajectory, stream.truth).rmse <= 1.1 * clean
        assert run.accepted.all()  # the true loops still get in


def test_a_false_loop_taken_without_the_check_is_reported_with_its_small_robust_weight() -> None:
    stream, _ = recorded()
    config = BackendConfig(loops=LoopPolicy(gate=1.0))  # no check: the Huber kernel alone
    run = replay(stream, inject=3, seed=2, config=config)
    assert run.injected_rejected == 0 and len(run.injected_weights) == 3
    assert all(0.0 < w < 0.1 for w in run.injected_weights)
    assert run.injected_down_weighted == 3


def test_false_loops_join_keyframes_far_apart_and_old_enough_and_repeat_by_seed() -> None:
    stream, _ = recorded()
    drawn = false_loops(stream, count=20, seed=5)
    pairs = [(q, m) for q, ms in drawn.items() for m in ms]
    assert len(pairs) == 20 and drawn == false_loops(stream, count=20, seed=5)
    keyframes = set(stream.keyframes.tolist())
    for q, m in pairs:
        assert q in keyframes and m in keyframes
        assert stream.stamps[q] - stream.stamps[m] > MIN_GAP_S
        assert np.linalg.norm(stream.truth[q, :3, 3] - stream.truth[m, :3, 3]) > FALSE_MIN_M
    assert false_loops(stream, count=0, seed=5) == {}
    with pytest.raises(InvalidValueError, match="count=-1"):
        false_loops(stream, count=-1, seed=5)


def test_the_ate_is_split_into_horizontal_and_vertical_and_skips_frames_without_a_truth() -> None:
    truth = np.stack([pose(float(x)) for x in range(10)])
    estimate = truth.copy()
    estimate[:, :3, 3] += (3.0, 4.0, 0.0)
    truth[2] = np.nan
    err = trajectory_error(estimate, truth)
    assert err.frames == 9
    assert err.rmse == pytest.approx(5.0) and err.horizontal == pytest.approx(5.0) and err.vertical == 0.0
    assert err.aligned == pytest.approx(0.0, abs=1e-9)  # a shift is what the rigid fit removes
    with pytest.raises(InvalidValueError, match=r"estimate \(10, 4, 4\) and truth \(9, 4, 4\)"):
        trajectory_error(estimate, truth[1:])


def test_a_stream_is_saved_and_loaded_unchanged(tmp_path: Path) -> None:
    stream, _ = recorded(laps=2)
    stream.seconds = {"kiss_icp": 1.5}
    stream.save(tmp_path / "stream.npz")
    back = LoopStream.load(tmp_path / "stream.npz")
    for name in ("stamps", "truth", "odometry", "keyframes", "loops", "loop_T", "loop_cov", "base_T_lidar"):
        np.testing.assert_array_equal(getattr(back, name), getattr(stream, name))
    assert back.seconds == {"kiss_icp": 1.5}


def test_measured_ups_are_recorded_saved_and_replayed_into_the_back_end(tmp_path: Path) -> None:
    stream, _ = recorded(laps=1)
    assert stream.ups.shape == (len(stream.keyframes), 3) and np.isnan(stream.ups).all()  # none measured
    rec = StreamRecorder(base_T_lidar=EXT)
    for i, t in enumerate(stream.stamps):
        rec.add_frame(float(t), odometry=stream.odometry[i], truth=stream.truth[i])
        if i % EVERY == 0:
            up = (stream.truth[i] @ EXT)[:3, :3].T @ np.array([0.0, 0.0, 1.0])
            rec.add_result(Result(stamp=float(t), keyframe_id=i // EVERY, reason="keyframe", up=up))
    measured = rec.stream()
    assert np.isfinite(measured.ups).all()
    measured.save(tmp_path / "stream.npz")
    np.testing.assert_array_equal(LoopStream.load(tmp_path / "stream.npz").ups, measured.ups)
    assert replay(measured).stats.ups == len(measured.keyframes)
    assert replay(measured.without_ups()).stats.ups == 0
    evaluation = evaluate_backend(measured, odometry_name="drifted")
    assert evaluation.to_dict()["ups_taken"] == len(measured.keyframes)
    assert f"the walls' up of {len(measured.keyframes)} keyframes" in evaluation.text()

    given = [(float(measured.stamps[k]), u) for k, u in zip(measured.keyframes, measured.ups, strict=True)]
    joined, skipped = stream.with_ups([*given, (0.5, np.array([0.0, 0.0, 1.0]))])  # the last names no keyframe
    assert skipped == 1
    np.testing.assert_array_equal(joined.ups, measured.ups)


def test_the_recorder_refuses_frames_out_of_order_and_results_of_frames_it_never_saw() -> None:
    rec = StreamRecorder(base_T_lidar=np.eye(4))
    rec.add_frame(10.0, odometry=np.eye(4), truth=None)
    with pytest.raises(InvalidValueError, match="10.0"):
        rec.add_frame(10.0, odometry=np.eye(4), truth=None)
    with pytest.raises(InvalidValueError, match="stamp 11.0, a frame never recorded"):
        rec.add_result(Result(stamp=11.0, keyframe_id=0, reason="keyframe"))
    rec.add_result(Result(stamp=10.0, keyframe_id=None, reason="too soon"))  # not a keyframe: nothing to record
    assert len(rec.stream().keyframes) == 0
    with pytest.raises(InvalidValueError, match="base_T_lidar of shape"):
        StreamRecorder(base_T_lidar=np.eye(3))


@dataclasses.dataclass(frozen=True)
class PlainCandidate:
    query_stamp: float
    match_stamp: float
    verified: bool
    match_T_query: np.ndarray | None
    covariance: np.ndarray | None


@dataclasses.dataclass(frozen=True)
class PlainResult:
    stamp: float
    keyframe_id: int | None
    up: np.ndarray | None
    candidates: tuple[PlainCandidate, ...]


def test_the_recorder_takes_any_detectors_result_that_carries_the_fields_it_reads() -> None:
    rec = StreamRecorder(base_T_lidar=np.eye(4))
    for t in (10.0, 20.0, 30.0):
        rec.add_frame(t, odometry=pose(t), truth=None)
    rel = np.linalg.inv(pose(10.0)) @ pose(30.0)
    rec.add_result(PlainResult(10.0, 0, None, ()))
    rec.add_result(PlainResult(20.0, None, None, ()))  # not a keyframe: nothing recorded
    rec.add_result(PlainResult(30.0, 1, np.array([0.0, 0.0, 1.0]), (
        PlainCandidate(30.0, 10.0, True, rel, None),
        PlainCandidate(30.0, 20.0, False, None, None),  # unverified: not a loop
        PlainCandidate(30.0, 99.0, True, rel, None))))  # a frame never recorded: skipped
    stream = rec.stream()
    assert stream.keyframes.tolist() == [0, 2] and stream.loops.tolist() == [[2, 0]]
    np.testing.assert_array_equal(stream.loop_T[0], rel)
    assert np.isnan(stream.loop_cov[0]).all() and np.isnan(stream.ups[0]).all() and stream.ups[1, 2] == 1.0
    assert rec.skipped_loops == 1


def test_a_whole_evaluation_reports_both_ates_and_draws_the_png(tmp_path: Path) -> None:
    stream, _ = recorded()
    result = evaluate_backend(dataclasses.replace(stream), odometry_name="drifted")
    summary = result.to_dict()
    assert summary["loops_accepted"] == len(stream.loops)
    assert summary["ate_backend"]["rmse"] < summary["ate_odometry"]["rmse"]
    assert "drifted odometry ATE" in result.text()
    result.write_plot(tmp_path / "backend.png", title="test")
    assert (tmp_path / "backend.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
