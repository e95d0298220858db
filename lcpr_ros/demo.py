"""The end-to-end demo: a synthetic drive with loops, replayed through DDS into a real lcpr_node.

    lcpr_demo [--frames 160] [--seed 0] [--weights FILE | --seeded] [--rate 1.0] [--out out/demo]

1. makes (or reuses) a synthetic-city drive with revisits (nuScenes-like rig) as a rosbag2;
2. starts ``lcpr_node`` as its own process (a private ROS_DOMAIN_ID);
3. replays the bag over DDS with its original stamps, listening to what the node publishes;
4. compares the loops on ``~/loop_closure`` with the true revisits (<= 9 m, >= 30 s
   older) and prints precision, recall, latency and where the PR plot was written.
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
from pathlib import Path

import numpy as np

from lcpr_core.atomic import write_bytes_atomic
from lcpr_core.metrics import pr_sweep
from lcpr_core.metrics import plot_pr_curve
from lcpr_core.pretrained import BUNDLED_MAX_DISTANCE, default_weights
from msg_tools.frames import NUSCENES_TOPICS
from msg_tools.ground_truth import revisit_pairs

RADIUS = 9.0  # m: a loop is correct when the matched keyframe is this close (the paper's threshold)
MIN_GAP = 30.0  # s: the node excludes younger keyframes, and so does the ground truth


@dataclass(frozen=True)
class Truth:
    stamps: np.ndarray  # N keyframe stamps
    positions: np.ndarray  # N x 2
    has_revisit: np.ndarray  # N bool: an earlier keyframe >= 30 s older lies within 9 m

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
                   help="seed of the synthetic city and drive (7: held out; the bundled weights saw 1 and 2)")
    p.add_argument("--image-size", default="640x360", help="rendered camera size WxH")
    weights = p.add_mutually_exclusive_group()
    weights.add_argument("--weights", default=None, help="LCPR checkpoint (default: the bundled trained one)")
    weights.add_argument("--seeded", action="store_true", help="use the seeded random initialisation")
    p.add_argument("--max-distance", type=float, default=None,
                   help=f"match.max_distance for the node (bundled weights: {BUNDLED_MAX_DISTANCE}, chosen on a "
                        "validation city; otherwise the node's default)")
    p.add_argument("--rate", type=float, default=1.0, help="replay speed (1.0 = real time)")
    p.add_argument("--out", type=Path, default=Path("out/demo"), help="working folder")
    p.add_argument("--startup-timeout", type=float, default=120.0, help="s to wait for the node")
    return p.parse_args(argv)


def make_drive(args: argparse.Namespace) -> tuple[Path, Truth]:
    from tqdm import tqdm

    from msg_tools.synth import SynthConfig, SyntheticDrive, write_bag

    width, height = (int(v) for v in args.image_size.lower().split("x"))
    drive = SyntheticDrive(SynthConfig(rig="nuscenes", frames=args.frames, seed=args.seed, image_size=(width, height)))
    stamps, positions = np.asarray(drive.keyframes.stamps, float), np.asarray(drive.keyframes.xy, float)
    has = np.zeros(len(stamps), bool)
    pairs = revisit_pairs(positions, stamps, radius=RADIUS, min_time_gap=MIN_GAP)
    has[pairs[:, 0]] = True
    bag = args.out / f"drive_seed{args.seed}_{args.frames}f_{width}x{height}"
    if bag.exists():
        print(f"[1/4] reusing the drive {bag}")
    else:
        print(f"[1/4] rendering a {len(stamps)}-keyframe drive of the synthetic city into {bag}")
        write_bag(drive, bag, workers=2,
                  wrap=lambda frames: tqdm(frames, total=len(stamps), desc="rendering", unit="frame"))
    return bag, Truth(stamps, positions, has)


def start_node(args: argparse.Namespace, weights: str, domain: int, log: Path) -> subprocess.Popen:
    params = {
        "camera_topics": "[" + ",".join(NUSCENES_TOPICS.cameras) + "]",
        "lidar_topic": NUSCENES_TOPICS.lidar,
        "odom_topic": NUSCENES_TOPICS.odom,
        "input_qos": "reliable",  # a replay should lose nothing; live sensors use sensor_data
        "model.threads": "2",
    }
    if weights:  # an empty value is not valid --ros-args syntax; "" is the default anyway
        params["model.weights"] = weights
    if args.max_distance is not None:
        params["match.max_distance"] = str(args.max_distance)
    cmd = [sys.executable, "-m", "lcpr_ros.node", "--ros-args"]
    for key, value in params.items():
        cmd += ["-p", f"{key}:={value}"]
    env = {**os.environ, "ROS_DOMAIN_ID": str(domain), "PYTHONUNBUFFERED": "1"}
    return subprocess.Popen(cmd, env=env, stdout=log.open("w"), stderr=subprocess.STDOUT)


def run(args: argparse.Namespace) -> int:
    import rclpy
    from rclpy.executors import SingleThreadedExecutor

    from .harness import OutputListener
    from .replay import replay, shared_memory_profile

    args.out.mkdir(parents=True, exist_ok=True)
    weights = "" if args.seeded else (args.weights or default_weights() or "")
    if args.max_distance is None and weights and weights == default_weights():
        args.max_distance = BUNDLED_MAX_DISTANCE
    bag, truth = make_drive(args)
    domain = random.randint(1, 100)
    os.environ["ROS_DOMAIN_ID"] = str(domain)
    log = args.out / "node.log"
    described = weights or "seeded random initialisation (NOT a trained model: expect poor loops)"
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
    return report(args, truth, listener.out, detector, inputs, stats.seconds, described)


def _wait_until_quiet(listener, *, quiet_s: float, timeout: float) -> None:
    """Wait until no new output has arrived for ``quiet_s`` (the node finished its last frame)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        last = max(listener.out.received, default=0.0)
        if time.monotonic() - last > quiet_s and listener.latest_values("detector").get("worker busy", "0") == "0":
            return
        time.sleep(0.5)


