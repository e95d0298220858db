"""LCPR on a rosbag2: the bag run through the loop detector and scored against the bag's own odometry.

:func:`evaluate_bag` reads synchronised frames with :func:`msg_tools.bags.read_frames`, runs
:class:`lcpr_core.detector.LoopDetector` frame by frame (collecting every candidate: the
precision-recall sweep thresholds afterwards; ``max_distance`` is only the operating point
reported and drawn), runs the Scan Context baseline on the same keyframes and returns an
:class:`~lcpr_core.evaluation.EvaluationReport`; :func:`write_outputs` writes report.json,
pr_curve.png, latency.png, trajectory.png (and posegraph.png). The protocols and figures are the
shared layer's (:mod:`lcpr_core.evaluation`); the command line is ``lcpr_eval``
(:mod:`lcpr_ros.evaluate`), which can take the node's own parameter file. No DDS, no rclpy. It lives
here, above both lcpr_core and msg_tools, because it reads bags.

With geometric verification on (the default), every candidate is also registered against the
LiDAR and each keyframe's verified loop (``Result.loop``: the verified candidate with the best
fitness) is reported as "LCPR + verification" beside the retrieval rows: precision, recall, max
F1 over the fitness, recall at precision 1, the number of loops and their relative-pose error
against the bag's ground truth (odometry poses are world_T_base; the LiDAR extrinsic
base_T_lidar comes from /tf_static, ``base_frame`` to the clouds' frame, identity when the bag
has no such transform, as for KITTI-style bags where base = LiDAR). The verified loops are also
added to a pose graph over a seeded drift of the ground truth
(:func:`lcpr_core.loop_report.pose_graph_proof`, GTSAM): ATE before and after, and posegraph.png.

``odometry="kiss-icp"`` (``lcpr_eval --odometry kiss-icp``): the detector's poses come from KISS-ICP run
on the bag's own clouds (every frame, in order, started at the bag's first pose), as on a robot without
another odometry; the bag's odometry stays the ground truth. The KISS-ICP odometry and every verified
candidate are then replayed through the online back end (:mod:`lcpr_core.backend.replay`): ATE RMSE before
and after against the bag's odometry (``report.backend``) and backend.png. The default, ``"bag"``, hands
the detector the bag's odometry.

Throughput: the network describes a batch on a thread of its own while the batch before is matched and
stored, and verification runs on ``workers`` processes (``lcpr_eval --workers``; default: every core this
process may run on) a few keyframes behind: a keyframe's pairs and clouds are made as it is stored and
its verdicts collected later (:meth:`LoopDetector.finish_verification`), the same verdicts as the node's
immediate verification. ``report.stages`` says where the run's time went.
"""
from __future__ import annotations

import dataclasses
import os
import queue
import threading
import time
from collections import Counter, deque
from collections.abc import Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Generic, TypeVar, cast

import numpy as np

from lcpr_common.progress import progress_bar
from lcpr_core.backend.lidar_odometry import KissConfig, KissOdometry
from lcpr_core.backend.replay import BackendEvaluation, StreamRecorder, evaluate_backend
from lcpr_core.detector import (
    Candidate,
    DescribedBatch,
    DetectorConfig,
    Frame,
    LoopDetector,
    MatchConfig,
    Result,
)
from lcpr_core.errors import InvalidValueError, LcprError
from lcpr_core.evaluation import (
    EvaluationReport,
    MethodRun,
    StageTimes,
    VerifiedLoops,
    evaluate_method,
    evaluate_verified,
    ground_truth,
    plot_latency,
    plot_pr_curves,
    plot_trajectory,
)
from lcpr_core.keyframes import KeyframeConfig
from lcpr_core.lcpr.describer import Describer, ModelConfig
from lcpr_core.lcpr.preprocess.camera import CameraInput
from lcpr_core.loop_report import PublishedLoop, pose_graph_proof
from lcpr_core.posegraph import DriftModel
from lcpr_core.pretrained import effective_max_distance
from lcpr_core.scan_context import ScanContextConfig, ScanContextMatcher, rank_database
from lcpr_core.up import UpConfig
from lcpr_core.verification import SubmapConfig, VerifierConfig
from msg_tools.bags import read_frames, read_static_transforms
from msg_tools.errors import MsgToolsError
from msg_tools.frames import KITTI_TOPICS, NUSCENES_TOPICS, SensorFrame, Topics
from msg_tools.transforms import BASE_FRAME

