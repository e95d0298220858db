"""The fleet demo: two robots in one synthetic city, each with its own lcpr_node, one back end merging both, all
over DDS (``lcpr_demo --fleet``).

    lcpr_demo --fleet [--frames 120] [--seed 7] [--delay 0] [--rate 1.0] [--out out/fleet_demo]

1. renders drives 0 and 1 of one city (the same streets on two routes) as two bags, drive 1's clock moved to
   start ``--delay`` s after drive 0's (the robots share one clock);
2. starts, on a private ROS_DOMAIN_ID, ``lcpr_node`` in /robot1 and in /robot2 (sessions robot1 and robot2,
   each the other's peer) and ``lcpr_backend`` in /robot1 (session robot1, peers ['/robot2']);
3. replays both bags at once over DDS, each under its robot's namespace; each robot's odometry is its true
   poses drifted (:func:`lcpr_core.posegraph.drift_odometry`, from its true start), robot2's then moved by an
   arbitrary rigid transform, so that only robot1's odometry frame is the map's;
4. stops the back end (it saves its graph), reads the graph back and prints when robot2 was anchored, each
   robot's ATE and the merged ATE in the map frame (robot1's odometry frame: the truth is expressed there),
   the inter-robot loops on robot1's ``~/candidates`` judged by their pose (within 0.5 m / 3 deg, and by
   :func:`lcpr_core.loop_report.pose_right`), the bytes per keyframe on ``~/keyframes``, the CPU, whether the
   nodes kept up with ``--rate``, and writes ``fleet.png`` (a top view) and ``fleet_report.json``.
"""
from __future__ import annotations

import argparse
import heapq
import json
import os
import random
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import ExitStack
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np

from lcpr_common.progress import progress_iter
from lcpr_core.atomic import write_bytes_atomic
from lcpr_core.geometry import invert, pose_from_xyz_rpy, xyz_rpy_from_pose
from lcpr_core.posegraph import DriftModel, ate_rmse, drift_odometry
from lcpr_core.pretrained import BUNDLED, describe_weights, resolve_weights
from lcpr_core.timing import cpu_model
from lcpr_offline.relocalize import LOOSE_DEG, LOOSE_M, LoopScores, ate_against_map, map_places, random_move
from msg_tools.frames import NUSCENES_TOPICS

ROBOTS = ("robot1", "robot2")
DAY_S = 86400.0  # citysim's drive K starts K days after drive 0: moved back to share drive 0's clock
REPLAYED = (*NUSCENES_TOPICS.cameras, NUSCENES_TOPICS.lidar, NUSCENES_TOPICS.odom, NUSCENES_TOPICS.tf_static)


@dataclass
class RobotDrive:
    """One robot's drive: its bag, keyframe stamps, true poses (world = map) and the odometry it is given."""

    name: str
    bag: Path
    stamps: np.ndarray  # (N,) header stamps on the shared clock
    truth: np.ndarray  # (N, 4, 4) world_T_base
    odometry: np.ndarray  # (N, 4, 4) odom_T_base: drifted, robot2's moved
    base_T_lidar: np.ndarray

    def index(self, stamp: float) -> int:
        i = int(np.argmin(np.abs(self.stamps - stamp)))
        if abs(self.stamps[i] - stamp) > 1e-3:
            raise KeyError(f"stamp {stamp:.3f} is not a keyframe of {self.name}")
        return i


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog="lcpr_demo --fleet", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--frames", type=int, default=120, help="keyframes of each robot's drive (0.5 s, 5 m apart)")
    p.add_argument("--seed", type=int, default=7, help="seed of the synthetic city (7: a city the bundled weights "
                                                       "never saw)")
    p.add_argument("--delay", type=float, default=0.0, help="s robot2 starts after robot1 (default 0)")
    p.add_argument("--image-size", default="640x360", help="rendered camera size WxH")
    p.add_argument("--weights", default=None, help="LCPR checkpoint (default: the bundled trained one)")
    p.add_argument("--drift-seed", type=int, default=0, help="seed of the odometry drift (robot k: seed + k)")
    p.add_argument("--move-seed", type=int, default=1, help="seed of robot2's odometry frame move")
    p.add_argument("--rate", type=float, default=1.0, help="replay speed (1.0 = real time)")
    p.add_argument("--out", type=Path, default=Path("out/fleet_demo"), help="working folder")
    p.add_argument("--startup-timeout", type=float, default=120.0, help="s to wait for the nodes")
    args = p.parse_args(argv)
    if args.frames < 10:
        p.error(f"--frames {args.frames}; give at least 10")
    if args.delay < 0 or args.rate <= 0:
        p.error(f"--delay {args.delay}, --rate {args.rate}; expected delay >= 0 and rate > 0")
    return args


