"""A run relocalised in a prior map: the detector against yesterday's descriptor map, the back end against its
graph, and how soon and how well the run is placed (``lcpr_relocalize``).

    prior = build_prior(steps[:split], detector=DetectorConfig(...), session="prior")    # map + graph
    result = relocalize(prior, steps[split:], move=T, session="run")                    # a new session
    print(result.text())

Each :class:`Step` is a LiDAR frame with its odometry and a reference pose. The prior is what a first run
leaves: the detector's map (its keyframes, descriptors and compact clouds) and the back end's graph (its
odometry and its own verified loops), saved and loaded back as files, the graph held at its estimates
(``PoseGraphBackend.load(hold=True)``). The run's odometry is moved by ``move`` (an arbitrary rigid
transform: its frame owes nothing to the map's), its keyframes are matched against the prior map, and its
verified candidates that name the prior's session go to the back end as inter-session loops.

What is measured: when the run was anchored (travel since it first came within ``near_m`` of a prior
keyframe), the error of ``map_T_odom`` where the robot is (``map_T_odom @ odom``: a frame's error at its
origin would scale a rotation error by the lever to wherever the origin lies), the run's ATE from anchoring on
and whether each inter-session loop's relative pose was right (0.3 m / 2 deg, and 0.5 m / 3 deg). Errors are
taken **against the map**: the reference pose moved by the correction the prior map has at its nearest
keyframe (within ``LOCAL_M``), i.e. where the map has that place; the prior's own error against the reference
(its drift left after its own loops) is reported apart, with the run's ATE against the reference itself.
"""
from __future__ import annotations

import dataclasses
import math
import os
import tempfile
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from lcpr_common.cli import tool_main
from lcpr_common.progress import progress_iter
from lcpr_core.backend import BackendConfig, PoseGraphBackend
from lcpr_core.descriptor_map import DescriptorMap
from lcpr_core.detector import DetectorConfig, Frame, LoopDetector
from lcpr_core.errors import BackendError
from lcpr_core.geometry import invert, rotation_angle_deg
from lcpr_core.loop_report import pose_right
from lcpr_core.posegraph import ate_rmse

LOCAL_M = 25.0  # m: a run pose is judged against the map where a prior keyframe lies this close
LOOSE_M, LOOSE_DEG = 0.5, 3.0  # an inter-session loop a pose graph can use (the sessions' targets), beside pose_right

__all__ = ["LOCAL_M", "LOOSE_DEG", "LOOSE_M", "BagSteps", "CitysimSteps", "LoopScores", "Prior",
           "RelocalizationResult", "Step", "ate_against_map", "build_prior", "map_places", "random_move",
           "relocalize", "step_frame"]


@dataclass(frozen=True)
class Step:
    """One frame: stamp (s), points (N x 3, LiDAR frame), odometry and reference ``world_T_base``, and the
    cameras' images in rig order (None: LiDAR only)."""

    stamp: float
    points: np.ndarray
    odometry: np.ndarray
    reference: np.ndarray
    images: Sequence[Any] | None = None


@dataclass
class LoopScores:
    """Loops judged by their pose against the reference's: right (:func:`~lcpr_core.loop_report.pose_right`),
    within ``LOOSE_M`` / ``LOOSE_DEG``, and each one's error."""

    errors_m: list[float] = field(default_factory=list)
    errors_deg: list[float] = field(default_factory=list)
    right: int = 0
    within: int = 0

    def add(self, match_T_query: np.ndarray, true_match_T_query: np.ndarray) -> None:
        err = invert(true_match_T_query) @ match_T_query
        self.errors_m.append(float(np.linalg.norm(err[:3, 3])))
        self.errors_deg.append(float(rotation_angle_deg(err[:3, :3])))
        self.right += pose_right(match_T_query, true_match_T_query)
        self.within += self.errors_m[-1] <= LOOSE_M and self.errors_deg[-1] <= LOOSE_DEG

    @property
    def count(self) -> int:
        return len(self.errors_m)

    def counts(self) -> dict[str, int]:
        return {"right": self.right, "wrong": self.count - self.right, "within 0.5 m / 3 deg": self.within}

    def spread(self) -> dict[str, float]:
        """Median, p90 and largest error, in m and deg (empty without loops)."""
        if not self.count:
            return {}
        m, deg = np.array(self.errors_m), np.array(self.errors_deg)
        return {"p50_m": float(np.median(m)), "p90_m": float(np.percentile(m, 90)), "max_m": float(m.max()),
                "p50_deg": float(np.median(deg)), "p90_deg": float(np.percentile(deg, 90)),
                "max_deg": float(deg.max())}


