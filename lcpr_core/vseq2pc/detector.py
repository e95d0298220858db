"""VSeq2PC loop detection: labelled LiDAR scans build the map, camera frames build query sequences.

The node drives this class; it knows nothing of ROS (the same shape as :class:`lcpr_core.detector.LoopDetector`)::

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
Verification (``verify.enabled``, on by default; :mod:`lcpr_core.vseq2pc.verify`): every scan keeps a compact
cloud; each camera frame keeps its depth back-projected (:func:`~lcpr_core.vseq2pc.pseudo_cloud.frame_cloud`);
a completed query stacks its frames (the query frame to the last member) with odometry into a pseudo-cloud and
registers it against its best ``verify.top_k`` candidates; a verified candidate stays verified only when the
earlier queries confirm its camera pose (``verify.consistency``, :mod:`lcpr_core.vseq2pc.consistency`); a query
whose loop is so confirmed also confirms the earlier queries of its chain, which come again in ``result.queries``
with ``late=True`` (``verify.consistency.backfill``). ``SequenceQuery.loop`` is then the verified candidate
with the best fitness (None when none passed); candidates come verified first (best fitness first). A frame whose
depth, intrinsics or pose cannot give a cloud leaves its queries' candidates unverified with the reason
(:data:`~lcpr_core.vseq2pc.pseudo_cloud.INPUT_REASONS`); nothing is raised.
Sessions: a camera frame whose ``session`` differs from the last one's (header time jumped back) starts
sequences afresh; no sequence spans two sessions.
"""
from __future__ import annotations

import dataclasses
import time
from collections import OrderedDict
from collections.abc import Hashable
from dataclasses import dataclass, field
from typing import cast

import numpy as np

from ..errors import InputShapeError, InvalidValueError, LcprError, VerificationError
from ..keyframes import KeyframeConfig, KeyframeGate
from ..verification.clouds import compact_cloud
from .net import Vseq2pcNet
from .preprocess import camera_feature, structure_feature
from .pseudo_cloud import DEPTH_SIZE, accumulate, check_pose, frame_cloud, reason_of
from .retrieval import ScanMatch, SearchConfig, Vseq2pcMap
from .sequence import SequenceBatch, SequenceBuilder, SequenceConfig
from .verify import SequenceVerifier, SequenceVerifyConfig

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
    verify: SequenceVerifyConfig = field(default_factory=SequenceVerifyConfig)
    max_kept_frames: int = 512  # camera frames' clouds kept for pseudo-clouds at most (oldest dropped)

    def __post_init__(self) -> None:
        if not 0.0 <= self.min_probability <= 1.0:
            raise InvalidValueError(f"min_probability={self.min_probability!r}; it must lie in [0, 1]")
        if self.max_kept_frames < 1:
            raise InvalidValueError(f"max_kept_frames={self.max_kept_frames!r}; it must be >= 1")
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
    candidates: list[ScanMatch]  # each at or above min_probability; verified first (best fitness), then by rank
    verification: bool = False  # candidates were verified (the loop must be a verified one)
    # an earlier query again, its loop confirmed late by a later query's (verify.consistency_backfill); its
    # candidates then, with the confirmed one verified
    late: bool = False

    @property
    def loop(self) -> ScanMatch | None:
        """The candidate a SLAM back end should receive. Verification on: the verified candidate with the best
        fitness, None when none passed; off: the most probable one, or None."""
        if self.verification:
            verified = [c for c in self.candidates if c.verified]
            return max(verified, key=lambda c: (c.fitness, -c.rank)) if verified else None
        return self.candidates[0] if self.candidates else None


