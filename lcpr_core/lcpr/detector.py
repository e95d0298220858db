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

``match.method`` picks what proposes those candidates (:mod:`lcpr_core.lcpr.proposers`: one module per
method, registered by name): ``lcpr`` (the descriptor, default),
``scan_context`` (the ``match.top_k`` nearest Scan Contexts of the keyframes' clouds,
:class:`~lcpr_core.scan_context.ScanContextRows`, under ``match.sc_max_distance``) or ``fused``
(both lists, the descriptor's first). The exclusion rules are the same for all; the network runs
for every method so that the map stays searchable by any of them. Scan Contexts are kept in memory;
those of a prior map's keyframes are rebuilt from their stored compact clouds.

Verification (``verify.enabled``, on by default): every keyframe keeps a compact copy
of its cloud in the map; each candidate is registered against the query's cloud
(:class:`~lcpr_core.verification.GeometricVerifier`) and gets ``verified``,
``fitness``, ``match_T_query`` and ``covariance``. ``Result.loop`` is then the
verified candidate with the best fitness (None when none passed), not the nearest
descriptor. With verification off, ``Result.loop`` is the nearest candidate.

Submaps (``submap.*``, :mod:`lcpr_core.verification.submap`; "auto" by default: on for a keyframe
whose cloud covers less than 180 deg of azimuth): the query's cloud is verified with its previous
keyframes of this session stitched in by the odometry (``Frame.pose``), and each match's with its
neighbours on both sides; the two never share a keyframe. The map keeps each keyframe's full pose.

An evaluation that wants throughput rather than latency stores keyframes with
``store_batch(batch, defer_verification=True)``: each keyframe's pairs are formed and its clouds stitched
as it is stored (so from the map as it is then, as always), handed to the verification worker processes,
and :meth:`LoopDetector.finish_verification` completes the results later, oldest first, with the verdicts
an immediate verification gives.
"""
from __future__ import annotations

import dataclasses
import itertools
import logging
import math
import time
from collections import deque
from collections.abc import Callable, Hashable, Sequence
from dataclasses import dataclass, field
from typing import Any, TypedDict

import numpy as np

from lcpr_common.params import check_fields, param

from ..descriptor_map import DescriptorMap, MapConfig, Match
from ..errors import InvalidValueError, MapSchemaError, VerificationError
from ..exclusion import matchable_prefix
from ..geometry import invert
from ..keyframes import KeyframeConfig, keyframe_reason
from ..pretrained import AUTO_DISTANCE, effective_max_distance, operating_threshold, resolve_weights
from ..up import UpConfig, estimate_up
from ..verification import (
    GeometricVerifier,
    PreparedCache,
    PreparedCloud,
    Submap,
    SubmapConfig,
    Verification,
    VerifierConfig,
)
from ..verification.processes import CloudRef, Ticket, VerifierProcesses, shared_processes
from ..verification.submap import build_submap, submap_rows
from .describer import Describer, ModelConfig
from .peers import PeerKeyframe, PeerKeyframeError, decode_peer_keyframe, encode_peer_keyframe  # noqa: F401 - lcpr_core.detector's
from .preprocess.camera import CameraInput
from .proposers import (
    BUILT_IN_METHODS,
    CandidateProposer,
    KeyframeInput,
    ProposerSetup,
    SearchRequest,
    check_method,
    make_proposer,
)

log = logging.getLogger(__name__)

_DETECTOR_TOKENS = itertools.count()
PREPARED_CACHE = 64  # prepared map clouds kept for the next queries (consecutive queries share candidates)
#: match.method: what proposes the candidates (docs/lidar_only.md compares them on real LiDARs)
MATCH_METHODS = BUILT_IN_METHODS  # of lcpr_core.lcpr.proposers' registry; a plug-in's name is accepted too
_RIGID_TOLERANCE = 1e-4  # a pose whose rotation block is farther from orthonormal is stored as a position only
_SUBMAP_SPAN = 64  # map rows scanned per stitched keyframe for a submap's neighbours of one source (peers interleave)

#: why :meth:`LoopDetector.add_peer_keyframe` refused a keyframe (``Result.reason``; nothing is stored)
PEER_KEYFRAME = "peer keyframe"  # ``Result.reason`` of a peer keyframe taken
PEER_DESCRIPTOR_SIZE = "peer: wrong descriptor size"
PEER_NOT_FINITE = "peer: descriptor not finite"
PEER_WEIGHTS = "peer: other weights"
PEER_OWN_SESSION = "peer: our own session"
PEER_NO_SESSION = "peer: no session name"
PEER_CLOUD_SHAPE = "peer: bad cloud"
PEER_POSE = "peer: bad pose"
PEER_STAMP = "peer: bad stamp"
PEER_REPEATED = "peer: already taken"
PEER_REFUSALS: tuple[str, ...] = (PEER_DESCRIPTOR_SIZE, PEER_NOT_FINITE, PEER_WEIGHTS, PEER_OWN_SESSION,
                                  PEER_NO_SESSION, PEER_CLOUD_SHAPE, PEER_POSE, PEER_STAMP, PEER_REPEATED)
_CLOUD_REACH = 327.67  # m: the int16 centimetre grid clouds are kept on


class _SubmapArgs(TypedDict):
    """What :func:`build_submap` reads of a window of map rows (``centre``: the keyframe's row in it)."""

    centre: int
    world_T_base: np.ndarray
    stamps: np.ndarray
    cloud: Callable[[int], np.ndarray | None]


@dataclass(frozen=True)
class MatchConfig:
    top_k: int = param(10, "candidates per query", lo=1, hi=1000, dynamic=True)
    # the node's range stops at 2 (unit vectors); the Python API also takes a larger distance (the evaluation
    # collects every candidate with one just above 2), so __post_init__ checks this field itself
    max_distance: float = param(AUTO_DISTANCE, "descriptor L2 distance a candidate must be under (unit vectors: "
                                               "0..2); -1 = automatic: 1.0 with verification (every top-k candidate "
                                               "is checked), without it the weights file's operating threshold "
                                               "(bundled: 0.70; 1.0 for files without one)", lo=AUTO_DISTANCE,
                                hi=2.0, dynamic=True)
    exclude_recent_s: float = param(30.0, "this session's keyframes newer than this many seconds are not matched",
                                    lo=0.0, hi=1e9, dynamic=True)
    exclude_recent_count: int = param(0, "and neither are the last N keyframes; 0 = off", lo=0, hi=2**31 - 1,
                                      dynamic=True)
    method: str = param("lcpr", "what proposes the candidates: lcpr (the descriptor), scan_context (the top_k "
                                "nearest Scan Contexts of the keyframes' clouds) or fused (both lists); the network "
                                "runs for all (docs/lidar_only.md compares them on real LiDARs)",
                        choices=MATCH_METHODS)
    sc_max_distance: float = param(1.0, "Scan Context distance (0..1) a scan_context / fused candidate must be "
                                        "under; 1 = every top-k one (verification decides)", lo=0.0, hi=1.0,
                                   dynamic=True)

    def __post_init__(self) -> None:
        # method: any name registered now, a plug-in's too (its choices list the built-in ones)
        check_fields(self, error=InvalidValueError, prefix="match.", skip=("max_distance", "method"))
        check_method(self.method)
        if self.max_distance != AUTO_DISTANCE and not self.max_distance >= 0:
            raise InvalidValueError(f"match.max_distance={self.max_distance!r}; accepted: a distance >= 0, or "
                                    f"{AUTO_DISTANCE} for the weights file's operating threshold")


@dataclass(frozen=True)
class SensorConfig:
    require_lidar: bool = param(True, "no cloud -> no keyframe; false: an empty range image is used")


@dataclass(frozen=True)
class DetectorConfig:
    model: ModelConfig = field(default_factory=ModelConfig)
    keyframe: KeyframeConfig = field(default_factory=KeyframeConfig)
    match: MatchConfig = field(default_factory=MatchConfig)
    sensors: SensorConfig = field(default_factory=SensorConfig)
    map: MapConfig = field(default_factory=MapConfig)
    verify: VerifierConfig = field(default_factory=VerifierConfig)
    submap: SubmapConfig = field(default_factory=SubmapConfig)  # local submaps verified instead of single scans
    up: UpConfig = field(default_factory=UpConfig)  # each keyframe's up from its walls (Result.up), for the back end
    session: str = param("session", "source name stored with this run's keyframes")


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
    distance: float  # descriptor L2 (a Scan Context candidate: its Scan Context distance, 0..1)
    rank: int  # 0 = best
    match_position: tuple[float, float, float] | None
    degraded: bool  # the query had a missing camera
    verified: bool = False  # the LiDAR registration accepted this candidate
    fitness: float = 0.0  # overlap of the registered clouds, 0..1
    match_T_query: np.ndarray | None = None  # 4 x 4: query LiDAR frame in the match's (None: not registered)
    covariance: np.ndarray | None = None  # 6 x 6 (x, y, z, roll, pitch, yaw) of match_T_query
    verification: str = "off"  # "accepted", why not (see verification.REJECT_REASONS), "no cloud" or "off"
    query_session: str = ""  # the query keyframe's session (DetectorConfig.session, or a peer's)
    match_session: str = ""  # the match keyframe's session (its map entry's source)


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
    up: np.ndarray | None = None  # (3,) unit up in the LiDAR frame from the keyframe's walls; None: not measured

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


REASONS = ("keyframe", "too soon", "not moved", "no lidar", "out of order")  # of process(); peers: PEER_*


@dataclass
class DescribedBatch:
    """Frames whose keyframes are described but not yet matched or stored (:meth:`LoopDetector.describe_batch`)."""

    results: list[Result]  # one per frame, in order; keyframes' filled in by LoopDetector.store_batch
    keyframes: list[tuple[Frame, Result]]
    descriptors: np.ndarray  # K x D, one row per keyframe


@dataclass
class _Verifying:
    """A keyframe's candidates on their way through verification (:meth:`LoopDetector._verify_start`)."""

    candidates: list[Candidate]  # "no cloud" ones settled, the others still unverified
    pairs: list[int]  # the candidates (indices) whose pair is verified
    verdicts: list[Verification | Exception] | None = None  # verified in this process already
    ticket: Ticket | None = None  # else handed to these worker processes
    pool: VerifierProcesses | None = None


@dataclass
class _Deferred:
    """A stored keyframe whose verification is still to be finished (``store_batch(defer_verification=True)``)."""

    result: Result
    verifying: _Verifying
    seconds: float  # spent on it when stored: pairs formed, clouds stitched and sent


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
        self._session_rows: list[int] = []  # this session's keyframes' map rows (peers' rows may lie between them)
        self._peers_taken: set[tuple[str, float]] = set()  # (session, stamp) of the peer keyframes stored
        self._last_stamp = -np.inf
        self._kf_stamp: float | None = None  # the newest keyframe decided on (described or about to be)
        self._last_position: np.ndarray | None = None
        self.verifier = GeometricVerifier(config.verify)
        self._prepared = PreparedCache(PREPARED_CACHE)  # by (centre id, ids stitched)
        self._processes: VerifierProcesses | None = None  # with verify.processes > 0, from shared_processes
        self._deferred: deque[_Deferred] = deque()  # stored keyframes whose verdicts are still to come, oldest first
        self._token = next(_DETECTOR_TOKENS)  # first element of its cloud keys: shared workers keep detectors apart
        self._submap_config = config.submap  # what the prepared clouds were stitched with
        self.weights_threshold = operating_threshold(resolve_weights(config.model.weights))  # the file's, or None
        #: what proposes the candidates (match.method; read once: the method is fixed while a detector runs)
        self.proposer: CandidateProposer[Any] = make_proposer(config.match.method,
                                                              ProposerSetup(self.map, config.match))

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
        self._session_rows = []
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
        return self.store_batch(self.describe_batch(frames))

    def describe_batch(self, frames: Sequence[Frame]) -> DescribedBatch:
        """The first half of :meth:`process_batch`: keyframes decided and described, nothing matched or stored.
        The next batch may be described while this one is stored (:meth:`store_batch`), from another thread,
        as long as batches are described in order and stored in that order."""
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
            return DescribedBatch(results, [], np.zeros((0, self.map.dim), np.float32))
        try:
            descriptors = self._describe(keyframes)
        except Exception:
            self._kf_stamp, self._last_position = decided  # nothing was stored: keyframing state restored
            raise
        return DescribedBatch(results, keyframes, descriptors)

    def store_batch(self, batch: DescribedBatch, *, defer_verification: bool = False) -> list[Result]:
        """The second half of :meth:`process_batch`: each described keyframe matched, stored and verified in
        order; the batch's results.

        ``defer_verification``: each keyframe's candidates are handed to the verification worker processes
        (``verify.processes`` > 0; else verified now) and its result comes back unverified;
        :meth:`finish_verification` completes it. The verdicts are those of an immediate verification: the
        pairs and their clouds are made as the keyframe is stored, from the map as it is then.
        """
        for (frame, result), desc in zip(batch.keyframes, batch.descriptors, strict=True):
            self._store(frame, result, desc, defer=defer_verification)
        return batch.results

    @property
    def verifying(self) -> int:
        """Keyframes stored with ``defer_verification`` whose verification is not finished yet."""
        return len(self._deferred)

    def finish_verification(self, *, keep: int = 0) -> list[Result]:
        """Finish deferred verifications, oldest first, waiting for their verdicts, until at most ``keep`` are left
        (0: all); the results completed (candidates with their verdicts, ``errors``, ``timings["verify"]``: the
        seconds spent storing it plus its verification's as if alone), in the order they were stored."""
        if isinstance(keep, bool) or not isinstance(keep, int) or keep < 0:
            raise InvalidValueError(f"keep={keep!r}; accepted: an integer >= 0 (keyframes left unfinished)")
        done = []
        while len(self._deferred) > keep:
            item = self._deferred.popleft()
            result, verifying = item.result, item.verifying
            result.candidates = self._verify_finish(verifying, result.errors)
            result.timings["verify"] = item.seconds + (verifying.ticket.seconds if verifying.ticket else 0.0)
            done.append(result)
        return done

    def verification_processes(self) -> VerifierProcesses | None:
        """The worker processes verification runs on, started now if they are not yet (their counters tell how
        busy they were); None when verification is off or runs in this process (``verify.processes`` 0)."""
        if not self.config.verify.enabled or self.config.verify.processes <= 0:
            return None
        return self._pool()

    def add_peer_keyframe(self, kf: PeerKeyframe) -> Result:
        """Take a keyframe another robot's detector sent (:class:`~lcpr_core.lcpr.peers.PeerKeyframe`).

        It is matched against this map (this session's keyframes, a prior map's and other peers', never its own
        session's; none excluded by time: it is another session), its candidates verified with its cloud exactly
        as a keyframe of this run would be (its submap stitched from its session's earlier keyframes), and it is
        stored as an entry whose source is its session, so that this run's later keyframes match it. Each pair of
        two robots' keyframes is thus found when the later of the two arrives, in whatever order they come.

        A keyframe this detector cannot use is refused, nothing stored: ``Result.reason`` is one of
        :data:`PEER_REFUSALS` and ``Result.errors`` says which value and what is accepted.
        """
        result = Result(stamp=float(kf.stamp) if isinstance(kf.stamp, (int, float)) else math.nan, keyframe_id=None,
                        reason=PEER_KEYFRAME)
        refused = self._peer_refusal(kf)
        if refused is not None:
            result.reason, why = refused
            result.errors.append(why)
            return result
        desc = np.asarray(kf.descriptor, np.float32).reshape(-1)
        cloud = None if kf.cloud is None else np.asarray(kf.cloud, np.float32).reshape(-1, 3)
        world_T_base = None if kf.pose is None else (np.asarray(kf.pose, np.float64)
                                                     @ invert(self.config.submap.base_T_lidar()))
        points = cloud if cloud is not None else np.zeros((0, 3), np.float32)
        tic = time.perf_counter()
        query = self.proposer.describe(KeyframeInput(desc, points, float(kf.stamp), world_T_base))
        if self.proposer.stage is not None:
            result.timings[self.proposer.stage] = time.perf_counter() - tic
        tic = time.perf_counter()
        hits = self._search(query, self._request([], other_source=kf.session))
        result.timings["search"] = time.perf_counter() - tic

        tic = time.perf_counter()
        (new_id,) = self.map.add(desc, stamps=float(kf.stamp), poses=_map_pose(world_T_base), sources=kf.session)
        self._peers_taken.add((kf.session, float(kf.stamp)))
        result.keyframe_id = int(new_id)
        self.proposer.add(query)
        result.candidates = self._candidates(int(new_id), float(kf.stamp), hits, degraded=False, session=kf.session)
        result.timings["add"] = time.perf_counter() - tic
        self._verifier_for(result)
        if self.config.verify.enabled:
            if cloud is None:
                result.candidates = [dataclasses.replace(c, verification="no cloud") for c in result.candidates]
            else:
                self.map.clouds.add(int(new_id), cloud)
                stored = self.map.clouds.get(int(new_id))  # on the map's grid, as every stored cloud
                tic = time.perf_counter()
                result.candidates = self._verify(cloud if stored is None else stored, result.candidates,
                                                 result.errors)
                result.timings["verify"] = time.perf_counter() - tic
        return result

    def _peer_refusal(self, kf: PeerKeyframe) -> tuple[str, str] | None:
        """(reason, why) when this detector cannot take ``kf``; None when it can."""
        if not isinstance(kf.session, str) or not kf.session:
            return PEER_NO_SESSION, f"peer keyframe session {kf.session!r}; accepted: a non-empty name"
        where = f"peer keyframe of session {kf.session!r} at {kf.stamp!r}"
        if kf.session == self.config.session:
            return PEER_OWN_SESSION, (f"{where}: the session is this detector's own (session={self.config.session!r}); "
                                      "accepted: another robot's session (give each robot its own session name)")
        if isinstance(kf.stamp, bool) or not isinstance(kf.stamp, (int, float)) or not math.isfinite(kf.stamp):
            return PEER_STAMP, f"{where}: the stamp is not a finite time; accepted: seconds"
        if (kf.session, float(kf.stamp)) in self._peers_taken:
            return PEER_REPEATED, f"{where}: a keyframe of that session and stamp is stored already; accepted: new ones"
        desc = np.asarray(kf.descriptor)
        if desc.dtype.kind != "f" or desc.shape != (self.map.dim,):
            return PEER_DESCRIPTOR_SIZE, (f"{where}: descriptor of shape {desc.shape} dtype {desc.dtype}; accepted: "
                                          f"({self.map.dim},) floats, the size of this map's descriptors")
        if not np.isfinite(desc.astype(np.float32)).all():
            return PEER_NOT_FINITE, f"{where}: the descriptor holds NaN or inf (as float32); accepted: finite values"
        ours = self.describer.weights_id
        if kf.weights_id != ours:
            return PEER_WEIGHTS, (f"{where}: made by LCPR weights {kf.weights_id!r}; accepted: this detector's "
                                  f"{ours!r} (other weights' descriptors cannot be compared)")
        if kf.pose is not None:
            pose = np.asarray(kf.pose)
            kept = _map_pose(pose) if pose.shape == (4, 4) and pose.dtype.kind in "fi" else None
            if kept is None or kept.shape != (1, 4, 4):
                return PEER_POSE, (f"{where}: pose of shape {pose.shape}; accepted: None or a finite rigid 4 x 4 "
                                   "world_T_lidar")
        if kf.cloud is not None:
            cloud = np.asarray(kf.cloud)
            if cloud.ndim != 2 or cloud.shape[1] != 3 or cloud.dtype.kind != "f" or not np.isfinite(cloud).all() \
                    or (len(cloud) and float(np.abs(cloud).max()) > _CLOUD_REACH):
                return PEER_CLOUD_SHAPE, (f"{where}: cloud of shape {cloud.shape} dtype {cloud.dtype}; accepted: "
                                          f"None or M x 3 finite floats within {_CLOUD_REACH} m (a compact cloud)")
        return None

    def _candidates(self, new_id: int, stamp: float, hits: Sequence[Any], *, degraded: bool,
                    session: str) -> list[Candidate]:
        """The new keyframe's hits as candidates, best first (unverified yet)."""
        return [Candidate(new_id, h.id, stamp, h.stamp, h.distance, rank, h.pose, degraded, query_session=session,
                          match_session=h.source) for rank, h in enumerate(hits)]

    def _verifier_for(self, result: Result) -> None:
        """Mark whether ``result``'s candidates are verified, and follow verify settings changed at run time."""
        result.verification = self.config.verify.enabled
        if self.verifier.config is not self.config.verify:
            self.verifier = GeometricVerifier(self.config.verify)
            self._prepared.clear()

    def peer_keyframe(self, keyframe_id: int) -> PeerKeyframe:
        """One of this run's keyframes as its peers take it (what ``~/keyframes`` publishes): its descriptor,
        world_T_lidar (the odometry pose through ``submap.lidar_xyz`` / ``lidar_rpy``; None without a full pose)
        and compact cloud (None with verification off)."""
        row = self.map.row_of(keyframe_id)
        if row is None:
            raise InvalidValueError(f"keyframe {keyframe_id} is not in the map ({len(self.map)} keyframes)")
        world_T_base = self.map.pose_matrices([row])[0]
        pose = world_T_base @ self.config.submap.base_T_lidar() if np.isfinite(world_T_base).all() else None
        return PeerKeyframe(stamp=float(self.map.stamps[row]), session=self.map.source_at(row),
                            descriptor=self.map.descriptor_at(row), pose=pose,
                            weights_id=self.describer.weights_id, cloud=self.map.clouds.get(int(keyframe_id)))

    def _describe(self, keyframes: list[tuple[Frame, Result]]) -> np.ndarray:
        """K x D descriptors of the keyframes, one network call; cameras that could not be used are marked."""
        tic = time.perf_counter()
        batch = self.describer.prepare_many(
            [(frame.images, frame.points if frame.points is not None else np.zeros((0, 3), np.float32))
             for frame, _ in keyframes])
        share = (time.perf_counter() - tic) / len(keyframes)
        for (_, result), failed in zip(keyframes, batch.failed, strict=True):
            if failed:  # unusable images: those cameras count as missing (degraded frame)
                result.missing_cameras = tuple(sorted(set(result.missing_cameras) | set(failed)))
                result.camera_errors = dict(failed)
            result.timings["preprocess"] = share
        tic = time.perf_counter()
        descriptors = self.describer.describe_tensors(batch.images, batch.ranges)
        share = (time.perf_counter() - tic) / len(keyframes)
        for _, result in keyframes:
            result.timings["network"] = share
        return descriptors

    def _store(self, frame: Frame, result: Result, desc: np.ndarray, *, defer: bool = False) -> None:
        """Match a described keyframe against the map before it, add it, verify its candidates (``defer``: hand
        them to the workers; :meth:`finish_verification` completes the result)."""
        points = frame.points if frame.points is not None else np.zeros((0, 3), np.float32)
        tic = time.perf_counter()
        query = self.proposer.describe(KeyframeInput(desc, points, frame.stamp, frame.pose))
        if self.proposer.stage is not None:
            result.timings[self.proposer.stage] = time.perf_counter() - tic
        tic = time.perf_counter()
        hits = self._search(query, self._request(self._hidden_rows(frame.stamp)))
        result.timings["search"] = time.perf_counter() - tic

        tic = time.perf_counter()
        (new_id,) = self.map.add(desc, stamps=frame.stamp, poses=_map_pose(frame.pose), sources=self.config.session)
        self._session_rows.append(len(self.map) - 1)
        self._session_stamps.append(frame.stamp)
        result.keyframe_id = int(new_id)
        self.proposer.add(query)
        degraded = bool(result.missing_cameras)
        result.candidates = self._candidates(int(new_id), frame.stamp, hits, degraded=degraded,
                                             session=self.config.session)
        result.timings["add"] = time.perf_counter() - tic
        self._verifier_for(result)
        walls = points  # what the up is measured on
        if self.config.verify.enabled:
            tic = time.perf_counter()
            compact = self.verifier.compact(points) if len(points) else np.zeros((0, 3), np.float32)
            walls = compact  # the same up as the full cloud's within 0.1 deg on the cities, 5-8x faster
            self.map.clouds.add(int(new_id), compact)
            result.timings["compact"] = time.perf_counter() - tic
            tic = time.perf_counter()
            verifying = self._verify_start(compact, result.candidates, together=defer)
            if defer:  # finished in turn, also when it needed no worker
                result.timings["verify"] = time.perf_counter() - tic  # so far; finish_verification adds the rest
                self._deferred.append(_Deferred(result, verifying, result.timings["verify"]))
            else:
                result.candidates = self._verify_finish(verifying, result.errors)
                result.timings["verify"] = time.perf_counter() - tic
        if self.config.up.enabled and len(walls):
            tic = time.perf_counter()
            found = estimate_up(walls, config=self.config.up)
            result.up = None if found is None else found.up
            result.timings["up"] = time.perf_counter() - tic

    def _verify(self, compact: np.ndarray, candidates: list[Candidate], errors: list[str]) -> list[Candidate]:
        """Each candidate with the verdict of registering the query cloud against the match's.

        A registration that raises makes that candidate "failed" and its cause is appended to ``errors``.
        With ``verify.processes`` > 0 the pairs are verified over that many worker processes (the same verdicts).
        """
        return self._verify_finish(self._verify_start(compact, candidates), errors)

    def _verify_start(self, compact: np.ndarray, candidates: list[Candidate], *, together: bool = False
                      ) -> _Verifying:
        """The first half of :meth:`_verify`: the pairs formed and their clouds stitched from the map as it is now
        (the query's submap: its keyframe and those before it; a match's: no row from where the query's own
        keyframes start), then handed to the worker processes, or verified here when there are none."""
        if not candidates:
            return _Verifying(candidates, [], verdicts=[])
        if self.config.submap != self._submap_config:  # settings changed at run time
            self._submap_config = self.config.submap
            self._prepared.clear()
            self._close_processes()
        query_id = candidates[0].query_id
        query_row = self.map.row_of(query_id)
        query_sub = self._submap(query_id, before_only=True)
        first = None if query_sub is None else query_sub.rows[0]  # the query's own keyframes start here
        query = CloudRef((self._token, query_id, "submap"), lambda: compact if query_sub is None else query_sub.xyz)
        scan_alone = CloudRef((self._token, query_id, "scan"), lambda: compact)  # pairs within the query's submap
        # a match's submap ends at the query: keyframes stored after it never enter, verified now or later
        after_query = None if query_row is None else query_row + 1
        pairs: list[tuple[int, CloudRef, CloudRef]] = []  # (candidate index, source, match)
        out = list(candidates)
        for k, c in enumerate(candidates):
            row = self.map.row_of(c.match_id)
            own = row is not None and query_row is not None and self._same_run(row, query_row)  # query's session
            stitched = own and first is not None and row is not None and row >= first  # a keyframe the query
            # stitches: scan against scan; a match of the query's own run ends where the query's submap starts
            match = self._match_cloud(c.match_id, end=first if own and first is not None else after_query)
            if match is None:
                out[k] = dataclasses.replace(c, verification="no cloud")
            else:
                pairs.append((k, scan_alone if stitched else query, match))
        refs = [(source, match) for _, source, match in pairs]
        if self.config.verify.processes > 0 and refs:
            pool = self._pool()
            ticket = pool.submit(refs, together=together)  # together: throughput, a query prepared once
            return _Verifying(out, [k for k, _, _ in pairs], ticket=ticket, pool=pool)
        return _Verifying(out, [k for k, _, _ in pairs], verdicts=self._verify_pairs(refs))

    def _verify_finish(self, verifying: _Verifying, errors: list[str]) -> list[Candidate]:
        """The second half of :meth:`_verify`: the verdicts (waited for) applied to the candidates."""
        verdicts = verifying.verdicts
        if verifying.ticket is not None and verifying.pool is not None:
            pool = verifying.pool
            before = pool.fallbacks
            verdicts = pool.collect(verifying.ticket)
            if pool.fallbacks > before:
                errors.append(f"a verification worker process failed: {pool.fallbacks - before} pairs were "
                              f"verified in the detector's process instead (verify.processes={pool.processes})")
        assert verdicts is not None
        out = verifying.candidates
        for k, v in zip(verifying.pairs, verdicts, strict=True):
            c = out[k]
            if isinstance(v, Exception):  # a bad pair must not cost the keyframe
                errors.append(f"verification of {c.query_id} against {c.match_id}: {type(v).__name__}: {v}")
                v = Verification(False, "failed", np.eye(4), 0.0)
            out[k] = dataclasses.replace(c, verified=v.accepted, fitness=v.fitness, match_T_query=v.match_T_query,
                                         covariance=v.covariance, verification=v.reason)
        return out

    def _pool(self) -> VerifierProcesses:
        """The worker processes of the verify settings now (shared with other detectors of the same settings)."""
        if self._processes is None or self._processes.config != self.config.verify \
                or self._processes.processes == 0:
            self._processes = shared_processes(self.config.verify, processes=self.config.verify.processes,
                                               cache=PREPARED_CACHE)
        return self._processes

    def _verify_pairs(self, pairs: list[tuple[CloudRef, CloudRef]]) -> list[Verification | Exception]:
        """(source, match) pairs' verdicts here, an exception in the place of a pair that raised, with the cache of
        prepared match clouds (``verify.processes`` 0)."""
        self._close_processes()
        sources: dict[Hashable, PreparedCloud] = {}
        out: list[Verification | Exception] = []
        for source_ref, match_ref in pairs:
            try:
                source = sources.get(source_ref.key)
                if source is None:
                    source = sources[source_ref.key] = self.verifier.prepare(source_ref.load())
                match = self._prepared_cloud(match_ref)
                out.append(self.verifier.verify_prepared(source, match))
            except Exception as err:  # noqa: BLE001 - returned in the pair's place
                out.append(err)
        return out

    def _prepared_cloud(self, ref: CloudRef) -> PreparedCloud:
        """A match cloud prepared, from the small LRU cache of prepared clouds (a hit stitches nothing)."""
        cached = self._prepared.get(ref.key)
        return cached if cached is not None else self._prepared.put(ref.key, self.verifier.prepare(ref.load()))

    def _close_processes(self) -> None:
        self._processes = None  # shared: its workers stop when no detector holds it and another replaced it

    def close(self) -> None:
        """Let go of the verification worker processes (they stop once no detector uses them)."""
        self._close_processes()

    def _match_cloud(self, keyframe_id: int, *, end: int | None) -> CloudRef | None:
        """The match keyframe's cloud by key (its submap when submaps apply; no row from ``end`` on, where the
        query's own keyframes start: its cloud alone when it is one of them), keyed by the keyframe (whose LiDAR
        frame the cloud is in) and the keyframes stitched: a cache hit stitches nothing. None without a cloud."""
        window = self._submap_window(keyframe_id, before_only=False, end=end)
        if window is None:
            return None
        at, rows = window[0], window[1]
        key = (self._token, int(keyframe_id), *(int(i) for i in self.map.ids[at[list(rows)]]))

        def load() -> np.ndarray:
            sub = self._submap(keyframe_id, before_only=False, end=end, window=window)
            if sub is None:
                raise VerificationError(f"keyframe {keyframe_id} has no cloud")
            return sub.xyz
        return CloudRef(key, load)

    def _submap(self, keyframe_id: int, *, before_only: bool, end: int | None = None,
                window: tuple[np.ndarray, tuple[int, ...], _SubmapArgs] | None = None) -> Submap | None:
        """A keyframe's cloud with its neighbours of one session stitched in (rows: map rows), its cloud alone when
        submaps are off or do not apply; None without a cloud. ``end``: no row from it on. ``window``:
        :meth:`_submap_window`'s answer when the caller has it."""
        window = window if window is not None else self._submap_window(keyframe_id, before_only=before_only, end=end)
        if window is None:
            return None
        at, rows, args = window
        sub = build_submap(args["centre"], world_T_base=args["world_T_base"], stamps=args["stamps"],
                           cloud=args["cloud"], config=self.config.submap, before_only=before_only, rows=rows)
        return None if sub is None else Submap(sub.xyz, tuple(int(at[r]) for r in sub.rows))

    def _submap_window(self, keyframe_id: int, *, before_only: bool, end: int | None
                       ) -> tuple[np.ndarray, tuple[int, ...], _SubmapArgs] | None:
        """(the window's map rows, ascending; the submap's rows within the window; what build_submap reads) of a
        keyframe's submap, without stitching; None without a cloud. The window holds the keyframe's session
        only (its source, within this run or the earlier ones): peers' keyframes between them are skipped."""
        cfg = self.config.submap
        row = self.map.row_of(keyframe_id)
        if row is None or self.map.clouds.get(keyframe_id) is None:
            return None
        if cfg.mode == "off" or (end is not None and end <= row):
            window = np.array([row], np.int64)
        else:
            # one session: this run's rows or the earlier ones, one source, within reach of max_keyframes
            lo, hi = (self._session_start, len(self.map)) if row >= self._session_start else (0, self._session_start)
            reach = cfg.max_keyframes - 1
            span = _SUBMAP_SPAN * (reach + 1)
            lo, hi = max(lo, row - span), min(hi, row + 1 if before_only else row + span + 1)
            if end is not None:
                hi = min(hi, end)
            codes = self.map.source_codes[lo:hi]
            same = lo + np.flatnonzero(codes == codes[row - lo])
            at = int(np.searchsorted(same, row))
            window = same[max(0, at - reach): at + 1 if before_only else at + reach + 1]
        ids = self.map.ids[window]
        args: _SubmapArgs = {"centre": int(np.searchsorted(window, row)),
                             "world_T_base": self.map.pose_matrices(window), "stamps": self.map.stamps[window],
                             "cloud": lambda r: self.map.clouds.get(int(ids[r]))}
        if len(window) == 1:
            return window, (0,), args
        rows = submap_rows(args["centre"], world_T_base=args["world_T_base"], stamps=args["stamps"],
                           cloud=args["cloud"], config=cfg, before_only=before_only)
        return None if rows is None else (window, rows, args)

    def _same_run(self, a: int, b: int) -> bool:
        """Whether map rows ``a`` and ``b`` are keyframes of one session: one source, both of this run or both
        of the earlier ones."""
        codes = self.map.source_codes
        return bool(codes[a] == codes[b]) and (a >= self._session_start) == (b >= self._session_start)

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

    def _hidden_rows(self, stamp: float) -> list[int]:
        """Map rows of this session's keyframes the exclusion rules hide from a query at ``stamp``."""
        excluded = self._excluded_count(stamp)
        return self._session_rows[len(self._session_rows) - excluded:] if excluded else []

    def _request(self, hidden: list[int], *, other_source: str | None = None) -> SearchRequest | None:
        """The search over the map's rows but ``hidden`` (and, for a peer's keyframe, its own session's rows:
        ``other_source``); None when no row is left. Without peers the hidden rows are the map's newest and
        ``eligible`` alone says which rows are left, as it always did."""
        n = len(self.map)
        cfg = self.config.match
        if other_source is None and (not hidden or hidden[0] == n - len(hidden)):  # the newest rows only
            eligible = n - len(hidden)
            return SearchRequest(eligible, cfg, self.max_distance) if eligible > 0 else None
        allowed = np.ones(n, np.bool_)
        allowed[np.asarray(hidden, np.int64)] = False
        code = None if other_source is None else self.map.source_code_of(other_source)
        if code is not None:
            allowed &= self.map.source_codes != code
        left = np.flatnonzero(allowed)
        if not len(left):
            return None
        eligible = int(left[-1]) + 1
        mask = allowed[:eligible]
        return SearchRequest(eligible, cfg, self.max_distance, allowed=None if mask.all() else mask)

    def _search(self, query: object, request: SearchRequest | None) -> list[Match]:
        """The proposer's top-k map entries for ``query`` under ``request`` (the same exclusion rules for every
        ``match.method``); a hit outside ``request.allowed`` (a method that does not read it) is dropped."""
        if request is None:
            return []
        hits = self.proposer.search(query, request)
        if request.allowed is None:
            return hits
        allowed = request.allowed

        def kept(h: Match) -> bool:
            row = self.map.row_of(h.id)
            return row is not None and row < request.eligible and bool(allowed[row])
        return [h for h in hits if kept(h)]

    def _excluded_count(self, stamp: float) -> int:
        """How many of this session's newest keyframes the exclusion rules hide from ``stamp``."""
        cfg = self.config.match
        by_time = len(self._session_stamps) - matchable_prefix(self._session_stamps, stamp, cfg.exclude_recent_s)
        return min(len(self._session_stamps), max(by_time, int(cfg.exclude_recent_count)))


def _map_pose(pose: np.ndarray | None) -> np.ndarray | None:
    """What the map keeps of a frame's world_T_base: the full pose (1, 4, 4) when it is rigid, else the position
    (1, 3) (odometry with a damaged rotation still keyframes and matches, but gets no submap); None: none."""
    if pose is None:
        return None
    T = np.asarray(pose, np.float64)
    R = T[:3, :3]
    if np.isfinite(T).all() and np.abs(R.T @ R - np.eye(3)).max() <= _RIGID_TOLERANCE and np.linalg.det(R) > 0:
        return T[None]
    return T[None, :3, 3]