def report(args, truth: Truth, out, detector: dict, inputs: dict, replay_s: float, weights: str) -> int:
    loops = [(q, m, truth.correct(q, m)) for q, m in out.loops]
    tp = sum(ok for *_, ok in loops)
    found = {truth.index(q) for q, _, ok in loops if ok}
    n_true = int(truth.has_revisit.sum())
    precision = tp / len(loops) if loops else float("nan")
    recall = len(found) / n_true if n_true else float("nan")

    best = {}  # query stamp -> (top-1 distance, correct)
    for rows in out.candidates:
        for row in rows:
            if row["rank"] == 0:
                best[row["query_stamp"]] = (row["distance"], truth.correct(row["query_stamp"], row["match_stamp"]))
    dist = np.array([d for d, _ in best.values()])
    ok = np.array([c for _, c in best.values()], bool)
    pr = pr_sweep(dist, ok, num_positives=n_true, num_queries=len(truth.stamps)) if len(dist) else None
    plot = args.out / "pr_curve.png"
    if pr is not None:
        plot_pr_curve(pr, plot, title="lcpr_node on the demo drive (top-1)")

    print(f"\nLCPR loop closure through DDS: {len(truth.stamps)} keyframes replayed in {replay_s:.0f} s")
    print(f"  weights:            {weights}")
    print(f"  true revisits:      {n_true} keyframes have an earlier keyframe within {RADIUS:.0f} m "
          f"and >= {MIN_GAP:.0f} s older")
    print(f"  loops published:    {len(loops)} on ~/loop_closure, {tp} correct, {len(loops) - tp} wrong")
    print(f"  precision:          {precision:.2f}")
    print(f"  recall:             {recall:.2f} ({len(found)} of {n_true} revisiting keyframes closed)")
    print(f"  keyframes:          {detector.get('session keyframes', '?')} in the node's map "
          f"({detector.get('frames too soon', 0)} too soon, drops: "
          f"{', '.join(f'{k[8:]} {v}' for k, v in inputs.items() if k.startswith('dropped ')) or 'none'})")
    print(f"  latency per frame:  p50 {detector.get('latency p50 (ms)', '?')} ms, "
          f"p90 {detector.get('latency p90 (ms)', '?')} ms (model p50 {detector.get('model p50 (ms)', '?')} ms)")
    if pr is not None:
        print(f"  max F1 over ~/candidates distances: {pr.max_f1:.2f} at distance {pr.max_f1_threshold:.3f}")
        print(f"  PR plot:            {plot}")
    summary = {
        "weights": weights, "keyframes": len(truth.stamps), "true_revisits": n_true, "loops": len(loops),
        "correct": tp, "precision": precision, "recall": recall, "max_f1": None if pr is None else pr.max_f1,
        "detector": detector, "inputs": inputs,
    }
    write_bytes_atomic(args.out / "demo_report.json", json.dumps(summary, indent=2).encode())
    print(f"  report:             {args.out / 'demo_report.json'}")
    return 0


def main(argv: list[str] | None = None) -> int:
    return run(parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
