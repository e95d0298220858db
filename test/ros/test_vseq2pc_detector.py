"""VSeq2PC's core detector (lcpr_core.vseq2pc.detector): what the node calls, tested without ROS.

Drive: a short KITTI-like synthetic drive (citysim, 320 x 96 images, 2.5 m between frames), its labelled
LiDAR scans as the map and its depth + label images as the camera pass 100 s later, with the bundled weights.
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from lcpr_core.errors import InvalidValueError
from lcpr_core.keyframes import KEYFRAME, NOT_MOVED, KeyframeConfig
from lcpr_core.vseq2pc.detector import (
    SequenceDetector,
    SequenceDetectorConfig,
)
from lcpr_core.vseq2pc.retrieval import SearchConfig
from lcpr_core.vseq2pc.sequence import sequence_table
from lcpr_core.vseq2pc.verify import SequenceVerifyConfig
from vseq2pc_drives import DT, FRAMES, REVISIT, Drive, bundled_net, short_drive
from vseq2pc_ros.config import NodeConfig, Vseq2pcMatchConfig


@pytest.fixture(scope="module")
def drive() -> Drive:
    _, scans, cameras = short_drive()
    return Drive(scans, cameras, NodeConfig().extrinsics.lidar_T_cam(), bundled_net())


def detector(drive: Drive, **config: object) -> SequenceDetector:
    cfg = SequenceDetectorConfig(lidar_T_cam=drive.extrinsics, search=SearchConfig(k=3), **config)  # type: ignore[arg-type]
    det = SequenceDetector(cfg, net=drive.net)
    for scan in drive.scans:
        assert det.scan_keyframe(scan.stamp, scan.pose) == KEYFRAME
        det.add_scan(scan)
    return det


def test_a_camera_pass_over_the_map_completes_one_query_per_frame_with_a_frame_15_m_on(drive: Drive) -> None:
    det = detector(drive, verify=SequenceVerifyConfig(enabled=False))  # retrieval alone: its order and its loop
    assert len(det.map) == FRAMES
    queries = []
    for frame in drive.cameras:
        queries += det.process(frame).queries
    xy = np.array([s.pose[:2, 3] for s in drive.scans if s.pose is not None])
    expected = int((sequence_table(xy)[:, 0] >= 0).sum())
    assert [q.query_id for q in queries] == list(range(expected))
    assert [q.stamp for q in queries] == pytest.approx([REVISIT + i * DT for i in range(expected)])
    for q in queries:
        assert len(q.candidates) == 3 and [m.rank for m in q.candidates] == [0, 1, 2]
        assert all(a.probability >= b.probability for a, b in zip(q.candidates, q.candidates[1:], strict=False))
        assert q.loop is q.candidates[0]
    best = np.array([q.loop.id for q in queries if q.loop is not None])
    off = np.hypot(*(xy[best] - xy[:expected]).T)
    assert (off < 3.0).sum() >= 4, f"best scan this far from each query: {np.round(off, 1)} m"


def test_candidates_under_min_probability_are_dropped_and_such_a_query_has_no_loop(drive: Drive) -> None:
    det = detector(drive, min_probability=1.0)
    queries = [q for frame in drive.cameras for q in det.process(frame).queries]
    assert queries and all(q.candidates == [] and q.loop is None for q in queries)


def test_a_new_session_leaves_its_unfinished_queries_and_no_sequence_spans_two(drive: Drive) -> None:
    det = detector(drive)
    half = 5  # 10 m: no query is complete yet
    first = [q for frame in drive.cameras[:half] for q in det.process(frame).queries]
    assert first == []
    pending = det.builder.pending
    assert pending > 0
    replay = replace(drive.cameras[0], stamp=50.0, session=1)
    result = det.process(replay)
    assert result.unfinished == pending and result.queries == []
    later = [q for frame in drive.cameras[1:] for q in det.process(replace(frame, session=1)).queries]
    assert later and min(q.query_id for q in later) >= half  # the second session's frames only


def test_scans_and_camera_frames_each_keep_their_own_keyframe_rule(drive: Drive) -> None:
    det = SequenceDetector(SequenceDetectorConfig(scan=KeyframeConfig(min_interval=0.0, min_distance=4.0)),
                           net=drive.net)
    reasons = [det.scan_keyframe(s.stamp, s.pose) for s in drive.scans[:4]]  # 2.5 m apart
    assert reasons == [KEYFRAME, NOT_MOVED, KEYFRAME, NOT_MOVED]
    assert [det.camera_keyframe(c.stamp, c.pose) for c in drive.cameras[:4]] == [KEYFRAME] * 4
    det.restart_keyframing("scan")
    assert det.scan_keyframe(drive.scans[3].stamp, drive.scans[3].pose) == KEYFRAME
    with pytest.raises(InvalidValueError, match="stream='lidar'; accepted: scan, camera"):
        det.restart_keyframing("lidar")


def test_bad_settings_are_refused_with_the_value_named() -> None:
    with pytest.raises(InvalidValueError, match="min_probability=1.5"):
        SequenceDetectorConfig(min_probability=1.5)
    with pytest.raises(InvalidValueError, match="lidar_T_cam has 3 values"):
        SequenceDetectorConfig(lidar_T_cam=(1.0, 0.0, 0.0))


def test_the_node_parameters_build_the_detector_settings_it_runs() -> None:
    cfg = NodeConfig(match=Vseq2pcMatchConfig(top_k=4, min_probability=0.3, exclude_recent_s=12.0))
    det = cfg.detector()
    assert det.search.k == 4 and det.search.exclude_recent_s == 12.0 and det.min_probability == 0.3
    assert np.allclose(det.extrinsics(), cfg.extrinsics.lidar_T_cam())
    assert det.scan == KeyframeConfig(min_interval=0.0, min_distance=0.0)
