"""What the online back end buys a real LiDAR odometry: ATE of KISS-ICP before and after the verified loops.

    python benchmarks/tools/backend_ate.py [--seed 7] [--frames 1000] [--spacing 1.0] [--every 5] [--inject 20]
                                           [--level-sigma 3]

1. a held-out synthetic city drive (citysim, grid route, city seed 7: the demo's test city, which the
   bundled weights never saw), its LiDAR rendered every ``--spacing`` m (1 m: 10 Hz at 10 m/s; KISS-ICP
   loses track of this 32-beam rig at 2.5 m steps);
2. KISS-ICP (lcpr_core.lidar_odometry) over those clouds: the odometry, with its real registration drift;
3. the detector (bundled weights, ``BUNDLED_MAX_DISTANCE``, LiDAR verification on) on every ``--every``-th
   frame (5 m apart, cameras rendered at 640 x 360) with the odometry as its poses;
4. the back end (lcpr_core.backend) fed online, in the order a robot would see them: each odometry
   message, and after each keyframe its verified candidates as loops;
5. ATE RMSE (posegraph.ate_rmse, no alignment, both starting at the true first pose) of the odometry and
   of the corrected trajectory against the ground truth, and a top view (posegraph.plot_trajectories).

``--level-sigma DEG`` gives the back end its level prior (``BackendConfig.level_sigma_deg``: a ground
vehicle's roll and pitch are level on average), which removes the early roll/pitch tilt of KISS-ICP that
loops cannot observe; the run then also prints the prior alone, without loops.

``--inject N`` replays the same stream a second time with N random false loops added at random
keyframes (two keyframes more than 20 m apart claimed to be one place: identity match_T_query with a
confident covariance, 5 cm / 0.5 deg), and prints how many the consistency check rejected and the ATE.
The odometry and the detector's loops are cached in ``--out`` (same seed, frames, spacing and every: reused).
A loop the back end refuses (BackendError: a stamp it cannot attach) is counted, as the node counts it.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from lcpr_core.backend import BackendConfig

FALSE_LOOP_COV = np.diag([0.05**2] * 3 + [math.radians(0.5) ** 2] * 3)  # "confident": as a good ICP claims
FALSE_MIN_M = 20.0  # an injected loop joins keyframes at least this far apart: truly wrong
MIN_GAP_S = 30.0  # and this much older (as the detector's exclusion)


@dataclass
class Stream:
    """What the robot saw, in order: odometry per frame and, per detector keyframe, its verified loops."""

    stamps: np.ndarray  # (N,) frame stamps
    truth: np.ndarray  # (N, 4, 4) world_T_base
    odometry: np.ndarray  # (N, 4, 4) KISS-ICP world_T_base
    keyframes: np.ndarray  # (K,) frame indices that went to the detector
    loops: np.ndarray  # (L, 2) frame indices (query, match) of verified candidates
    loop_T: np.ndarray  # (L, 4, 4) match_T_query (LiDAR frames)
    loop_cov: np.ndarray  # (L, 6, 6)
    base_T_lidar: np.ndarray  # (4, 4)
    seconds: dict[str, float]

    def save(self, path: Path) -> None:
        from lcpr_core.atomic import atomic_path

        with atomic_path(path) as tmp, open(tmp, "wb") as fh:
            np.savez(fh, stamps=self.stamps, truth=self.truth, odometry=self.odometry, keyframes=self.keyframes,
                     loops=self.loops, loop_T=self.loop_T, loop_cov=self.loop_cov, base_T_lidar=self.base_T_lidar,
                     seconds=np.array(json.dumps(self.seconds)))

    @classmethod
    def load(cls, path: Path) -> Stream:
        with np.load(path, allow_pickle=False) as z:
            return cls(**{k: z[k] for k in ("stamps", "truth", "odometry", "keyframes", "loops", "loop_T",
                                             "loop_cov", "base_T_lidar")}, seconds=json.loads(str(z["seconds"])))


def record(args: argparse.Namespace) -> Stream:
    """Render the drive, run KISS-ICP and the detector; the stream of what they produced."""
    from citysim import SynthConfig, SyntheticDrive
    from citysim.hashing import rng_for
    from citysim.lidar import render_lidar
    from lcpr_common.progress import progress_iter
    from lcpr_core.detector import DetectorConfig, Frame, LoopDetector
    from lcpr_core.keyframes import KeyframeConfig
    from lcpr_core.lcpr.config import ModelConfig
    from lcpr_core.lcpr.detector import MatchConfig
    from lcpr_core.lidar_odometry import KissConfig, KissOdometry
    from lcpr_core.pretrained import BUNDLED_MAX_DISTANCE, default_weights

    weights = default_weights()
    if weights is None:
        raise SystemExit("backend_ate: the bundled weights are not installed (weights/lcpr_synth_narrow.pth)")
    drive = SyntheticDrive(SynthConfig(rig="nuscenes", frames=args.frames, seed=args.seed,
                                       keyframe_spacing=args.spacing, image_size=(640, 360)))
    rig = drive.rig
    ext = np.asarray(rig.lidar.base_T_lidar, np.float64)
    truth = np.stack([drive.pose(i) for i in range(len(drive))])
    stamps = np.asarray(drive.keyframes.stamps, np.float64)
    odometry = KissOdometry(KissConfig(threads=args.threads), base_T_lidar=ext, world_T_base0=truth[0])
    detector = LoopDetector(DetectorConfig(
        model=ModelConfig(weights=weights, threads=args.threads),
        keyframe=KeyframeConfig(min_interval=0.0),  # every frame handed over is a keyframe (chosen here)
        match=MatchConfig(max_distance=BUNDLED_MAX_DISTANCE)))
    seconds = {"render": 0.0, "kiss_icp": 0.0, "detector": 0.0}
    poses, keyframes, loops, loop_T, loop_cov = [], [], [], [], []
    index_of = {float(t): i for i, t in enumerate(stamps)}
    for i in progress_iter(range(len(drive)), total=len(drive), desc="drive", unit="frame"):
        tic = time.perf_counter()
        if i % args.every == 0:
            frame = drive.frame(i)  # cameras too: a detector keyframe
            cloud = frame.cloud
        else:  # LiDAR only, exactly as SyntheticDrive.frame renders it
            x, y = (float(v) for v in drive.keyframes.xy[i])
            objects = drive.world.objects_near(x, y, rig.lidar.max_range + 5.0, stamp=float(stamps[i]))
            cloud = render_lidar(objects, drive.world.ground, rig.lidar, truth[i] @ ext, float(drive.keyframes.yaw[i]),
                                 rng_for(args.seed, 40, i), noise=drive.config.lidar_noise)
        xyz = np.stack([cloud["x"], cloud["y"], cloud["z"]], axis=1).astype(np.float64)
        seconds["render"] += time.perf_counter() - tic
        tic = time.perf_counter()
        pose = odometry.register(xyz, float(stamps[i]))
        poses.append(pose)
        seconds["kiss_icp"] += time.perf_counter() - tic
        if i % args.every:
            continue
        tic = time.perf_counter()
        images = [None if c is None else c.jpeg for c in frame.cameras]
        result = detector.process(Frame(stamp=float(stamps[i]), images=images, points=xyz, pose=pose))
        seconds["detector"] += time.perf_counter() - tic
        keyframes.append(i)
        for c in result.candidates:
            if c.verified and c.match_T_query is not None:
                loops.append((index_of[float(c.query_stamp)], index_of[float(c.match_stamp)]))
                loop_T.append(np.asarray(c.match_T_query, np.float64))
                cov = c.covariance
                loop_cov.append(np.full((6, 6), np.nan) if cov is None else np.asarray(cov, np.float64))
    return Stream(stamps=stamps, truth=truth, odometry=np.stack(poses), keyframes=np.array(keyframes, np.int64),
                  loops=np.array(loops, np.int64).reshape(-1, 2), loop_T=np.array(loop_T).reshape(-1, 4, 4),
                  loop_cov=np.array(loop_cov).reshape(-1, 6, 6), base_T_lidar=ext, seconds=seconds)


@dataclass
class Run:
    trajectory: np.ndarray  # (N, 4, 4) corrected
    accepted: np.ndarray  # (L,) bool per detector loop
    injected_rejected: int
    injected: int
    loop_ms: list[float]
    refused: int  # loops the back end refused as inputs (BackendError)


def replay(stream: Stream, *, inject: int, seed: int, config: BackendConfig | None = None) -> Run:
    """Feed the back end online: odometry per frame, after each keyframe its loops (and the injected ones).

    ``config``: the back end's (its ``base_T_lidar`` is the rig's); None = the defaults.
    """
    from lcpr_core.backend import BackendConfig, PoseGraphBackend
    from lcpr_core.errors import BackendError

    rng = np.random.default_rng(seed)
    by_query: dict[int, list[int]] = {}
    for k, (q, _) in enumerate(stream.loops):
        by_query.setdefault(int(q), []).append(k)
    false_at: dict[int, list[int]] = {}  # query frame -> match frames of injected loops
    positions = stream.truth[:, :3, 3]
    queries = [int(q) for q in stream.keyframes if stream.stamps[q] - stream.stamps[0] > MIN_GAP_S]
    while sum(len(v) for v in false_at.values()) < inject and queries:
        q = int(rng.choice(queries))
        older = [int(m) for m in stream.keyframes if stream.stamps[q] - stream.stamps[m] > MIN_GAP_S
                 and np.linalg.norm(positions[m] - positions[q]) > FALSE_MIN_M]
        if older:
            false_at.setdefault(q, []).append(int(rng.choice(older)))
    config = dataclasses.replace(config or BackendConfig(), base_T_lidar=stream.base_T_lidar)
    g = PoseGraphBackend(config)
    accepted = np.zeros(len(stream.loops), bool)
    rejected_false = refused = 0
    loop_ms: list[float] = []
    for i, (t, pose) in enumerate(zip(stream.stamps, stream.odometry, strict=True)):
        g.add_odometry(float(t), pose)
        events = [(True, k) for k in by_query.get(i, [])] + [(False, m) for m in false_at.get(i, [])]
        for e in rng.permutation(len(events)):  # the false loops come in among the true ones
            detected, k = events[int(e)]
            tic = time.perf_counter()
            try:
                if detected:
                    cov = stream.loop_cov[k]
                    accepted[k] = g.add_loop(float(t), float(stream.stamps[stream.loops[k, 1]]), stream.loop_T[k],
                                             cov if np.isfinite(cov).all() else None)
                else:
                    rejected_false += not g.add_loop(float(t), float(stream.stamps[k]), np.eye(4), FALSE_LOOP_COV)
            except BackendError as err:
                print(f"  refused: {err}")
                refused += 1
                rejected_false += not detected
            loop_ms.append((time.perf_counter() - tic) * 1e3)
    _, trajectory = g.trajectory()
    return Run(trajectory, accepted, rejected_false, sum(len(v) for v in false_at.values()), loop_ms, refused)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--seed", type=int, default=7, help="city and drive seed (7: a test city the weights never saw)")
    p.add_argument("--frames", type=int, default=1000, help="LiDAR frames of the drive")
    p.add_argument("--spacing", type=float, default=1.0, help="m between LiDAR frames")
    p.add_argument("--every", type=int, default=5, help="every n-th LiDAR frame goes to the detector")
    p.add_argument("--inject", type=int, default=0, help="random false loops added in a second replay")
    p.add_argument("--inject-seed", type=int, default=0)
    p.add_argument("--threads", type=int, default=1, help="KISS-ICP and torch threads")
    p.add_argument("--level-sigma", type=float, default=0.0,
                   help="deg: the back end's level prior (BackendConfig.level_sigma_deg; 0 = off, loops only)")
    p.add_argument("--out", type=Path, default=Path("out/backend_ate"))
    args = p.parse_args(argv)

    from lcpr_core.atomic import write_bytes_atomic
    from lcpr_core.backend import BackendConfig, config_dict
    from lcpr_core.posegraph import ate_rmse, plot_trajectories
    from lcpr_core.timing import cpu_model

    args.out.mkdir(parents=True, exist_ok=True)
    cache = args.out / f"stream_seed{args.seed}_{args.frames}f_{args.spacing:g}m_every{args.every}.npz"
    print(f"CPU: {cpu_model()}, {os.cpu_count()} cores, load average {os.getloadavg()[0]:.2f}")
    if cache.exists():
        stream = Stream.load(cache)
        print(f"reusing {cache}")
    else:
        stream = record(args)
        stream.save(cache)
    length = float(np.linalg.norm(np.diff(stream.truth[:, :3, 3], axis=0), axis=1).sum())
    times = ", ".join(f"{k} {v:.0f} s" for k, v in stream.seconds.items())
    print(f"drive: seed {args.seed}, {len(stream.stamps)} LiDAR frames {args.spacing:g} m apart ({length:.0f} m), "
          f"{len(stream.keyframes)} detector keyframes; {times}")
    positions = stream.truth[:, :3, 3]
    wrong = np.linalg.norm(positions[stream.loops[:, 0]] - positions[stream.loops[:, 1]], axis=1) > 9.0
    print(f"detector: {len(stream.loops)} verified candidates ({int(wrong.sum())} farther than 9 m apart)")

    before = ate_rmse(stream.odometry, stream.truth)
    config = BackendConfig(level_sigma_deg=args.level_sigma)
    level = f"loops and a level prior of {args.level_sigma:g} deg" if args.level_sigma else "loops only"
    print(f"back end: {level}")
    clean = replay(stream, inject=0, seed=args.inject_seed, config=config)
    after = ate_rmse(clean.trajectory, stream.truth)
    cost = (f"; add_loop p50 {np.percentile(clean.loop_ms, 50):.1f} ms, p95 {np.percentile(clean.loop_ms, 95):.1f} ms"
            if clean.loop_ms else "")
    print(f"ATE RMSE: KISS-ICP odometry {before:.2f} m {_split(stream.odometry, stream.truth)} -> with the back "
          f"end {after:.2f} m {_split(clean.trajectory, stream.truth)} ({after / before:.0%} of before)")
    print(f"loops: {int(clean.accepted.sum())} accepted, "
          f"{int((~clean.accepted).sum()) - clean.refused} rejected and {clean.refused} refused (of those not "
          f"accepted, {int((~clean.accepted & wrong).sum())} join keyframes farther than 9 m apart){cost}")
    summary: dict[str, object] = {"seed": args.seed, "frames": len(stream.stamps), "length_m": length,
                                  "backend": config_dict(config),
                                  "ate_odometry": before, "ate_backend": after,
                                  "loops": len(stream.loops), "accepted": int(clean.accepted.sum())}
    tag = f"seed{args.seed}" + (f"_level{args.level_sigma:g}" if args.level_sigma else "")
    png = args.out / f"backend_ate_{tag}.png"
    pairs = [(int(q), int(m)) for (q, m), ok in zip(stream.loops, clean.accepted, strict=True) if ok]
    plot_trajectories(stream.truth, stream.odometry, clean.trajectory, png, loops=pairs,
                      title=f"KISS-ICP + lcpr_backend ({level}), city seed {args.seed}")
    print(f"plot: {png}")
    if args.level_sigma:  # what the prior does without a single loop
        alone = replay(dataclasses.replace(stream, loops=stream.loops[:0], loop_T=stream.loop_T[:0],
                                           loop_cov=stream.loop_cov[:0]), inject=0, seed=0, config=config)
        ate = ate_rmse(alone.trajectory, stream.truth)
        print(f"the level prior alone (no loops): ATE {ate:.2f} m {_split(alone.trajectory, stream.truth)}; "
              f"the loops take it to {after / ate:.0%} of that")
        summary.update(ate_level_prior_alone=ate)
    if args.inject:
        dirty = replay(stream, inject=args.inject, seed=args.inject_seed, config=config)
        ate = ate_rmse(dirty.trajectory, stream.truth)
        print(f"with {dirty.injected} injected false loops: {dirty.injected_rejected} rejected, ATE {ate:.2f} m "
              f"({ate / after - 1:+.0%} against the clean run)")
        summary.update(injected=dirty.injected, injected_rejected=dirty.injected_rejected, ate_injected=ate)
        plot_trajectories(stream.truth, stream.odometry, dirty.trajectory,
                          args.out / f"backend_ate_{tag}_inject{args.inject}.png",
                          title=f"KISS-ICP + lcpr_backend, {dirty.injected} false loops injected")
    write_bytes_atomic(args.out / f"backend_ate_{tag}.json", json.dumps(summary, indent=2).encode())
    return 0


def _split(estimate: np.ndarray, truth: np.ndarray) -> str:
    """The horizontal and vertical parts of the ATE RMSE, as text."""
    err = estimate[:, :3, 3] - truth[:, :3, 3]
    return (f"(horizontal {np.sqrt((err[:, :2] ** 2).sum(axis=1).mean()):.2f} m, "
            f"vertical {np.sqrt((err[:, 2] ** 2).mean()):.2f} m)")


if __name__ == "__main__":
    sys.exit(main())
