"""Loop-closure detection: synchronised frames in, keyframe decisions and loop candidates out.

The node, the offline evaluation and the demo all drive this class; it knows
nothing of ROS. One call per synchronised frame::

    detector = LoopDetector(DetectorConfig())
    result = detector.process(Frame(stamp=t, images=[...six...], points=xyz, pose=T))
    if result.loop is not None: ...   # best accepted candidate

Keyframes: every frame, at most one per ``keyframe.min_interval`` seconds, and,
when poses are known and ``keyframe.min_distance`` > 0, only after that many
metres of travel. Matching: the ``match.top_k`` nearest map entries within
``match.max_distance`` (descriptor L2), skipping keyframes of this session newer
than ``match.exclude_recent_s`` seconds or among the last
``match.exclude_recent_count``. Entries of a map loaded from an earlier session
are never excluded by time (their stamps belong to another clock run).

Verification (``verify.enabled``, on by default): every keyframe keeps a compact copy
of its cloud in the map; each candidate is registered against the query's cloud
(:class:`~lcpr_core.verification.GeometricVerifier`) and gets ``verified``,
``fitness``, ``match_T_query`` and ``covariance``. ``Result.loop`` is then the
verified candidate with the best fitness (None when none passed), not the nearest
descriptor. With verification off, ``Result.loop`` is the nearest candidate, as before.
"""
from __future__ import annotations

import dataclasses
import logging
import time
from collections import OrderedDict
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import cast

import numpy as np
import torch

from ..descriptor_map import DescriptorMap, MapConfig, Match
from ..errors import InvalidValueError, MapSchemaError
from ..exclusion import matchable_prefix
from ..keyframes import KeyframeConfig, keyframe_reason
from ..pretrained import AUTO_DISTANCE, effective_max_distance, operating_threshold, resolve_weights
from ..verification import GeometricVerifier, PreparedCloud, Verification, VerifierConfig
from .describer import Describer, ModelConfig
from .preprocess.camera import CameraInput

log = logging.getLogger(__name__)

PREPARED_CACHE = 64  # prepared map clouds kept for the next queries (consecutive queries share candidates)


def _non_negative(obj: object, *names: str) -> None:
    for name in names:
        value = getattr(obj, name)
        if not value >= 0:
            raise InvalidValueError(f"{type(obj).__name__}.{name}={value!r}; it must be >= 0")


@dataclass(frozen=True)
class MatchConfig:
    top_k: int = 10  # candidates per query (all of them are verified)
    # descriptor L2 distance (unit vectors: 0..2) a candidate must be under; AUTO_DISTANCE (-1): 1.0 with
    # verification (every top-k candidate is checked), else the weights file's operating threshold (bundled 0.70)
    max_distance: float = AUTO_DISTANCE
    exclude_recent_s: float = 30.0  # this session's keyframes newer than this are not matched
    exclude_recent_count: int = 0  # and neither are the last N keyframes (0 = off)

    def __post_init__(self) -> None:
        if self.top_k < 1:
            raise InvalidValueError(f"match.top_k={self.top_k}; it must be at least 1")
        if self.max_distance != AUTO_DISTANCE and not self.max_distance >= 0:
            raise InvalidValueError(f"match.max_distance={self.max_distance!r}; accepted: a distance >= 0, or "
                                    f"{AUTO_DISTANCE} for the weights file's operating threshold")
        _non_negative(self, "exclude_recent_s", "exclude_recent_count")


@dataclass(frozen=True)
class SensorConfig:
    require_lidar: bool = True  # no cloud -> no keyframe; False: an empty range image is used


@dataclass(frozen=True)
class DetectorConfig:
    model: ModelConfig = field(default_factory=ModelConfig)
    keyframe: KeyframeConfig = field(default_factory=KeyframeConfig)
    match: MatchConfig = field(default_factory=MatchConfig)
    sensors: SensorConfig = field(default_factory=SensorConfig)
    map: MapConfig = field(default_factory=MapConfig)
    verify: VerifierConfig = field(default_factory=VerifierConfig)
    session: str = "session"  # source name stored with this run's keyframes


