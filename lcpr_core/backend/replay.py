"""A recorded drive replayed through the back end as a robot feeds it; ATE before and after.

    rec = StreamRecorder(base_T_lidar=T)
    rec.add_frame(stamp, odometry=world_T_base, truth=true_world_T_base)   # every LiDAR frame, in order
    rec.add_result(detector.process(frame))                                # a DetectorResult, after its frame
    stream = rec.stream()
    run = replay(stream, inject=20, seed=0, config=BackendConfig())
    before, after = trajectory_error(stream.odometry, stream.truth), trajectory_error(run.trajectory, stream.truth)

One home for what the back end's measurements share: ``benchmarks/tools/backend_ate.py`` (synthetic
cities), ``benchmarks/tools/backend_ate_real.py`` (the Livox sequences) and ``lcpr_eval --odometry
kiss-icp`` record a :class:`LoopStream` (the odometry of every frame, the truth, and each detector
keyframe's verified candidates) and :func:`replay` it: every odometry message in order, and after
each keyframe's frame its verified candidates as loops, the order a robot sees them in.

False loops (``inject``): random pairs of keyframes more than ``FALSE_MIN_M`` apart (by the truth;
``false_min_m`` for a smaller place) and ``MIN_GAP_S`` apart in time, each claimed to be one place with
an identity ``match_T_query`` and a confident covariance (``FALSE_LOOP_COV``: 5 cm, 0.5 deg), mixed in
among the true loops of their query keyframe. Each one is counted as rejected (the consistency check,
or refused as an input) or, when the back end took it, by the weight the robust kernel gives it in the
final graph (``ReplayRun.injected_weights``: 1 = full weight, below 1 = down-weighted).

ATE (:func:`trajectory_error`): RMSE of the positions without alignment (both trajectories start at the
true first pose: the odometry is started there), split into horizontal and vertical, and after the rigid
(SE(3), no scale) fit that suits the estimate best (Umeyama), as tools like evo report it.
"""
from __future__ import annotations

import dataclasses
import json
import math
import os
import time
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from ..atomic import atomic_path
from ..errors import BackendError, InvalidValueError
from ..geometry import invert
from ..loop_report import covariance_lidar_to_body
from ..posegraph import ate_rmse, lidar_to_body, plot_trajectories
from .config import BackendConfig, config_dict
from .graph import BackendStats, PoseGraphBackend

__all__ = ["FALSE_LOOP_COV", "FALSE_MIN_M", "MIN_GAP_S", "BackendEvaluation", "DetectedCandidate", "DetectorResult",
           "LoopStream", "ReplayRun", "StreamRecorder", "TrajectoryAccuracy", "evaluate_backend", "false_loops",
           "loop_pairs", "replay", "trajectory_error"]

FALSE_LOOP_COV = np.diag([0.05**2] * 3 + [math.radians(0.5) ** 2] * 3)  # "confident": as a good ICP claims
FALSE_MIN_M = 20.0  # an injected loop joins keyframes at least this far apart (by the truth): truly wrong
MIN_GAP_S = 30.0  # and this much older (as the detector's exclusion)
_ARRAYS = ("stamps", "truth", "odometry", "keyframes", "loops", "loop_T", "loop_cov", "base_T_lidar")


class DetectedCandidate(Protocol):
    """What the recorder reads of a detector's candidate (lcpr_core.detector.Candidate has it)."""

    @property
    def query_stamp(self) -> float: ...
    @property
    def match_stamp(self) -> float: ...
    @property
    def verified(self) -> bool: ...
    @property
    def match_T_query(self) -> np.ndarray | None: ...  # 4 x 4, LiDAR frames; None: not registered
    @property
    def covariance(self) -> np.ndarray | None: ...  # 6 x 6 of match_T_query; None: not given


class DetectorResult(Protocol):
    """What the recorder reads of a detector's result of one frame (lcpr_core.detector.Result has it), so that
    the back end takes any detector's output without importing a detector."""

    @property
    def stamp(self) -> float: ...
    @property
    def keyframe_id(self) -> int | None: ...  # None: the frame did not become a keyframe
    @property
    def up(self) -> np.ndarray | None: ...  # (3,) up from the keyframe's walls, LiDAR frame; None: not measured
    @property
    def candidates(self) -> Sequence[DetectedCandidate]: ...