from .verdicts import candidate_record

#: msg_tools_scans2bag's layout: one LiDAR and its poses, no cameras.
SCAN_TOPICS = dataclasses.replace(NUSCENES_TOPICS, cameras=(), camera_info=(), depth=(), labels=(), lidar="/points",
                                  odom="/odom")
TOPIC_PRESETS: dict[str, Topics] = {"nuscenes": NUSCENES_TOPICS, "kitti": KITTI_TOPICS, "scans": SCAN_TOPICS}
LIDAR_FOR_TOPICS = {"nuscenes": "nuscenes_lidar_top", "kitti": "kitti_hdl64e", "scans": "nuscenes_lidar_top"}
COLLECT_ALL = 2.0 + 1e-3  # unit descriptors are at most 2 apart: every candidate is kept
N_VALUES = (1, 5, 10)
OUTPUT_FILES = ("report.json", "pr_curve.png", "latency.png", "trajectory.png")
POSEGRAPH_FILE = "posegraph.png"  # written besides OUTPUT_FILES when the pose-graph proof ran
BACKEND_FILE = "backend.png"  # written besides OUTPUT_FILES with odometry="kiss-icp"
ODOMETRY_SOURCES = ("bag", "kiss-icp")  # what gives the detector its poses
AUTO_BATCH = 0  # EvalOptions.batch: 1 frame per network call on the CPU, CUDA_BATCH on a GPU
#: frames per network call on a GPU by default: one CUDA graph of that batch, inputs decoded together
CUDA_BATCH = 16
MAX_WORKERS = 64  # verification worker processes at most (verify.processes' range)
#: keyframes whose verification may still be running, per worker, before storing waits for the oldest: enough to
#: keep every worker busy through a keyframe with many candidates, few enough to hold little memory
VERIFY_AHEAD_PER_WORKER = 3


@dataclass(frozen=True)
class EvalOptions:
    """Everything an evaluation run depends on besides the bag."""

    topics: Topics = NUSCENES_TOPICS
    model: ModelConfig = field(default_factory=ModelConfig)
    keyframe: KeyframeConfig = field(default_factory=KeyframeConfig)
    exclude_recent_s: float = MatchConfig().exclude_recent_s  # the detector's defaults (one source)
    radius: float = 9.0  # m: a candidate this close to the query's true position is correct
    # descriptor distance of the reported operating point (AUTO_DISTANCE: the weights file's threshold)
    max_distance: float = MatchConfig().max_distance
    scan_context: ScanContextConfig | None = field(default_factory=ScanContextConfig)  # None = no baseline
    sc_max_distance: float | None = None  # Scan Context distance under which a loop is accepted; None = max F1
    slop: float = 0.05  # s between a cloud and its camera images
    limit: int = 0  # frames to process; 0 = all
    warmup: int = 5  # keyframes left out of the latency statistics
    split_offset: float | None = None  # s after the first keyframe where database/query split; None = first revisit
    verify: VerifierConfig = field(default_factory=VerifierConfig)  # enabled=False: retrieval only
    submap: SubmapConfig = field(default_factory=SubmapConfig)  # local submaps verified instead of single scans
    base_frame: str = BASE_FRAME  # the odometry's child frame: base_T_lidar = /tf_static base_frame -> cloud frame
    drift_seed: int = 0  # seed of the odometry drift of the pose-graph proof
    pose_graph: bool = True  # run the pose-graph proof with the verified loops (needs gtsam)
    # frames whose keyframes are described in one network call (matched in order, as online); AUTO_BATCH: 1 on
    # the CPU, CUDA_BATCH on a GPU
    batch: int = AUTO_BATCH
    lidar_only: bool = False  # no cameras read: every frame described with all camera slots empty
    odometry: str = "bag"  # the detector's poses: the bag's odometry, or "kiss-icp" on its clouds (then the back end)
    # verification worker processes (verify.processes as run; overlapping the network and the map); None: one per
    # core this process may run on; 0: verified in this process, each keyframe as it is stored
    workers: int | None = None

    def __post_init__(self) -> None:
        if self.odometry not in ODOMETRY_SOURCES:
            raise InvalidValueError(f"odometry={self.odometry!r}; accepted: {', '.join(ODOMETRY_SOURCES)}")
        if self.workers is not None and (isinstance(self.workers, bool) or not isinstance(self.workers, int)
                                         or not 0 <= self.workers <= MAX_WORKERS):
            raise InvalidValueError(f"workers={self.workers!r}; accepted: 0..{MAX_WORKERS} verification worker "
                                    "processes (0: verified in this process), or None for one per core")
        MatchConfig(max_distance=self.max_distance)  # a distance >= 0 or AUTO_DISTANCE, refused as the node does
        for name in ("exclude_recent_s", "sc_max_distance", "slop", "limit", "warmup", "drift_seed"):
            value = getattr(self, name)
            if value is not None and not value >= 0:
                raise InvalidValueError(f"{name}={value!r}; it must be >= 0")
        if not self.radius > 0:
            raise InvalidValueError(f"radius={self.radius!r}; it must be a positive distance in metres")
        if self.batch < 0:
            raise InvalidValueError(f"batch={self.batch!r}; it must be >= 1 frame, or {AUTO_BATCH} (auto)")
        if self.lidar_only and self.topics.cameras:
            raise InvalidValueError(f"lidar_only with camera topics {list(self.topics.cameras)}; give no camera topics")
        if not self.lidar_only and self.model.num_cameras != len(self.topics.cameras):
            raise InvalidValueError(f"model.num_cameras={self.model.num_cameras} but the topics name "
                             f"{len(self.topics.cameras)} cameras; they must agree")


