"""The back end on real LiDAR: real odometry on the Livox sequences, LiDAR-only loops, ATE before and after.

    python benchmarks/tools/backend_ate_real.py [--odometry kiss-icp|fast-lio2] [--sets walk_loop campus]
                                                [--inject 5 20] [--kiss-max-range 100] [--out out/backend_ate_real]

For each scan folder of ``../shared/data/livox_hku`` (handheld Livox Avia, about 70 deg field of view):

1. the odometry, with its real drift, started at the first reference pose: ``kiss-icp`` (default) runs
   KISS-ICP (lcpr_core.backend.lidar_odometry; its default settings, or ``--kiss-max-range`` and
   ``--kiss-min-range``: KISS-ICP's voxels are max_range / 100) over the scans in order; ``fast-lio2``
   reads the folder's ``odom_poses.txt``, the LiDAR-inertial odometry (FAST-LIO2) the sequence was
   recorded with, before its own loop closing: the "LIO without loop closure" a user brings;
2. the detector in its LiDAR-only mode (bundled weights, every camera slot empty, the node's default
   keyframing, matching and verification: what ``lcpr_node lidar_only:=true`` runs) on every scan, with
   the KISS-ICP pose as the frame's pose;
3. the back end (lcpr_core.backend, default configuration: no level prior, a handheld sensor is not a
   ground vehicle; the walls' up of each keyframe, which a 70 deg Livox scan never measures, so
   ``--up-sigma`` changes nothing unless the detector's ``up.min_fov_deg`` does) fed online: each
   odometry pose, then the keyframe's verified candidates as loops (lcpr_core.backend.replay);
4. ATE RMSE of the odometry and of the corrected trajectory against ``optimized_poses.txt`` (the SLAM
   system's poses after its own loop closing: a reference good to a few cm, not surveyed truth), without
   alignment (both start at the first reference pose) and after a rigid SE(3) fit; a top view per set;
5. for each ``--inject N``: the same stream replayed with N random false loops (keyframes more than
   ``--false-min-m`` apart by the reference, default 10 m: walk_loop spans 15 m, and over 30 s apart,
   claimed to be one place with a 5 cm / 0.5 deg covariance), counted as rejected or down-weighted,
   and the ATE against the clean run.

Nothing here chooses a parameter of the back end or the detector: every setting is a default chosen
elsewhere (docs/backend.md). The odometry and the loops are cached in ``--out`` per set and KISS-ICP
setting (delete the .npz to record again). Loops are scored against the reference: a loop whose
relative pose is more than 0.3 m or 2 deg off the reference's is counted as wrong.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from lcpr_common.cli import tool_main

if TYPE_CHECKING:  # the package (and torch with it) is imported after the arguments are read
    from lcpr_core.backend.lidar_odometry import KissConfig
    from lcpr_core.backend.replay import LoopStream

SETS = ("walk_loop", "campus")
ODOMETRY = ("kiss-icp", "fast-lio2")
WRONG_M, WRONG_DEG = 0.3, 2.0  # a loop this far off the reference's relative pose is wrong (verify_real.py's rule)


def loop_errors(stream: LoopStream, *, against: str = "truth") -> tuple[np.ndarray, np.ndarray]:
    """(m, deg) error of each loop's match_T_query against the relative pose of the reference (``truth``) or of
    the odometry (``odometry``)."""
    from lcpr_core.geometry import rotation_angle_deg

    lidar = getattr(stream, against) @ stream.base_T_lidar
    ref = np.linalg.inv(lidar[stream.loops[:, 1]]) @ lidar[stream.loops[:, 0]]
    err = np.linalg.inv(ref) @ stream.loop_T
    return np.linalg.norm(err[:, :3, 3], axis=1), np.asarray(rotation_angle_deg(err[:, :3, :3])).reshape(-1)


def record(folder: Path, *, threads: int, kiss: KissConfig | None) -> LoopStream:
    """The odometry (KISS-ICP, or the folder's ``odom_poses.txt`` when ``kiss`` is None) and the LiDAR-only
    detector over one scan folder; the stream of what they produced."""
    from lcpr_common.progress import progress_iter
    from lcpr_core.backend.lidar_odometry import KissOdometry
    from lcpr_core.backend.replay import StreamRecorder
    from lcpr_core.detector import DetectorConfig, Frame, LoopDetector
    from lcpr_core.lcpr.config import ModelConfig
    from lcpr_core.pretrained import default_weights
    from msg_tools.convert.scan_folder import ScanFolder

    weights = default_weights()
    if weights is None:
        raise SystemExit("backend_ate_real: the bundled weights are not installed (weights/lcpr_synth_narrow.pth)")
    seq = ScanFolder(folder)  # optimized_poses.txt: the reference
    if kiss is not None:
        odometry = KissOdometry(kiss, world_T_base0=seq.poses[0])  # scans in the body frame
    else:  # the recorded LIO odometry, moved to start at the first reference pose
        lio = ScanFolder(folder, poses_file="odom_poses.txt").poses
        lio = seq.poses[0] @ np.linalg.inv(lio[0]) @ lio
    model = ModelConfig(weights=weights, threads=threads)
    detector = LoopDetector(DetectorConfig(model=model))
    empty = [None] * model.num_cameras  # LiDAR only: every camera slot empty
    recorder = StreamRecorder(base_T_lidar=np.eye(4))
    seconds = {"read": 0.0, "kiss_icp": 0.0, "detector": 0.0}
    for i in progress_iter(range(len(seq)), total=len(seq), desc=folder.name, unit="scan"):
        tic = time.perf_counter()
        xyz, stamp = seq.points(i), float(seq.stamps[i])
        seconds["read"] += time.perf_counter() - tic
        tic = time.perf_counter()
        pose = odometry.register(xyz, stamp) if kiss is not None else lio[i]
        recorder.add_frame(stamp, odometry=pose, truth=seq.poses[i])
        seconds["kiss_icp"] += time.perf_counter() - tic
        tic = time.perf_counter()
        recorder.add_result(detector.process(Frame(stamp=stamp, images=empty, points=xyz, pose=pose)))
        seconds["detector"] += time.perf_counter() - tic
    return recorder.stream(seconds=seconds)


@tool_main
def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", type=Path, default=None,
                   help="folder holding the sets (default: livox_hku under the shared data folder)")
    p.add_argument("--sets", nargs="+", choices=SETS, default=list(SETS), help="sequences to run")
    p.add_argument("--inject", type=int, nargs="*", default=[5, 20],
                   help="numbers of random false loops, one replay each (default 5 20)")
    p.add_argument("--inject-seed", type=int, default=0)
    p.add_argument("--false-min-m", type=float, default=10.0,
                   help="m (by the reference) between the keyframes a false loop joins (default 10)")
    p.add_argument("--odometry", choices=ODOMETRY, default=ODOMETRY[0],
                   help="kiss-icp: run KISS-ICP on the scans (default); fast-lio2: the folder's odom_poses.txt")
    p.add_argument("--gravity-sigma", type=float, default=0.0,
                   help="deg: the back end's gravity prior (BackendConfig.gravity_sigma_deg; 0 = off, the default; "
                        "0.5 is the documented setting for a LIO such as FAST-LIO2)")
    p.add_argument("--up-sigma", type=float, default=None,
                   help="deg: std dev of the up measured from each keyframe's walls (BackendConfig.up_sigma_deg; "
                        "default: the back end's; 0 = off)")
    p.add_argument("--kiss-max-range", type=float, default=None,
                   help="KISS-ICP's max_range in m (its voxels are a hundredth of it; default KissConfig's 100)")
    p.add_argument("--kiss-min-range", type=float, default=None,
                   help="KISS-ICP's min_range in m (default KissConfig's 2)")
    p.add_argument("--threads", type=int, default=1, help="KISS-ICP and torch threads")
    p.add_argument("--out", type=Path, default=Path("out/backend_ate_real"))
    args = p.parse_args(argv)

    from lcpr_common.shared_data import shared_path
    from lcpr_core.atomic import write_bytes_atomic
    from lcpr_core.backend import BackendConfig, config_dict
    from lcpr_core.backend.lidar_odometry import KissConfig
    from lcpr_core.backend.replay import LoopStream, loop_pairs, replay, trajectory_error
    from lcpr_core.posegraph import plot_trajectories
    from lcpr_core.timing import cpu_model

    data = args.data if args.data is not None else shared_path("data", "livox_hku")
    if not data.is_dir():
        raise SystemExit(f"backend_ate_real: {data} is not a folder; give --data .../livox_hku")
    args.out.mkdir(parents=True, exist_ok=True)
    cpu = cpu_model()
    print(f"CPU: {cpu}, {os.cpu_count()} cores, load average {os.getloadavg()[0]:.2f}")
    config = BackendConfig(gravity_sigma_deg=args.gravity_sigma)
    if args.up_sigma is not None:
        config = dataclasses.replace(config, up_sigma_deg=args.up_sigma)
    given = (("max_range", args.kiss_max_range), ("min_range", args.kiss_min_range))
    ranges = {k: v for k, v in given if v is not None}
    kiss = KissConfig(threads=args.threads, **ranges)
    kiss_icp = args.odometry == "kiss-icp"
    if kiss_icp:
        tag = f"kiss{kiss.max_range:g}m_{kiss.min_range:g}m"
        print(f"KISS-ICP: max_range {kiss.max_range:g} m, min_range {kiss.min_range:g} m, voxels "
              f"{kiss.voxel_size or kiss.max_range / 100:g} m; back end: defaults")
    else:
        tag = "fastlio2"
        print("odometry: the sequences' FAST-LIO2 odom_poses.txt; back end: defaults")
    if args.gravity_sigma > 0:
        print(f"back end: gravity prior {args.gravity_sigma:g} deg (the nodes' tilt held to the odometry's)")
    label = "KISS-ICP" if kiss_icp else "FAST-LIO2"
    tag_out = f"{tag}_gravity{args.gravity_sigma:g}" if args.gravity_sigma > 0 else tag  # outputs; the cache: tag
    if config.up_sigma_deg > 0:
        print(f"back end: the walls' up of each keyframe ({config.up_sigma_deg:g} deg)")
    else:
        tag_out += "_noup"
    rows = []
    for name in args.sets:
        cache = args.out / f"stream_{name}_{tag}.npz"
        if cache.exists():
            stream = LoopStream.load(cache)
            print(f"\n{name}: reusing {cache}")
        else:
            stream = record(data / name, threads=args.threads, kiss=kiss if kiss_icp else None)
            stream.save(cache)
        n = len(stream.stamps)
        times = ", ".join(f"{k} {v / n * 1e3:.0f} ms/scan" for k, v in stream.seconds.items())
        err_m, err_deg = loop_errors(stream)
        wrong = (err_m > WRONG_M) | (err_deg > WRONG_DEG)
        print(f"{name}: {n} scans ({stream.length_m:.0f} m), {len(stream.keyframes)} detector keyframes; {times} "
              "(means)")
        print(f"  detector: {len(stream.loops)} verified candidates, {int(wrong.sum())} wrong (> {WRONG_M} m or "
              f"{WRONG_DEG:g} deg off the reference); median error "
              f"{np.median(err_m) if len(err_m) else math.nan:.3f} m; against the odometry's relative pose "
              f"{np.median(loop_errors(stream, against='odometry')[0]) if len(err_m) else math.nan:.3f} m")
        before = trajectory_error(stream.odometry, stream.truth)
        clean = replay(stream, config=config)
        after = trajectory_error(clean.trajectory, stream.truth)
        ms = np.array(clean.loop_ms)
        print(f"  ATE {label} odometry {before.text()}\n  ATE with the back end {after.text()} "
              f"({after.rmse / before.rmse:.0%} of before; aligned {after.aligned / before.aligned:.0%})")
        ups = int(np.isfinite(stream.ups).all(axis=1).sum())
        loops_only = None
        if config.up_sigma_deg > 0 and ups:  # with no up measured the run above is the loops-only one
            loops_only = trajectory_error(replay(stream.without_ups(), config=config).trajectory, stream.truth)
            print(f"  the walls' up measured at {ups} of {len(stream.keyframes)} keyframes; without it (loops "
                  f"only): ATE {loops_only.text()} ({loops_only.rmse / before.rmse:.0%} of before)")
        elif config.up_sigma_deg > 0:
            print(f"  the walls' up measured at none of {len(stream.keyframes)} keyframes: loops only")
        print(f"  loops: {int(clean.accepted.sum())} accepted ({int((clean.accepted & wrong).sum())} wrong), "
              f"{int((~clean.accepted).sum()) - len(clean.refused)} rejected ({int((~clean.accepted & wrong).sum())} "
              f"wrong), {len(clean.refused)} refused"
              + (f"; add_loop p50 {np.median(ms):.1f} ms, p95 {np.percentile(ms, 95):.1f} ms" if len(ms) else ""))
        png = args.out / f"backend_ate_real_{name}_{tag_out}.png"
        plot_trajectories(stream.truth, stream.odometry, clean.trajectory, png, loops=loop_pairs(stream, clean),
                          title=f"{name}: {label} + LiDAR-only loops + back end ({tag_out})")
        row: dict[str, object] = {"set": name, "scans": n, "length_m": stream.length_m, "loops": len(stream.loops),
                                  "wrong_loops": int(wrong.sum()), "accepted": int(clean.accepted.sum()),
                                  "accepted_wrong": int((clean.accepted & wrong).sum()), "odometry": before.to_dict(),
                                  "backend": after.to_dict(), "ups": ups,
                                  "loops_only": None if loops_only is None else loops_only.to_dict(),
                                  "add_loop_ms_p50": float(np.median(ms)) if len(ms)
                                  else None, "seconds": stream.seconds, "injected": []}
        for count in args.inject:
            dirty = replay(stream, inject=count, seed=args.inject_seed, config=config, false_min_m=args.false_min_m)
            ate = trajectory_error(dirty.trajectory, stream.truth)
            weights = ", ".join(f"{w:.3f}" for w in dirty.injected_weights)
            print(f"  {dirty.injected} false loops injected: {dirty.injected_rejected} rejected, "
                  f"{dirty.injected_down_weighted} accepted and down-weighted"
                  + (f" (final weights {weights})" if weights else "")
                  + f"; ATE {ate.rmse:.2f} m ({ate.rmse / after.rmse - 1:+.1%} against the clean run)")
            row["injected"].append({"count": dirty.injected, "rejected": dirty.injected_rejected,  # type: ignore[attr-defined]
                                    "down_weighted": dirty.injected_down_weighted,
                                    "weights": dirty.injected_weights, "ate": ate.to_dict()})
        rows.append(row)
    summary = {"cpu": cpu, "odometry": args.odometry, "gravity_sigma_deg": args.gravity_sigma,
               "kiss_icp": {"max_range": kiss.max_range, "min_range": kiss.min_range} if kiss_icp else None,
               "backend": config_dict(config), "false_min_m": args.false_min_m, "sets": rows}
    write_bytes_atomic(args.out / f"backend_ate_real_{tag_out}.json", json.dumps(summary, indent=2).encode())
    print(f"\nwritten: {args.out}/backend_ate_real_{tag_out}.json and backend_ate_real_*_{tag_out}.png")
    return 0


if __name__ == "__main__":
    sys.exit(main())