@dataclass
class Prior:
    """A first run's files: the detector's map and the back end's graph (and the reference of its keyframes)."""

    map_path: Path
    graph_path: Path
    session: str
    keyframe_stamps: np.ndarray  # (K,) stamps of the prior's keyframes
    keyframe_reference: np.ndarray  # (K, 4, 4) their reference poses
    ate_m: float  # the prior's own corrected trajectory against the reference


@dataclass
class RelocalizationResult:
    session: str
    keyframes: int
    reached_s: float | None  # stamp of the first keyframe within near_m of a prior keyframe (reference)
    anchored_s: float | None  # stamp at which the back end first placed the session
    anchored_at: int | None  # the run's frame at which it was
    anchored_xy: tuple[float, float] | None  # where, in the map frame (the graph's pose of that frame)
    travel_to_anchor_m: float | None  # m walked from reaching mapped ground to being anchored
    frame_error_at_anchor: tuple[float, float] | None  # (m, deg) of map_T_odom where the robot was
    frame_error_end: tuple[float, float] | None
    frame_error_max: tuple[float, float] | None  # the worst, from anchoring on
    ate_m: float | None  # the run's poses against where the map has their places, from anchoring on
    prior_ate_m: float
    loops: dict[str, int] = field(default_factory=dict)  # inter-session loops: right / wrong pose
    inter_session: dict[str, int] = field(default_factory=dict)  # the back end's counters
    refused: dict[str, int] = field(default_factory=dict)  # loops the back end refused as inputs, by reason
    anchor_solve_s: float | None = None
    track: list[list[float]] = field(default_factory=list)  # x, y of the run's reference, for the plot
    ate_truth_m: float | None = None  # the same against the reference itself (the map's own error included)
    frame_error_truth_end: tuple[float, float] | None = None

    def text(self) -> str:
        def pair(v: tuple[float, float] | None) -> str:
            return "-" if v is None else f"{v[0]:.3f} m / {v[1]:.2f} deg"

        lines = [f"session {self.session!r}: {self.keyframes} keyframes against the prior "
                 f"(its own ATE {self.prior_ate_m:.3f} m)"]
        if self.anchored_s is None:
            lines.append("  never anchored")
        else:
            xy = self.anchored_xy or (math.nan, math.nan)
            lines.append(f"  anchored {self.travel_to_anchor_m:.1f} m after reaching mapped ground, at stamp "
                         f"{self.anchored_s:.3f}, at x {xy[0]:.1f} m, y {xy[1]:.1f} m in the map "
                         f"(solve {self.anchor_solve_s or 0.0:.3f} s)")
            lines.append(f"  map_T_odom error where the robot is: at anchoring {pair(self.frame_error_at_anchor)}, "
                         f"worst after {pair(self.frame_error_max)}, at the end {pair(self.frame_error_end)}")
            lines.append(f"  ATE from anchoring on: {_m(self.ate_m)} against the map, {_m(self.ate_truth_m)} against "
                         f"the reference (the map's own error included; map_T_odom at the end "
                         f"{pair(self.frame_error_truth_end)})")
        lines.append(f"  inter-session loops by pose: {self.loops}; back end: {self.inter_session}; refused "
                     f"inputs: {self.refused}")
        return "\n".join(lines)

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


def _xy(pose: np.ndarray) -> tuple[float, float]:
    return float(pose[0, 3]), float(pose[1, 3])


def _m(value: float | None) -> str:
    return "-" if value is None else f"{value:.3f} m"


def _detector(config: DetectorConfig, session: str, prior_map: DescriptorMap | None = None) -> LoopDetector:
    return LoopDetector(dataclasses.replace(config, session=session), prior_map=prior_map)