@dataclass
class LoopStream:
    """What the robot saw, in order: odometry per frame and, per detector keyframe, its verified loops."""

    stamps: np.ndarray  # (N,) frame stamps, increasing
    truth: np.ndarray  # (N, 4, 4) world_T_base (NaN where unknown)
    odometry: np.ndarray  # (N, 4, 4) world_T_base of the odometry under test
    keyframes: np.ndarray  # (K,) frame indices that became detector keyframes
    loops: np.ndarray  # (L, 2) frame indices (query, match) of verified candidates
    loop_T: np.ndarray  # (L, 4, 4) match_T_query (LiDAR frames)
    loop_cov: np.ndarray  # (L, 6, 6), NaN where the detector gave none
    base_T_lidar: np.ndarray  # (4, 4)
    seconds: dict[str, float] = field(default_factory=dict)  # time spent per stage while recording
    # (K, 3) up measured from each keyframe's walls (LiDAR frame), NaN: none; not given = none measured
    ups: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))

    def __post_init__(self) -> None:
        if self.ups.shape == (0, 3):
            self.ups = np.full((len(self.keyframes), 3), np.nan)
        if self.ups.shape != (len(self.keyframes), 3):
            raise InvalidValueError(f"LoopStream ups {self.ups.shape} for {len(self.keyframes)} keyframes; "
                                    "expected (K, 3)")
        n = len(self.stamps)
        if self.truth.shape != (n, 4, 4) or self.odometry.shape != (n, 4, 4):
            raise InvalidValueError(f"LoopStream of {n} stamps with truth {self.truth.shape} and odometry "
                                    f"{self.odometry.shape}; expected ({n}, 4, 4) each")
        if n > 1 and not np.all(np.diff(self.stamps) > 0):
            raise InvalidValueError("LoopStream stamps do not increase; expected frames in stamp order")
        if not np.isfinite(self.odometry).all():
            raise InvalidValueError("LoopStream odometry holds NaN or inf; every frame needs an odometry pose")
        nl = len(self.loops)
        if self.loops.shape != (nl, 2) or self.loop_T.shape != (nl, 4, 4) or self.loop_cov.shape != (nl, 6, 6):
            raise InvalidValueError(f"LoopStream loops {self.loops.shape}, loop_T {self.loop_T.shape}, loop_cov "
                                    f"{self.loop_cov.shape}; expected (L, 2), (L, 4, 4), (L, 6, 6)")
        if nl and (self.loops.min() < 0 or self.loops.max() >= n):
            raise InvalidValueError(f"LoopStream loops name frames {self.loops.min()}..{self.loops.max()}; "
                                    f"expected 0..{n - 1}")

    @property
    def length_m(self) -> float:
        """Distance travelled (m) by the truth (the odometry where the truth is unknown)."""
        pos = np.where(np.isfinite(self.truth[:, :3, 3]), self.truth[:, :3, 3], self.odometry[:, :3, 3])
        return float(np.linalg.norm(np.diff(pos, axis=0), axis=1).sum()) if len(pos) > 1 else 0.0

    def without_loops(self) -> LoopStream:
        """The same stream with no detected loop (what the back end does on odometry alone)."""
        return dataclasses.replace(self, loops=self.loops[:0], loop_T=self.loop_T[:0], loop_cov=self.loop_cov[:0])

    def without_ups(self) -> LoopStream:
        """The same stream with no measured up (loops alone)."""
        return dataclasses.replace(self, ups=np.full((len(self.keyframes), 3), np.nan))

    def with_loops(self, loops: Iterable[tuple[float, float, np.ndarray, np.ndarray | None]], *,
                   tolerance: float = 1e-3) -> tuple[LoopStream, int]:
        """(this stream with ``loops`` added, how many were left out): each ``(query_stamp, match_stamp,
        match_T_query, covariance or None)`` attached to the frames at those stamps (within ``tolerance``
        s); a loop naming a stamp no frame has is left out. For loops found apart from the recording (a
        node's output)."""
        pairs, poses, covs, skipped = [], [], [], 0
        for q, m, rel, cov in loops:
            query, match = _row_at(self.stamps, q, tolerance), _row_at(self.stamps, m, tolerance)
            if query is None or match is None:
                skipped += 1
                continue
            pairs.append([query, match])
            poses.append(np.asarray(rel, np.float64))
            covs.append(np.full((6, 6), np.nan) if cov is None else np.asarray(cov, np.float64))
        out = dataclasses.replace(
            self, loops=np.concatenate([self.loops, np.array(pairs, np.int64).reshape(-1, 2)]),
            loop_T=np.concatenate([self.loop_T, np.array(poses).reshape(-1, 4, 4)]),
            loop_cov=np.concatenate([self.loop_cov, np.array(covs).reshape(-1, 6, 6)]))
        return out, skipped

    def with_ups(self, ups: Iterable[tuple[float, np.ndarray]], *, tolerance: float = 1e-3) -> tuple[LoopStream, int]:
        """(this stream with each ``(stamp, up)`` set on the keyframe at that stamp (within ``tolerance`` s), how
        many named no keyframe): ups measured apart from the recording (a node's ``~/up``)."""
        out, skipped = self.ups.copy(), 0
        key_stamps = self.stamps[self.keyframes]
        for t, up in ups:
            k = _row_at(key_stamps, t, tolerance)
            if k is None:
                skipped += 1
                continue
            out[k] = np.asarray(up, np.float64).reshape(3)
        return dataclasses.replace(self, ups=out), skipped

    def save(self, path: str | os.PathLike[str]) -> None:
        """Write the stream as .npz (atomically, no pickled objects): a cache of a slow recording."""
        with atomic_path(path) as tmp, open(tmp, "wb") as fh:
            np.savez(fh, **{k: getattr(self, k) for k in _ARRAYS}, ups=self.ups,
                     seconds=np.array(json.dumps(self.seconds)))

    @classmethod
    def load(cls, path: str | os.PathLike[str]) -> LoopStream:
        with np.load(path, allow_pickle=False) as z:
            return cls(**{k: z[k] for k in _ARRAYS}, seconds=json.loads(str(z["seconds"])),
                       ups=z["ups"] if "ups" in z.files else np.zeros((0, 3)))