def make_drives(args: argparse.Namespace) -> list[RobotDrive]:
    """Render (or reuse) each robot's bag; its truth and the odometry it will be given."""
    from citysim import SynthConfig, SyntheticDrive, write_bag_once


    width, height = (int(v) for v in args.image_size.lower().split("x"))
    drives = []
    for k, name in enumerate(ROBOTS):
        start = 1.7e9 - DAY_S * k + (args.delay if k else 0.0)
        cfg = SynthConfig(rig="nuscenes", seed=args.seed, drive=k, frames=args.frames, image_size=(width, height),
                          start_time=start)
        drive = SyntheticDrive(cfg)
        truth = np.stack([drive.pose(i) for i in range(len(drive))])
        odometry, _ = drift_odometry(truth, model=DriftModel(seed=args.drift_seed + k))
        if k:
            odometry = random_move(args.move_seed) @ odometry
        bag = args.out / f"drive{k}_seed{args.seed}_{args.frames}f_{width}x{height}_delay{args.delay if k else 0:g}"
        print(f"[1/4] {'reusing' if bag.exists() else 'rendering'} {name}'s drive ({len(truth)} keyframes, drive {k} "
              f"of the city): {bag}")
        write_bag_once(drive, bag, desc=f"rendering {name}")
        drives.append(RobotDrive(name, bag, np.asarray(drive.keyframes.stamps, np.float64), truth, odometry,
                                 np.asarray(drive.rig.lidar.base_T_lidar, np.float64)))
    return drives


def start_processes(args: argparse.Namespace, drives: list[RobotDrive], weights: str, env: dict[str, str],
                    graph: Path) -> list[subprocess.Popen[bytes]]:
    """Both detectors (each its robot's namespace, the other its peer) and robot1's back end."""
    procs = []
    cameras = ",".join(t.lstrip("/") for t in NUSCENES_TOPICS.cameras)
    for name in ROBOTS:
        peer = next(n for n in ROBOTS if n != name)
        params = {"session": name, "peers": f"[/{peer}]", "camera_topics": f"[{cameras}]",
                  "lidar_topic": NUSCENES_TOPICS.lidar.lstrip("/"), "odom_topic": "odom",
                  "tf_static_topic": "tf_static", "input_qos": "reliable", "model.threads": "1",
                  "model.weights": weights}
        remaps = ["-r", f"__ns:=/{name}", "-r", f"/diagnostics:=/{name}/diagnostics"]
        procs.append(_spawn("lcpr_ros.node", params, remaps, env, args.out / f"{name}_node.log"))
    xyz, rpy = xyz_rpy_from_pose(drives[0].base_T_lidar)
    params = {"session": ROBOTS[0], "peers": f"[/{ROBOTS[1]}]", "odom_topic": "odom",
              "candidates_topic": "lcpr/candidates", "sessions_topic": "lcpr/sessions", "up_topic": "lcpr/up",
              "input_qos": "reliable", "graph.path": str(graph), "diagnostics.period": "0.5",
              "lidar.xyz": "[" + ",".join(f"{v:.9f}" for v in xyz) + "]",
              "lidar.rpy": "[" + ",".join(f"{v:.9f}" for v in rpy) + "]"}
    procs.append(_spawn("backend_ros.node", params, ["-r", f"__ns:=/{ROBOTS[0]}"], env, args.out / "backend.log"))
    return procs