def step_frame(step: Step, odometry: np.ndarray, cameras: int, *, stamp: float | None = None) -> Frame:
    """The detector's frame of a step (its odometry as given; every camera slot empty without images)."""
    images = list(step.images) if step.images is not None else []
    images += [None] * (cameras - len(images))
    return Frame(stamp=step.stamp if stamp is None else stamp, images=images, points=step.points, pose=odometry)


def build_prior(steps: Sequence[Step], *, detector: DetectorConfig, backend: BackendConfig | None = None,
                session: str = "prior", folder: str | os.PathLike[str] | None = None,
                progress: bool = True) -> Prior:
    """Run the detector and the back end over a first run and save both (``folder``: a temporary one if None)."""
    out = Path(folder) if folder is not None else Path(tempfile.mkdtemp(prefix="lcpr_prior_"))
    out.mkdir(parents=True, exist_ok=True)
    det = _detector(detector, session)
    graph = PoseGraphBackend(backend)
    cameras = detector.model.num_cameras
    kf_ref, kf_stamps, refs = [], [], []
    for step in progress_iter(steps, total=len(steps), desc="prior", unit="frame", enabled=progress):
        graph.add_odometry(step.stamp, step.odometry, session=session)
        refs.append(step.reference)
        result = det.process(step_frame(step, step.odometry, cameras))
        if result.keyframe_id is not None:
            kf_ref.append(step.reference)
            kf_stamps.append(step.stamp)
        for c in result.candidates:
            if c.verified and c.match_T_query is not None:
                try:
                    graph.add_loop(c.query_stamp, c.match_stamp, c.match_T_query, c.covariance,
                                   query_session=session, match_session=session)
                except BackendError:
                    pass
    map_path, graph_path = out / "prior_map.npz", out / "prior_graph.npz"
    det.map.save(map_path)
    graph.save(graph_path)
    _, traj = graph.trajectory(session)
    ate = ate_rmse(traj, np.stack(refs))
    return Prior(map_path=map_path, graph_path=graph_path, session=session,
                 keyframe_stamps=np.array(kf_stamps, np.float64),
                 keyframe_reference=np.stack(kf_ref) if kf_ref else np.zeros((0, 4, 4)), ate_m=ate)