@dataclass
class _RunRecord:
    """What the run recorded, per keyframe in keyframe order."""

    detector: LoopDetector
    matcher: ScanContextMatcher | None
    stamps: list[float] = field(default_factory=list)
    lcpr_ids: list[list[int]] = field(default_factory=list)  # map ids, best first
    lcpr_dist: list[list[float]] = field(default_factory=list)
    lcpr_timings: list[dict[str, float]] = field(default_factory=list)
    sc_ids: list[list[int]] = field(default_factory=list)
    sc_dist: list[list[float]] = field(default_factory=list)
    sc_timings: list[dict[str, float]] = field(default_factory=list)
    map_ids: list[int] = field(default_factory=list)
    poses: list[np.ndarray] = field(default_factory=list)  # 4 x 4 world_T_base, NaN where unknown
    verified: list[Candidate | None] = field(default_factory=list)  # the keyframe's verified loop (Result.loop)
    verdicts: dict[str, dict[str, Any]] = field(default_factory=dict)  # every candidate's, by "query-match" ids
    lidar_frame: str | None = None  # frame id of the clouds (the first keyframe's)
    reasons: Counter = field(default_factory=Counter)
    degraded: int = 0
    odometry: _KissRun | None = None  # odometry="kiss-icp": KISS-ICP on the clouds, the stream for the back end

    frames: int = 0

    @property
    def positions(self) -> np.ndarray:
        """(N, 3) keyframe positions, NaN where unknown."""
        return np.asarray(self.poses, np.float64).reshape(-1, 4, 4)[:, :3, 3]


class _KissRun:
    """KISS-ICP over a bag's clouds: the detector's poses, and the stream the back end replays afterwards."""

    def __init__(self, bag: str | os.PathLike[str], opts: EvalOptions) -> None:
        self.bag, self.opts = bag, opts
        self.odometry: KissOdometry | None = None
        self.recorder: StreamRecorder | None = None
        self.extrinsic_source = ""
        self.seconds = 0.0

    def step(self, frame: SensorFrame, det_frame: Frame) -> Frame:
        """``det_frame`` with KISS-ICP's pose of its cloud (None without a cloud); the frame recorded."""
        if det_frame.points is None:
            return dataclasses.replace(det_frame, pose=None)
        tic = time.perf_counter()
        if self.odometry is None:
            ext, self.extrinsic_source = base_T_lidar_of(self.bag, frame.lidar_frame_id,
                                                         base_frame=self.opts.base_frame,
                                                         tf_static=self.opts.topics.tf_static)
            start = np.eye(4) if frame.pose is None else np.asarray(frame.pose, np.float64)
            self.odometry = KissOdometry(KissConfig(threads=max(self.opts.model.threads, 1)), base_T_lidar=ext,
                                         world_T_base0=start)
            self.recorder = StreamRecorder(base_T_lidar=ext)
        assert self.recorder is not None
        pose = self.odometry.register(det_frame.points, frame.stamp)
        self.recorder.add_frame(frame.stamp, odometry=pose, truth=frame.pose)
        self.seconds += time.perf_counter() - tic
        return dataclasses.replace(det_frame, pose=pose)

    def result(self, det_frame: Frame, result: Result) -> None:
        if self.recorder is not None and det_frame.points is not None:
            self.recorder.add_result(result)

    def evaluate(self) -> BackendEvaluation | None:
        """The back end over the recorded stream; None when no frame had a cloud or no truth is known."""
        if self.recorder is None or len(self.recorder) < 2:
            return None
        stream = self.recorder.stream(seconds={"kiss_icp": self.seconds})
        if not np.isfinite(stream.truth).all(axis=(1, 2)).any():
            return None
        return evaluate_backend(stream, odometry_name="KISS-ICP")


