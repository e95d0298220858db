"""The end-to-end demo: a synthetic drive with loops, replayed through DDS into a real lcpr_node.

    lcpr_demo [--frames 200] [--seed 7] [--weights FILE | --seeded] [--rate 1.0] [--out out/demo]

1. makes (or reuses) a synthetic-city drive with revisits (nuScenes-like rig) as a rosbag2;
2. starts ``lcpr_node`` as its own process (a private ROS_DOMAIN_ID);
3. replays the bag over DDS with its original stamps, listening to what the node publishes;
4. compares the loops on ``~/loop_closure`` (verified against the LiDAR) with the true
   revisits (<= 9 m, >= 30 s older) and prints, beside what retrieval alone would have
   published (the nearest descriptor under the bundled threshold, judged by the 9 m rule),
   the loops by their relative pose against the drive's ground truth (right within 9 m,
   right beyond it: a valid constraint, wrong: harmful; :mod:`lcpr_core.loop_report`),
   precision by pose, recall, the pose error, latency, and what a pose graph gains: the
   drive's poses with seeded odometry drift, the verified loops added as between-factors
   with their covariances, optimised with GTSAM (ATE before and after, ``posegraph.png``).

``--odometry kiss-icp`` adds what a robot without another odometry gets: KISS-ICP run on the drive's own
LiDAR (rendered every metre along the same path in the same world, :mod:`lcpr_offline.drive_odometry`:
the bag's 5 m keyframes are too far apart for it), the node's verified candidates as loops (and its ``~/up``), and the
online back end (:mod:`lcpr_core.backend.replay`): ATE RMSE before and after against the drive's ground
truth, and ``backend.png``. The default (``drift``) prints only the seeded-drift pose graph above.

``lcpr_demo --fleet`` runs the fleet demo instead: two robots, two detectors and a back end merging both over
DDS (:mod:`lcpr_ros.fleet_demo`; ``lcpr_demo --fleet --help``).
"""
from __future__ import annotations

import argparse
import json
import os
import random
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from lcpr_core.atomic import write_bytes_atomic
from lcpr_core.errors import LcprError
from lcpr_core.evaluation import recall_at_full_precision
from lcpr_core.loop_report import LoopScore, PublishedLoop, pose_graph_proof, score_loops, verified_fitness_sweep
from lcpr_core.metrics import plot_pr_curve, pr_sweep
from lcpr_core.posegraph import DriftModel
from lcpr_core.pretrained import BUNDLED, BUNDLED_MAX_DISTANCE, SEEDED, describe_weights, resolve_weights
from lcpr_core.revisits import revisit_pairs
from msg_tools.frames import NUSCENES_TOPICS

if TYPE_CHECKING:
    from citysim import SyntheticDrive
    from lcpr_core.backend.replay import BackendEvaluation

RADIUS = 9.0  # m: a loop is correct when the matched keyframe is this close (the paper's threshold)
MIN_GAP = 30.0  # s: the node excludes younger keyframes, and so does the ground truth
ODOMETRY_MODES = ("drift", "kiss-icp")