def relocalize(prior: Prior, steps: Sequence[Step], *, detector: DetectorConfig, move: np.ndarray,
               backend: BackendConfig | None = None, session: str = "run", near_m: float = 3.0,
               progress: bool = True) -> RelocalizationResult:
    """Replay ``steps`` as a new session against ``prior``'s map and graph, the odometry moved by ``move``."""
    base_T_lidar = np.eye(4) if backend is None else backend.base_T_lidar
    prior_map = DescriptorMap.load(prior.map_path, expect=detector.map)
    det = _detector(detector, session, prior_map)
    graph = PoseGraphBackend.load(prior.graph_path, backend, hold=True)
    graph.check_map(prior_map.sources, prior_map.stamps, where=str(prior.map_path))
    cameras = detector.model.num_cameras
    prior_xyz = prior.keyframe_reference[:, :3, 3]
    reached = anchored = None
    anchored_at: int | None = None
    travel, last = 0.0, None
    travel_at_reach = travel_at_anchor = None
    errors: list[tuple[float, float, float]] = []  # (stamp, m, deg) from anchoring on
    at_anchor = None
    scores = LoopScores()
    refs: list[np.ndarray] = []
    prior_lidar = {float(t): p for t, p in zip(prior.keyframe_stamps, prior.keyframe_reference, strict=True)}
    in_map = map_places(graph, prior.session, prior.keyframe_stamps, prior.keyframe_reference)

    truth_errors: list[tuple[float, float]] = []
    for step in progress_iter(steps, total=len(steps), desc=session, unit="frame", enabled=progress):
        odom = move @ step.odometry
        refs.append(step.reference)
        graph.add_odometry(step.stamp, odom, session=session)
        if last is not None:
            travel += float(np.linalg.norm(step.reference[:3, 3] - last[:3, 3]))
        last = step.reference
        result = det.process(step_frame(step, odom, cameras))
        if result.keyframe_id is not None and reached is None and len(prior_xyz):
            if np.min(np.linalg.norm(prior_xyz - step.reference[:3, 3], axis=1)) <= near_m:
                reached, travel_at_reach = step.stamp, travel
        for c in result.candidates:
            if not (c.verified and c.match_T_query is not None):
                continue
            match_session = prior.session if c.match_stamp in prior_lidar else session
            if match_session != session:
                scores.add(c.match_T_query,
                           invert(prior_lidar[c.match_stamp] @ base_T_lidar) @ step.reference @ base_T_lidar)
            try:  # a refused loop is counted by the back end (stats().refused), as the node does
                graph.add_loop(c.query_stamp, c.match_stamp, c.match_T_query, c.covariance,
                               query_session=session, match_session=match_session)
            except BackendError:
                pass
        if graph.anchored(session):
            correction = graph.map_T_odom(session)
            assert correction is not None
            if anchored is None:
                anchored, travel_at_anchor, anchored_at = step.stamp, travel, len(refs) - 1
            truth_err = invert(step.reference) @ correction @ odom
            truth_errors.append((float(np.linalg.norm(truth_err[:3, 3])),
                                 float(rotation_angle_deg(truth_err[:3, :3]))))
            there = in_map(step.reference)
            if there is not None:
                err = invert(there) @ correction @ odom
                e = (step.stamp, float(np.linalg.norm(err[:3, 3])), float(rotation_angle_deg(err[:3, :3])))
                at_anchor = e if at_anchor is None else at_anchor
                errors.append(e)
    stats = graph.stats()
    out = RelocalizationResult(session=session, keyframes=det.session_keyframes, reached_s=reached,
                               track=np.stack(refs)[:, :2, 3].tolist(),
                               anchored_s=anchored, anchored_at=anchored_at, travel_to_anchor_m=None,
                               anchored_xy=None if anchored is None else _xy(graph.pose(anchored, session=session)),
                               frame_error_at_anchor=None,
                               frame_error_end=None, frame_error_max=None, ate_m=None, prior_ate_m=prior.ate_m,
                               loops=scores.counts(),
                               inter_session=stats.inter_session, refused=stats.refused,
                               anchor_solve_s=stats.last_anchor_s)
    if anchored is not None and at_anchor is not None and travel_at_anchor is not None:
        out.travel_to_anchor_m = travel_at_anchor - (travel_at_reach if travel_at_reach is not None else 0.0)
        out.frame_error_at_anchor = at_anchor[1:]
        out.frame_error_end = errors[-1][1:]
        out.frame_error_max = (max(e[1] for e in errors), max(e[2] for e in errors))
        stamps, traj = graph.trajectory(session)
        ref = np.stack(refs)
        keep = stamps >= anchored
        out.ate_truth_m = ate_rmse(traj[keep], ref[keep])
        out.ate_m = ate_against_map(traj[keep], ref[keep], in_map)
        out.frame_error_truth_end = truth_errors[-1]
    return out


def map_places(graph: PoseGraphBackend, session: str, stamps: np.ndarray,
               references: np.ndarray) -> Callable[[np.ndarray], np.ndarray | None]:
    """A reference pose -> where the map (``session``'s estimate in ``graph``) has that place: the pose moved by
    the correction the map holds at its nearest keyframe (``stamps``, ``references``: its keyframes' stamps and
    reference poses), or None beyond ``LOCAL_M`` of every one. A robot placed in a map can be no closer to the
    truth than the map; this is what a pose is judged against."""
    local = np.stack([graph.pose(float(t), session=session) @ invert(r)
                      for t, r in zip(stamps, references, strict=True)])
    xyz = references[:, :3, 3]

    def in_map(reference: np.ndarray) -> np.ndarray | None:
        d = np.linalg.norm(xyz - reference[:3, 3], axis=1)
        j = int(np.argmin(d))
        return local[j] @ reference if d[j] <= LOCAL_M else None

    return in_map