def _row_at(stamps: np.ndarray, t: float, tolerance: float) -> int | None:
    """The row of ``stamps`` (increasing) nearest ``t`` when within ``tolerance`` s, else None."""
    if not len(stamps):
        return None
    row = int(np.argmin(np.abs(stamps - float(t))))
    return row if abs(stamps[row] - float(t)) <= tolerance else None


class StreamRecorder:
    """Collects a :class:`LoopStream` while a drive runs: frames (odometry, truth) and detector results."""

    def __init__(self, *, base_T_lidar: np.ndarray) -> None:
        self.base_T_lidar = np.asarray(base_T_lidar, np.float64)
        if self.base_T_lidar.shape != (4, 4) or not np.isfinite(self.base_T_lidar).all():
            raise InvalidValueError(f"base_T_lidar of shape {self.base_T_lidar.shape}; expected a finite (4, 4) pose")
        self._stamps: list[float] = []
        self._odometry: list[np.ndarray] = []
        self._truth: list[np.ndarray] = []
        self._index: dict[float, int] = {}
        self._keyframes: list[int] = []
        self._ups: list[np.ndarray] = []
        self._loops: list[tuple[int, int]] = []
        self._loop_T: list[np.ndarray] = []
        self._loop_cov: list[np.ndarray] = []
        self.skipped_loops = 0  # verified candidates naming a frame that was never recorded

    def __len__(self) -> int:
        return len(self._stamps)

    def add_frame(self, stamp: float, *, odometry: np.ndarray, truth: np.ndarray | None) -> int:
        """Record one frame (its odometry pose and true pose, None = unknown); its index."""
        t = float(stamp)
        if self._stamps and not t > self._stamps[-1]:
            raise InvalidValueError(f"frame stamp {t!r} is not after the previous frame's {self._stamps[-1]!r}; "
                                    "expected frames in stamp order")
        self._index[t] = len(self._stamps)
        self._stamps.append(t)
        self._odometry.append(np.asarray(odometry, np.float64).reshape(4, 4))
        self._truth.append(np.full((4, 4), np.nan) if truth is None else np.asarray(truth, np.float64).reshape(4, 4))
        return len(self._stamps) - 1

    def add_keyframe(self, stamp: float, *, up: np.ndarray | None = None) -> int:
        """Mark the recorded frame at ``stamp`` as a detector keyframe (``up``: measured from its walls); its index."""
        index = self._index.get(float(stamp))
        if index is None:
            raise InvalidValueError(f"a keyframe at stamp {stamp!r}, a frame never recorded; add_frame comes first")
        self._keyframes.append(index)
        self._ups.append(np.full(3, np.nan) if up is None else np.asarray(up, np.float64).reshape(3))
        return index

    def add_loop(self, query_stamp: float, match_stamp: float, match_T_query: np.ndarray,
                 covariance: np.ndarray | None) -> bool:
        """A verified loop between two recorded frames; False (counted in ``skipped_loops``) when one was not."""
        query, match = self._index.get(float(query_stamp)), self._index.get(float(match_stamp))
        if query is None or match is None:
            self.skipped_loops += 1
            return False
        self._loops.append((query, match))
        self._loop_T.append(np.asarray(match_T_query, np.float64))
        self._loop_cov.append(np.full((6, 6), np.nan) if covariance is None else np.asarray(covariance, np.float64))
        return True

    def add_result(self, result: DetectorResult) -> None:
        """A detector result of a recorded frame: a keyframe, and its verified candidates as loops."""
        if result.keyframe_id is None:
            return
        if float(result.stamp) not in self._index:
            raise InvalidValueError(f"a detector result at stamp {result.stamp!r}, a frame never recorded; "
                                    "add_frame comes first")
        self.add_keyframe(result.stamp, up=result.up)
        for c in result.candidates:
            if c.verified and c.match_T_query is not None:
                self.add_loop(c.query_stamp, c.match_stamp, c.match_T_query, c.covariance)

    def stream(self, *, seconds: dict[str, float] | None = None) -> LoopStream:
        """Everything recorded so far."""
        return LoopStream(
            stamps=np.array(self._stamps, np.float64), truth=np.array(self._truth).reshape(-1, 4, 4),
            odometry=np.array(self._odometry).reshape(-1, 4, 4), keyframes=np.array(self._keyframes, np.int64),
            loops=np.array(self._loops, np.int64).reshape(-1, 2), loop_T=np.array(self._loop_T).reshape(-1, 4, 4),
            loop_cov=np.array(self._loop_cov).reshape(-1, 6, 6), base_T_lidar=self.base_T_lidar.copy(),
            seconds=dict(seconds or {}), ups=np.array(self._ups, np.float64).reshape(-1, 3))