T = TypeVar("T")


class Prefetched(Generic[T]):
    """An iterator read ahead by a thread, ``depth`` items at most: reading a bag (sqlite, CDR, numpy; much
    of it outside the GIL) overlaps describing the frames before. Order and items are the iterator's own;
    its exception is raised where the item would have been."""

    _END = object()

    def __init__(self, source: Iterator[T], *, depth: int = 8) -> None:
        self._queue: queue.Queue[object] = queue.Queue(maxsize=max(1, depth))
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._fill, args=(source,), name="lcpr-prefetch", daemon=True)
        self._thread.start()

    def _fill(self, source: Iterator[T]) -> None:
        try:
            for item in source:
                if not self._offer(item):
                    return
            self._offer(self._END)
        except Exception as err:  # noqa: BLE001 - handed to the consumer, raised there
            self._offer(err)

    def _offer(self, item: object) -> bool:
        """Queue ``item``, waiting for room; False when closed first."""
        while not self._stop.is_set():
            try:
                self._queue.put(item, timeout=0.1)
                return True
            except queue.Full:
                continue
        return False

    def __iter__(self) -> Prefetched[T]:
        return self

    def __next__(self) -> T:
        item = self._queue.get()
        if item is self._END:
            self._queue.put(item)  # stays at the end for a later call
            raise StopIteration
        if isinstance(item, Exception):
            raise item
        return cast(T, item)

    def close(self) -> None:
        """Stop reading ahead and wait for the thread (the source can then be closed)."""
        self._stop.set()
        self._thread.join()


def to_detector_frame(frame: SensorFrame, *, cameras: int | None = None) -> Frame:
    """A bag frame as the detector takes it: encoded or RGB images (None = missing; ``cameras`` slots, padded
    with None, when given), N x 3 points, pose."""
    images: list[CameraInput | None] = [None if c is None else (c.jpeg if c.jpeg is not None else c.rgb)
                                        for c in frame.cameras]
    if cameras is not None:
        images += [None] * (cameras - len(images))
    return Frame(stamp=frame.stamp, images=images, points=frame.xyz, pose=frame.pose)


