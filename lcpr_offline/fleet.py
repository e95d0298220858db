"""Robots sharing one site, replayed in one process: each its own detector, keyframes passed between them as
``~/keyframes`` carries them, one back end merging every robot's session (``lcpr_fleet``).

    robots = [Robot("robot1", steps_1), Robot("robot2", steps_2, delay_s=60.0, move=T)]
    result = fleet_replay(robots, detector=DetectorConfig(...))
    print(result.text())

Each robot's frames are replayed in header-time order across all robots (its clock starts ``delay_s`` after
the first robot's). A robot's keyframe is encoded as the wire record (``lcpr_core.detector.
encode_peer_keyframe``: what the node publishes; its bytes are counted), decoded and given to every other
robot's detector (``add_peer_keyframe``); a robot that has not started yet gets the ones it missed when it
starts, as a transient-local subscription does. Each verified candidate, from a robot's own keyframe or from
a peer's, goes to the back end with its two sessions (a pair found by both robots is taken once). The first
robot's odometry starts at its reference pose and defines the map frame; the others' odometry frames are
moved by ``move`` (their frames owe nothing to the map's).

Measured against the reference poses: when each robot was anchored, its ATE in the map frame from then on,
the merged ATE over every anchored pose, each inter-robot loop's pose (right within 0.3 m / 2 deg, as
:func:`lcpr_core.loop_report.pose_right`) and the bytes per keyframe on the wire. The replay is
event-ordered, not timed: the result does not depend on how fast it runs.
"""
from __future__ import annotations

import dataclasses
import heapq
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from lcpr_common.cli import tool_main
from lcpr_common.progress import progress_iter
from lcpr_core.backend import BackendConfig, PoseGraphBackend
from lcpr_core.detector import (
    DetectorConfig,
    Frame,
    LoopDetector,
    Result,
    decode_peer_keyframe,
    encode_peer_keyframe,
)
from lcpr_core.errors import BackendError
from lcpr_core.geometry import invert
from lcpr_core.posegraph import ate_rmse

from .relocalize import LoopScores, Step, ate_against_map, map_places

__all__ = ["FleetResult", "Robot", "fleet_replay"]


@dataclass
class Robot:
    """One robot: its session name, its frames, its start delay (s) and its odometry frame's move."""

    name: str
    steps: Sequence[Step]
    delay_s: float = 0.0
    move: np.ndarray = field(default_factory=lambda: np.eye(4))


@dataclass
class FleetResult:
    robots: list[str]
    anchored_at_s: dict[str, float | None]  # seconds after the robot's start
    ate_m: dict[str, float | None]  # each robot in the map frame, from its anchoring on
    merged_ate_m: float | None  # every anchored pose of every robot
    ate_vs_map_m: dict[str, float | None]  # each other robot against where the first robot's map has its places
    loops: dict[str, int]  # inter-robot loops taken by the back end: right / wrong pose
    keyframes: int  # keyframes sent
    bytes_per_keyframe: float  # mean wire record size
    inter_session: dict[str, int] = field(default_factory=dict)
    refused: dict[str, int] = field(default_factory=dict)
    loop_error: dict[str, float] = field(default_factory=dict)  # inter-robot loops' pose error: p50, p90, max

    def text(self) -> str:
        lines = [f"{len(self.robots)} robots, {self.keyframes} keyframes sent, "
                 f"{self.bytes_per_keyframe / 1024:.1f} KiB a keyframe on the wire"]
        for name in self.robots:
            at, ate = self.anchored_at_s[name], self.ate_m[name]
            where = "defines the map" if name == self.robots[0] else (
                "never anchored" if at is None else f"anchored {at:.1f} s after its start")
            against = self.ate_vs_map_m.get(name)
            lines.append(f"  {name}: {where}; ATE in the map frame {'-' if ate is None else f'{ate:.3f} m'}"
                         + ("" if against is None else f", {against:.3f} m against the first robot's map"))
        merged = "-" if self.merged_ate_m is None else f"{self.merged_ate_m:.3f} m"
        lines.append(f"  merged ATE {merged}; inter-robot loops by pose {self.loops}; their error against the "
                     f"reference {self.loop_error}")
        lines.append(f"  back end: {self.inter_session}; refused inputs: {self.refused}")
        return "\n".join(lines)

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


