"""The loop detector keyframes, excludes recent frames and finds revisits, without ROS."""
from __future__ import annotations

from typing import cast

import numpy as np
import pytest
import torch

from lcpr_core.descriptor_map import DescriptorMap
from lcpr_core.detector import DetectorConfig, Frame, KeyframeConfig, LoopDetector, MatchConfig, SensorConfig
from lcpr_core.errors import MapSchemaError
from lcpr_core.lcpr.describer import Describer, Prepared, prepare_each
from lcpr_core.verification import VerifierConfig

RETRIEVAL_ONLY = VerifierConfig(enabled=False)  # these tests are about keyframing and retrieval


class PlaceDescriber:
    """Stands in for the network: the descriptor is a function of the place (first point)."""

    weights_id = "place-test"  # what made the descriptors, as a Describer says

    def inputs(self, images, points):
        return torch.zeros(1), torch.as_tensor(np.asarray(points, np.float64)[:1])

    def prepare(self, images, points):
        return Prepared(*self.inputs(images, points))

    def prepare_many(self, frames):
        return prepare_each(self.prepare, frames)

    def describe_tensors(self, images, ranges):
        rows = []
        for x, y in ranges[:, :2].tolist():
            v = np.random.default_rng(int(round(x)) * 100_003 + int(round(y))).normal(size=256).astype(np.float32)
            rows.append(v / np.linalg.norm(v))
        return np.stack(rows)


def place_describer() -> Describer:
    """A PlaceDescriber in a Describer's place: the detector calls only prepare and describe_tensors."""
    return cast(Describer, PlaceDescriber())


def frame(t: float, x: float, y: float = 0.0, *, cams=6, pose=True, missing=()) -> Frame:
    pose_m = np.eye(4)
    pose_m[:3, 3] = (x, y, 0)
    images = [None if i in missing else b"jpeg" for i in range(cams)]
    return Frame(stamp=t, images=images, points=np.array([[x, y, 0.0]]), pose=pose_m if pose else None)


def detector(**match) -> LoopDetector:
    config = DetectorConfig(match=MatchConfig(**{"max_distance": 0.5, **match}), verify=RETRIEVAL_ONLY)
    return LoopDetector(config, describer=place_describer())


def test_without_odometry_at_most_one_keyframe_per_half_second():
    det = detector()
    reasons = [det.process(frame(t, t, pose=False)).reason for t in (0.0, 0.2, 0.5, 0.9, 1.0)]
    assert reasons == ["keyframe", "too soon", "keyframe", "too soon", "keyframe"]


def test_with_odometry_a_keyframe_needs_the_configured_travel():
    det = LoopDetector(DetectorConfig(keyframe=KeyframeConfig(min_distance=2.0)), describer=place_describer())
    reasons = [det.process(frame(t, x)).reason for t, x in ((0, 0), (1, 1), (2, 2.5), (3, 3))]
    assert reasons == ["keyframe", "not moved", "keyframe", "not moved"]


def test_out_of_order_duplicate_and_lidar_less_frames_are_not_keyframes():
    det = detector()
    assert det.process(frame(5.0, 0)).reason == "keyframe"
    assert det.process(frame(5.0, 1)).reason == "out of order"
    assert det.process(frame(4.0, 1)).reason == "out of order"
    no_cloud = Frame(stamp=6.0, images=[b"x"] * 6, points=None)
    assert det.process(no_cloud).reason == "no lidar"
    assert det.session_keyframes == 1


def test_a_missing_cloud_can_still_make_a_keyframe_when_configured():
    det = LoopDetector(DetectorConfig(sensors=SensorConfig(require_lidar=False)), describer=place_describer())

    class NoPoints(PlaceDescriber):
        def inputs(self, images, points):
            return torch.zeros(1), torch.zeros(1, 3, dtype=torch.float64)

    det.describer = cast(Describer, NoPoints())
    assert det.process(Frame(stamp=0.0, images=[b"x"] * 6, points=None)).reason == "keyframe"