def _spawn(module: str, params: dict[str, str], remaps: list[str], env: dict[str, str],
           log: Path) -> subprocess.Popen[bytes]:
    cmd = [sys.executable, "-m", module, "--ros-args", *remaps]
    for key, value in params.items():
        cmd += ["-p", f"{key}:={value}"]
    return subprocess.Popen(cmd, env=env, stdout=log.open("w"), stderr=subprocess.STDOUT)


@dataclass
class Listener:
    """What the demo hears: robot1's candidates and session table, every keyframe record's size, each node's
    newest diagnostics, and when the back end first reported robot2 anchored."""

    rows: list[dict[str, float]] = field(default_factory=list)
    table: list[str] = field(default_factory=list)
    keyframe_bytes: dict[str, list[int]] = field(default_factory=lambda: {n: [] for n in ROBOTS})
    diagnostics: dict[str, dict[str, str]] = field(default_factory=dict)  # "<robot>: <status>" -> values
    anchored_wall: float | None = None
    last_heard: float = 0.0
    lock: threading.Lock = field(default_factory=threading.Lock)

    def subscribe(self, node: Any) -> None:
        from diagnostic_msgs.msg import DiagnosticArray
        from std_msgs.msg import Float64MultiArray, String, UInt8MultiArray

        from ros_common.qos import CANDIDATE_QOS, LATCHED_QOS, keyframes_qos

        node.create_subscription(Float64MultiArray, f"/{ROBOTS[0]}/lcpr/candidates", self._on_candidates,
                                 CANDIDATE_QOS)
        node.create_subscription(String, f"/{ROBOTS[0]}/lcpr/sessions", self._on_sessions, LATCHED_QOS)
        for name in ROBOTS:
            node.create_subscription(UInt8MultiArray, f"/{name}/lcpr/keyframes",
                                     partial(self._on_keyframe, name), keyframes_qos(1000))
            node.create_subscription(DiagnosticArray, f"/{name}/diagnostics", partial(self._on_diagnostics, name),
                                     10)
        node.create_subscription(DiagnosticArray, "/diagnostics", partial(self._on_diagnostics, "backend"), 10)

    def _on_candidates(self, msg: Any) -> None:
        from ros_common.tables import parse_candidates

        with self.lock:
            self.rows.extend(parse_candidates(msg))
            self.last_heard = time.monotonic()

    def _on_sessions(self, msg: Any) -> None:
        from ros_common.tables import parse_sessions

        with self.lock:
            self.table = parse_sessions(msg)

    def _on_keyframe(self, robot: str, msg: Any) -> None:
        with self.lock:
            self.keyframe_bytes[robot].append(len(msg.data))
            self.last_heard = time.monotonic()

    def _on_diagnostics(self, source: str, msg: Any) -> None:
        with self.lock:
            for status in msg.status:
                values = {kv.key: kv.value for kv in status.values}
                self.diagnostics[f"{source}: {status.name.split(':')[-1].strip()}"] = values
                if (self.anchored_wall is None and ROBOTS[1] in values.get("peer sessions anchored", "").split(", ")):
                    self.anchored_wall = time.monotonic()

    def values(self, key: str) -> dict[str, str]:
        with self.lock:
            return dict(self.diagnostics.get(key, {}))

    def busy(self) -> bool:
        """Whether a detector still works on a frame or a peer's keyframe, or the back end on its queue."""
        return any(self.values(f"{n}: detector").get("worker busy", "0") != "0" for n in ROBOTS) or \
            self.values("backend: graph").get("worker waiting", "0") != "0"