def ate_against_map(poses: np.ndarray, references: np.ndarray,
                    in_map: Callable[[np.ndarray], np.ndarray | None]) -> float | None:
    """RMSE (m) of ``poses`` (N, 4, 4) against where the map has their ``references`` (:func:`map_places`), over
    the poses near the map; None when none is."""
    placed = [(x, there) for x, r in zip(poses, references, strict=True) if (there := in_map(r)) is not None]
    if not placed:
        return None
    return ate_rmse(np.stack([x for x, _ in placed]), np.stack([m for _, m in placed]))


def random_move(seed: int, *, span_m: float = 100.0) -> np.ndarray:
    """An arbitrary rigid transform: any yaw, a few degrees of roll and pitch, up to ``span_m`` away."""
    from lcpr_core.geometry import so3_exp

    rng = np.random.default_rng(seed)
    out = np.eye(4)
    out[:3, :3] = so3_exp(np.array([*np.radians(rng.uniform(-5, 5, 2)), rng.uniform(-math.pi, math.pi)]))
    out[:3, 3] = rng.uniform(-span_m, span_m, 3) * np.array([1.0, 1.0, 0.1])
    return out


def scan_folder_steps(folder: str | os.PathLike[str], *, odometry: str = "fast-lio2") -> list[Step]:
    """The frames of a scan folder (Scans/*.pcd, optimized_poses.txt as the reference): ``fast-lio2`` takes the
    folder's ``odom_poses.txt`` (a LIO before its own loop closing) moved to start at the first reference pose,
    ``reference`` the reference itself (an odometry without drift)."""
    from msg_tools.convert.scan_folder import ScanFolder

    seq = ScanFolder(folder)
    if odometry == "reference":
        odom = seq.poses
    else:
        lio = ScanFolder(folder, poses_file="odom_poses.txt").poses
        odom = seq.poses[0] @ invert(lio[0]) @ lio
    return [Step(stamp=float(seq.stamps[i]), points=seq.points(i), odometry=odom[i], reference=seq.poses[i])
            for i in range(len(seq))]


class CitysimSteps(Sequence[Step]):
    """A synthetic drive's frames as steps, rendered as they are read (``workers`` processes when iterated):
    cameras and LiDAR, the truth as the reference, odometry drifted from it (``DriftModel(seed=drift_seed)``,
    1-2 % of distance), started at the first true pose."""

    def __init__(self, *, seed: int, drive: int, frames: int, drift_seed: int, workers: int = 2) -> None:
        from citysim import SynthConfig, SyntheticDrive
        from lcpr_core.posegraph import DriftModel, drift_odometry

        self.drive = SyntheticDrive(SynthConfig(seed=seed, drive=drive, frames=frames))
        self.truth = np.stack([self.drive.pose(i) for i in range(len(self.drive))])
        self.odometry, _ = drift_odometry(self.truth, model=DriftModel(seed=drift_seed))
        self.base_T_lidar = np.asarray(self.drive.rig.lidar.base_T_lidar, np.float64)
        self.workers = workers

    def __len__(self) -> int:
        return len(self.truth)

    def _step(self, i: int, frame: Any) -> Step:
        images = [None if c is None else (c.jpeg if c.jpeg is not None else c.rgb) for c in frame.cameras]
        return Step(stamp=float(frame.stamp), points=frame.xyz, odometry=self.odometry[i], reference=self.truth[i],
                    images=images)

    def __getitem__(self, i: Any) -> Any:
        if isinstance(i, slice):
            raise TypeError("CitysimSteps is read in order; slices are not rendered")
        return self._step(int(i), self.drive.frame(int(i)))

    def __iter__(self) -> Any:
        for i, frame in enumerate(self.drive.frames(workers=self.workers)):
            yield self._step(i, frame)