def drive_loop(det: LoopDetector) -> list:
    """0..59 s along x, then back to the start: places 0..59 are revisited at t = 100.."""
    results = [det.process(frame(float(t), float(t))) for t in range(60)]
    results += [det.process(frame(100.0 + t, float(t))) for t in range(10)]
    return results


def test_a_revisit_is_matched_to_the_first_visit_and_recent_frames_are_excluded():
    results = drive_loop(detector())
    assert all(r.loop is None for r in results[:60])  # only recent (<30 s) or different places
    for t, r in enumerate(results[60:]):
        assert r.loop is not None
        assert r.loop.match_id == t and r.loop.match_stamp == t and r.loop.distance < 1e-6
        assert r.loop.query_id == 60 + t and r.loop.rank == 0
        assert r.loop.match_position == (t, 0.0, 0.0)


def test_nothing_newer_than_the_exclusion_window_is_returned():
    det = detector(max_distance=2.0, top_k=100)
    for t in range(100):
        r = det.process(frame(float(t), float(t)))
        assert all(c.match_stamp <= t - 30 for c in r.candidates)
        assert len(r.candidates) == max(0, t - 29)  # exactly 30 s old is eligible


def test_exclusion_by_count_adds_to_exclusion_by_time():
    det = detector(max_distance=2.0, top_k=100, exclude_recent_s=0.0, exclude_recent_count=5)
    for t in range(20):
        r = det.process(frame(float(t), float(t)))
    assert len(r.candidates) == 19 - 5
    assert max(c.match_id for c in r.candidates) == 13


def test_entries_of_a_prior_session_are_never_excluded_by_time():
    prior_det = detector()
    for t in range(5):
        prior_det.process(frame(1000.0 + t, float(t)))
    det = LoopDetector(DetectorConfig(match=MatchConfig(max_distance=0.5), verify=RETRIEVAL_ONLY),
                       describer=place_describer(), prior_map=prior_det.map)
    r = det.process(frame(0.0, 3.0))  # earlier clock, same place as prior keyframe 3
    assert r.loop is not None and r.loop.match_id == 3
    assert r.keyframe_id == 5


def test_after_start_session_earlier_stamps_are_keyframes_and_the_first_pass_matches_at_once():
    """A bag played twice: the second pass restarts at the first pass's stamps."""
    det = detector()
    for t in range(5):
        det.process(frame(100.0 + t, float(t)))
    assert det.process(frame(100.0, 0.0)).reason == "out of order"
    det.start_session()
    r = det.process(frame(100.0, 0.0))  # the same stamp and place again, 0 s "later"
    assert r.reason == "keyframe" and r.loop is not None and r.loop.match_id == 0
    assert det.session_keyframes == 1 and len(det.map) == 6
    r = det.process(frame(101.0, 1.0))
    assert r.loop is not None and r.loop.match_id == 1  # the first pass is an earlier session: never excluded
    assert all(c.match_id != 5 for c in r.candidates)  # this session's own keyframes still are (< 30 s)


def test_a_candidate_from_a_frame_with_a_dark_camera_is_flagged_degraded():
    det = detector()
    det.process(frame(0.0, 7.0))
    r = det.process(frame(50.0, 7.0, missing=(2,)))
    assert r.missing_cameras == (2,)
    assert r.loop is not None and r.loop.degraded


def test_stage_timings_are_reported_for_keyframes():
    r = detector().process(frame(0.0, 1.0))
    assert set(r.timings) == {"preprocess", "network", "search", "add", "up"}


def test_bad_settings_are_refused_with_the_setting_named():
    with pytest.raises(ValueError, match="match.top_k=0"):
        MatchConfig(top_k=0)
    with pytest.raises(ValueError, match="KeyframeConfig.min_interval=-1"):
        KeyframeConfig(min_interval=-1)