# ============================================================================ replay
@dataclass
class ReplayRun:
    """What the back end made of a stream."""

    trajectory: np.ndarray  # (N, 4, 4) corrected world_T_base of every frame
    accepted: np.ndarray  # (L,) bool per detected loop
    injected: int  # false loops added
    injected_rejected: int  # of those, rejected by the consistency check or refused as inputs
    injected_weights: list[float]  # robust-kernel weight of each accepted false loop in the final graph
    loop_ms: list[float]  # time of each add_loop call
    refused: list[str]  # why each refused loop (BackendError) was refused
    stats: BackendStats
    up_refused: list[str] = field(default_factory=list)  # why each refused measured up was refused

    @property
    def injected_down_weighted(self) -> int:
        """Accepted false loops that the robust kernel weighs less than a true one (weight < 1)."""
        return sum(w < 1.0 for w in self.injected_weights)


def false_loops(stream: LoopStream, *, count: int, seed: int, min_distance: float = FALSE_MIN_M
                ) -> dict[int, list[int]]:
    """``count`` random false loops: query frame -> match frames (module docstring); none when none fit.

    ``min_distance``: m (by the truth) between the two keyframes an injected loop joins.
    """
    if count < 0:
        raise InvalidValueError(f"count={count!r}; expected a number of false loops >= 0")
    if not min_distance > 0:
        raise InvalidValueError(f"min_distance={min_distance!r}; expected a distance > 0 m")
    rng = np.random.default_rng(seed)
    positions, stamps, kf = stream.truth[:, :3, 3], stream.stamps, stream.keyframes
    choices: dict[int, list[int]] = {}
    for q in kf:
        if stamps[q] - stamps[0] <= MIN_GAP_S or not np.isfinite(positions[q]).all():
            continue
        far = np.linalg.norm(positions[kf] - positions[q], axis=1) > min_distance  # NaN: False
        older = [int(m) for m, ok in zip(kf, far, strict=True) if ok and stamps[q] - stamps[m] > MIN_GAP_S]
        if older:
            choices[int(q)] = older
    out: dict[int, list[int]] = {}
    queries = sorted(choices)
    for _ in range(count if queries else 0):
        q = int(rng.choice(queries))
        out.setdefault(q, []).append(int(rng.choice(choices[q])))
    return out