class BagSteps(Sequence[Step]):
    """A rosbag2's synchronised frames as steps, read as they are iterated: the bag's odometry topic is the
    reference (ground truth in a synthetic bag, a SLAM system's poses in a real one), and the odometry is that
    reference drifted step by step (``drift_seed``; :func:`lcpr_core.posegraph.drift_step`) or, with
    ``drift_seed`` None, the bag's odometry itself (errors are then against that odometry)."""

    def __init__(self, bag: str | os.PathLike[str], *, topics: str = "nuscenes", drift_seed: int | None = 0,
                 lidar_only: bool = False) -> None:
        from lcpr_offline.lcpr_evaluate import TOPIC_PRESETS
        from msg_tools.bags.reader import read_frames

        if topics not in TOPIC_PRESETS:
            raise ValueError(f"topics={topics!r}; accepted: {', '.join(sorted(TOPIC_PRESETS))}")
        from lcpr_offline.lcpr_evaluate import base_T_lidar_of

        self.bag, self.topics = Path(bag), TOPIC_PRESETS[topics]
        self.drift_seed, self.lidar_only = drift_seed, lidar_only
        self._read = read_frames
        with self._open() as stream:
            self._len = len(stream)
            first = next(iter(stream), None)
        self.base_T_lidar = base_T_lidar_of(self.bag, None if first is None else first.lidar_frame_id)[0]

    def _open(self) -> Any:
        return self._read(self.bag, topics=self.topics, decode_compressed=False,
                          min_cameras=0 if self.lidar_only else 1)

    def __len__(self) -> int:
        return self._len

    def __getitem__(self, i: Any) -> Any:
        raise TypeError("BagSteps is read in order")

    def __iter__(self) -> Any:
        from lcpr_core.posegraph import DriftModel, drift_step

        model = None if self.drift_seed is None else DriftModel(seed=self.drift_seed)
        rng = np.random.default_rng(None if model is None else model.seed)
        last_ref = last_odom = None
        with self._open() as stream:
            for frame in stream:
                if frame.pose is None:
                    continue  # no reference: not a step
                ref = np.asarray(frame.pose, np.float64)
                if model is None:
                    odom = ref
                elif last_ref is None or last_odom is None:
                    odom = ref.copy()
                else:
                    odom = last_odom @ drift_step(invert(last_ref) @ ref, model=model, rng=rng)[0]
                last_ref, last_odom = ref, odom
                images = None if self.lidar_only else [
                    None if c is None else (c.jpeg if c.jpeg is not None else c.rgb) for c in frame.cameras]
                yield Step(stamp=float(frame.stamp), points=frame.xyz, odometry=odom, reference=ref, images=images)