def evaluate_bag(
    bag: str | os.PathLike[str],
    options: EvalOptions | None = None,
    *,
    describer: Describer | None = None,
    progress: bool = True,
) -> EvaluationReport:
    """Run the detector (and the baseline) over a bag and evaluate both; nothing is written."""
    opts = options if options is not None else EvalOptions()
    start = time.perf_counter()
    workers = verification_workers(opts)
    opts = dataclasses.replace(opts, verify=dataclasses.replace(opts.verify, processes=workers))  # as run
    batch = frames_per_call(opts)
    stream = read_frames(bag, topics=opts.topics, slop=opts.slop, decode_compressed=False,
                         min_cameras=0 if opts.lidar_only else 1)
    frames: Prefetched[SensorFrame] | None = None
    total = len(stream) if not opts.limit else min(opts.limit, len(stream))
    bar = progress_bar(total, desc="lcpr_eval", unit="frame", enabled=progress)
    try:
        config = DetectorConfig(
            model=opts.model, keyframe=opts.keyframe,
            match=MatchConfig(top_k=max(N_VALUES), max_distance=COLLECT_ALL, exclude_recent_s=opts.exclude_recent_s),
            verify=opts.verify, submap=opts.submap,
            # each keyframe's up from its walls is for the back end: measured only when it runs (kiss-icp)
            up=UpConfig(enabled=opts.odometry == "kiss-icp"),
        )
        sc_cfg = None if opts.scan_context is None else dataclasses.replace(
            opts.scan_context, exclude_recent_s=opts.exclude_recent_s)
        matcher = None if sc_cfg is None else ScanContextMatcher(sc_cfg)
        record = _RunRecord(LoopDetector(config, describer=describer), matcher)
        if opts.odometry == "kiss-icp":
            record.odometry = _KissRun(bag, opts)
        record.detector.describer.reserve(batch)  # a GPU captures a graph of that batch
        pool = record.detector.verification_processes()  # its workers started before the clock does
        setup = time.perf_counter() - start
        cpu = time.process_time()
        frames = Prefetched(stream, depth=2 * batch + 4)  # the bag is read while the detector works
        ahead = VERIFY_AHEAD_PER_WORKER * workers if pool is not None else 0
        with _Pipeline(record, bar, overlap=record.odometry is None, verify_ahead=ahead) as pipeline:
            pending: list[SensorFrame] = []
            tic = time.perf_counter()
            for frame in frames:
                pipeline.stages.read_wait += time.perf_counter() - tic
                if opts.limit and record.frames + pipeline.queued + len(pending) >= opts.limit:
                    break
                pending.append(frame)
                if len(pending) >= batch:
                    pipeline.add(pending)
                    pending = []
                tic = time.perf_counter()
            if pending:
                pipeline.add(pending)
    finally:
        if frames is not None:
            frames.close()
        stream.close()
        bar.close()
    detect = time.perf_counter() - start - setup
    stages = pipeline.stages
    stages.run, stages.workers = detect, workers if pool is not None else 0
    stages.cpu, stages.cores = time.process_time() - cpu, len(os.sched_getaffinity(0))
    stages.verify_busy, stages.verify_cpu = pipeline.verify_seconds()
    stats = dataclasses.asdict(stream.stats)
    counts = {
        "frames": record.frames, "frames_in_bag": len(stream), "keyframes": len(record.stamps),
        "not_keyframes": {r: n for r, n in record.reasons.items() if r != "keyframe"},
        "degraded_keyframes": record.degraded,
        "keyframes_without_pose": int((~np.isfinite(record.positions).all(axis=1)).sum()),
        "dropped_clouds": stream.stats.dropped_clouds, "reader": stats,
    }
    report = _evaluate(record, opts, sc_cfg, counts, os.fspath(bag))
    if opts.verify.enabled:
        report.verified = _verified(record, opts, report, bag)
    if record.odometry is not None:
        report.backend = record.odometry.evaluate()
        report.counts["backend"] = "run" if report.backend is not None else "not run (no frame with a cloud and a pose)"
    report.wall_time_s, report.setup_time_s, report.detect_time_s = time.perf_counter() - start, setup, detect
    report.stages = stages
    return report


def verification_workers(opts: EvalOptions) -> int:
    """``opts.workers``, or for None one per core this process may run on (its CPU affinity), at most
    MAX_WORKERS; 0 with verification off."""
    if not opts.verify.enabled:
        return 0
    if opts.workers is not None:
        return opts.workers
    return max(1, min(len(os.sched_getaffinity(0)), MAX_WORKERS))


def frames_per_call(opts: EvalOptions) -> int:
    """``opts.batch``, or for AUTO_BATCH what suits the device: CUDA_BATCH frames on a GPU, one on the CPU."""
    if opts.batch != AUTO_BATCH:
        return opts.batch
    return CUDA_BATCH if str(opts.model.device).startswith("cuda") else 1


def base_T_lidar_of(bag: str | os.PathLike[str], lidar_frame: str | None, *, base_frame: str = BASE_FRAME,
                    tf_static: str = "/tf_static") -> tuple[np.ndarray, str]:
    """(base_T_lidar (4, 4), where it came from): ``tf_static`` ``base_frame`` -> ``lidar_frame``, else identity."""
    if lidar_frame is None:
        return np.eye(4), "identity (no keyframe, no cloud frame)"
    if lidar_frame == base_frame:
        return np.eye(4), f"identity (the clouds are in {base_frame!r})"
    try:
        found = read_static_transforms(bag, topic=tf_static).lookup(base_frame, lidar_frame)
    except MsgToolsError as err:
        return np.eye(4), f"identity ({tf_static} unreadable: {err})"
    if found is None:
        return np.eye(4), f"identity (no {tf_static} transform links {base_frame!r} to {lidar_frame!r})"
    return np.asarray(found, np.float64), f"{tf_static} {base_frame} -> {lidar_frame}"