@dataclass(frozen=True)
class Truth:
    stamps: np.ndarray  # N keyframe stamps
    positions: np.ndarray  # N x 2
    has_revisit: np.ndarray  # N bool: an earlier keyframe >= 30 s older lies within 9 m
    world_T_base: np.ndarray  # N x 4 x 4
    base_T_lidar: np.ndarray  # 4 x 4

    def index(self, stamp: float) -> int:
        i = int(np.argmin(np.abs(self.stamps - stamp)))
        if abs(self.stamps[i] - stamp) > 1e-3:
            raise KeyError(f"stamp {stamp:.3f} is not a keyframe of the drive")
        return i

    def correct(self, query_stamp: float, match_stamp: float) -> bool:
        q, m = self.index(query_stamp), self.index(match_stamp)
        return bool(np.linalg.norm(self.positions[q] - self.positions[m]) <= RADIUS)


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--frames", type=int, default=200, help="keyframes of the drive (0.5 s, 5 m apart)")
    p.add_argument("--seed", type=int, default=7,
                   help="seed of the synthetic city and drive (7: a test city the bundled weights never saw)")
    p.add_argument("--image-size", default="640x360", help="rendered camera size WxH")
    weights = p.add_mutually_exclusive_group()
    weights.add_argument("--weights", default=None, help="LCPR checkpoint (default: the bundled trained one)")
    weights.add_argument("--seeded", action="store_true", help="use the seeded random initialisation")
    p.add_argument("--max-distance", type=float, default=None,
                   help="match.max_distance for the node (default: the node's automatic choice: every candidate "
                        "of the top 10 is verified; with --no-verify the weights file's operating threshold, "
                        f"{BUNDLED_MAX_DISTANCE:.2f} for the bundled weights, chosen on a validation city)")
    p.add_argument("--no-verify", action="store_true",
                   help="publish the nearest descriptor without checking it against the LiDAR (the old behaviour)")
    p.add_argument("--drift-seed", type=int, default=0, help="seed of the odometry drift of the pose-graph proof")
    p.add_argument("--odometry", choices=ODOMETRY_MODES, default="drift",
                   help="drift: the pose graph over a seeded drift of the truth only (default); kiss-icp: also "
                        "KISS-ICP on the drive's own LiDAR corrected by the back end with the node's loops "
                        "(ATE before and after, backend.png; renders a LiDAR frame per metre, minutes)")
    p.add_argument("--rate", type=float, default=1.0, help="replay speed (1.0 = real time)")
    p.add_argument("--out", type=Path, default=Path("out/demo"), help="working folder")
    p.add_argument("--startup-timeout", type=float, default=120.0, help="s to wait for the node")
    return p.parse_args(argv)


def demo_drive(args: argparse.Namespace) -> SyntheticDrive:
    """The demo's synthetic drive (nuScenes-like rig, keyframes 5 m apart)."""
    from citysim import SynthConfig, SyntheticDrive

    width, height = (int(v) for v in args.image_size.lower().split("x"))
    return SyntheticDrive(SynthConfig(rig="nuscenes", frames=args.frames, seed=args.seed, image_size=(width, height)))


def make_drive(args: argparse.Namespace) -> tuple[Path, Truth]:
    from citysim import write_bag_once

    width, height = (int(v) for v in args.image_size.lower().split("x"))
    drive = demo_drive(args)
    stamps, positions = np.asarray(drive.keyframes.stamps, float), np.asarray(drive.keyframes.xy, float)
    has = np.zeros(len(stamps), bool)
    pairs = revisit_pairs(positions, stamps, radius=RADIUS, min_time_gap=MIN_GAP)
    has[pairs[:, 0]] = True
    poses = np.stack([drive.pose(i) for i in range(len(stamps))])
    bag = args.out / f"drive_seed{args.seed}_{args.frames}f_{width}x{height}"
    print(f"[1/4] {'reusing the drive' if bag.exists() else 'rendering a drive of the synthetic city into'} {bag}")
    write_bag_once(drive, bag, desc="rendering")
    return bag, Truth(stamps, positions, has, poses, np.asarray(drive.rig.lidar.base_T_lidar, np.float64))


def start_node(args: argparse.Namespace, weights: str, domain: int, log: Path) -> subprocess.Popen:
    params = {
        "camera_topics": "[" + ",".join(NUSCENES_TOPICS.cameras) + "]",
        "lidar_topic": NUSCENES_TOPICS.lidar,
        "odom_topic": NUSCENES_TOPICS.odom,
        "input_qos": "reliable",  # a replay should lose nothing; live sensors use sensor_data
        "model.threads": "2",
    }
    params["model.weights"] = weights
    if args.max_distance is not None:
        params["match.max_distance"] = str(args.max_distance)
    if args.no_verify:
        params["verify.enabled"] = "false"
    cmd = [sys.executable, "-m", "lcpr_ros.node", "--ros-args"]
    for key, value in params.items():
        cmd += ["-p", f"{key}:={value}"]
    env = {**os.environ, "ROS_DOMAIN_ID": str(domain), "PYTHONUNBUFFERED": "1"}
    return subprocess.Popen(cmd, env=env, stdout=log.open("w"), stderr=subprocess.STDOUT)