def plot(prior: Prior, result: RelocalizationResult, path: str | os.PathLike[str], *, title: str) -> None:
    """A top view: the prior's keyframes, the run's reference path, and where it was anchored."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from lcpr_core.atomic import save_figure

    fig, ax = plt.subplots(figsize=(7, 6))
    ref = np.array(result.track).reshape(-1, 2)
    ax.plot(prior.keyframe_reference[:, 0, 3], prior.keyframe_reference[:, 1, 3], ".", color="0.6", ms=4,
            label="prior keyframes")
    ax.plot(ref[:, 0], ref[:, 1], "-", color="tab:blue", lw=1.2, label="run (reference)")
    if result.anchored_at is not None:
        ax.plot(*ref[min(result.anchored_at, len(ref) - 1)], "r*", ms=14, label="anchored")
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title(title, fontsize=9)
    ax.legend(fontsize=8)
    save_figure(fig, path)
    plt.close(fig)


@tool_main
def main(argv: list[str] | None = None) -> int:
    import argparse
    import json

    from lcpr_common.shared_data import shared_path
    from lcpr_core.atomic import write_bytes_atomic
    from lcpr_core.lcpr.config import ModelConfig
    from lcpr_core.pretrained import default_weights
    from lcpr_core.timing import cpu_model

    p = argparse.ArgumentParser(prog="lcpr_relocalize", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("folder", type=Path, nargs="?", default=None,
                   help="scan folder (Scans/*.pcd, optimized_poses.txt, odom_poses.txt, times.txt) cut by time into "
                        "the prior and the run; default: the shared walk_loop")
    p.add_argument("--split", type=float, default=0.5,
                   help="share of the folder's frames (by time) that make the prior (default 0.5)")
    p.add_argument("--odometry", choices=("fast-lio2", "reference"), default="fast-lio2",
                   help="a scan folder's odometry: its odom_poses.txt (default) or the reference itself")
    p.add_argument("--bag", type=Path, default=None,
                   help="instead of a folder: a rosbag2 replayed against --prior-bag's map and graph (their "
                        "odometry topics the reference)")
    p.add_argument("--prior-bag", type=Path, default=None, help="with --bag: the bag that makes the prior")
    p.add_argument("--topics", default="nuscenes", help="with --bag: the topic preset (nuscenes, kitti, scans)")
    p.add_argument("--lidar-only", action="store_true", help="with --bag: no cameras")
    p.add_argument("--drift-seed", type=int, default=0,
                   help="with --bag: the odometry is the reference drifted 1-2 %% with this seed; -1 = the bag's "
                        "odometry as it is")
    p.add_argument("--city", type=int, default=None, metavar="SEED",
                   help="instead of a folder: the synthetic city SEED, its drive 0 the prior and drive 1 the run "
                        "(cameras and LiDAR, odometry drifted 1-2 %%)")
    p.add_argument("--run-city", type=int, default=None, metavar="SEED",
                   help="with --city: the run drives through this other city instead (it must never anchor)")
    p.add_argument("--frames", type=int, default=300, help="with --city: keyframes per drive (default 300)")
    p.add_argument("--move-seed", type=int, default=0, help="seed of the run's odometry frame move (default 0)")
    p.add_argument("--out", type=Path, default=Path("out/relocalize"))
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    args = p.parse_args(argv)
    weights = default_weights()
    if weights is None:
        raise SystemExit("lcpr_relocalize: the bundled weights are not installed")
    if not 0.05 <= args.split <= 0.95:
        raise SystemExit(f"lcpr_relocalize: --split {args.split}; expected a share in [0.05, 0.95]")
    detector = DetectorConfig(model=ModelConfig(weights=weights, threads=args.threads))
    args.out.mkdir(parents=True, exist_ok=True)
    prior_steps: Sequence[Step]
    run_steps: Sequence[Step]
    if args.bag is not None:
        if args.prior_bag is None:
            raise SystemExit("lcpr_relocalize: --bag needs --prior-bag (the recording that makes the prior)")
        seed = None if args.drift_seed < 0 else args.drift_seed
        prior_steps = BagSteps(args.prior_bag, topics=args.topics, drift_seed=seed, lidar_only=args.lidar_only)
        run_steps = BagSteps(args.bag, topics=args.topics, drift_seed=None if seed is None else seed + 1,
                             lidar_only=args.lidar_only)
        backend = BackendConfig(base_T_lidar=prior_steps.base_T_lidar)
        name = f"{args.prior_bag.name} (prior), {args.bag.name} (run)"
    elif args.city is not None:
        prior_steps = CitysimSteps(seed=args.city, drive=0, frames=args.frames, drift_seed=1000 + args.city)
        run_city = args.city if args.run_city is None else args.run_city
        run_steps = CitysimSteps(seed=run_city, drive=1, frames=args.frames, drift_seed=2000 + run_city)
        backend = BackendConfig(base_T_lidar=prior_steps.base_T_lidar)
        name = f"city {args.city} drive 0 (prior), city {run_city} drive 1 (run)"
    else:
        folder = args.folder if args.folder is not None else shared_path("data", "livox_hku", "walk_loop")
        steps = scan_folder_steps(folder, odometry=args.odometry)
        t = np.array([s.stamp for s in steps])
        cut = int(np.searchsorted(t, t[0] + args.split * (t[-1] - t[0])))
        prior_steps, run_steps, backend = steps[:cut], steps[cut:], BackendConfig()
        name = f"{folder.name}: prior = frames 0..{cut - 1}, run = frames {cut}..{len(steps) - 1}"
    print(f"CPU: {cpu_model()}; {name}")
    prior = build_prior(prior_steps, detector=detector, backend=backend, folder=args.out, progress=not args.quiet)
    move = random_move(args.move_seed)
    result = relocalize(prior, run_steps, detector=detector, backend=backend, move=move, progress=not args.quiet)
    print(result.text())
    write_bytes_atomic(args.out / "relocalize.json", json.dumps(result.to_dict(), indent=2).encode())
    plot(prior, result, args.out / "relocalize.png", title=f"{name}: the run against the prior")
    print(f"wrote {args.out / 'relocalize.json'} and relocalize.png")
    return 0