def _verified(record: _RunRecord, opts: EvalOptions, report: EvaluationReport,
              bag: str | os.PathLike[str]) -> VerifiedLoops:
    """Score each keyframe's verified loop and put them in a pose graph over drifted ground truth."""
    row_of = {map_id: row for row, map_id in enumerate(record.map_ids)}
    loops, fitness = [], []
    for row, loop in enumerate(record.verified):
        if loop is not None and loop.match_id in row_of:
            loops.append(PublishedLoop(row, row_of[loop.match_id], loop.match_T_query, loop.covariance))
            fitness.append(loop.fitness)
    base_T_lidar, source = base_T_lidar_of(bag, record.lidar_frame, base_frame=opts.base_frame,
                                           tf_static=opts.topics.tf_static)
    world_T_base = np.asarray(record.poses, np.float64).reshape(-1, 4, 4)
    result = evaluate_verified(report.ground_truth, loops, fitness, world_T_lidar=world_T_base @ base_T_lidar)
    proof, note = None, ""
    missing = int((~np.isfinite(world_T_base).all(axis=(1, 2))).sum())
    if not opts.pose_graph:
        note = "not run (disabled)"
    elif len(world_T_base) < 2:
        note = f"not run ({len(world_T_base)} keyframes)"
    elif missing:
        note = f"not run ({missing} keyframes without an odometry pose)"
    elif not any(loop.match_T_query is not None for loop in loops):
        note = "not run (no verified loop with a pose)"
    else:
        try:
            proof = pose_graph_proof(world_T_base, loops, body_T_lidar=base_T_lidar,
                                     drift=DriftModel(seed=opts.drift_seed))
        except LcprError as err:  # gtsam missing, or a pose it cannot use
            note = f"not run: {err}"
    return dataclasses.replace(result, pose_graph=proof, pose_graph_note=note, base_T_lidar=base_T_lidar,
                               base_T_lidar_source=source, verdicts=record.verdicts)


class _Pipeline:
    """Batches of frames through the detector: each batch's keyframes described (one network call) on a worker
    thread while the batch before is matched and stored here, in order (``overlap``; else one after the other).
    A GPU then decodes and runs the network for the next batch while the CPU searches the map. With
    ``verify_ahead`` > 0 verification runs on the worker processes behind the map, up to that many keyframes
    behind; results are recorded in order as their verdicts come. ``stages`` counts where the time went."""

    def __init__(self, record: _RunRecord, bar: Any, *, overlap: bool, verify_ahead: int = 0) -> None:
        self.record, self.bar, self.overlap, self.verify_ahead = record, bar, overlap, verify_ahead
        self.stages = StageTimes()
        self._worker = ThreadPoolExecutor(max_workers=1, thread_name_prefix="lcpr-describe")
        self._waiting: tuple[list[SensorFrame], list[Frame], Future[DescribedBatch]] | None = None
        self._stored: deque[tuple[SensorFrame, Frame, Result]] = deque()  # stored, not recorded yet
        self._stored_keyframes = 0  # of them keyframes
        self._pool = record.detector.verification_processes()  # its counters: the workers' share
        self._pool_start = (0.0, 0.0) if self._pool is None else (self._pool.worker_busy_seconds,
                                                                  self._pool.worker_cpu_seconds)

    @property
    def queued(self) -> int:
        """Frames handed over but not yet recorded."""
        return (0 if self._waiting is None else len(self._waiting[0])) + len(self._stored)

    def verify_seconds(self) -> tuple[float, float]:
        """(wall, CPU) seconds the verification workers spent on this run's keyframes, all together."""
        if self._pool is None:
            return 0.0, 0.0
        return (self._pool.worker_busy_seconds - self._pool_start[0],
                self._pool.worker_cpu_seconds - self._pool_start[1])

    def add(self, frames: list[SensorFrame]) -> None:
        record = self.record
        det_frames = [to_detector_frame(frame, cameras=record.detector.config.model.num_cameras) for frame in frames]
        if record.odometry is not None:  # the detector runs on KISS-ICP's poses; the bag's stay the truth
            det_frames = [record.odometry.step(frame, det) for frame, det in zip(frames, det_frames, strict=True)]
        described = self._worker.submit(self._describe, det_frames)
        if self.overlap:
            self.finish()  # the batch before, stored while this one is described
        self._waiting = (frames, det_frames, described)
        if not self.overlap:
            self.finish()

    def _describe(self, frames: list[Frame]) -> DescribedBatch:
        tic = time.perf_counter()
        try:
            return self.record.detector.describe_batch(frames)
        finally:
            self.stages.describe += time.perf_counter() - tic

    def finish(self) -> None:
        """Store the batch waiting, if any, and record what is complete."""
        if self._waiting is None:
            return
        frames, det_frames, described = self._waiting
        self._waiting = None
        tic = time.perf_counter()
        batch = described.result()
        toc = time.perf_counter()
        results = self.record.detector.store_batch(batch, defer_verification=self.verify_ahead > 0)
        self.stages.network_wait += toc - tic
        self.stages.store += time.perf_counter() - toc
        self._stored.extend(zip(frames, det_frames, results, strict=True))
        self._stored_keyframes += sum(r.keyframe_id is not None for r in results)
        self._settle(keep=self.verify_ahead)

    def _settle(self, *, keep: int) -> None:
        """Wait for the oldest verdicts until at most ``keep`` keyframes are left verifying; record, in order,
        every stored frame before the first keyframe still verifying."""
        detector = self.record.detector
        tic = time.perf_counter()
        detector.finish_verification(keep=keep)
        toc = time.perf_counter()
        self.stages.verify_wait += toc - tic
        complete = self._stored_keyframes - detector.verifying  # the oldest keyframes stored are finished first
        recorded = 0
        while self._stored:
            frame, det_frame, result = self._stored[0]
            if result.keyframe_id is not None:
                if not complete:
                    break
                complete -= 1
                self._stored_keyframes -= 1
            self._stored.popleft()
            _record(frame, det_frame, result, self.record)
            if self.record.odometry is not None:
                self.record.odometry.result(det_frame, result)
            recorded += 1
        self.stages.record += time.perf_counter() - toc
        if recorded:
            self.bar.update(recorded)
            self.bar.set_postfix(keyframes=len(self.record.stamps), refresh=False)

    def __enter__(self) -> _Pipeline:
        return self

    def __exit__(self, kind: object, *_: object) -> None:
        try:
            if kind is None:
                self.finish()
                self._settle(keep=0)
        finally:
            self._worker.shutdown(wait=True, cancel_futures=True)


