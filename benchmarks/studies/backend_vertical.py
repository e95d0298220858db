"""Why loops leave most of KISS-ICP's error on the synthetic cities, and the level prior chosen on validation.

    python benchmarks/studies/backend_vertical.py [--validation 3] [--test 7 9] [--streams out/backend_ate]

Reads the streams ``benchmarks/tools/backend_ate.py --seed S`` cached (KISS-ICP odometry of a 1,000 m
drive, the detector's verified loops; record them first) and asks, per city:

1. where the error is: ATE 3-D, horizontal and vertical of the odometry and of the back end (loops only);
2. whether the loops are the limit: the same back end with *oracle* loops, one per pair of keyframes
   within 9 m and over 30 s apart at the TRUE relative pose (2 cm / 0.2 deg), what a perfect detector
   would give;
3. whether iSAM2 stopped short: the final graph of the loops-only run (its saved factors) solved again
   in one batch with Levenberg-Marquardt from the odometry;
4. whether the odometry noise model is wrong: KISS-ICP's error per frame step (1 m) on each axis
   against the model's standard deviation, and its mean (a bias a random walk does not model);
5. whether the loops are in the wrong frame: their pose error against the truth, as measured (LiDAR
   frames) and as the graph takes them (base frames);
6. the level prior's ``level_sigma_deg``: swept on the ``--validation`` cities only, the one with the
   lowest mean ATE is then reported on the ``--test`` cities (held out: nothing is chosen on them).

Writes ``OUT/backend_vertical.json`` and ``OUT/backend_vertical_seed{S}.png`` (height error and tilt along
the drive) per test city. Conclusions: docs/backend.md (Why loops alone leave the height error).
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
import tempfile
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from lcpr_core.backend.replay import LoopStream

SIGMAS_DEG = (0.5, 1.0, 2.0, 3.0, 5.0, 10.0)
ORACLE_COV = np.diag([0.02**2] * 3 + [math.radians(0.2) ** 2] * 3)  # the verifier's smallest


def oracle(stream: LoopStream) -> LoopStream:
    """The stream with a TRUE loop for every keyframe pair within 9 m and more than 30 s apart."""
    from lcpr_core.revisits import revisit_pairs

    kf = stream.keyframes
    pairs = revisit_pairs(stream.truth[kf, :3, 3], stream.stamps[kf], radius=9.0, min_time_gap=30.0)
    loops = kf[pairs]
    lidar = stream.truth @ stream.base_T_lidar
    rel = np.linalg.inv(lidar[loops[:, 1]]) @ lidar[loops[:, 0]]
    return dataclasses.replace(stream, loops=loops, loop_T=rel, loop_cov=np.repeat(ORACLE_COV[None], len(loops), 0))


def batch_solution(saved: Path) -> tuple[np.ndarray, np.ndarray]:
    """(node rows, node poses) of a saved back-end graph solved in one batch (Levenberg-Marquardt from the odometry)."""
    import gtsam

    from lcpr_core.backend import LoopPolicy
    from lcpr_core.posegraph import to_gtsam_covariance

    z = np.load(saved, allow_pickle=False)
    odom, idx = z["odometry"], z["node_index"]
    nodes = odom[idx]
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    graph.add(gtsam.PriorFactorPose3(0, gtsam.Pose3(nodes[0]), gtsam.noiseModel.Isotropic.Sigma(6, 1e-3)))
    for k, pose in enumerate(nodes):
        values.insert(k, gtsam.Pose3(pose))
    for k, cov in enumerate(z["step_covariance"]):
        step = np.linalg.inv(nodes[k]) @ nodes[k + 1]
        noise = gtsam.noiseModel.Gaussian.Covariance(to_gtsam_covariance(cov, step[:3, :3]))
        graph.add(gtsam.BetweenFactorPose3(k, k + 1, gtsam.Pose3(step), noise))
    huber = gtsam.noiseModel.mEstimator.Huber.Create(LoopPolicy().robust_param)
    for (parent, child), measured, cov in zip(z["loop_nodes"], z["loop_measured"], z["loop_covariance"], strict=True):
        noise = gtsam.noiseModel.Gaussian.Covariance(to_gtsam_covariance(cov, measured[:3, :3]))
        graph.add(gtsam.BetweenFactorPose3(int(parent), int(child), gtsam.Pose3(measured),
                                           gtsam.noiseModel.Robust.Create(huber, noise)))
    result = gtsam.LevenbergMarquardtOptimizer(graph, values).optimize()
    return idx, np.stack([result.atPose3(k).matrix() for k in range(len(nodes))])


def step_errors(stream: LoopStream) -> dict[str, Any]:
    """KISS-ICP's error per frame step (1 m; its body frame) per axis: std dev and mean, beside the model's."""
    from lcpr_core.backend import OdometryNoise

    errs = []
    for a in range(len(stream.stamps) - 1):
        b = a + 1
        est = np.linalg.inv(stream.odometry[a]) @ stream.odometry[b]
        ref = np.linalg.inv(stream.truth[a]) @ stream.truth[b]
        e = np.linalg.inv(ref) @ est
        r = e[:3, :3]
        roll, pitch, yaw = math.atan2(r[2, 1], r[2, 2]), -math.asin(max(-1.0, min(1.0, r[2, 0]))), math.atan2(r[1, 0],
                                                                                                             r[0, 0])
        errs.append([*e[:3, 3], *np.degrees([roll, pitch, yaw])])
    arr = np.asarray(errs)
    lengths = np.linalg.norm(np.diff(stream.truth[:, :3, 3], axis=0), axis=1)
    straight = np.eye(4)
    straight[0, 3] = float(np.median(lengths))  # the model on a straight step of the median length
    model = OdometryNoise().covariance(straight)
    sd = np.sqrt(np.diag(model))
    sd[3:] = np.degrees(sd[3:])
    names = ("x", "y", "z", "roll", "pitch", "yaw")
    return {"steps": len(arr), "step_m": float(np.median(lengths)), "units": "m for x, y, z; deg for roll, pitch, yaw",
            "kiss_sd": dict(zip(names, arr.std(axis=0).round(4).tolist(), strict=True)),
            "kiss_mean": dict(zip(names, arr.mean(axis=0).round(4).tolist(), strict=True)),
            "model_sd": dict(zip(names, sd.round(4).tolist(), strict=True))}


def loop_errors(stream: LoopStream) -> dict[str, float]:
    """Median pose error (m, deg) of the detected loops against the truth, in LiDAR frames and in base frames."""
    from lcpr_core.geometry import rotation_angle_deg
    from lcpr_core.posegraph import lidar_to_body

    if not len(stream.loops):
        return {}
    q, m = stream.loops[:, 0], stream.loops[:, 1]
    lidar = stream.truth @ stream.base_T_lidar
    out: dict[str, float] = {}
    for name, truth, meas in (
            ("lidar", np.linalg.inv(lidar[m]) @ lidar[q], stream.loop_T),
            ("base", np.linalg.inv(stream.truth[m]) @ stream.truth[q],
             np.stack([lidar_to_body(t, stream.base_T_lidar) for t in stream.loop_T]))):
        e = np.linalg.inv(truth) @ meas
        out[f"{name}_m"] = float(np.median(np.linalg.norm(e[:, :3, 3], axis=1)))
        out[f"{name}_deg"] = float(np.median(rotation_angle_deg(e[:, :3, :3])))
    return out


def tilt_deg(poses: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """Angle (deg) between each pose's up axis and the true one's."""
    return np.degrees(np.arccos(np.clip((poses[:, :3, 2] * truth[:, :3, 2]).sum(axis=1), -1.0, 1.0)))


def plot(stream: LoopStream, runs: dict[str, np.ndarray], path: Path, title: str) -> None:
    """Height error and tilt along the drive, per trajectory; the detected loops' ends marked. PNG."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    from lcpr_core.atomic import save_figure

    dist = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(stream.truth[:, :3, 3], axis=0), axis=1))]
    fig = Figure(figsize=(9, 6), dpi=100)
    FigureCanvasAgg(fig)
    ax_z, ax_t = fig.add_subplot(2, 1, 1), fig.add_subplot(2, 1, 2, sharex=None)
    for name, traj in runs.items():
        ax_z.plot(dist, traj[:, 2, 3] - stream.truth[:, 2, 3], lw=1.2, label=name)
        ax_t.plot(dist, tilt_deg(traj, stream.truth), lw=1.2, label=name)
    for q, m in stream.loops:
        ax_z.axvspan(dist[m] - 0.5, dist[m] + 0.5, color="tab:green", alpha=0.15, lw=0)
        ax_z.axvspan(dist[q] - 0.5, dist[q] + 0.5, color="tab:green", alpha=0.15, lw=0)
    ax_z.set(ylabel="height error [m]", title=title)
    ax_t.set(xlabel="distance driven [m] (green: ends of detected loops)", ylabel="tilt error [deg]")
    for ax in (ax_z, ax_t):
        ax.grid(alpha=0.3)
    ax_z.legend(fontsize=8, loc="best")
    save_figure(fig, path)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--validation", type=int, nargs="*", default=[3], help="cities that choose level_sigma_deg")
    p.add_argument("--level-sigma", type=float, default=None,
                   help="deg: skip the sweep and use this level prior (no validation city needed)")
    p.add_argument("--test", type=int, nargs="+", default=[7, 9], help="held-out cities, reported only")
    p.add_argument("--streams", type=Path, default=Path("out/backend_ate"), help="backend_ate.py's --out")
    p.add_argument("--out", type=Path, default=Path("out/backend_vertical"))
    args = p.parse_args(argv)

    from lcpr_core.atomic import write_bytes_atomic
    from lcpr_core.backend import BackendConfig, PoseGraphBackend
    from lcpr_core.backend.replay import LoopStream, replay, trajectory_error
    from lcpr_core.timing import cpu_model

    args.out.mkdir(parents=True, exist_ok=True)
    streams: dict[int, LoopStream] = {}
    for seed in (*args.validation, *args.test):
        path = args.streams / f"stream_seed{seed}_1000f_1m_every5.npz"
        if not path.exists():
            raise SystemExit(f"{path} is missing: run python benchmarks/tools/backend_ate.py --seed {seed} first")
        streams[seed] = LoopStream.load(path)
    print(f"CPU: {cpu_model()}")
    report: dict[str, Any] = {"cpu": cpu_model(), "validation": args.validation, "test": args.test, "cities": {}}

    sweep: dict[float, list[float]] = {s: [] for s in SIGMAS_DEG}
    if args.level_sigma is None and not args.validation:
        raise SystemExit("backend_vertical: give --validation cities to choose the level prior, or --level-sigma")
    for seed in args.validation if args.level_sigma is None else ():
        for sigma in SIGMAS_DEG:
            run = replay(streams[seed], config=BackendConfig(level_sigma_deg=sigma))
            sweep[sigma].append(trajectory_error(run.trajectory, streams[seed].truth).rmse)
        print(f"validation seed {seed}: level prior sweep (loops on) "
              + ", ".join(f"{s:g} deg {sweep[s][-1]:.2f} m" for s in SIGMAS_DEG))
    if args.level_sigma is None:
        chosen = min(SIGMAS_DEG, key=lambda s: float(np.mean(sweep[s])))
        print(f"chosen on validation seeds {args.validation}: level_sigma_deg = {chosen:g}")
    else:
        chosen = args.level_sigma
        print(f"level_sigma_deg = {chosen:g} as given (not chosen here)")
    report["level_sweep"] = {f"{s:g}": v for s, v in sweep.items()}
    report["level_sigma_chosen"] = chosen

    for seed, stream in streams.items():
        role = "validation" if seed in args.validation else "test"
        kiss = trajectory_error(stream.odometry, stream.truth)
        loops_run = replay(stream)
        loops = trajectory_error(loops_run.trajectory, stream.truth)
        perfect = oracle(stream)
        oracle_run = replay(perfect)
        best = trajectory_error(oracle_run.trajectory, stream.truth)
        level_run = replay(stream, config=BackendConfig(level_sigma_deg=chosen))
        level = trajectory_error(level_run.trajectory, stream.truth)
        alone_run = replay(stream.without_loops(), config=BackendConfig(level_sigma_deg=chosen))
        alone = trajectory_error(alone_run.trajectory, stream.truth)
        # iSAM2 against a batch solve of the same final graph (loops only)
        g = PoseGraphBackend(dataclasses.replace(BackendConfig(), base_T_lidar=stream.base_T_lidar))
        for t, pose in zip(stream.stamps, stream.odometry, strict=True):
            g.add_odometry(float(t), pose)
        accepted = [k for k, ok in enumerate(loops_run.accepted) if ok]
        with tempfile.TemporaryDirectory() as tmp:
            # the loops again, in one go after all odometry: the final graph is the same set of factors
            for k in accepted:
                g.add_loop(float(stream.stamps[stream.loops[k, 0]]), float(stream.stamps[stream.loops[k, 1]]),
                           stream.loop_T[k], stream.loop_cov[k] if np.isfinite(stream.loop_cov[k]).all() else None)
            g.save(Path(tmp) / "graph.npz")
            rows, batch = batch_solution(Path(tmp) / "graph.npz")
        isam_nodes = loops_run.trajectory[rows]
        city: dict[str, Any] = {
            "role": role, "length_m": stream.length_m, "loops_detected": len(stream.loops),
            "loops_accepted": int(loops_run.accepted.sum()), "oracle_loops": len(perfect.loops),
            "odometry": kiss.to_dict(), "loops_only": loops.to_dict(), "oracle_loops_only": best.to_dict(),
            "isam2_nodes_ate": trajectory_error(isam_nodes, stream.truth[rows]).rmse,
            "batch_nodes_ate": trajectory_error(batch, stream.truth[rows]).rmse,
            "level_prior_alone": alone.to_dict(), "loops_and_level_prior": level.to_dict(),
            "odometry_steps": step_errors(stream), "loop_pose_error": loop_errors(stream)}
        report["cities"][str(seed)] = city
        print(f"\nseed {seed} ({role}, {stream.length_m:.0f} m): {len(stream.loops)} detected loops "
              f"({city['loops_accepted']} accepted), {len(perfect.loops)} oracle loops")
        for name, err in (("KISS-ICP odometry", kiss), ("loops only", loops), ("oracle loops only", best),
                          (f"level prior {chosen:g} deg alone", alone), (f"loops + level prior {chosen:g} deg", level)):
            print(f"  {name:28s} {err.text()}  ({err.rmse / kiss.rmse:.0%})")
        print(f"  the loops-only graph at its nodes: iSAM2 {city['isam2_nodes_ate']:.3f} m, batch LM "
              f"{city['batch_nodes_ate']:.3f} m")
        steps = city["odometry_steps"]
        print(f"  KISS-ICP error per {steps['step_m']:.2f} m step, sd (mean) vs the model's sd: " + ", ".join(
            f"{k} {steps['kiss_sd'][k]:.3g} ({steps['kiss_mean'][k]:+.2g}) vs {steps['model_sd'][k]:.3g}"
            for k in steps["kiss_sd"]))
        if city["loop_pose_error"]:
            e = city["loop_pose_error"]
            print(f"  loop pose error (median): LiDAR frames {e['lidar_m'] * 100:.1f} cm / {e['lidar_deg']:.3f} deg, "
                  f"base frames {e['base_m'] * 100:.1f} cm / {e['base_deg']:.3f} deg")
        if role == "test":
            plot(stream, {"KISS-ICP": stream.odometry, "loops only": loops_run.trajectory,
                          "oracle loops only": oracle_run.trajectory,
                          f"loops + level prior {chosen:g} deg": level_run.trajectory},
                 args.out / f"backend_vertical_seed{seed}.png", title=f"Height and tilt error along the drive, "
                                                                      f"city seed {seed} (held out)")
    write_bytes_atomic(args.out / "backend_vertical.json", json.dumps(report, indent=2).encode())
    print(f"\nwritten: {args.out}/backend_vertical.json and backend_vertical_seed*.png")
    return 0


if __name__ == "__main__":
    sys.exit(main())