def run(args: argparse.Namespace) -> int:
    import rclpy
    from rclpy.executors import SingleThreadedExecutor

    from ros_common.harness import OutputListener

    from .replay import replay, shared_memory_profile

    args.out.mkdir(parents=True, exist_ok=True)
    weights = SEEDED if args.seeded else (args.weights or BUNDLED)
    bag, truth = make_drive(args)
    domain = random.randint(1, 100)
    os.environ["ROS_DOMAIN_ID"] = str(domain)
    log = args.out / "node.log"
    resolved = resolve_weights(weights)
    described = describe_weights(resolved)
    print(f"[2/4] starting lcpr_node (weights: {described}); its log: {log}")
    node_proc = start_node(args, weights, domain, log)
    with shared_memory_profile():  # the replaying participant's segment must hold whole frames (see .replay)
        rclpy.init()
        node = rclpy.create_node("lcpr_demo")
        listener = OutputListener(node)
        executor = SingleThreadedExecutor()
        executor.add_node(node)
        spinner = threading.Thread(target=executor.spin, daemon=True)
        spinner.start()
        try:
            try:
                listener.wait_for_publishers(timeout=args.startup_timeout)
            except TimeoutError:
                print(f"lcpr_demo: the node did not come up; see {log}", file=sys.stderr)
                return 1
            print(f"[3/4] replaying {bag.name} over DDS at {args.rate}x")
            stats = replay(node, bag, rate=args.rate, wait_subscribers=30.0, progress=True)
            _wait_until_quiet(listener, quiet_s=4.0, timeout=120.0)
            detector, inputs = listener.latest_values("detector"), listener.latest_values("inputs")
        finally:
            node_proc.send_signal(signal.SIGINT)
            try:
                node_proc.wait(timeout=60)
            except subprocess.TimeoutExpired:
                node_proc.kill()
            executor.shutdown()
            node.destroy_node()
            rclpy.shutdown()
    print("[4/4] scoring what the node published")
    return report(args, truth, listener.out, detector, inputs, stats.seconds, resolved or SEEDED)


def _wait_until_quiet(listener, *, quiet_s: float, timeout: float) -> None:
    """Wait until no new output has arrived for ``quiet_s`` (the node finished its last frame)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        last = max(listener.out.received, default=0.0)
        if time.monotonic() - last > quiet_s and listener.latest_values("detector").get("worker busy", "0") == "0":
            return
        time.sleep(0.5)


def published_loops(truth: Truth, loops: list[tuple[float, float]], rows: dict[tuple[float, float], dict[str, float]]
                    ) -> list[PublishedLoop]:
    """The loops on ~/loop_closure as keyframe indices, with the pose their ~/candidates rows carry."""
    from .outputs import row_covariance, row_pose  # rclpy message types: imported once ROS is in use

    return [PublishedLoop(truth.index(q), truth.index(m), row_pose(rows.get((q, m), {})),
                          row_covariance(rows.get((q, m), {}))) for q, m in loops]


def kiss_icp_backend(args: argparse.Namespace, out) -> tuple[BackendEvaluation, int]:
    """(KISS-ICP on the drive's own LiDAR corrected by the back end with the node's verified candidates,
    how many of those named a stamp the dense drive lacks)."""
    from lcpr_core.backend.replay import evaluate_backend
    from lcpr_offline.drive_odometry import dense_drive, record_drive

    from .outputs import row_covariance, row_pose

    drive = demo_drive(args)
    dense = dense_drive(drive, spacing=1.0)  # the bag's keyframe k is frame 5 k here
    print(f"  KISS-ICP on the drive's LiDAR, rendered every metre ({len(dense)} frames)")
    stream = record_drive(dense, every=int(round(drive.spacing)), threads=2)
    rows = [r for batch in out.candidates for r in batch if r.get("verified", 0.0) == 1.0]
    loops = [(r["query_stamp"], r["match_stamp"], pose, row_covariance(r)) for r in rows
             if (pose := row_pose(r)) is not None]
    stream, skipped = stream.with_loops(loops)
    stream, _ = stream.with_ups(out.ups)  # the node's ~/up of each keyframe
    return evaluate_backend(stream, odometry_name="KISS-ICP"), skipped


def retrieval_only(truth: Truth, out, max_distance: float) -> list[PublishedLoop]:
    """What the node published before verification: each query's nearest descriptor under ``max_distance``."""
    loops = []
    for batch in out.candidates:
        for row in batch:
            if row["rank"] == 0 and row["distance"] <= max_distance:
                loops.append(PublishedLoop(truth.index(row["query_stamp"]), truth.index(row["match_stamp"]),
                                           None, None))
    return loops


