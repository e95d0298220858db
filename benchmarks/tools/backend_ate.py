"""What the online back end buys a real LiDAR odometry: ATE of KISS-ICP before and after the verified loops.

    python benchmarks/tools/backend_ate.py [--seed 7] [--frames 1000] [--spacing 1.0] [--every 5] [--inject 20]
                                           [--level-sigma 3]

1. a held-out synthetic city drive (citysim, grid route, city seed 7: the demo's test city, which the
   bundled weights never saw; seed 9 is the other test city, seed 3 the validation city), its LiDAR
   rendered every ``--spacing`` m (1 m: 10 Hz at 10 m/s; KISS-ICP loses track of this 32-beam rig at
   2.5 m steps);
2. KISS-ICP (lcpr_core.backend.lidar_odometry, via lcpr_offline.drive_odometry) over those clouds: the odometry,
   with its real registration drift;
3. the detector (bundled weights, ``BUNDLED_MAX_DISTANCE``, LiDAR verification on) on every ``--every``-th
   frame (5 m apart, cameras rendered at 640 x 360) with the odometry as its poses;
4. the back end (lcpr_core.backend) fed online, in the order a robot would see them
   (lcpr_core.backend.replay): each odometry message, and after each keyframe its verified candidates as
   loops;
5. ATE RMSE (no alignment, both starting at the true first pose; split into horizontal and vertical, and
   SE(3)-aligned beside) of the odometry and of the corrected trajectory against the ground truth, and a
   top view (posegraph.plot_trajectories).

The detector also measures each keyframe's up from its walls (lcpr_core.up) and the back end holds the map's
roll and pitch with it (the default; ``--up-sigma 0``: loops only; ``--up-sigma DEG``: its std dev); the run
then also prints what the ups do without a single loop.

``--level-sigma DEG`` gives the back end its level prior (``BackendConfig.level_sigma_deg``: a ground
vehicle's roll and pitch are level on average), which removes the height error of KISS-ICP's pitch bias
that loops cannot observe (2 deg: chosen on validation city seed 3 by benchmarks/studies/backend_vertical.py);
the run then also prints the prior alone, without loops.

``--inject N`` replays the same stream a second time with N random false loops added at random
keyframes (two keyframes more than 20 m apart claimed to be one place: identity match_T_query with a
confident covariance, 5 cm / 0.5 deg), and prints how many the consistency check rejected, how many the
robust kernel down-weighted, and the ATE.
The odometry and the detector's loops are cached in ``--out`` (same seed, frames, spacing and every: reused).
A loop the back end refuses (BackendError: a stamp it cannot attach) is counted, as the node counts it.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from lcpr_common.cli import tool_main

if TYPE_CHECKING:  # the package (and torch with it) is imported after the arguments are read
    from lcpr_core.backend.replay import LoopStream


def record(args: argparse.Namespace) -> LoopStream:
    """Render the drive, run KISS-ICP and the detector (lcpr_offline.drive_odometry); what they produced."""
    from citysim import SynthConfig, SyntheticDrive
    from lcpr_core.detector import DetectorConfig, LoopDetector, MatchConfig
    from lcpr_core.keyframes import KeyframeConfig
    from lcpr_core.lcpr.config import ModelConfig
    from lcpr_core.pretrained import BUNDLED_MAX_DISTANCE, default_weights
    from lcpr_offline.drive_odometry import record_drive

    weights = default_weights()
    if weights is None:
        raise SystemExit("backend_ate: the bundled weights are not installed (weights/lcpr_synth_narrow.pth)")
    drive = SyntheticDrive(SynthConfig(rig="nuscenes", frames=args.frames, seed=args.seed,
                                       keyframe_spacing=args.spacing, image_size=(640, 360)))
    detector = LoopDetector(DetectorConfig(
        model=ModelConfig(weights=weights, threads=args.threads),
        keyframe=KeyframeConfig(min_interval=0.0),  # every frame handed over is a keyframe (chosen here)
        match=MatchConfig(max_distance=BUNDLED_MAX_DISTANCE)))
    return record_drive(drive, every=args.every, detector=detector, threads=args.threads)


@tool_main
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
    p.add_argument("--up-sigma", type=float, default=None,
                   help="deg: std dev of the up measured from each keyframe's walls (BackendConfig.up_sigma_deg; "
                        "default: the back end's; 0 = off)")
    p.add_argument("--out", type=Path, default=Path("out/backend_ate"))
    args = p.parse_args(argv)

    from lcpr_core.atomic import write_bytes_atomic
    from lcpr_core.backend import BackendConfig, config_dict
    from lcpr_core.backend.replay import LoopStream, loop_pairs, replay, trajectory_error
    from lcpr_core.posegraph import plot_trajectories
    from lcpr_core.timing import cpu_model

    args.out.mkdir(parents=True, exist_ok=True)
    cache = args.out / f"stream_seed{args.seed}_{args.frames}f_{args.spacing:g}m_every{args.every}.npz"
    print(f"CPU: {cpu_model()}, {os.cpu_count()} cores, load average {os.getloadavg()[0]:.2f}")
    if cache.exists():
        stream = LoopStream.load(cache)
        print(f"reusing {cache}")
    else:
        stream = record(args)
        stream.save(cache)
    times = ", ".join(f"{k} {v:.0f} s" for k, v in stream.seconds.items())
    print(f"drive: seed {args.seed}, {len(stream.stamps)} LiDAR frames {args.spacing:g} m apart "
          f"({stream.length_m:.0f} m), {len(stream.keyframes)} detector keyframes; {times}")
    positions = stream.truth[:, :3, 3]
    wrong = np.linalg.norm(positions[stream.loops[:, 0]] - positions[stream.loops[:, 1]], axis=1) > 9.0
    print(f"detector: {len(stream.loops)} verified candidates ({int(wrong.sum())} farther than 9 m apart)")

    before = trajectory_error(stream.odometry, stream.truth)
    config = BackendConfig(level_sigma_deg=args.level_sigma)
    if args.up_sigma is not None:
        config = dataclasses.replace(config, up_sigma_deg=args.up_sigma)
    measured = int(np.isfinite(stream.ups).all(axis=1).sum()) if config.up_sigma_deg > 0 else 0
    priors = ([f"the walls' up at {measured} keyframes ({config.up_sigma_deg:g} deg)"] if measured else []) + (
        [f"a level prior of {args.level_sigma:g} deg"] if args.level_sigma else [])
    level = "loops and " + " and ".join(priors) if priors else "loops only"
    print(f"back end: {level}")
    clean = replay(stream, inject=0, seed=args.inject_seed, config=config)
    after = trajectory_error(clean.trajectory, stream.truth)
    cost = (f"; add_loop p50 {np.percentile(clean.loop_ms, 50):.1f} ms, p95 {np.percentile(clean.loop_ms, 95):.1f} ms"
            if clean.loop_ms else "")
    print(f"ATE RMSE: KISS-ICP odometry {before.text()}\n       -> with the back end {after.text()} "
          f"({after.rmse / before.rmse:.0%} of before)")
    print(f"loops: {int(clean.accepted.sum())} accepted, {int((~clean.accepted).sum()) - len(clean.refused)} "
          f"rejected and {len(clean.refused)} refused (of those not accepted, "
          f"{int((~clean.accepted & wrong).sum())} join keyframes farther than 9 m apart){cost}")
    summary: dict[str, object] = {"seed": args.seed, "frames": len(stream.stamps), "length_m": stream.length_m,
                                  "cpu": cpu_model(), "backend": config_dict(config),
                                  "ate_odometry": before.rmse, "ate_backend": after.rmse,
                                  "odometry_error": before.to_dict(), "backend_error": after.to_dict(),
                                  "loops": len(stream.loops), "accepted": int(clean.accepted.sum())}
    tag = (f"seed{args.seed}" + (f"_level{args.level_sigma:g}" if args.level_sigma else "")
           + ("" if measured else "_noup"))
    png = args.out / f"backend_ate_{tag}.png"
    plot_trajectories(stream.truth, stream.odometry, clean.trajectory, png, loops=loop_pairs(stream, clean),
                      title=f"KISS-ICP + lcpr_backend ({level}), city seed {args.seed}")
    print(f"plot: {png}")
    if priors:  # what the priors do without a single loop
        alone = trajectory_error(replay(stream.without_loops(), config=config).trajectory, stream.truth)
        print(f"{' and '.join(priors)} alone (no loops): ATE {alone.text()} ({alone.rmse / before.rmse:.0%} of "
              f"before); the loops take it to {after.rmse / alone.rmse:.0%} of that")
        summary.update(ate_priors_alone=alone.rmse)
    if args.inject:
        dirty = replay(stream, inject=args.inject, seed=args.inject_seed, config=config)
        ate = trajectory_error(dirty.trajectory, stream.truth).rmse
        print(f"with {dirty.injected} injected false loops: {dirty.injected_rejected} rejected, "
              f"{dirty.injected_down_weighted} down-weighted, ATE {ate:.2f} m ({ate / after.rmse - 1:+.0%} against "
              "the clean run)")
        summary.update(injected=dirty.injected, injected_rejected=dirty.injected_rejected,
                       injected_down_weighted=dirty.injected_down_weighted, ate_injected=ate)
        plot_trajectories(stream.truth, stream.odometry, dirty.trajectory,
                          args.out / f"backend_ate_{tag}_inject{args.inject}.png",
                          title=f"KISS-ICP + lcpr_backend, {dirty.injected} false loops injected")
    write_bytes_atomic(args.out / f"backend_ate_{tag}.json", json.dumps(summary, indent=2).encode())
    return 0


if __name__ == "__main__":
    sys.exit(main())