def replay_both(node: Any, drives: list[RobotDrive], *, rate: float, clock: dict[str, float],
                progress: bool = True) -> float:
    """Publish both bags at once under /robot1 and /robot2, paced by header time on the shared clock; each odometry
    message carries its robot's given odometry (not the bag's true pose). ``clock`` holds each robot's newest
    replayed stamp. Returns the wall seconds taken."""
    from nav_msgs.msg import Odometry
    from rclpy.duration import Duration
    from rclpy.serialization import deserialize_message

    from msg_tools.bags.open import open_bag
    from ros_common.stamps import NS_PER_S

    from .replay import LATCHED, QOS, message_class

    streams = []
    publishers: dict[str, Any] = {}
    bags = ExitStack()
    for k, drive in enumerate(drives):
        reader = bags.enter_context(open_bag(drive.bag))
        connections = [c for c in reader.connections if c.topic in REPLAYED]
        for c in connections:
            topic = f"/{drive.name}{c.topic}"
            if topic not in publishers and (cls := message_class(c.msgtype)) is not None:
                publishers[topic] = node.create_publisher(cls, topic, LATCHED if c.topic.endswith("tf_static")
                                                          else QOS)
        streams.append(_tagged(reader.messages(connections=connections), k))
    _wait_for_subscribers(publishers, timeout=30.0)
    total = sum(len(d.stamps) * (len(NUSCENES_TOPICS.cameras) + 2) for d in drives)
    merged: Iterator[tuple[int, int, str, Any]] = heapq.merge(*streams)
    start_wall, first_ns = time.monotonic(), None
    try:
        for log_ns, k, topic, raw in progress_iter(merged, total=total, desc="replay", unit="msg", enabled=progress):
            drive = drives[k]
            name = f"/{drive.name}{topic}"
            if name not in publishers:
                continue
            first_ns = log_ns if first_ns is None else first_ns
            delay = start_wall + (log_ns - first_ns) / NS_PER_S / rate - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            if topic == NUSCENES_TOPICS.odom:
                msg = deserialize_message(bytes(raw), Odometry)
                stamp = msg.header.stamp.sec + msg.header.stamp.nanosec / NS_PER_S
                _set_pose(msg, drive.odometry[drive.index(stamp)])
                publishers[name].publish(msg)
                clock[drive.name] = stamp
            else:
                publishers[name].publish(bytes(raw))
    finally:
        bags.close()
    for publisher in publishers.values():
        publisher.wait_for_all_acked(Duration(seconds=2))
    return time.monotonic() - start_wall


def _tagged(messages: Iterator[tuple[Any, int, Any]], robot: int) -> Iterator[tuple[int, int, str, Any]]:
    """A bag's messages as (log time, robot index, topic, raw) for merging by time."""
    for connection, log_ns, raw in messages:
        yield log_ns, robot, connection.topic, raw


def _wait_for_subscribers(publishers: dict[str, Any], *, timeout: float) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if all(p.get_subscription_count() > 0 for t, p in publishers.items() if not t.endswith("tf_static")):
            return
        time.sleep(0.1)


def _set_pose(msg: Any, pose: np.ndarray) -> None:
    from msg_tools.geometry import pose_to_parts

    t, q = pose_to_parts(pose)
    p = msg.pose.pose
    p.position.x, p.position.y, p.position.z = (float(v) for v in t)
    p.orientation.x, p.orientation.y, p.orientation.z, p.orientation.w = (float(v) for v in q)