def _record(frame: SensorFrame, det_frame: Frame, result: Result, record: _RunRecord) -> None:
    record.frames += 1
    record.reasons[result.reason] += 1
    if result.keyframe_id is None:
        return
    pose = np.full((4, 4), np.nan) if frame.pose is None else np.asarray(frame.pose, np.float64)
    position = pose[:3, 3].copy()
    record.stamps.append(frame.stamp)
    record.poses.append(pose)
    record.map_ids.append(result.keyframe_id)
    if record.lidar_frame is None:
        record.lidar_frame = frame.lidar_frame_id
    record.verified.append(result.loop if result.verification else None)
    if result.verification:
        record.verdicts.update((f"{c.query_id}-{c.match_id}", candidate_record(c)) for c in result.candidates)
    record.lcpr_ids.append([c.match_id for c in result.candidates])
    record.lcpr_dist.append([c.distance for c in result.candidates])
    record.lcpr_timings.append(dict(result.timings))
    record.degraded += bool(result.missing_cameras)
    if record.matcher is not None:
        assert det_frame.points is not None  # keyframes always have a cloud (require_lidar)
        sc = record.matcher.process(det_frame.points, stamp=frame.stamp, position=position, k=max(N_VALUES))
        record.sc_ids.append([m.id for m in sc.matches])  # matcher ids are keyframe rows
        record.sc_dist.append([m.distance for m in sc.matches])
        record.sc_timings.append(sc.timings)


def _ranked(
    ids: list[list[int]], dist: list[list[float]], row_of: dict[int, int], k: int
) -> tuple[np.ndarray, np.ndarray]:
    """Candidate lists -> (N, k) keyframe rows (-1 = none) and distances (inf = none)."""
    out_ids = np.full((len(ids), k), -1, np.int64)
    out_d = np.full((len(ids), k), np.inf)
    for r, (row_ids, row_d) in enumerate(zip(ids, dist, strict=True)):
        for c, (i, d) in enumerate(zip(row_ids[:k], row_d[:k], strict=True)):
            out_ids[r, c], out_d[r, c] = row_of[i], d
    return out_ids, out_d