@dataclass
class CameraResult:
    stamp: float
    frame_id: int  # this camera frame's number
    queries: list[SequenceQuery] = field(default_factory=list)  # the sequences this frame completed
    unfinished: int = 0  # queries a new session left without their last member
    timings: dict[str, float] = field(default_factory=dict)  # stage -> seconds
    frame_problem: str | None = None  # why this frame gives no pseudo-cloud (pseudo_cloud.INPUT_REASONS), or None
    errors: list[str] = field(default_factory=list)  # why a candidate's registration "failed" (an exception)


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
        self.verifier = SequenceVerifier(self.config.verify)
        # frame number -> (M x 3 cloud in its vehicle frame, world_T_base) or the reason it has none
        self._clouds: OrderedDict[int, tuple[np.ndarray, np.ndarray] | str] = OrderedDict()

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
        cloud = None
        if self.config.verify.keep_clouds or self.config.verify.enabled:
            cloud = compact_cloud(scan.points, self.config.verify.scan_cloud)
        return self.map.add_feature(feature, stamp=scan.stamp, pose=scan.pose, cloud=cloud)

    def process(self, frame: CameraFrame) -> CameraResult:
        """Add a camera frame to the sequences; match the sequences it completes."""
        result = CameraResult(stamp=frame.stamp, frame_id=self._frames)
        if frame.session != self._session:
            result.unfinished = self.builder.pending
            self.builder.reset()
            self._clouds.clear()
            self.verifier.restart()
            self._session = frame.session
        if self.builder.config != self.config.sequence:  # settings changed at run time
            result.unfinished += self.builder.pending
            self.builder = SequenceBuilder(self.config.sequence)
        if self.verifier.config != self.config.verify:
            self.verifier = SequenceVerifier(self.config.verify)
        tic = time.perf_counter()
        try:
            feature: np.ndarray | None = camera_feature(frame.depth, frame.labels, frame.K, self.config.extrinsics())
        except InputShapeError:  # depth and labels of different sizes: the frame is left out of sequences
            feature, result.frame_problem = None, DEPTH_SIZE
        result.timings["feature"] = time.perf_counter() - tic
        index = self._frames
        batch = self.builder.push(feature, stamp=frame.stamp, pose=frame.pose, index=index)
        self._frames += 1
        verify = self.config.verify.enabled
        if verify:
            tic = time.perf_counter()
            self._keep_cloud(index, frame, result)
            result.timings["cloud"] = time.perf_counter() - tic
        if batch is None:
            return result
        tic = time.perf_counter()
        matches = self.map.query(batch, config=self.config.search)
        result.timings["match"] = time.perf_counter() - tic
        min_p = self.config.min_probability
        tic = time.perf_counter()
        for q, found in enumerate(matches):
            kept = [m for m in found if m.probability >= min_p]
            query_id, stamp = int(batch.query_indices[q]), float(batch.query_stamps[q])
            late: list[tuple[Hashable, list[ScanMatch]]] = []
            if verify:
                kept = self._verify(batch, q, kept, result.errors)
                kept, late = self.verifier.confirm_all(batch.poses[q, 0], kept, lidar_T_cam=self.config.extrinsics(),
                                                       key=(query_id, stamp))
            result.queries.append(SequenceQuery(query_id, stamp, kept, verification=verify))
            for key, candidates in late:
                late_id, late_stamp = cast(tuple[int, float], key)
                result.queries.append(SequenceQuery(late_id, late_stamp, candidates, verification=True, late=True))
        if verify:
            result.timings["verify"] = time.perf_counter() - tic
            self._forget_before(int(batch.query_indices[-1]))
        return result

    # -- verification ------------------------------------------------------------------------------
    def _keep_cloud(self, index: int, frame: CameraFrame, result: CameraResult) -> None:
        """The frame's cloud in its vehicle frame (or why it has none), kept for the queries it belongs to."""
        try:
            pose = check_pose(frame.pose, "the frame's pose")
            cloud = frame_cloud(frame.depth, frame.K, self.config.extrinsics(), labels=frame.labels,
                                config=self.config.verify.pseudo)
            entry: tuple[np.ndarray, np.ndarray] | str = (cloud, pose)
        except VerificationError as err:
            entry = reason_of(err)
            result.frame_problem = result.frame_problem or entry
        self._clouds[index] = entry
        while len(self._clouds) > self.config.max_kept_frames:
            self._clouds.popitem(last=False)

    def _forget_before(self, index: int) -> None:
        """Drop the clouds of frames before ``index``: later queries start after it."""
        while self._clouds and next(iter(self._clouds)) < index:
            self._clouds.popitem(last=False)

    def _pseudo_cloud(self, batch: SequenceBatch, q: int) -> np.ndarray | str:
        """The query's frames (its first to its last member) stacked in the query frame, or why not."""
        first, last = int(batch.indices[q, 0]), int(batch.indices[q, -1])
        frames = []
        for i in range(first, last + 1):
            entry = self._clouds.get(i)
            if isinstance(entry, str):
                if i in (int(j) for j in batch.indices[q]):  # a sequence member is unusable: say why
                    return entry
                continue  # a frame in between: left out
            if entry is not None:
                frames.append(entry)
        if not frames or first not in self._clouds:
            return "no frames"
        try:
            return accumulate(frames, query_pose=batch.poses[q, 0], config=self.config.verify.pseudo)
        except VerificationError as err:
            return reason_of(err)

    def _verify(self, batch: SequenceBatch, q: int, candidates: list[ScanMatch], errors: list[str]
                ) -> list[ScanMatch]:
        """The query's candidates with their verdicts, verified first (best fitness first)."""
        if not candidates:
            return candidates
        points = self._pseudo_cloud(batch, q)
        if isinstance(points, str):
            return [dataclasses.replace(c, verification=points) for c in candidates]
        try:
            query = self.verifier.prepare_query(points)
        except (LcprError, ValueError, RuntimeError) as err:  # small_gicp raises RuntimeError
            errors.append(f"pseudo-cloud of query {int(batch.indices[q, 0])}: {err}")
            return [dataclasses.replace(c, verification="failed") for c in candidates]
        return self.verifier.verify_all(query, candidates, lambda c: self.map.cloud(c.id),
                                        lidar_T_cam=self.config.extrinsics(), errors=errors)