def _stop(procs: list[subprocess.Popen[bytes]], timeout: float = 60.0) -> None:
    for proc in procs:
        if proc.poll() is None:
            proc.send_signal(signal.SIGINT)
    for proc in procs:
        try:
            proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def run(args: argparse.Namespace) -> int:
    import rclpy
    from rclpy.executors import SingleThreadedExecutor

    from .replay import shared_memory_profile

    args.out.mkdir(parents=True, exist_ok=True)
    drives = make_drives(args)
    weights = args.weights or BUNDLED
    resolved = resolve_weights(weights)
    domain = random.randint(1, 100)
    env = {**os.environ, "ROS_DOMAIN_ID": str(domain), "PYTHONUNBUFFERED": "1"}
    os.environ["ROS_DOMAIN_ID"] = str(domain)
    graph = args.out / "graph.npz"
    graph.unlink(missing_ok=True)
    print(f"[2/4] starting lcpr_node in /robot1 and /robot2 and lcpr_backend in /robot1 (weights: "
          f"{describe_weights(resolved)}); logs in {args.out}")
    procs = start_processes(args, drives, weights, env, graph)
    listener, clock = Listener(), {n: -np.inf for n in ROBOTS}
    anchored_stamp: float | None = None
    with shared_memory_profile():
        rclpy.init()
        node = rclpy.create_node("lcpr_fleet_demo")
        listener.subscribe(node)
        executor = SingleThreadedExecutor()
        executor.add_node(node)
        threading.Thread(target=executor.spin, daemon=True).start()
        try:
            if not _wait_for_nodes(node, args.startup_timeout):
                print(f"lcpr_demo --fleet: the nodes did not come up; see the logs in {args.out}", file=sys.stderr)
                return 1
            watch = threading.Event()

            def note_anchoring() -> None:  # robot2's newest replayed stamp when the back end reports it anchored
                nonlocal anchored_stamp
                while not watch.wait(0.05):
                    if listener.anchored_wall is not None:
                        anchored_stamp = clock[ROBOTS[1]]
                        return

            watcher = threading.Thread(target=note_anchoring, daemon=True)
            watcher.start()
            span = max(d.stamps[-1] for d in drives) - min(d.stamps[0] for d in drives)
            print(f"[3/4] replaying both drives ({span:.0f} s of header time) over DDS at {args.rate}x")
            replay_s = replay_both(node, drives, rate=args.rate, clock=clock)
            ended = time.monotonic()
            quiet = _wait_until_quiet(listener, quiet_s=5.0, timeout=300.0)
            lag_s = quiet - ended
            watch.set()
        finally:
            _stop(procs[:2])
            _stop(procs[2:])  # the back end last: it saves its graph on the way out
            executor.shutdown()
            node.destroy_node()
            rclpy.try_shutdown()
    print("[4/4] scoring the back end's graph and what the nodes published")
    return report(args, drives, listener, graph, replay_s=replay_s, lag_s=lag_s, anchored_stamp=anchored_stamp,
                  span_s=span)


def _wait_for_nodes(node: Any, timeout: float) -> bool:
    topics = [f"/{n}/lcpr/candidates" for n in ROBOTS] + [f"/{ROBOTS[0]}/lcpr_backend/localized"]
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if all(node.count_publishers(t) > 0 for t in topics):
            return True
        time.sleep(0.2)
    return False


def _wait_until_quiet(listener: Listener, *, quiet_s: float, timeout: float) -> float:
    """Wait until nothing new was heard for ``quiet_s`` and no worker is busy; the monotonic time of the last
    output (the nodes' lag behind the replay ends there)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if time.monotonic() - listener.last_heard > quiet_s and not listener.busy():
            break
        time.sleep(0.5)
    return listener.last_heard


def check_loops(drives: list[RobotDrive], rows: list[dict[str, float]], table: list[str]) -> LoopScores:
    """Robot1's verified inter-robot rows judged against the truth."""
    from ros_common.tables import row_pose

    by_name = {d.name: d for d in drives}
    out = LoopScores()
    for row in rows:
        if row.get("verified", 0.0) != 1.0 or (pose := row_pose(row)) is None:
            continue
        codes = (row.get("query_session", np.nan), row.get("match_session", np.nan))
        if not all(np.isfinite(codes)) or codes[0] == codes[1] or max(codes) >= len(table):
            continue
        q, m = by_name[table[int(codes[0])]], by_name[table[int(codes[1])]]
        out.add(pose, invert(m.truth[m.index(row["match_stamp"])] @ m.base_T_lidar)
                @ q.truth[q.index(row["query_stamp"])] @ q.base_T_lidar)
    return out