def report(args, truth: Truth, out, detector: dict, inputs: dict, replay_s: float, weights: str) -> int:
    world_T_lidar = truth.world_T_base @ truth.base_T_lidar
    positions = np.c_[truth.positions, np.zeros(len(truth.positions))]
    score = partial(score_loops, positions=positions, world_T_lidar=world_T_lidar, has_revisit=truth.has_revisit,
                    radius=RADIUS)
    by_pair = {(r["query_stamp"], r["match_stamp"]): r for batch in out.candidates for r in batch}
    loops = published_loops(truth, out.loops, by_pair)
    verified = score(loops)
    baseline = score(retrieval_only(truth, out, BUNDLED_MAX_DISTANCE))
    n_true = int(truth.has_revisit.sum())

    best = {}  # query stamp -> (top-1 distance, correct)
    for rows in out.candidates:
        for row in rows:
            if row["rank"] == 0:
                best[row["query_stamp"]] = (row["distance"], truth.correct(row["query_stamp"], row["match_stamp"]))
    dist = np.array([d for d, _ in best.values()])
    ok = np.array([c for _, c in best.values()], bool)
    pr = pr_sweep(dist, ok, num_positives=n_true, num_queries=len(truth.stamps)) if len(dist) else None
    # verified: each published loop swept over its fitness (a loop needs fitness >= t), right as by its precision
    fitness = np.array([by_pair.get(loop, {}).get("fitness", np.nan) for loop in out.loops])
    pr_verified = verified_fitness_sweep(loops, fitness, positions=positions, world_T_lidar=world_T_lidar,
                                         has_revisit=truth.has_revisit, radius=RADIUS)
    plot = args.out / "pr_curve.png"
    if pr is not None:
        plot_pr_curve(pr, plot, title="lcpr_node on the demo drive (top-1 descriptor distance)")
    proof, proof_note = None, ""
    graph_png = args.out / "posegraph.png"
    try:
        proof = pose_graph_proof(truth.world_T_base, loops, body_T_lidar=truth.base_T_lidar,
                                 drift=DriftModel(seed=args.drift_seed), plot=graph_png,
                                 title="demo drive: verified loops in a GTSAM pose graph")
    except LcprError as err:
        proof_note = f"pose graph skipped: {err}"

    backend = None
    if args.odometry == "kiss-icp":
        backend, skipped = kiss_icp_backend(args, out)
        backend.write_plot(args.out / "backend.png", title="demo drive: KISS-ICP corrected by lcpr_backend with "
                                                           "the node's verified loops")
        if skipped:
            print(f"  {skipped} verified candidates named a stamp the drive's LiDAR frames lack; left out")

    mode = "retrieval only (--no-verify)" if args.no_verify else "verified against the LiDAR"
    print(f"\nLCPR loop closure through DDS: {len(truth.stamps)} keyframes replayed in {replay_s:.0f} s")
    print(f"  weights:            {weights}")
    print(f"  true revisits:      {n_true} keyframes have an earlier keyframe within {RADIUS:.0f} m "
          f"and >= {MIN_GAP:.0f} s older")
    for line in loop_lines(verified, baseline, mode=mode):
        print(line)
    print(f"  recall:             {_f(verified.recall)} ({verified.closed} of {n_true} revisiting keyframes closed; "
          f"retrieval alone: {_f(baseline.recall)})")
    if verified.trans_err_median is not None:
        print(f"  loop pose error:    median {verified.trans_err_median:.3f} m / {verified.yaw_err_median:.2f} deg, "
              f"p95 {verified.trans_err_p95:.3f} m / {verified.yaw_err_p95:.2f} deg (vs ground truth)")
    print(f"  keyframes:          {detector.get('session keyframes', '?')} in the node's map "
          f"({detector.get('frames too soon', 0)} too soon, drops: "
          f"{', '.join(f'{k[8:]} {v}' for k, v in inputs.items() if k.startswith('dropped ')) or 'none'})")
    print(f"  latency per frame:  p50 {detector.get('latency p50 (ms)', '?')} ms, "
          f"p90 {detector.get('latency p90 (ms)', '?')} ms (model p50 {detector.get('model p50 (ms)', '?')} ms, "
          f"verification p50 {detector.get('verify p50 (ms)', '?')} ms)")
    print(f"  candidates:         {detector.get('candidates verified', 0)} verified, "
          f"{detector.get('candidates rejected', 0)} rejected")
    if proof is not None:
        print(f"  pose graph:         {proof.text()}; plot {graph_png}")
    elif proof_note:
        print(f"  {proof_note}")
    if backend is not None:
        print(f"  back end:           {backend.text()}; plot {args.out / 'backend.png'}")
    if pr_verified is not None:
        print(f"  verified loops:     max F1 {pr_verified.max_f1:.2f} (swept over fitness), recall at precision 1.0 "
              f"{_f(recall_at_full_precision(pr_verified))}")
    if pr is not None:
        print(f"  retrieval alone:    max F1 {pr.max_f1:.2f} (swept over top-1 distance, "
              f"best at {pr.max_f1_threshold:.3f}), "
              f"recall at precision 1.0 {_f(recall_at_full_precision(pr))}")
        print(f"  PR plot:            {plot}")
    summary = {
        "weights": weights, "keyframes": len(truth.stamps), "true_revisits": n_true, "verify": not args.no_verify,
        "loops": verified.loops, "correct": verified.correct, "precision": verified.precision,
        "precision_by_pose": verified.precision_by_pose,
        "recall": verified.recall, "verified": verified.to_dict(), "retrieval_only": baseline.to_dict(),
        "pose_graph": None if proof is None else proof.to_dict(),
        "backend": None if backend is None else backend.to_dict(),
        "max_f1": None if pr is None else pr.max_f1,
        "max_f1_verified": None if pr_verified is None else pr_verified.max_f1,
        "recall_at_full_precision_verified": recall_at_full_precision(pr_verified),
        "recall_at_full_precision_retrieval": recall_at_full_precision(pr),
        "detector": detector, "inputs": inputs,
    }
    write_bytes_atomic(args.out / "demo_report.json", json.dumps(summary, indent=2, default=str).encode())
    print(f"  report:             {args.out / 'demo_report.json'}")
    return 0


def loop_lines(verified: LoopScore, baseline: LoopScore, *, mode: str) -> list[str]:
    """The summary's lines on the published loops: their groups by pose and the precision, beside retrieval
    alone (which has no pose: judged by the radius rule)."""
    within = f"within {RADIUS:.0f} m"
    precision = (f"{_f(verified.precision_by_pose)} by pose, {_f(verified.precision)} {within}"
                 if verified.judged_by_pose else f"{_f(verified.precision)} {within}")
    return [f"  loops published:    {verified.loops} on ~/loop_closure ({mode}): {verified.groups_text(RADIUS)}",
            f"  precision:          {precision}   (retrieval alone, nearest descriptor under "
            f"{BUNDLED_MAX_DISTANCE:.2f}: {_f(baseline.precision)} {within})"]


def _f(value: float | None) -> str:
    return "n/a" if value is None or not np.isfinite(value) else f"{value:.2f}"


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else list(argv)
    if "--fleet" in args:  # two robots and a back end: a demo of its own (lcpr_demo --fleet --help)
        from .fleet_demo import main as fleet_main

        return fleet_main([a for a in args if a != "--fleet"])
    return run(parse_args(args))


if __name__ == "__main__":
    sys.exit(main())
