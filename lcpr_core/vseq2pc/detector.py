"""VSeq2PC loop detection: labelled LiDAR scans build the map, camera frames build query sequences.

The node drives this class; it knows nothing of ROS (the same shape as :class:`lcpr_core.lcpr.detector.LoopDetector`)::

    detector = SequenceDetector(SequenceDetectorConfig(), net=Vseq2pcNet.from_files(...))
    if detector.scan_keyframe(stamp, pose) == KEYFRAME:           # cheap: where scans arrive
        detector.add_scan(LabelledScan(stamp, points, labels, pose))
    if detector.camera_keyframe(stamp, pose) == KEYFRAME:         # cheap: where camera frames arrive
        result = detector.process(CameraFrame(stamp, depth, labels, K, pose))
        for query in result.queries:
            if query.loop is not None: ...                        # best scan at or above min_probability

Keyframes: scans and camera frames each follow :mod:`lcpr_core.keyframes` (``scan.*`` and ``camera.*``).
The decision is separate from the work so a caller can make it before queueing the frame for a worker.
Sequences: :class:`~lcpr_core.vseq2pc.sequence.SequenceBuilder` (the query frame and the frames 5, 10 and
15 m further on); matching: :class:`~lcpr_core.vseq2pc.retrieval.Vseq2pcMap` with ``search`` (top-k, the
"exclude recent" rule); candidates under ``min_probability`` are dropped.
Sessions: a camera frame whose ``session`` differs from the last one's (header time jumped back) starts
sequences afresh; no sequence spans two sessions.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from ..errors import InvalidValueError
from ..keyframes import KeyframeConfig, KeyframeGate
from .net import Vseq2pcNet
from .preprocess import camera_feature, structure_feature
from .retrieval import ScanMatch, SearchConfig, Vseq2pcMap
from .sequence import SequenceBuilder, SequenceConfig

__all__ = ["CameraFrame", "CameraResult", "LabelledScan", "SequenceDetector", "SequenceDetectorConfig",
           "SequenceQuery"]

NO_KEYFRAMING = KeyframeConfig(min_interval=0.0, min_distance=0.0)


@dataclass(frozen=True)
class SequenceDetectorConfig:
    scan: KeyframeConfig = NO_KEYFRAMING  # which LiDAR scans join the map
    camera: KeyframeConfig = NO_KEYFRAMING  # which camera frames join sequences
    sequence: SequenceConfig = field(default_factory=SequenceConfig)
    search: SearchConfig = field(default_factory=SearchConfig)
    min_probability: float = 0.0  # candidates under this match probability are dropped
    lidar_T_cam: tuple[float, ...] = tuple(np.eye(4).ravel().tolist())  # 4 x 4, row-major

    def __post_init__(self) -> None:
        if not 0.0 <= self.min_probability <= 1.0:
            raise InvalidValueError(f"min_probability={self.min_probability!r}; it must lie in [0, 1]")
        if len(self.lidar_T_cam) != 16 or not np.all(np.isfinite(self.lidar_T_cam)):
            raise InvalidValueError(f"lidar_T_cam has {len(self.lidar_T_cam)} values; give 16 finite values "
                                    "(4 x 4, row-major)")

    def extrinsics(self) -> np.ndarray:
        return np.asarray(self.lidar_T_cam, np.float64).reshape(4, 4)


@dataclass(frozen=True)
class LabelledScan:
    stamp: float  # s
    points: np.ndarray  # N x (>=3), LiDAR frame
    labels: np.ndarray  # N SemanticKITTI ids
    pose: np.ndarray | None  # 4 x 4 world_T_lidar


@dataclass(frozen=True)
class CameraFrame:
    stamp: float  # s
    depth: np.ndarray  # H x W metres
    labels: np.ndarray  # H x W SemanticKITTI ids
    K: np.ndarray  # 3 x 3 intrinsics
    pose: np.ndarray  # 4 x 4 world_T_base
    session: int = 0  # header-time sessions so far (a sequence never spans two)


@dataclass(frozen=True)
class SequenceQuery:
    query_id: int  # camera frame number of the sequence's query frame
    stamp: float  # its stamp
    candidates: list[ScanMatch]  # best first, each at or above min_probability

    @property
    def loop(self) -> ScanMatch | None:
        """The candidate a SLAM back end should receive: the most probable one, or None."""
        return self.candidates[0] if self.candidates else None


@dataclass
class CameraResult:
    stamp: float
    frame_id: int  # this camera frame's number
    queries: list[SequenceQuery] = field(default_factory=list)  # the sequences this frame completed
    unfinished: int = 0  # queries a new session left without their last member
    timings: dict[str, float] = field(default_factory=dict)  # stage -> seconds


class SequenceDetector:
    """Keyframing, sequence building and matching against a growing map of labelled LiDAR scans."""

    def __init__(self, config: SequenceDetectorConfig | None = None, *, net: Vseq2pcNet,
                 prior_map: Vseq2pcMap | None = None) -> None:
        self.config = config if config is not None else SequenceDetectorConfig()
        self.map = prior_map if prior_map is not None else Vseq2pcMap(net, config=self.config.search)
        self.builder = SequenceBuilder(self.config.sequence)
        self._scan_gate, self._camera_gate = KeyframeGate(), KeyframeGate()
        self._frames = 0
        self._session = 0

    # -- keyframing (cheap) ----------------------------------------------------------------------
    def scan_keyframe(self, stamp: float, pose: np.ndarray | None) -> str:
        """``KEYFRAME`` when this scan joins the map, else why not (``scan.*``)."""
        return self._scan_gate.decide(stamp, pose, self.config.scan)

    def camera_keyframe(self, stamp: float, pose: np.ndarray | None) -> str:
        """``KEYFRAME`` when this camera frame joins the sequences, else why not (``camera.*``)."""
        return self._camera_gate.decide(stamp, pose, self.config.camera)

    def restart_keyframing(self, stream: str) -> None:
        """Header time went back on ``stream`` ("scan" or "camera"): its next frame is a keyframe."""
        gates = {"scan": self._scan_gate, "camera": self._camera_gate}
        if stream not in gates:
            raise InvalidValueError(f"stream={stream!r}; accepted: scan, camera")
        gates[stream].reset()

    # -- work --------------------------------------------------------------------------------------
    def add_scan(self, scan: LabelledScan) -> int:
        """Describe a labelled scan and add it to the map; returns its map id."""
        feature = structure_feature(scan.points, scan.labels)
        return self.map.add_feature(feature, stamp=scan.stamp, pose=scan.pose)

    def process(self, frame: CameraFrame) -> CameraResult:
        """Add a camera frame to the sequences; match the sequences it completes."""
        result = CameraResult(stamp=frame.stamp, frame_id=self._frames)
        if frame.session != self._session:
            result.unfinished = self.builder.pending
            self.builder.reset()
            self._session = frame.session
        if self.builder.config != self.config.sequence:  # settings changed at run time
            result.unfinished += self.builder.pending
            self.builder = SequenceBuilder(self.config.sequence)
        tic = time.perf_counter()
        feature = camera_feature(frame.depth, frame.labels, frame.K, self.config.extrinsics())
        result.timings["feature"] = time.perf_counter() - tic
        batch = self.builder.push(feature, stamp=frame.stamp, pose=frame.pose, index=self._frames)
        self._frames += 1
        if batch is None:
            return result
        tic = time.perf_counter()
        matches = self.map.query(batch, config=self.config.search)
        result.timings["match"] = time.perf_counter() - tic
        min_p = self.config.min_probability
        for q, found in enumerate(matches):
            kept = [m for m in found if m.probability >= min_p]
            result.queries.append(SequenceQuery(int(batch.query_indices[q]), float(batch.query_stamps[q]), kept))
        return result