def test_the_map_of_a_detector_saves_and_loads_with_every_keyframe(tmp_path):
    det = detector()
    drive_loop(det)
    det.map.save(tmp_path / "map.npz")
    loaded = DescriptorMap.load(tmp_path / "map.npz")
    assert len(loaded) == 70 and loaded.ids.tolist() == list(range(70))


def test_a_new_map_records_the_describer_that_fills_it():
    assert detector().map.weights_id == "place-test"


def test_a_prior_map_made_by_other_weights_is_refused_naming_both():
    prior = DescriptorMap(weights_id="0123456789abcdef")
    prior.add(np.eye(256, dtype=np.float32)[:1], stamps=[0.0])
    with pytest.raises(MapSchemaError, match="weights 0123456789abcdef.*weights place-test"):
        LoopDetector(DetectorConfig(verify=RETRIEVAL_ONLY), describer=place_describer(), prior_map=prior)


def test_a_prior_map_that_does_not_say_which_weights_made_it_is_used_with_a_warning(caplog):
    prior = DescriptorMap()
    prior.add(np.eye(256, dtype=np.float32)[:1], stamps=[0.0])
    with caplog.at_level("WARNING"):
        det = LoopDetector(DetectorConfig(verify=RETRIEVAL_ONLY), describer=place_describer(), prior_map=prior)
    assert len(det.map) == 1 and det.map.weights_id == ""
    assert "does not record which weights made it" in caplog.text
    empty = LoopDetector(DetectorConfig(verify=RETRIEVAL_ONLY), describer=place_describer(), prior_map=DescriptorMap())
    assert empty.map.weights_id == "place-test"


def test_frames_processed_in_batches_give_the_results_of_one_frame_at_a_time():
    frames = [frame(float(t), float(t)) for t in range(60)] + [frame(100.0 + t, float(t)) for t in range(10)]
    frames.insert(30, frame(29.5, 29.5))  # out of order: not a keyframe, in the middle of a batch
    single, batched = detector(), detector()
    one = [single.process(f) for f in frames]
    many = [r for i in range(0, len(frames), 8) for r in batched.process_batch(frames[i:i + 8])]
    assert [r.reason for r in one] == [r.reason for r in many]
    assert [r.keyframe_id for r in one] == [r.keyframe_id for r in many]
    assert [[(c.match_id, c.distance) for c in r.candidates] for r in one] == \
        [[(c.match_id, c.distance) for c in r.candidates] for r in many]
    assert sum(r.loop is not None for r in many) == 10


def test_a_batch_described_while_the_one_before_is_stored_gives_the_results_of_one_frame_at_a_time():
    frames = [frame(float(t), float(t)) for t in range(60)] + [frame(100.0 + t, float(t)) for t in range(10)]
    single, pipelined = detector(), detector()
    one = [single.process(f) for f in frames]
    batches = [frames[i:i + 8] for i in range(0, len(frames), 8)]
    described = pipelined.describe_batch(batches[0])
    many = []
    for nxt in batches[1:]:
        ahead = pipelined.describe_batch(nxt)  # described before the batch in front of it is stored
        many += pipelined.store_batch(described)
        described = ahead
    many += pipelined.store_batch(described)
    assert [(r.reason, r.keyframe_id) for r in one] == [(r.reason, r.keyframe_id) for r in many]
    assert [[(c.match_id, c.distance) for c in r.candidates] for r in one] == \
        [[(c.match_id, c.distance) for c in r.candidates] for r in many]


def test_a_prefetched_iterator_keeps_the_order_raises_the_source_error_and_stops_early():
    from lcpr_offline.lcpr_evaluate import Prefetched

    assert list(Prefetched(iter(range(100)), depth=3)) == list(range(100))

    def broken():
        yield 1
        raise ValueError("bad bag record")

    items = Prefetched(broken(), depth=2)
    assert next(items) == 1
    with pytest.raises(ValueError, match="bad bag record"):
        next(items)
    endless = Prefetched(iter(int, 1), depth=2)  # never ends: close() must still return
    assert next(endless) == 0
    endless.close()