def _evaluate(record: _RunRecord, opts: EvalOptions, sc_cfg: ScanContextConfig | None, counts: dict[str, Any],
              source: str) -> EvaluationReport:
    k = max(N_VALUES)
    stamps = np.asarray(record.stamps, np.float64)
    positions = record.positions
    split = None if opts.split_offset is None or not len(stamps) else float(stamps[0]) + opts.split_offset
    gt = ground_truth(stamps, positions, radius=opts.radius, exclude_recent_s=opts.exclude_recent_s, split_time=split)
    row_of = {map_id: row for row, map_id in enumerate(record.map_ids)}
    ids, dist = _ranked(record.lcpr_ids, record.lcpr_dist, row_of, k)
    max_distance = effective_max_distance(opts.max_distance, record.detector.weights_threshold,
                                          verified=opts.verify.enabled)
    runs = [MethodRun(name="LCPR", ranked_ids=ids, ranked_distances=dist, threshold=max_distance,
                      timings=record.lcpr_timings, descriptors=_descriptors(record, row_of),
                      distance="descriptor L2 (0..2)")]
    if sc_cfg is not None and record.matcher is not None:
        ids, dist = _ranked(record.sc_ids, record.sc_dist, {i: i for i in range(len(record.sc_ids))}, k)
        scs = record.matcher.descriptors

        def retrieve(q: np.ndarray, db: np.ndarray, kk: int) -> tuple[np.ndarray, np.ndarray]:
            return rank_database(scs[q], scs[db], k=kk, config=sc_cfg)

        runs.append(MethodRun(name="Scan Context", ranked_ids=ids, ranked_distances=dist,
                              threshold=opts.sc_max_distance, timings=record.sc_timings, retrieve=retrieve,
                              distance="column-shift cosine (0..1)"))
    methods = [evaluate_method(run, gt, n_values=N_VALUES, warmup=opts.warmup) for run in runs]
    settings = {
        "topics": dataclasses.asdict(opts.topics), "model": dataclasses.asdict(record.detector.describer.config),
        "keyframe": dataclasses.asdict(opts.keyframe), "exclude_recent_s": opts.exclude_recent_s,
        "radius": opts.radius, "max_distance": max_distance, "sc_max_distance": opts.sc_max_distance,
        "scan_context": None if sc_cfg is None else dataclasses.asdict(sc_cfg), "slop": opts.slop,
        "limit": opts.limit, "warmup": opts.warmup, "n_values": list(N_VALUES), "split_offset": opts.split_offset,
        "verify": dataclasses.asdict(opts.verify), "submap": dataclasses.asdict(opts.submap),
        "base_frame": opts.base_frame, "drift_seed": opts.drift_seed, "pose_graph": opts.pose_graph,
        "odometry": opts.odometry,
    }
    return EvaluationReport(source=source, settings=settings, counts=counts, ground_truth=gt, methods=methods)


def _descriptors(record: _RunRecord, row_of: dict[int, int]) -> np.ndarray | None:
    """(N, D) LCPR descriptors in keyframe order, read back from the detector's map."""
    if not row_of:
        return None
    ids = record.detector.map.ids
    desc = record.detector.map.descriptors
    out = np.zeros((len(row_of), desc.shape[1]), np.float32)
    for pos, map_id in enumerate(ids.tolist()):
        if map_id in row_of:
            out[row_of[map_id]] = desc[pos]
    return out


def write_outputs(report: EvaluationReport, out: str | os.PathLike[str]) -> list[Path]:
    """report.json, the three figures, posegraph.png when the pose-graph proof ran and backend.png when the
    back end ran (``odometry="kiss-icp"``) into ``out``.

    Returns the paths written.
    """
    folder = Path(out)
    paths = [folder / name for name in OUTPUT_FILES]
    report.write_json(paths[0])
    plot_pr_curves(report.methods, paths[1])
    plot_latency(report.methods, paths[2], warmup=int(report.settings.get("warmup", 0)))
    plot_trajectory(report.ground_truth, report.methods, paths[3])
    proof = None if report.verified is None else report.verified.pose_graph
    if proof is not None:
        paths.append(folder / POSEGRAPH_FILE)
        proof.write_plot(paths[-1], title=f"{Path(report.source).name}: verified loops in a GTSAM pose graph "
                                          "(seeded odometry drift)")
    if report.backend is not None:
        paths.append(folder / BACKEND_FILE)
        report.backend.write_plot(paths[-1], title=f"{Path(report.source).name}: {report.backend.odometry_name} "
                                                   "odometry corrected by lcpr_backend with the verified loops")
    return paths