def replay(stream: LoopStream, *, inject: int = 0, seed: int = 0, config: BackendConfig | None = None,
           false_min_m: float = FALSE_MIN_M) -> ReplayRun:
    """Feed the back end online: odometry per frame, after each keyframe its loops (and the false ones).

    ``config``: the back end's (its ``base_T_lidar`` is the stream's); None = the defaults. ``seed``
    draws the false loops (``false_min_m`` apart at least) and the order they come in among the true ones.
    """
    rng = np.random.default_rng(seed)
    by_query: dict[int, list[int]] = {}
    for k, (q, _) in enumerate(stream.loops):
        by_query.setdefault(int(q), []).append(k)
    ups = {int(i): u for i, u in zip(stream.keyframes, stream.ups, strict=True) if np.isfinite(u).all()}
    false_at = false_loops(stream, count=inject, seed=seed + 1, min_distance=false_min_m) if inject else {}
    config = dataclasses.replace(config or BackendConfig(), base_T_lidar=stream.base_T_lidar)
    g = PoseGraphBackend(config)
    accepted = np.zeros(len(stream.loops), bool)
    rejected_false = 0
    taken_false: list[tuple[float, float]] = []
    refused: list[str] = []
    up_refused: list[str] = []
    loop_ms: list[float] = []
    for i, (t, pose) in enumerate(zip(stream.stamps, stream.odometry, strict=True)):
        g.add_odometry(float(t), pose)
        if i in ups:
            try:
                g.add_up(float(t), ups[i])
            except BackendError as err:
                up_refused.append(str(err))
        events = [(True, k) for k in by_query.get(i, [])] + [(False, m) for m in false_at.get(i, [])]
        for e in rng.permutation(len(events)):  # the false loops come in among the true ones
            detected, k = events[int(e)]
            tic = time.perf_counter()
            try:
                if detected:
                    cov = stream.loop_cov[k]
                    accepted[k] = g.add_loop(float(t), float(stream.stamps[stream.loops[k, 1]]), stream.loop_T[k],
                                             cov if np.isfinite(cov).all() else None)
                elif g.add_loop(float(t), float(stream.stamps[k]), np.eye(4), FALSE_LOOP_COV):
                    taken_false.append((float(t), float(stream.stamps[k])))
                else:
                    rejected_false += 1
            except BackendError as err:
                refused.append(str(err))
                rejected_false += not detected
            loop_ms.append((time.perf_counter() - tic) * 1e3)
    _, trajectory = g.trajectory()
    weights = [_false_loop_weight(g, q, m) for q, m in taken_false]
    return ReplayRun(trajectory, accepted, sum(len(v) for v in false_at.values()), rejected_false, weights, loop_ms,
                     refused, g.stats(), up_refused)


def _false_loop_weight(g: PoseGraphBackend, query: float, match: float) -> float:
    """The robust kernel's weight of an accepted false loop in the final graph (1 = full weight).

    Its whitened residual ``r`` (the loop's identity claim against the corrected poses, weighed by its
    covariance moved to the base frames), and the kernel's weight at ``r``: Huber ``min(1, k / r)``,
    Cauchy ``1 / (1 + (r / k)^2)``, none 1.
    """
    ext = g.config.base_T_lidar
    measured = lidar_to_body(np.eye(4), ext)
    cov = covariance_lidar_to_body(FALSE_LOOP_COV, np.eye(4), ext)
    rel = invert(measured) @ invert(g.pose(match)) @ g.pose(query)
    rotvec = _rotation_vector(rel[:3, :3])
    err = np.concatenate([rel[:3, 3], rotvec])
    r = math.sqrt(float(err @ np.linalg.solve(cov, err)))
    k = g.config.loops.robust_param
    kernel = g.config.loops.robust
    if kernel == "huber":
        return min(1.0, k / r) if r > 0 else 1.0
    if kernel == "cauchy":
        return 1.0 / (1.0 + (r / k) ** 2)
    return 1.0


def _rotation_vector(r: np.ndarray) -> np.ndarray:
    """Axis times angle (rad) of a (3, 3) rotation."""
    angle = math.acos(max(-1.0, min(1.0, (float(np.trace(r)) - 1.0) / 2.0)))
    axis = np.array([r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]])
    s = math.sin(angle)
    return axis / 2.0 if s < 1e-9 else axis * (angle / (2.0 * s))


# ============================================================================ errors
@dataclass(frozen=True)
class TrajectoryAccuracy:
    """ATE RMSE (m) of a trajectory against the truth (module docstring)."""

    rmse: float  # 3-D, no alignment
    horizontal: float  # x, y part
    vertical: float  # z part
    aligned: float  # 3-D after the best rigid fit (Umeyama, no scale)
    frames: int  # frames with a known truth

    def text(self) -> str:
        return (f"{_metres(self.rmse)} (horizontal {_metres(self.horizontal)}, vertical {_metres(self.vertical)}; "
                f"SE(3)-aligned {_metres(self.aligned)})")

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


