"""LiDAR-only loop closure on real sequences: our pipeline, Scan Context + the same verifier, and MapClosures.

    python benchmarks/tools/lidar_loops_compare.py                       # livox_hku walk_loop and campus
    python benchmarks/tools/lidar_loops_compare.py --folder PATH [...]   # any scan folder, in addition
    python benchmarks/tools/lidar_loops_compare.py --only-folders --folder PATH
    python benchmarks/tools/lidar_loops_compare.py --sets campus --out out/lidar_loops_compare/campus
    python benchmarks/tools/lidar_loops_compare.py --merge out/lidar_loops_compare/*/results.json

A folder is ``Scans/*.pcd`` (or ``*.pcd``, ``velodyne/*.bin``, ``*.bin``: KITTI) with one 3 x 4 pose a
line (``optimized_poses.txt``, ``poses.txt`` with ``calib.txt`` moved to the LiDAR, or ``--poses``) as the
reference, ``odom_poses.txt`` as the odometry (else the reference) and ``times.txt`` (else 0.1 s apart).

Every scan is a keyframe. Methods, fed the same scans in the same order:

- ``lcpr``, ``scan_context``, ``fused``: :class:`~lcpr_core.detector.LoopDetector` with the bundled
  weights, all six camera slots empty and the node's defaults (top 10 candidates among keyframes > 30 s older,
  verification with its submaps) but ``match.method``: candidates from the LCPR descriptor, from Scan Context
  (``lcpr_core.scan_context``) or both; the loop is ``Result.loop`` (the verified candidate with the best
  fitness). One fused detector runs and records which method proposed each candidate and what each cost
  (:func:`recording_detector`): a verdict does not depend on who proposed the pair, so each method's loop and
  time follow from it (each counts the network: the detector runs it for every method);
- ``map_closures L``: MapClosures (PyPI ``map-closures``) as its pipeline drives it: the scans integrated into
  local maps with the odometry poses, a new map after ``L`` m of travel keeping the last map's points within
  ``L`` m (its pipeline uses the 100 m max range for both, which gives a 60 m walk one map), closures with more
  than ``inliers_threshold`` ORB + RANSAC inliers published when a map is closed.

Scoring against the reference poses (the SLAM system's own estimates after loop closing):

- every loop is judged by its relative pose against the reference's, by the project's one rule
  (:func:`lcpr_core.loop_report.pose_right`: within 0.3 m and 2 deg of the whole rotation angle), in three
  groups: right pose with its keyframes < 5 m apart ("correct"), right pose >= 5 m apart (a valid constraint
  between keyframes farther apart) and wrong pose (what would hurt a pose graph); precision by pose is the
  right ones over all loops;
- revisiting queries: keyframes with an older keyframe < 3 m away, > 30 s older and turned < 30 deg
  (:func:`lcpr_offline.verification_pairs.true_pairs`); closed when the keyframe's loop is correct. A
  MapClosures closure joins two local maps (pose: query map anchor from reference map anchor): it is correct
  when that pose is right by the same rule and the maps hold keyframes < 5 m apart, and then closes every
  revisiting query of the query map with a true match in the reference map (generous to it);
- time per scan: everything a method does for one scan, one thread each (median, and mean, which for
  MapClosures carries its per-map query), on the CPU named.

Writes ``OUT/results.json`` (every number, every loop) and ``OUT/loops.png``; ``--merge`` joins runs of single
sequences. MapClosures needs ``pip install map-closures`` (left out, with a message, without it). Results and
why: docs/lidar_only.md.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from lcpr_common.cli import tool_main
from lcpr_core.loop_report import POSE_OK_DEG, POSE_OK_M, pose_right

DEFAULT_SETS = ("walk_loop", "campus")
CORRECT_M = 5.0  # a loop's keyframes closer than this, with the right pose (pose_right), are correct
TOP_K = 10
MC_MAP_LENGTHS = (5.0, 10.0, 20.0, 100.0)  # m of travel per MapClosures local map (100: its pipeline's own)
METHODS = ("lcpr", "scan_context", "fused")


@dataclass
class ScanSequence:
    """A folder of scans: the files, stamps, reference poses and odometry poses (N x 4 x 4, LiDAR in world)."""

    name: str
    scans: list[Path]
    stamps: np.ndarray
    poses: np.ndarray
    odom: np.ndarray
    pose_source: str

    def __len__(self) -> int:
        return len(self.scans)

    def points(self, i: int) -> np.ndarray:
        """Scan i as N x 3 float32, sensor frame, finite points only."""
        from msg_tools.convert.scans2bag import read_cloud

        cloud = read_cloud(self.scans[i])
        xyz = np.stack([cloud["x"], cloud["y"], cloud["z"]], axis=1).astype(np.float32)
        return xyz[np.isfinite(xyz).all(axis=1)]


def read_sequence(folder: Path, *, poses: Path | None = None) -> ScanSequence:
    """A scan folder (scans2bag's layouts) with its reference and odometry poses; DatasetError naming what is wrong."""
    from msg_tools.convert.kitti_files import read_calibration
    from msg_tools.convert.scan_folder import read_kitti_poses
    from msg_tools.convert.scans2bag import POSE_FILES, find_scans, line_index
    from msg_tools.errors import DatasetError

    scans = find_scans(folder)
    times = folder / "times.txt"
    stamps = (np.loadtxt(times, dtype=np.float64, ndmin=1) if times.is_file()
              else np.arange(len(scans), dtype=np.float64) * 0.1)
    stamps = stamps[line_index(scans, len(stamps), str(times))]
    ref_file = poses or next((folder / n for n in POSE_FILES if (folder / n).is_file()), None)
    if ref_file is None:
        raise DatasetError(f"{folder} has none of {', '.join(POSE_FILES)}; give --poses FILE (the reference)")

    def load(path: Path) -> np.ndarray:
        world_T = read_kitti_poses(path)
        world_T = world_T[line_index(scans, len(world_T), str(path))]
        calib = path.parent / "calib.txt"
        if path.name == "poses.txt" and calib.is_file():  # KITTI: camera-0 poses -> the Velodyne's
            world_T = read_calibration(calib).velodyne_poses(world_T)
        return world_T

    reference = load(ref_file)
    odom_file = folder / "odom_poses.txt"
    odom = load(odom_file) if odom_file.is_file() else reference
    odom_name = odom_file.name if odom_file.is_file() else ref_file.name
    return ScanSequence(folder.name, scans, stamps, reference, odom, f"reference {ref_file.name}, odometry {odom_name}")


@dataclass
class Loop:
    """One published loop: query and match keyframes (or local maps) and the query's pose in the match's frame."""

    query: int
    match: int
    match_T_query: np.ndarray
    score: float  # fitness (keyframe methods) or RANSAC inliers (MapClosures)
    correct: bool = False  # right pose, < 5 m apart
    near: bool = False  # the keyframes (or maps) are < 5 m apart
    right_pose: bool = False  # the relative pose is right (pose_right), however far apart
    err_m: float = float("nan")
    err_deg: float = float("nan")
    closes: list[int] = field(default_factory=list)  # revisiting queries this loop closes


@dataclass
class MethodResult:
    loops: list[Loop] = field(default_factory=list)
    seconds: list[float] = field(default_factory=list)  # per scan

    def summary(self, revisiting: int) -> dict[str, Any]:
        closed = sorted({q for loop in self.loops if loop.correct for q in loop.closes})
        correct = sum(loop.correct for loop in self.loops)
        pose_ok = sum(loop.right_pose for loop in self.loops)
        s = np.asarray(self.seconds)
        return {"loops": len(self.loops), "correct": correct, "wrong": len(self.loops) - correct,
                "wrong_right_pose_far": pose_ok - correct, "wrong_pose": len(self.loops) - pose_ok,
                "right_within_radius": correct, "right_beyond_radius": pose_ok - correct,
                "precision_by_pose": pose_ok / len(self.loops) if self.loops else None,
                "revisiting_closed": len(closed), "revisiting": revisiting,
                "ms_per_scan_median": 1e3 * float(np.median(s)) if len(s) else float("nan"),
                "ms_per_scan_mean": 1e3 * float(np.mean(s)) if len(s) else float("nan")}


def score_keyframe_loop(loop: Loop, seq: ScanSequence, truth: dict[int, set[int]]) -> Loop:
    """Its pose judged (pose_right), correct (< 5 m and the right pose) and which revisiting query it closes."""
    from lcpr_offline.verification_pairs import pose_error

    P = seq.poses
    reference = np.linalg.inv(P[loop.match]) @ P[loop.query]
    loop.err_m, loop.err_deg = pose_error(loop.match_T_query, reference)
    loop.near = float(np.linalg.norm(P[loop.query, :3, 3] - P[loop.match, :3, 3])) < CORRECT_M
    loop.right_pose = pose_right(loop.match_T_query, reference)
    loop.correct = loop.near and loop.right_pose
    loop.closes = [loop.query] if loop.query in truth else []
    return loop


def recording_detector(config: Any) -> Any:
    """A LoopDetector (``match.method`` fused) that records, per keyframe, which candidates each method proposed
    and what each stage and each candidate's verification cost, so that one run scores all three methods.

    A candidate's verdict does not depend on the method that proposed it (same query, same map, same clouds), so
    the lcpr (scan_context) detector's ``Result.loop`` is the verified candidate with the best fitness among the
    descriptor's (Scan Context's) proposals, and its time is the run's minus what only the other method needed.
    """
    from lcpr_core.detector import LoopDetector

    class Recording(LoopDetector):
        def reset(self) -> None:
            self.proposed: dict[str, list[int]] = {"lcpr": [], "scan_context": []}
            self.search_s = {"lcpr": 0.0, "scan_context": 0.0}
            self.cost: dict[int, float] = {}  # candidate keyframe -> preparing its cloud + verifying it
            self._order: list[int] = []  # candidates whose cloud was found, in verification order

        def _prepared_cloud(self, ref: Any) -> Any:
            keyframe_id = ref.key[1]  # the match keyframe (after the detector's token; the stitched ones follow)
            tic = time.perf_counter()
            prepared = super()._prepared_cloud(ref)
            self.cost[keyframe_id] = self.cost.get(keyframe_id, 0.0) + time.perf_counter() - tic
            self._order.append(keyframe_id)
            return prepared

        def verified(self, seconds: float) -> None:  # called by TimedVerifier after each registration
            kf = self._order[len(self._verify_times)]
            self._verify_times.append(seconds)
            self.cost[kf] = self.cost.get(kf, 0.0) + seconds

        def process(self, frame: Any) -> Any:
            self.reset()
            self._verify_times: list[float] = []
            return super().process(frame)

    class TimedPart:
        """One part of the fused proposer, recording for the detector what it proposed and how long it searched."""

        def __init__(self, inner: Any, owner: Any, method: str) -> None:
            self.inner, self.owner, self.method = inner, owner, method

        def __getattr__(self, name: str) -> Any:
            return getattr(self.inner, name)

        def search(self, *args: Any, **kwargs: Any) -> Any:
            tic = time.perf_counter()
            hits = self.inner.search(*args, **kwargs)
            self.owner.search_s[self.method] = time.perf_counter() - tic
            self.owner.proposed[self.method] = [h.id for h in hits]
            return hits

    class TimedVerifier:
        """The detector's verifier, timing each registration for the detector (``config`` is the same object)."""

        def __init__(self, inner: Any, owner: Any) -> None:
            self.inner, self.owner = inner, owner

        def __getattr__(self, name: str) -> Any:
            return getattr(self.inner, name)

        def verify_prepared(self, *args: Any, **kwargs: Any) -> Any:
            tic = time.perf_counter()
            verdict = self.inner.verify_prepared(*args, **kwargs)
            self.owner.verified(time.perf_counter() - tic)
            return verdict

    detector = Recording(config)
    detector.reset()
    detector.verifier = TimedVerifier(detector.verifier, detector)  # type: ignore[assignment]
    fused: Any = detector.proposer  # lcpr_core.lcpr.proposers.FusedProposer: its two parts searched and timed apart
    fused.descriptor = TimedPart(fused.descriptor, detector, "lcpr")
    fused.scan_context = TimedPart(fused.scan_context, detector, "scan_context")
    return detector


class KeyframeMethods:
    """Our detector's three ``match.method`` values (lcpr, scan_context, fused) on one sequence, scan by scan."""

    def __init__(self, *, threads: int, submap: str | None = None) -> None:
        from lcpr_core.detector import DetectorConfig, MatchConfig
        from lcpr_core.keyframes import KeyframeConfig
        from lcpr_core.lcpr.describer import ModelConfig
        from lcpr_core.pretrained import BUNDLED

        config = DetectorConfig(model=ModelConfig(weights=BUNDLED, threads=threads),
                                keyframe=KeyframeConfig(min_interval=0.0),
                                match=MatchConfig(top_k=TOP_K, method="fused"))
        # verified in this process: each candidate's registration is timed and charged to the method proposing it
        config = dataclasses.replace(config, verify=dataclasses.replace(config.verify, processes=0))
        if submap is not None:  # submap.mode other than the node's default
            config = dataclasses.replace(config, submap=dataclasses.replace(config.submap, mode=submap))
        self.detector = recording_detector(config)
        self.results = {m: MethodResult() for m in METHODS}

    def step(self, i: int, stamp: float, points: np.ndarray, odom_pose: np.ndarray) -> None:
        from lcpr_core.detector import Frame

        det = self.detector
        tic = time.perf_counter()
        result = det.process(Frame(stamp, [None] * 6, points, odom_pose))
        wall = time.perf_counter() - tic
        if result.keyframe_id != i:
            raise RuntimeError(f"scan {i} became keyframe {result.keyframe_id} ({result.reason}); every scan must be")
        sc_only_s = result.timings.get("scan_context", 0.0) + det.search_s["scan_context"]
        for method in METHODS:
            mine = set(det.proposed["lcpr"]) | set(det.proposed["scan_context"]) if method == "fused" else \
                set(det.proposed[method])
            others = {c.match_id for c in result.candidates} - mine
            seconds = wall - sum(det.cost.get(kf, 0.0) for kf in others)
            seconds -= {"lcpr": sc_only_s, "scan_context": det.search_s["lcpr"], "fused": 0.0}[method]
            verified = [c for c in result.candidates if c.match_id in mine and c.verified]
            r = self.results[method]
            r.seconds.append(seconds)
            if verified:
                best = max(verified, key=lambda c: c.fitness)
                r.loops.append(Loop(i, best.match_id, np.asarray(best.match_T_query, np.float64), best.fitness))


class MapClosuresRun:
    """MapClosures as its own pipeline drives it, local maps of ``length`` m built with the odometry poses."""

    def __init__(self, length: float) -> None:
        from map_closures.config import MapClosuresConfig
        from map_closures.map_closures import MapClosures
        from map_closures.voxel_map import VoxelMap

        self.length = length
        self.config = MapClosuresConfig()
        self.closures = MapClosures(self.config)
        self.local = VoxelMap(voxel_size=self.config.density_map_resolution, max_distance=length)
        self.anchor = np.eye(4)  # the current map's frame: the odometry pose of its first scan
        self.anchor_scan = 0
        self.maps: list[tuple[int, int]] = []  # per map: [first scan, last scan + 1)
        self.raw: list[tuple[int, int, np.ndarray, int]] = []  # (reference map, query map, query_T_ref, inliers)
        self.result = MethodResult()

    def step(self, i: int, points: np.ndarray, odom_pose: np.ndarray, *, last: bool) -> None:
        tic = time.perf_counter()
        if i == 0:
            self.anchor = odom_pose.copy()
        frame_to_map = np.linalg.inv(self.anchor) @ odom_pose
        self.local.integrate_frame(points.astype(np.float64), frame_to_map)
        if np.linalg.norm(frame_to_map[:3, 3]) > self.length or last:
            map_id = len(self.maps)
            for c in self.closures.get_closures(map_id, self.local.point_cloud()):
                if c.number_of_inliers > self.config.inliers_threshold:
                    self.raw.append((int(c.source_id), int(c.target_id), np.asarray(c.pose, np.float64),
                                     int(c.number_of_inliers)))
            self.maps.append((self.anchor_scan, i + 1))
            self.local.remove_far_away_points(frame_to_map[:3, 3])
            keep = self.local.point_cloud()
            self.local.clear()
            self.local.integrate_frame(keep, np.linalg.inv(odom_pose) @ self.anchor)
            self.anchor, self.anchor_scan = odom_pose.copy(), i
        self.result.seconds.append(time.perf_counter() - tic)

    def score(self, seq: ScanSequence, truth: dict[int, set[int]]) -> MethodResult:
        """The closures as loops between map anchors, scored against the reference poses."""
        from lcpr_offline.verification_pairs import pose_error

        P = seq.poses
        for ref, query, query_T_ref, inliers in self.raw:
            (r0, r1), (q0, q1) = self.maps[ref], self.maps[query]
            reference = np.linalg.inv(P[q0]) @ P[r0]  # query anchor from reference anchor
            err_m, err_deg = pose_error(query_T_ref, reference)
            gap = np.linalg.norm(P[q0:q1, None, :3, 3] - P[None, r0:r1, :3, 3], axis=-1).min()
            near = bool(gap < CORRECT_M)
            right = pose_right(query_T_ref, reference)
            closes = [q for q in range(q0, q1) if any(r0 <= m < r1 for m in truth.get(q, ()))]
            self.result.loops.append(Loop(query, ref, np.linalg.inv(query_T_ref), float(inliers), near and right,
                                          near, right, err_m, err_deg, closes))
        return self.result


def run_sequence(seq: ScanSequence, args: argparse.Namespace) -> dict[str, Any]:
    """All methods over one sequence; the summary per method, and every loop."""
    from tqdm import tqdm

    from lcpr_offline.verification_pairs import true_pairs

    pairs = true_pairs(seq)  # type: ignore[arg-type]  # needs .poses and .stamps only
    truth: dict[int, set[int]] = {}
    for q, m in pairs.tolist():
        truth.setdefault(q, set()).add(m)
    kf = KeyframeMethods(threads=args.threads, submap=args.submap)
    mcs = [MapClosuresRun(length) for length in args.mc_map_length]
    for i in tqdm(range(len(seq)), desc=seq.name, unit="scan"):
        points = seq.points(i)
        kf.step(i, float(seq.stamps[i]), points, seq.odom[i])
        for mc in mcs:
            mc.step(i, points, seq.odom[i], last=i == len(seq) - 1)
    results: dict[str, MethodResult] = {}
    for method in METHODS:
        r = kf.results[method]
        r.loops = [score_keyframe_loop(loop, seq, truth) for loop in r.loops]
        results[method] = r
    for mc in mcs:
        results[f"map_closures {mc.length:g} m ({len(mc.maps)} maps)"] = mc.score(seq, truth)
    revisiting = len(truth)
    out: dict[str, Any] = {"scans": len(seq), "revisiting_queries": revisiting, "true_pairs": len(pairs),
           "poses": seq.pose_source, "methods": {}}
    for name, r in results.items():
        out["methods"][name] = {**r.summary(revisiting),
                                "loop_list": [{k: v for k, v in asdict(loop).items() if k != "match_T_query"}
                                              for loop in r.loops]}
    return out


def print_table(name: str, res: dict[str, Any]) -> None:
    print(f"\n{name}: {res['scans']} scans, {res['revisiting_queries']} revisiting queries ({res['poses']})")
    print(f"  {'method':30s} {'loops':>5s} {'right pose: <5 m':>16s} {'>=5 m':>5s} {'wrong pose':>10s} "
          f"{'precision':>9s} {'revisits closed':>15s} {'ms/scan med':>11s} {'mean':>7s}")
    for method, s in res["methods"].items():
        print(f"  {method:30s} {s['loops']:5d} {s['correct']:16d} {s['wrong_right_pose_far']:5d} "
              f"{s['wrong_pose']:10d} {_precision_by_pose(s):>9s} "
              f"{s['revisiting_closed']:7d} / {s['revisiting']:<5d} {s['ms_per_scan_median']:11.1f} "
              f"{s['ms_per_scan_mean']:7.1f}")


def _precision_by_pose(summary: dict[str, Any]) -> str:
    """Right poses (< 5 m and beyond) over all loops, from counts every results.json holds (--merge reads any)."""
    if not summary["loops"]:
        return "-"
    return f"{(summary['correct'] + summary['wrong_right_pose_far']) / summary['loops']:.2f}"


def plot(results: dict[str, dict[str, Any]], path: Path, cpu: str) -> None:
    """Per sequence: revisiting queries closed and the loops of every method by pose (one bar group each):
    right pose < 5 m apart, right pose farther apart (a valid constraint), wrong pose (harmful)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(results), figsize=(6.5 * len(results), 4.8), squeeze=False)
    for ax, (name, res) in zip(axes[0], results.items(), strict=True):
        methods = list(res["methods"])
        x = np.arange(len(methods))
        bars = (("revisiting_closed", "revisiting queries closed", "tab:blue"),
                ("correct", "right pose, < 5 m apart", "tab:green"),
                ("wrong_right_pose_far", "right pose, >= 5 m apart (a valid constraint)", "tab:olive"),
                ("wrong_pose", "wrong pose (harmful)", "tab:red"))
        for j, (key, label, colour) in enumerate(bars):
            ax.bar(x + (j - 1.5) * 0.2, [res["methods"][m][key] for m in methods], 0.2, label=label, color=colour)
        ax.axhline(res["revisiting_queries"], color="k", ls=":", lw=1, label="revisiting queries")
        ax.set_xticks(x, [m.replace(" (", "\n(") + f"\nprecision by pose {_precision_by_pose(res['methods'][m])}"
                          for m in methods], fontsize=7, rotation=30, ha="right")
        ax.set_title(f"{name}: {res['scans']} scans")
        ax.legend(fontsize=7)
    fig.suptitle(f"LiDAR-only loops: match.method values and MapClosures ({cpu})", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def merge(files: list[Path], out: Path) -> int:
    """Several runs' results.json (one sequence each, say) as one results.json, table and figure."""
    runs = [json.loads(f.read_text()) for f in files]
    results = {name: res for run in runs for name, res in run["sequences"].items()}
    for name, res in results.items():
        print_table(name, res)
    out.mkdir(parents=True, exist_ok=True)
    meta = {**runs[0]["meta"], "merged": [str(f) for f in files], "commands": [r["meta"]["command"] for r in runs]}
    (out / "results.json").write_text(json.dumps({"meta": meta, "sequences": results}, indent=1))
    plot(results, out / "loops.png", meta["cpu"])
    print(f"\nwrote {out / 'results.json'} and {out / 'loops.png'}")
    return 0


@tool_main
def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", type=Path, default=None, help="the livox_hku folder (default: ../shared/data/livox_hku)")
    p.add_argument("--sets", nargs="*", default=list(DEFAULT_SETS), help="livox_hku sequences to run")
    p.add_argument("--folder", type=Path, action="append", default=[], help="another scan folder (repeatable)")
    p.add_argument("--only-folders", action="store_true", help="run the --folder sequences only")
    p.add_argument("--poses", type=Path, default=None, help="reference pose file of the --folder sequences")
    p.add_argument("--mc-map-length", type=float, nargs="*", default=list(MC_MAP_LENGTHS),
                   help="MapClosures local-map lengths (m of travel), one run each")
    p.add_argument("--submap", choices=("off", "on", "auto"), default=None,
                   help="submap.mode of the verification (default: the node's)")
    p.add_argument("--threads", type=int, default=1, help="torch threads of the network (default 1)")
    p.add_argument("--limit", type=int, default=0, help="first N scans of each sequence only (0 = all)")
    p.add_argument("--merge", type=Path, nargs="*", default=None,
                   help="run nothing: merge these results.json files (runs of single sequences) into OUT")
    p.add_argument("--out", type=Path, default=Path("out/lidar_loops_compare"))
    args = p.parse_args(argv)
    if args.merge:
        return merge(args.merge, args.out)
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    from lcpr_common.shared_data import shared_path
    from lcpr_core.timing import cpu_model

    if args.mc_map_length:
        try:
            import map_closures  # noqa: F401
        except ImportError:
            print("MapClosures left out: `pip install map-closures` (PyPI) to compare with it", file=sys.stderr)
            args.mc_map_length = []
    data = args.data or shared_path("data", "livox_hku")
    folders = [] if args.only_folders else [(data / s, None) for s in args.sets]
    folders += [(f, args.poses) for f in args.folder]
    cpu = cpu_model()
    print(f"CPU: {cpu}; network threads {args.threads}, verifier threads 1")
    results: dict[str, dict[str, Any]] = {}
    for folder, poses in folders:
        seq = read_sequence(folder, poses=poses)
        if args.limit:
            seq = ScanSequence(seq.name, seq.scans[: args.limit], seq.stamps[: args.limit], seq.poses[: args.limit],
                               seq.odom[: args.limit], seq.pose_source)
        results[seq.name] = run_sequence(seq, args)
        print_table(seq.name, results[seq.name])
    args.out.mkdir(parents=True, exist_ok=True)
    meta = {"cpu": cpu, "command": " ".join(["python", "benchmarks/tools/lidar_loops_compare.py", *sys.argv[1:]]),
            "top_k": TOP_K, "correct_m": CORRECT_M, "submap": args.submap or "node default",
            "pose_ok": [POSE_OK_M, POSE_OK_DEG]}
    (args.out / "results.json").write_text(json.dumps({"meta": meta, "sequences": results}, indent=1))
    plot(results, args.out / "loops.png", cpu)
    print(f"\nwrote {args.out / 'results.json'} and {args.out / 'loops.png'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