@dataclass(frozen=True)
class Frame:
    """One synchronised frame. images: one per camera in rig order, None = camera missing."""

    stamp: float
    images: Sequence[CameraInput | None]
    points: np.ndarray | None  # N x (>=3), LiDAR frame; None = no cloud
    pose: np.ndarray | None = None  # 4 x 4 world_T_base, or None


@dataclass(frozen=True)
class Candidate:
    query_id: int
    match_id: int
    query_stamp: float
    match_stamp: float
    distance: float  # descriptor L2
    rank: int  # 0 = best
    match_position: tuple[float, float, float] | None
    degraded: bool  # the query had a missing camera
    verified: bool = False  # the LiDAR registration accepted this candidate
    fitness: float = 0.0  # overlap of the registered clouds, 0..1
    match_T_query: np.ndarray | None = None  # 4 x 4: query LiDAR frame in the match's (None: not registered)
    covariance: np.ndarray | None = None  # 6 x 6 (x, y, z, roll, pitch, yaw) of match_T_query
    verification: str = "off"  # "accepted", why not (see verification.REJECT_REASONS), "no cloud" or "off"


@dataclass
class Result:
    stamp: float
    keyframe_id: int | None  # None: the frame did not become a keyframe
    reason: str  # "keyframe" or why not: "too soon", "not moved", "no lidar", "out of order"
    candidates: list[Candidate] = field(default_factory=list)
    missing_cameras: tuple[int, ...] = ()
    timings: dict[str, float] = field(default_factory=dict)  # stage -> seconds
    verification: bool = True  # candidates were verified (the loop must be a verified one)
    errors: list[str] = field(default_factory=list)  # why a candidate's verification "failed" (an exception)
    camera_errors: dict[int, str] = field(default_factory=dict)  # camera slot -> why its image was left out

    @property
    def loop(self) -> Candidate | None:
        """The candidate a SLAM back end should receive.

        Verification on: the verified candidate with the best fitness (ties: the nearer
        descriptor), None when none passed. Off: the nearest descriptor.
        """
        if not self.verification:
            return self.candidates[0] if self.candidates else None
        verified = [c for c in self.candidates if c.verified]
        return max(verified, key=lambda c: (c.fitness, -c.distance)) if verified else None


REASONS = ("keyframe", "too soon", "not moved", "no lidar", "out of order")


