"""Verification deferred (an evaluation's throughput path): the verdicts of immediate verification, in order, and
no keyframe lost when a worker process dies with keyframes in flight."""
from __future__ import annotations

import dataclasses
from typing import Any, cast

import numpy as np
import pytest
from test_map_clouds import KeyedDescriber
from test_submap import MOUNT, narrow
from test_verification import pose, scene, view

from lcpr_core.detector import Candidate, DetectorConfig, Frame, LoopDetector, MatchConfig, Result
from lcpr_core.errors import InvalidValueError
from lcpr_core.lcpr.describer import Describer, PreparedBatch
from lcpr_core.verification import SubmapConfig, VerifierConfig

LAP = 10  # keyframes a lap
VERIFY = VerifierConfig(num_threads=1, processes=2)


class BatchKeyedDescriber(KeyedDescriber):
    """KeyedDescriber describing a batch of frames in one call."""

    def prepare_many(self, frames):
        return PreparedBatch(cast(Any, [images[0] for images, _ in frames]), cast(Any, None), [{} for _ in frames])

    def describe_tensors(self, images, ranges):
        return np.stack([self.table[key] for key in images])


def drive() -> tuple[dict[str, np.ndarray], list[Frame]]:
    """Two laps of a 4 m circle seen by a 70 deg sensor, a keyframe a second: each keyframe's descriptor lies near
    its place's on the other lap, so lap two's candidates are lap one's keyframes and this lap's recent ones (only
    2 s are excluded): matches whose neighbours on both sides are stitched into their submaps."""
    rng = np.random.default_rng(3)
    places = [rng.normal(size=256) for _ in range(LAP)]
    table, frames = {}, []
    world = scene(2)
    for i in range(2 * LAP):
        v = places[i % LAP] + 0.3 * rng.normal(size=256)
        table[f"k{i}"] = (v / np.linalg.norm(v)).astype(np.float32)
        angle = 360.0 * i / LAP
        T = pose(4.0 * np.cos(np.radians(angle)), 4.0 * np.sin(np.radians(angle)), angle + 90.0)
        images = cast(Any, [f"k{i}"] * 6)  # not images: KeyedDescriber reads the key
        frames.append(Frame(stamp=float(i), images=images, points=narrow(view(world, T, seed=100 + i)), pose=T))
    return table, frames


def detector(table: dict[str, np.ndarray], verify: VerifierConfig = VERIFY) -> LoopDetector:
    return LoopDetector(DetectorConfig(match=MatchConfig(top_k=4, max_distance=2.0, exclude_recent_s=2.0),
                                       verify=verify, submap=SubmapConfig(lidar_xyz=MOUNT)),
                        describer=cast(Describer, BatchKeyedDescriber(table)))


def verdicts(results: list[Result]) -> list[tuple[Any, ...]]:
    """Every candidate's verdict, exactly: ids, decision, reason, fitness, pose and covariance bytes."""
    def one(c: Candidate) -> tuple[Any, ...]:
        return (c.query_id, c.match_id, c.verified, c.verification, c.fitness,
                None if c.match_T_query is None else c.match_T_query.tobytes(),
                None if c.covariance is None else c.covariance.tobytes())
    return [(r.keyframe_id, tuple(one(c) for c in r.candidates)) for r in results]


@pytest.fixture(scope="module")
def drive_and_immediate() -> tuple[dict[str, np.ndarray], list[Frame], list[Result]]:
    table, frames = drive()
    det = detector(table)
    try:
        immediate = [det.process(frame) for frame in frames]
    finally:
        det.close()
    return table, frames, immediate


def test_deferred_verification_gives_the_verdicts_of_immediate_verification_in_order(drive_and_immediate):
    table, frames, immediate = drive_and_immediate
    assert sum(len(r.candidates) for r in immediate) >= 30 and any(r.loop is not None for r in immediate)
    assert sum(c.verified for r in immediate for c in r.candidates) == LAP  # lap two closes every place
    assert any(c.match_id >= r.keyframe_id - 3 for r in immediate[LAP:] for c in r.candidates)  # recent ones
    det = detector(table)
    done: list[Result] = []
    try:
        for k in range(0, len(frames), 3):  # batches of 3 frames, at most 4 keyframes verifying
            stored = det.store_batch(det.describe_batch(frames[k:k + 3]), defer_verification=True)
            assert all(not c.verified for r in stored for c in r.candidates)  # their verdicts are still to come
            done += det.finish_verification(keep=4)
            assert det.verifying <= 4
        done += det.finish_verification()
    finally:
        det.close()
    assert det.verifying == 0 and [r.keyframe_id for r in done] == [r.keyframe_id for r in immediate]
    assert verdicts(done) == verdicts(immediate)
    assert all(r.timings["verify"] > 0 for r in done if r.candidates) and not any(r.errors for r in done)


def test_in_process_verification_deferred_is_finished_in_turn_with_the_same_verdicts(drive_and_immediate):
    table, frames, immediate = drive_and_immediate
    det = detector(table, dataclasses.replace(VERIFY, processes=0))
    stored = [r for frame in frames for r in det.store_batch(det.describe_batch([frame]), defer_verification=True)]
    assert det.verifying == len(frames)  # nothing to wait for, yet finished in order with the others
    assert det.finish_verification() == stored and verdicts(stored) == verdicts(immediate)


def test_a_worker_that_dies_with_keyframes_in_flight_loses_none_of_them(drive_and_immediate):
    table, frames, immediate = drive_and_immediate
    det = detector(table, dataclasses.replace(VERIFY, min_points=199))  # a pool of its own (its workers die here)
    pool = det.verification_processes()
    assert pool is not None
    try:
        results = [r for frame in frames[:LAP + 5] for r in
                   det.store_batch(det.describe_batch([frame]), defer_verification=True)]
        for worker in pool._workers:  # both workers killed with lap two's first keyframes in flight
            assert worker is not None
            worker.process.kill()
            worker.process.wait(timeout=10)
        results += [r for frame in frames[LAP + 5:] for r in
                    det.store_batch(det.describe_batch([frame]), defer_verification=True)]
        done = det.finish_verification()
    finally:
        pool.close()
    assert done == results and pool.fallbacks > 0
    assert any("verification worker process failed" in e for r in done for e in r.errors)
    # the pairs verified in the detector's process after later keyframes were stored: their clouds are the
    # ones stitched when the keyframe was, so the verdicts are those of immediate verification
    strip = dataclasses.replace
    assert verdicts([strip(r, errors=[]) for r in done]) == verdicts(immediate)


def test_a_bad_number_of_keyframes_to_keep_verifying_is_refused_naming_it():
    det = detector({})
    for keep in (-1, 1.5, True):
        with pytest.raises(InvalidValueError, match=r"keep=.*accepted: an integer >= 0"):
            det.finish_verification(keep=keep)  # type: ignore[arg-type]