def fleet_replay(robots: Sequence[Robot], *, detector: DetectorConfig, backend: BackendConfig | None = None,
                 progress: bool = True) -> FleetResult:
    """Replay ``robots`` together (the module docstring says how and what is measured)."""
    names = [r.name for r in robots]
    if len(set(names)) != len(names) or len(robots) < 2:
        raise ValueError(f"robots {names}; expected two or more with distinct names")
    base_T_lidar = np.eye(4) if backend is None else backend.base_T_lidar
    dets = {r.name: LoopDetector(dataclasses.replace(detector, session=r.name)) for r in robots}
    graph = PoseGraphBackend(backend)
    cameras = detector.model.num_cameras
    t0 = min(r.steps[0].stamp for r in robots)
    # header time of each robot: its own stamps shifted so that it starts delay_s after t0
    shift = {r.name: t0 + r.delay_s - r.steps[0].stamp for r in robots}
    events = [(s.stamp + shift[r.name], k, i) for k, r in enumerate(robots) for i, s in enumerate(r.steps)]
    heapq.heapify(events)
    started: set[str] = set()
    sent: list[tuple[str, bytes]] = []  # every record so far, for a robot that starts late
    truth: dict[tuple[str, float], np.ndarray] = {}  # (session, stamp) -> reference pose
    taken: set[tuple[str, float, str, float]] = set()
    scores = LoopScores()
    anchored: dict[str, float | None] = {r.name: None for r in robots}

    def take(result: Result) -> None:
        for c in result.candidates:
            if not (c.verified and c.match_T_query is not None):
                continue
            key = (c.query_session, c.query_stamp, c.match_session, c.match_stamp)
            if key in taken or (key[2], key[3], key[0], key[1]) in taken:
                continue
            taken.add(key)
            try:
                ok = graph.add_loop(c.query_stamp, c.match_stamp, c.match_T_query, c.covariance,
                                    query_session=c.query_session, match_session=c.match_session)
            except BackendError:
                continue
            if c.query_session != c.match_session and (ok or graph.anchored(c.query_session)):
                scores.add(c.match_T_query, invert(truth[(c.match_session, c.match_stamp)] @ base_T_lidar)
                           @ truth[(c.query_session, c.query_stamp)] @ base_T_lidar)

    def deliver(sender: str, record: bytes, to: list[str]) -> None:
        for name in to:
            take(dets[name].add_peer_keyframe(decode_peer_keyframe(record)))

    for _ in progress_iter(range(len(events)), total=len(events), desc="fleet", unit="frame", enabled=progress):
        t, k, i = heapq.heappop(events)
        robot, step = robots[k], robots[k].steps[i]
        if robot.name not in started:  # a late joiner: the keyframes it missed, as transient-local delivers them
            started.add(robot.name)
            for sender, record in sent:
                deliver(sender, record, [robot.name])
        odom = robot.move @ step.odometry
        truth[(robot.name, t)] = step.reference
        try:
            graph.add_odometry(t, odom, session=robot.name)
        except BackendError:
            pass
        frame = Frame(stamp=t, images=[None] * cameras, points=step.points, pose=odom)
        result = dets[robot.name].process(frame)
        take(result)
        if result.keyframe_id is not None:
            record = encode_peer_keyframe(dets[robot.name].peer_keyframe(result.keyframe_id))
            sent.append((robot.name, record))
            deliver(robot.name, record, [n for n in started if n != robot.name])
        if anchored[robot.name] is None and graph.anchored(robot.name):
            anchored[robot.name] = t - (t0 + robot.delay_s)
    ates: dict[str, float | None] = {}
    against_map: dict[str, float | None] = {}
    tracks: list[tuple[np.ndarray, np.ndarray]] = []  # (estimate, reference) of each anchored robot
    first = robots[0].name
    kf = sorted(t for (name, t) in truth if name == first and t in set(graph.nodes(first)[0].tolist()))
    in_map = map_places(graph, first, np.array(kf), np.stack([truth[(first, t)] for t in kf])) if kf else None
    for r in robots:
        if not graph.anchored(r.name):
            ates[r.name] = None
            continue
        stamps, traj = graph.trajectory(r.name)
        ref = np.stack([truth[(r.name, float(s))] for s in stamps])
        since = anchored[r.name] or 0.0
        keep = stamps >= t0 + r.delay_s + since
        ates[r.name] = ate_rmse(traj[keep], ref[keep]) if keep.any() else None
        tracks.append((traj[keep], ref[keep]))
        if r.name != first and in_map is not None:
            against_map[r.name] = ate_against_map(traj[keep], ref[keep], in_map)
    merged = [np.concatenate([track[k] for track in tracks]) for k in (0, 1)] if tracks else None
    stats = graph.stats()
    return FleetResult(robots=names, anchored_at_s=anchored, ate_m=ates, ate_vs_map_m=against_map,
                       merged_ate_m=None if merged is None or not len(merged[0]) else ate_rmse(*merged),
                       loops=scores.counts(), keyframes=len(sent),
                       bytes_per_keyframe=float(np.mean([len(b) for _, b in sent])) if sent else 0.0,
                       inter_session=stats.inter_session, refused=stats.refused, loop_error=scores.spread())