class LoopDetector:
    """Keyframing, description and matching against a growing descriptor map."""

    def __init__(
        self,
        config: DetectorConfig | None = None,
        *,
        describer: Describer | None = None,
        prior_map: DescriptorMap | None = None,
    ) -> None:
        self.config = config = config if config is not None else DetectorConfig()
        self.describer = describer or Describer(config.model)
        self.map = self._checked(prior_map) if prior_map is not None else DescriptorMap(
            config.map, weights_id=self.describer.weights_id)
        self._session_start = len(self.map)  # rows before this index come from earlier sessions
        self._session_stamps: list[float] = []
        self._last_stamp = -np.inf
        self._kf_stamp: float | None = None  # the newest keyframe decided on (described or about to be)
        self._last_position: np.ndarray | None = None
        self.verifier = GeometricVerifier(config.verify)
        self._prepared: OrderedDict[int, PreparedCloud] = OrderedDict()
        self.weights_threshold = operating_threshold(resolve_weights(config.model.weights))  # the file's, or None

    def _checked(self, prior: DescriptorMap) -> DescriptorMap:
        """A prior map whose descriptors this describer can search: made by the same weights (whitening, turn
        averaging)."""
        ours = self.describer.weights_id
        if prior.weights_id and prior.weights_id != ours:
            raise MapSchemaError(
                f"the map's {len(prior)} descriptors were made by LCPR weights {prior.weights_id}, this detector "
                f"runs weights {ours} (model.weights {self.config.model.weights or '(none)'}, with its whitening and "
                f"turn averaging unless model.whitening / model.turn_average are false); their distances would "
                f"mean nothing. Load the weights the map "
                f"was made with, or start a new map")
        if not prior.weights_id:
            if len(prior):
                log.warning("the prior map (%d keyframes) does not record which weights made it (saved before "
                            "maps did); it is used as it is: if other weights made it, start a new map", len(prior))
            else:
                prior.weights_id = ours
        return prior

    @property
    def max_distance(self) -> float:
        """``match.max_distance`` as used: AUTO_DISTANCE resolved by ``pretrained.effective_max_distance``."""
        return effective_max_distance(self.config.match.max_distance, self.weights_threshold,
                                      verified=self.config.verify.enabled)

    @property
    def session_keyframes(self) -> int:
        return len(self._session_stamps)

    def start_session(self) -> None:
        """Header time went back (a bag played again, a simulator reset): the keyframes so far become an
        earlier session, matched whatever their stamps, and keyframing and the order check start afresh."""
        self._session_start = len(self.map)
        self._session_stamps = []
        self._last_stamp = -np.inf
        self._kf_stamp = None
        self._last_position = None

    def process(self, frame: Frame) -> Result:
        """Decide on one frame; describe, match and store it when it becomes a keyframe."""
        return self.process_batch([frame])[0]

    def process_batch(self, frames: Sequence[Frame]) -> list[Result]:
        """Frames in stamp order, their keyframes described in one network batch (a GPU's throughput), then
        matched, stored and verified one by one in order: each searches only the keyframes before it, as
        :meth:`process` on each frame would. Keyframing depends on stamps and poses only, so it is decided first.
        """
        decided = (self._kf_stamp, self._last_position)
        results, keyframes = [], []
        for frame in frames:
            reason = self._keyframe_reason(frame)
            missing = tuple(i for i, img in enumerate(frame.images) if img is None)
            result = Result(stamp=frame.stamp, keyframe_id=None, reason=reason, missing_cameras=missing)
            if frame.stamp > self._last_stamp:
                self._last_stamp = frame.stamp
            results.append(result)
            if reason == "keyframe":
                keyframes.append((frame, result))
                self._kf_stamp = frame.stamp
                if frame.pose is not None:
                    self._last_position = np.asarray(frame.pose, np.float64)[:3, 3]
        if not keyframes:
            return results
        try:
            descriptors = self._describe(keyframes)
        except Exception:
            self._kf_stamp, self._last_position = decided  # nothing was stored: keyframing goes on as before
            raise
        for (frame, result), desc in zip(keyframes, descriptors, strict=True):
            self._store(frame, result, desc)
        return results

    def _describe(self, keyframes: list[tuple[Frame, Result]]) -> np.ndarray:
        """K x D descriptors of the keyframes, one network call; cameras that could not be used are marked."""
        prepared = []
        for frame, result in keyframes:
            tic = time.perf_counter()
            points = frame.points if frame.points is not None else np.zeros((0, 3), np.float32)
            p = self.describer.prepare(frame.images, points)
            if p.failed:  # unusable images: those cameras count as missing (degraded frame)
                result.missing_cameras = tuple(sorted(set(result.missing_cameras) | set(p.failed)))
                result.camera_errors = dict(p.failed)
            prepared.append(p)
            result.timings["preprocess"] = time.perf_counter() - tic
        tic = time.perf_counter()
        images = prepared[0].images if len(prepared) == 1 else torch.cat([p.images for p in prepared])
        ranges = prepared[0].ranges if len(prepared) == 1 else torch.cat([p.ranges for p in prepared])
        descriptors = self.describer.describe_tensors(images, ranges)
        share = (time.perf_counter() - tic) / len(keyframes)
        for _, result in keyframes:
            result.timings["network"] = share
        return descriptors

    def _store(self, frame: Frame, result: Result, desc: np.ndarray) -> None:
        """Match a described keyframe against the map before it, add it, verify its candidates."""
        points = frame.points if frame.points is not None else np.zeros((0, 3), np.float32)
        tic = time.perf_counter()
        hits = self._search(desc, frame.stamp)
        result.timings["search"] = time.perf_counter() - tic

        tic = time.perf_counter()
        position = None if frame.pose is None else np.asarray(frame.pose, np.float64)[:3, 3]
        (new_id,) = self.map.add(desc, stamps=frame.stamp, poses=None if position is None else position[None],
                                 sources=self.config.session)
        result.keyframe_id = int(new_id)
        degraded = bool(result.missing_cameras)
        result.candidates = [
            Candidate(int(new_id), h.id, frame.stamp, h.stamp, h.distance, rank, h.pose, degraded)
            for rank, h in enumerate(hits)
        ]
        result.timings["add"] = time.perf_counter() - tic

        result.verification = self.config.verify.enabled
        if self.verifier.config is not self.config.verify:  # settings changed at run time
            self.verifier = GeometricVerifier(self.config.verify)
            self._prepared.clear()
        if self.config.verify.enabled:
            tic = time.perf_counter()
            compact = self.verifier.compact(points) if len(points) else np.zeros((0, 3), np.float32)
            self.map.clouds.add(int(new_id), compact)
            result.timings["compact"] = time.perf_counter() - tic
            tic = time.perf_counter()
            result.candidates = self._verify(compact, result.candidates, result.errors)
            result.timings["verify"] = time.perf_counter() - tic
        self._session_stamps.append(frame.stamp)

    def _verify(self, compact: np.ndarray, candidates: list[Candidate], errors: list[str]) -> list[Candidate]:
        """Each candidate with the verdict of registering the query cloud against the match's.

        A registration that raises makes that candidate "failed" and its cause is appended to ``errors``.
        """
        if not candidates:
            return candidates
        query = self.verifier.prepare(compact)
        out = []
        for c in candidates:
            match = self._prepared_cloud(c.match_id)
            if match is None:
                out.append(dataclasses.replace(c, verification="no cloud"))
                continue
            try:
                v = self.verifier.verify_prepared(query, match)
            except Exception as err:  # noqa: BLE001 - a bad pair must not cost the keyframe
                v = Verification(False, "failed", np.eye(4), 0.0)
                errors.append(f"verification of {c.query_id} against {c.match_id}: {type(err).__name__}: {err}")
            out.append(dataclasses.replace(c, verified=v.accepted, fitness=v.fitness,
                                           match_T_query=v.match_T_query, covariance=v.covariance,
                                           verification=v.reason))
        return out

    def _prepared_cloud(self, keyframe_id: int) -> PreparedCloud | None:
        """The match keyframe's prepared cloud, from a small LRU cache."""
        cached = self._prepared.get(keyframe_id)
        if cached is not None:
            self._prepared.move_to_end(keyframe_id)
            return cached
        xyz = self.map.clouds.get(keyframe_id)
        if xyz is None:
            return None
        prepared = self.verifier.prepare(xyz)
        self._prepared[keyframe_id] = prepared
        if len(self._prepared) > PREPARED_CACHE:
            self._prepared.popitem(last=False)
        return prepared

    def _keyframe_reason(self, frame: Frame) -> str:
        if frame.stamp <= self._last_stamp:
            return "out of order"
        if frame.points is None and self.config.sensors.require_lidar:
            return "no lidar"
        position = None if frame.pose is None else np.asarray(frame.pose, np.float64)[:3, 3]
        return keyframe_reason(frame.stamp, position,
                               last_stamp=self._kf_stamp,
                               last_position=self._last_position, min_interval=self.config.keyframe.min_interval,
                               min_distance=self.config.keyframe.min_distance)

    def _search(self, desc: np.ndarray, stamp: float) -> list[Match]:
        """Top-k map entries within max_distance, this session's recent keyframes left out.

        Excluded keyframes are the newest rows of the map, so the search asks for that
        many more hits and drops them: exact however many are excluded.
        """
        cfg = self.config.match
        excluded = self._excluded_count(stamp)
        eligible = len(self.map) - excluded
        if eligible <= 0:
            return []
        # one (D,) descriptor: search returns one list of matches
        hits = cast(list[Match], self.map.search(desc, k=min(cfg.top_k + excluded, len(self.map)),
                                                 max_distance=self.max_distance))
        newest_ids = set(self.map.ids[eligible:].tolist())
        return [h for h in hits if h.id not in newest_ids][: cfg.top_k]

    def _excluded_count(self, stamp: float) -> int:
        """How many of this session's newest keyframes the exclusion rules hide from ``stamp``."""
        cfg = self.config.match
        by_time = len(self._session_stamps) - matchable_prefix(self._session_stamps, stamp, cfg.exclude_recent_s)
        return min(len(self._session_stamps), max(by_time, int(cfg.exclude_recent_count)))