def _metres(value: float) -> str:
    """Metres to the centimetre, or to the millimetre under 1 m (a LIO's drift is a few cm)."""
    return f"{value:.3f} m" if abs(value) < 1.0 else f"{value:.2f} m"


def trajectory_error(estimate: np.ndarray, truth: np.ndarray) -> TrajectoryAccuracy:
    """ATE of (N, 4, 4) ``estimate`` against (N, 4, 4) ``truth``, over the frames whose truth is known."""
    est, ref = np.asarray(estimate, np.float64), np.asarray(truth, np.float64)
    if est.shape != ref.shape or est.ndim != 3 or est.shape[1:] != (4, 4):
        raise InvalidValueError(f"estimate {est.shape} and truth {ref.shape}; expected two (N, 4, 4) trajectories")
    known = np.isfinite(ref).all(axis=(1, 2))
    if not known.any():
        raise InvalidValueError("the truth holds no finite pose; an ATE needs at least one")
    e, r = est[known, :3, 3], ref[known, :3, 3]
    err = e - r
    return TrajectoryAccuracy(rmse=ate_rmse(e, r), horizontal=float(np.sqrt((err[:, :2] ** 2).sum(axis=1).mean())),
                           vertical=float(np.sqrt((err[:, 2] ** 2).mean())), aligned=ate_rmse(e, r, align=True),
                           frames=int(known.sum()))


def loop_pairs(stream: LoopStream, run: ReplayRun) -> list[tuple[int, int]]:
    """(query, match) frame indices of the detected loops the back end accepted (for the plot)."""
    return [(int(q), int(m)) for (q, m), ok in zip(stream.loops, run.accepted, strict=True) if ok]



# ============================================================================ a whole evaluation
@dataclass
class BackendEvaluation:
    """An odometry, the back end's correction of it and both ATEs (``lcpr_eval --odometry kiss-icp``)."""

    odometry_name: str  # what made the odometry, for the report and the plot
    stream: LoopStream
    run: ReplayRun
    before: TrajectoryAccuracy
    after: TrajectoryAccuracy
    config: BackendConfig

    def to_dict(self) -> dict[str, Any]:
        ms = np.asarray(self.run.loop_ms)
        return {"odometry": self.odometry_name, "frames": len(self.stream.stamps), "length_m": self.stream.length_m,
                "keyframes": len(self.stream.keyframes), "loops": len(self.stream.loops),
                "loops_accepted": int(self.run.accepted.sum()), "loops_refused": len(self.run.refused),
                "ups_taken": self.run.stats.ups, "ups_refused": len(self.run.up_refused),
                "ate_odometry": self.before.to_dict(), "ate_backend": self.after.to_dict(),
                "add_loop_ms_p50": float(np.median(ms)) if len(ms) else None, "config": config_dict(self.config)}

    def text(self) -> str:
        ratio = f" ({self.after.rmse / self.before.rmse:.0%} of before)" if self.before.rmse > 0 else ""
        ups = f", the walls' up of {self.run.stats.ups} keyframes" if self.run.stats.ups else ""
        return (f"{self.odometry_name} odometry ATE {self.before.text()}\n"
                f"  with the back end ({int(self.run.accepted.sum())} of {len(self.stream.loops)} verified loops "
                f"accepted{ups}) {self.after.text()}{ratio}")

    def write_plot(self, path: str | os.PathLike[str], *, title: str) -> None:
        """Top view of the truth, the odometry and the corrected trajectory (frames with a known truth), PNG."""
        known = np.isfinite(self.stream.truth).all(axis=(1, 2))
        row = np.cumsum(known) - 1  # frame index -> index among the known frames
        pairs = [(int(row[q]), int(row[m])) for q, m in loop_pairs(self.stream, self.run) if known[q] and known[m]]
        plot_trajectories(self.stream.truth[known], self.stream.odometry[known], self.run.trajectory[known], path,
                          loops=pairs, title=title)


def evaluate_backend(stream: LoopStream, *, odometry_name: str, config: BackendConfig | None = None
                     ) -> BackendEvaluation:
    """Replay ``stream`` through the back end (no false loops) and measure the ATE before and after."""
    config = config or BackendConfig()
    run = replay(stream, config=config)
    return BackendEvaluation(odometry_name, stream, run, trajectory_error(stream.odometry, stream.truth),
                             trajectory_error(run.trajectory, stream.truth), config)