def report(args: argparse.Namespace, drives: list[RobotDrive], listener: Listener, graph_file: Path, *,
           replay_s: float, lag_s: float, anchored_stamp: float | None, span_s: float) -> int:
    from lcpr_core.backend import BackendConfig, PoseGraphBackend

    if not graph_file.is_file():
        print(f"lcpr_demo --fleet: the back end saved no graph to {graph_file}; see {args.out / 'backend.log'}",
              file=sys.stderr)
        return 1
    xyz, rpy = (tuple(float(f"{v:.9f}") for v in part) for part in xyz_rpy_from_pose(drives[0].base_T_lidar))
    graph = PoseGraphBackend.load(graph_file, BackendConfig(base_T_lidar=pose_from_xyz_rpy(xyz, rpy)))
    ates: dict[str, float | None] = {}
    odom_ate: dict[str, float] = {}
    tracks: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    for d in drives:
        if d.name not in graph.sessions or not graph.anchored(d.name):
            ates[d.name] = None
            continue
        stamps, traj = graph.trajectory(d.name)
        truth = d.truth[[d.index(float(s)) for s in stamps]]
        ates[d.name], tracks[d.name] = ate_rmse(traj, truth), (traj, truth)
    odom_ate[ROBOTS[0]] = ate_rmse(drives[0].odometry, drives[0].truth)  # robot1's odometry frame is the map
    merged = None
    if len(tracks) == len(drives):
        merged = ate_rmse(np.concatenate([t for t, _ in tracks.values()]),
                          np.concatenate([r for _, r in tracks.values()]))
    against_map = None  # robot2 against where robot1's map has its places (lcpr_offline.relocalize.map_places)
    if ROBOTS[0] in tracks and ROBOTS[1] in tracks:
        kf, _ = graph.nodes(ROBOTS[0])
        in_map = map_places(graph, ROBOTS[0], kf, drives[0].truth[[drives[0].index(float(t)) for t in kf]])
        against_map = ate_against_map(*tracks[ROBOTS[1]], in_map)
    loops = check_loops(drives, listener.rows, listener.table)
    taken = [pair for pair in graph.session_loops() if pair[0] != pair[2]]
    sizes = [b for robot in ROBOTS for b in listener.keyframe_bytes[robot]]
    backend = listener.values("backend: graph")
    robot2_start = float(drives[1].stamps[0])
    anchored_after = None if anchored_stamp is None else anchored_stamp - robot2_start
    drops = {n: {k[8:]: v for k, v in listener.values(f"{n}: inputs").items() if k.startswith("dropped ") and v != "0"}
             for n in ROBOTS}
    kept_up = all(not d for d in drops.values()) and lag_s < 5.0
    png = args.out / "fleet.png"
    plot(drives, tracks, png, anchored_stamp=anchored_stamp)

    def show(v: float | None) -> str:
        return "-" if v is None else f"{v:.2f} m"

    print(f"\nLCPR fleet over DDS: 2 robots, {len(drives[0].stamps)} + {len(drives[1].stamps)} keyframes, "
          f"robot2 {args.delay:g} s late")
    print(f"  CPU:                {cpu_model()}, {os.cpu_count()} cores; replay at {args.rate:g}x: "
          f"{span_s:.0f} s of header time in {replay_s:.0f} s; last output {max(lag_s, 0.0):.1f} s after the "
          "replay ended")
    print(f"  kept up:            {'yes' if kept_up else 'no'} (dropped inputs: {drops})")
    where = ("never anchored" if ROBOTS[1] not in graph.sessions or not graph.anchored(ROBOTS[1]) else
             "anchored" + ("" if anchored_after is None else f" {anchored_after:.1f} s of its header time after its "
                                                               "start (its newest replayed stamp when the back end "
                                                               "reported it)"))
    print(f"  robot2:             {where}")
    print(f"  ATE in the map:     robot1 {show(ates[ROBOTS[0]])} (its odometry alone {odom_ate[ROBOTS[0]]:.2f} m), "
          f"robot2 {show(ates[ROBOTS[1]])}, merged {show(merged)} (every graph node of the saved graph); "
          f"robot2 against robot1's map {show(against_map)}")
    if loops.count:
        print(f"  inter-robot loops:  {loops.count} verified on robot1's ~/candidates: {loops.within} within "
              f"{LOOSE_M} m / {LOOSE_DEG:g} deg, {loops.right} right by pose_right; error median "
              f"{np.median(loops.errors_m):.3f} m / {np.median(loops.errors_deg):.2f} deg, max "
              f"{max(loops.errors_m):.3f} m / {max(loops.errors_deg):.2f} deg; {len(taken)} in the back end's graph")
    else:
        print(f"  inter-robot loops:  none verified on robot1's ~/candidates; {len(taken)} in the back end's graph")
    print(f"  ~/keyframes:        {len(sizes)} records, "
          f"{np.mean(sizes) / 1024 if sizes else 0:.1f} KiB a keyframe (mean; max {max(sizes, default=0) / 1024:.1f})")
    print("  back end:           " + ", ".join(f"{k} {v}" for k, v in backend.items()
                                                if k.startswith(("inter-session", "peer sessions", "refused"))))
    print(f"  plot:               {png}")
    summary = {
        "cpu": cpu_model(), "cores": os.cpu_count(), "rate": args.rate, "delay_s": args.delay,
        "frames": [len(d.stamps) for d in drives], "replay_s": replay_s, "span_s": span_s, "lag_s": lag_s,
        "kept_up": kept_up, "dropped": drops, "robot2_anchored_after_s": anchored_after, "ate_m": ates,
        "odometry_ate_m": odom_ate, "merged_ate_m": merged, "robot2_against_map_m": against_map,
        "inter_robot_loops": {"rows": loops.count, "within": loops.within, "pose_right": loops.right,
                              "in_graph": len(taken), "errors_m": loops.errors_m, "errors_deg": loops.errors_deg},
        "keyframe_bytes_mean": float(np.mean(sizes)) if sizes else None, "keyframes": len(sizes),
        "backend": backend, "detectors": {n: listener.values(f"{n}: detector") for n in ROBOTS},
    }
    write_bytes_atomic(args.out / "fleet_report.json", json.dumps(summary, indent=2, default=str).encode())
    print(f"  report:             {args.out / 'fleet_report.json'}")
    return 0