@tool_main
def main(argv: list[str] | None = None) -> int:
    import argparse
    import json
    import time
    from pathlib import Path

    from lcpr_common.shared_data import shared_path
    from lcpr_core.atomic import write_bytes_atomic
    from lcpr_core.lcpr.config import ModelConfig
    from lcpr_core.pretrained import default_weights
    from lcpr_core.timing import cpu_model

    from .relocalize import random_move, scan_folder_steps

    p = argparse.ArgumentParser(prog="lcpr_fleet", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("folder", type=Path, nargs="?", default=None,
                   help="scan folder cut into one part per robot, played at once (default: the shared walk_loop)")
    p.add_argument("--robots", type=int, default=2, help="robots: the folder cut by time into this many parts")
    p.add_argument("--delay", type=float, default=0.0, help="s each robot after the first starts late (default 0)")
    p.add_argument("--odometry", choices=("fast-lio2", "reference"), default="fast-lio2")
    p.add_argument("--move-seed", type=int, default=0, help="seed of the other robots' odometry frame moves")
    p.add_argument("--out", type=Path, default=Path("out/fleet"))
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    args = p.parse_args(argv)
    if not 2 <= args.robots <= 16:
        raise SystemExit(f"lcpr_fleet: --robots {args.robots}; expected 2 to 16")
    folder = args.folder if args.folder is not None else shared_path("data", "livox_hku", "walk_loop")
    weights = default_weights()
    if weights is None:
        raise SystemExit("lcpr_fleet: the bundled weights are not installed")
    steps = scan_folder_steps(folder, odometry=args.odometry)
    t = np.array([s.stamp for s in steps])
    cuts = np.searchsorted(t, t[0] + np.linspace(0.0, 1.0, args.robots + 1)[1:-1] * (t[-1] - t[0]))
    parts = np.split(np.arange(len(steps)), cuts)
    robots = []
    for k, idx in enumerate(parts):
        part = [steps[i] for i in idx]
        if k:  # each part's odometry restarted at its own first reference pose, then moved
            start = part[0].reference @ invert(part[0].odometry)
            part = [dataclasses.replace(s, odometry=start @ s.odometry) for s in part]
        robots.append(Robot(f"robot{k + 1}", part, delay_s=args.delay * k,
                            move=np.eye(4) if k == 0 else random_move(args.move_seed + k)))
    detector = DetectorConfig(model=ModelConfig(weights=weights, threads=args.threads))
    print(f"CPU: {cpu_model()}; {folder.name} as {args.robots} robots of {[len(x) for x in parts]} frames, "
          f"each after the first {args.delay:g} s later than the one before")
    tic = time.perf_counter()
    result = fleet_replay(robots, detector=detector, progress=not args.quiet)
    took = time.perf_counter() - tic
    span = max(r.delay_s + r.steps[-1].stamp - r.steps[0].stamp for r in robots)
    print(result.text())
    print(f"replayed {span:.0f} s of the robots' time in {took:.0f} s ({span / took:.2f} x real time)")
    args.out.mkdir(parents=True, exist_ok=True)
    write_bytes_atomic(args.out / "fleet.json", json.dumps({**result.to_dict(), "replay_s": took,
                                                            "span_s": span, "cpu": cpu_model()}, indent=2).encode())
    return 0