def plot(drives: list[RobotDrive], tracks: dict[str, tuple[np.ndarray, np.ndarray]], path: Path, *,
         anchored_stamp: float | None) -> None:
    """fleet.png: each robot's true path and its merged trajectory (the saved graph, map frame), top view."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from lcpr_core.atomic import save_figure

    fig, ax = plt.subplots(figsize=(7, 6))
    for d, color in zip(drives, ("tab:blue", "tab:orange"), strict=True):
        ax.plot(d.truth[:, 0, 3], d.truth[:, 1, 3], "-", color="0.6", lw=3, alpha=0.5)
        if d.name in tracks:
            traj = tracks[d.name][0]
            ax.plot(traj[:, 0, 3], traj[:, 1, 3], ".-", color=color, ms=3, lw=1, label=f"{d.name} merged")
    ax.plot([], [], "-", color="0.6", lw=3, alpha=0.5, label="truth")
    if anchored_stamp is not None:
        d = drives[1]
        i = int(np.argmin(np.abs(d.stamps - anchored_stamp)))
        ax.plot(d.truth[i, 0, 3], d.truth[i, 1, 3], "r*", ms=14, label="robot2 anchored")
    ax.set_aspect("equal")
    ax.set_xlabel("x (m, map = robot1's odometry frame)")
    ax.set_ylabel("y (m)")
    ax.set_title("lcpr fleet demo: both robots merged by lcpr_backend", fontsize=9)
    ax.legend(fontsize=8)
    save_figure(fig, path)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    return run(parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
