"""Are the loops' covariances calibrated, are loops of the same places correlated, and does thinning them help?

    python benchmarks/studies/backend_loop_redundancy.py [--validation 3] [--test 7 9]
                                                         [--streams out/backend_ate] [--real out/backend_ate_real]

Reads the streams cached by ``benchmarks/tools/backend_ate.py --seed S`` (KISS-ICP on a synthetic city,
the detector's verified loops, the true poses) and by ``benchmarks/tools/backend_ate_real.py`` (the Livox
sequences with FAST-LIO2's and KISS-ICP's odometry; their "truth" is ``optimized_poses.txt``, a reference
good to a few cm, not surveyed truth). Record them first. Then:

1. calibration: each loop's error against the truth (``Log(true^-1 measured)``, GTSAM's tangent) and its
   normalised squared error ``NEES = e^T C^-1 e`` with the loop's own covariance (a calibrated 6-dof
   covariance gives a mean of 6), per axis the RMS of ``e_i / sigma_i`` (1 when calibrated); "inliers"
   leave out loops more than 0.3 m or 2 deg off (wrong loops, which the consistency check is for);
2. redundancy: loops grouped by the stretches they join (10 m bins of distance travelled, query x
   match), the correlation of the whitened errors of two loops of one group, per axis, beside that of
   two random loops; the effective number of independent loops ``sum n / (1 + (n - 1) rho)``;
3. on the ``--validation`` city only: the back end swept over ``LoopPolicy.min_spacing_m`` (a loop whose
   both ends lie within that travel of an accepted loop's is skipped) at ``covariance_scale`` 1 and at
   the NEES-calibrated scale (mean inlier NEES / 6); the spacing with the lowest ATE with the level
   prior of 2 deg (the configuration the held-out target is reported with) is chosen with that scale;
4. without further tuning, the chosen setting beside the defaults: held-out cities (loops only, level
   prior 2 deg, level prior with 20 injected false loops) and the real sequences (FAST-LIO2 with the
   defaults and with the gravity prior 0.5 deg; KISS-ICP with its defaults); and, marked as a what-if
   chosen on nothing, the spacing sweep on the real sequences;
5. what limits FAST-LIO2 (what-ifs, chosen on nothing): the same loops at the reference's exact relative
   pose (can the graph follow the reference at all?), and the odometry model 10 times tighter (a LIO
   drifts far less than the KISS-ICP the defaults were set for).

Writes ``OUT/backend_loop_redundancy.json`` and ``OUT/backend_loop_redundancy.png``. Conclusions:
docs/backend.md (Loops of the same place, and their covariance).
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from lcpr_core.backend import BackendConfig
    from lcpr_core.backend.replay import LoopStream

SPACINGS_M = (0.0, 3.0, 5.0, 7.5, 10.0, 20.0)
BIN_M = 10.0  # stretches: bins of distance travelled
WRONG_M, WRONG_DEG = 0.3, 2.0  # a loop this far off the truth is wrong (backend_ate_real.py's rule)
LEVEL_DEG, GRAVITY_DEG = 2.0, 0.5  # the documented level prior (cities) and gravity prior (a LIO)
REAL = (("walk_loop", "fastlio2", 0.0), ("walk_loop", "fastlio2", GRAVITY_DEG), ("walk_loop", "kiss100m_2m", 0.0),
        ("campus", "fastlio2", 0.0), ("campus", "fastlio2", GRAVITY_DEG), ("campus", "kiss100m_2m", 0.0))
LIO_FACTOR = 0.1  # the what-if odometry model: every OdometryNoise field times this
AXES = ("roll", "pitch", "yaw", "x", "y", "z")  # GTSAM's tangent order, in the query (child) frame


def loop_errors(stream: LoopStream) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(L, 6) error of each loop against the truth (GTSAM tangent), (L,) NEES, (L,) inlier mask."""
    import gtsam

    from lcpr_core.geometry import rotation_angle_deg
    from lcpr_core.loop_report import DEFAULT_LOOP_COVARIANCE
    from lcpr_core.posegraph import to_gtsam_covariance

    q, m = stream.loops[:, 0], stream.loops[:, 1]
    lidar = stream.truth @ stream.base_T_lidar
    true = np.linalg.inv(lidar[m]) @ lidar[q]  # L x 4 x 4
    off = np.linalg.inv(true) @ stream.loop_T
    errors, nees = np.zeros((len(q), 6)), np.zeros(len(q))
    for k in range(len(q)):
        cov = stream.loop_cov[k] if np.isfinite(stream.loop_cov[k]).all() else DEFAULT_LOOP_COVARIANCE
        c = to_gtsam_covariance(cov, stream.loop_T[k][:3, :3])
        errors[k] = gtsam.Pose3.Logmap(gtsam.Pose3(off[k]))
        nees[k] = errors[k] @ np.linalg.solve(c, errors[k])
        errors[k] /= np.sqrt(np.diag(c))  # whitened per axis
    inlier = (np.linalg.norm(off[:, :3, 3], axis=1) <= WRONG_M) & (rotation_angle_deg(off[:, :3, :3]) <= WRONG_DEG)
    return errors, nees, np.asarray(inlier, bool)


def calibration(stream: LoopStream) -> dict[str, Any]:
    """NEES and whitened errors per axis, and the correlation of loops between the same stretches."""
    z, nees, inlier = loop_errors(stream)
    zi = z[inlier]
    pos = stream.truth[:, :3, 3]
    travel = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(pos, axis=0), axis=1))]
    groups: dict[tuple[int, int], list[int]] = {}
    for k in np.flatnonzero(inlier):
        q, m = stream.loops[k]
        groups.setdefault((int(travel[q] // BIN_M), int(travel[m] // BIN_M)), []).append(int(k))
    same = [(a, b) for idx in groups.values() for i, a in enumerate(idx) for b in idx[i + 1:]]
    rng = np.random.default_rng(0)
    pool = np.flatnonzero(inlier)
    other = [(int(a), int(b)) for a, b in rng.choice(pool, size=(2000, 2)) if a != b] if len(pool) > 1 else []

    def corr(pairs: list[tuple[int, int]]) -> list[float | None]:
        if len(pairs) < 3:
            return [None] * 6
        a, b = np.array(pairs).T
        left, right = np.r_[z[a], z[b]], np.r_[z[b], z[a]]  # both orders: the correlation is symmetric
        return [float(np.corrcoef(left[:, i], right[:, i])[0, 1]) for i in range(6)]

    rho_same = corr(same)
    rho = float(np.clip(np.nanmean([np.nan if r is None else r for r in rho_same]), 0.0, 1.0)) if same else 0.0
    sizes = [len(v) for v in groups.values()]
    return {
        "loops": len(nees), "inliers": int(inlier.sum()),
        "nees_mean_all": float(nees.mean()) if len(nees) else None,
        "nees_mean_inliers": float(nees[inlier].mean()) if inlier.any() else None,
        "nees_median_inliers": float(np.median(nees[inlier])) if inlier.any() else None,
        "z_rms_inliers": dict(zip(AXES, np.sqrt((zi**2).mean(axis=0)).round(3).tolist(), strict=True)),
        "z_mean_inliers": dict(zip(AXES, zi.mean(axis=0).round(3).tolist(), strict=True)),
        "groups": len(groups), "group_size_mean": float(np.mean(sizes)) if sizes else 0.0,
        "group_size_max": max(sizes, default=0), "pairs_same_group": len(same),
        "rho_same_group": dict(zip(AXES, rho_same, strict=True)),
        "rho_random_pairs": dict(zip(AXES, corr(other), strict=True)),
        "rho_mean_clipped": rho,
        "effective_loops": float(sum(n / (1 + (n - 1) * rho) for n in sizes)),
    }


def config(*, spacing: float, scale: float, level: float = 0.0, gravity: float = 0.0) -> BackendConfig:
    from lcpr_core.backend import BackendConfig, LoopPolicy

    return BackendConfig(level_sigma_deg=level, gravity_sigma_deg=gravity,
                         loops=LoopPolicy(min_spacing_m=spacing, covariance_scale=scale))


def ate(stream: LoopStream, cfg: BackendConfig, *, inject: int = 0) -> dict[str, Any]:
    from lcpr_core.backend.replay import replay, trajectory_error

    run = replay(stream, inject=inject, seed=0, config=cfg)
    err = trajectory_error(run.trajectory, stream.truth)
    ms = np.array(run.loop_ms)
    return {"ate": err.rmse, "vertical": err.vertical, "aligned": err.aligned, "accepted": int(run.accepted.sum()),
            "redundant": run.stats.loops_redundant, "rejected": run.stats.loops_rejected,
            "injected": run.injected, "injected_rejected": run.injected_rejected,
            "add_loop_ms_p95": float(np.percentile(ms, 95)) if len(ms) else None}


def plot(report: dict[str, Any], path: Path) -> None:
    """Three panels: whitened loop errors per axis, the validation sweep, the real-sequence what-if. PNG."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    from lcpr_core.atomic import save_figure

    fig = Figure(figsize=(15, 4.6), dpi=100)
    FigureCanvasAgg(fig)
    ax_z, ax_v, ax_r = (fig.add_subplot(1, 3, i) for i in (1, 2, 3))
    names = list(report["calibration"])
    width = 0.8 / max(len(names), 1)
    for i, name in enumerate(names):
        rms = [report["calibration"][name]["z_rms_inliers"][a] for a in AXES]
        ax_z.bar(np.arange(6) + i * width, rms, width, label=name)
    ax_z.axhline(1.0, color="k", lw=0.8, ls="--")
    ax_z.set(xticks=np.arange(6) + 0.4 - width / 2, xticklabels=AXES, yscale="log",
             ylabel="RMS of error / its sigma (1 = calibrated)", title="Loops' errors against their covariance")
    ax_z.legend(fontsize=7)
    for scale_key, rows in report["validation_sweep"].items():
        for level_key, style in (("loops_only", "--"), ("level_prior", "-")):
            ax_v.plot(SPACINGS_M, [r[level_key]["ate"] for r in rows], style, marker="o",
                      label=f"scale {scale_key}, {level_key.replace('_', ' ')}")
    ax_v.set(xlabel="min_spacing_m", ylabel="ATE [m]", title=f"Validation city seed {report['validation']}")
    ax_v.legend(fontsize=7)
    for key, rows in report["real_what_if"].items():
        before = rows["before"]
        ax_r.plot(SPACINGS_M, [r["ate"] / before for r in rows["sweep"]], marker="o", label=key)
    ax_r.axhline(1.0, color="k", lw=0.8, ls="--")
    ax_r.set(xlabel="min_spacing_m (what-if, chosen on nothing)", ylabel="ATE after / before",
             title="Real sequences, covariance scale 1")
    ax_r.legend(fontsize=7)
    for ax in (ax_z, ax_v, ax_r):
        ax.grid(alpha=0.3)
    save_figure(fig, path)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--validation", type=int, default=3, help="the city that chooses the setting")
    p.add_argument("--test", type=int, nargs="+", default=[7, 9], help="held-out cities, reported only")
    p.add_argument("--streams", type=Path, default=Path("out/backend_ate"), help="backend_ate.py's --out")
    p.add_argument("--real", type=Path, default=Path("out/backend_ate_real"), help="backend_ate_real.py's --out")
    p.add_argument("--out", type=Path, default=Path("out/backend_loop_redundancy"))
    args = p.parse_args(argv)

    import os

    from lcpr_common.progress import progress_bar
    from lcpr_core.atomic import write_bytes_atomic
    from lcpr_core.backend import BackendConfig, OdometryNoise
    from lcpr_core.backend.replay import LoopStream, trajectory_error
    from lcpr_core.timing import cpu_model

    args.out.mkdir(parents=True, exist_ok=True)
    cities: dict[int, LoopStream] = {}
    for seed in (args.validation, *args.test):
        path = args.streams / f"stream_seed{seed}_1000f_1m_every5.npz"
        if not path.exists():
            raise SystemExit(f"{path} is missing: run python benchmarks/tools/backend_ate.py --seed {seed} first")
        cities[seed] = LoopStream.load(path)
    real: dict[str, LoopStream] = {}
    for name, tag, _ in REAL:
        path = args.real / f"stream_{name}_{tag}.npz"
        if path.exists():
            real[f"{name}_{tag}"] = LoopStream.load(path)
        else:
            print(f"{path} is missing (run benchmarks/tools/backend_ate_real.py); skipped")
    cpu = cpu_model()
    print(f"CPU: {cpu}, {os.cpu_count()} cores, load average {os.getloadavg()[0]:.2f}")
    report: dict[str, Any] = {"cpu": cpu, "validation": args.validation, "test": args.test, "spacings_m": SPACINGS_M,
                              "bin_m": BIN_M, "calibration": {}}

    # 1-2: calibration and redundancy
    for key, stream in [*((f"seed{s}", c) for s, c in cities.items()), *real.items()]:
        cal = calibration(stream)
        report["calibration"][key] = cal
        rho = ", ".join(f"{a} {'-' if r is None else f'{r:+.2f}'}" for a, r in cal["rho_same_group"].items())
        print(f"{key}: {cal['loops']} loops ({cal['inliers']} inliers); NEES mean {cal['nees_mean_all']:.3g} (inliers "
              f"{cal['nees_mean_inliers']:.3g}, median {cal['nees_median_inliers']:.3g}; 6 = calibrated); RMS of "
              "error / sigma " + ", ".join(f"{a} {v:.2f}" for a, v in cal["z_rms_inliers"].items()))
        print(f"  {cal['groups']} stretch pairs ({BIN_M:g} m bins; {cal['group_size_mean']:.1f} loops each, at most "
              f"{cal['group_size_max']}); correlation within one: {rho}; effective loops {cal['effective_loops']:.0f}")

    # 3: the validation sweep
    val = cities[args.validation]
    scale = float(report["calibration"][f"seed{args.validation}"]["nees_mean_inliers"]) / 6.0
    scales = {"1": 1.0, f"{scale:.3g} (NEES)": scale}
    report["nees_scale"] = scale
    sweep: dict[str, list[dict[str, Any]]] = {}
    bar = progress_bar(len(scales) * len(SPACINGS_M) * 2, desc=f"seed {args.validation} sweep", unit="replay")
    for key, s in scales.items():
        sweep[key] = []
        for spacing in SPACINGS_M:
            cell: dict[str, Any] = {}
            for name, level in (("loops_only", 0.0), ("level_prior", LEVEL_DEG)):
                cell[name] = ate(val, config(spacing=spacing, scale=s, level=level))
                bar.update()
            sweep[key].append(cell)
    bar.close()
    report["validation_sweep"] = sweep
    best = min(range(len(SPACINGS_M)), key=lambda i: sweep[list(scales)[1]][i]["level_prior"]["ate"])
    chosen = {"min_spacing_m": SPACINGS_M[best], "covariance_scale": scale}
    report["chosen"] = chosen
    for key, rows in sweep.items():
        print(f"seed {args.validation}, scale {key}: " + ", ".join(
            f"{sp:g} m {r['loops_only']['ate']:.3f} / {r['level_prior']['ate']:.3f} m ({r['level_prior']['accepted']})"
            for sp, r in zip(SPACINGS_M, rows, strict=True)) + "  (spacing: loops only / level prior (loops taken))")
    print(f"chosen on seed {args.validation}: min_spacing_m {chosen['min_spacing_m']:g}, covariance_scale {scale:.3g}")

    # 4: held out and real, defaults beside the chosen setting
    settings = {"defaults": (0.0, 1.0), "chosen": (chosen["min_spacing_m"], scale)}
    held: dict[str, Any] = {}
    bar = progress_bar(len(args.test) * len(settings) * 3, desc="held-out cities", unit="replay")
    for seed in args.test:
        stream = cities[seed]
        out: dict[str, Any] = {"before": trajectory_error(stream.odometry, stream.truth).rmse}
        for name, (sp, sc) in settings.items():
            out[name] = {}
            for label, level, inject in (("loops_only", 0.0, 0), ("level_prior", LEVEL_DEG, 0),
                                         ("level_prior_inject20", LEVEL_DEG, 20)):
                out[name][label] = ate(stream, config(spacing=sp, scale=sc, level=level), inject=inject)
                bar.update()
        held[str(seed)] = out
    bar.close()
    report["held_out"] = held
    for seed, out in held.items():
        for name in settings:
            r = out[name]
            print(f"seed {seed} {name}: before {out['before']:.2f} m; loops only {r['loops_only']['ate']:.2f} m; level "
                  f"prior {r['level_prior']['ate']:.2f} m ({r['level_prior']['ate'] / out['before']:.0%}); with 20 "
                  f"false loops {r['level_prior_inject20']['ate']:.2f} m "
                  f"({r['level_prior_inject20']['ate'] / r['level_prior']['ate'] - 1:+.1%}; "
                  f"{r['level_prior_inject20']['injected_rejected']} of {r['level_prior_inject20']['injected']} "
                  "rejected)")

    real_rows: dict[str, Any] = {}
    what_if: dict[str, Any] = {}
    bar = progress_bar(len(REAL) * (len(settings) + len(SPACINGS_M)), desc="real sequences", unit="replay")
    for name, tag, gravity in REAL:
        found = real.get(f"{name}_{tag}")
        if found is None:
            continue
        stream = found
        key = f"{name}_{tag}" + (f"_gravity{gravity:g}" if gravity else "")
        before = trajectory_error(stream.odometry, stream.truth).rmse
        row: dict[str, Any] = {"before": before}
        for label, (sp, sc) in settings.items():
            row[label] = ate(stream, config(spacing=sp, scale=sc, gravity=gravity))
            bar.update()
        real_rows[key] = row
        what_if[key] = {"before": before, "sweep": []}
        for sp in SPACINGS_M:
            what_if[key]["sweep"].append(ate(stream, config(spacing=sp, scale=1.0, gravity=gravity)))
            bar.update()
    bar.close()
    report["real"] = real_rows
    report["real_what_if"] = what_if
    for key, row in real_rows.items():
        print(f"{key}: before {row['before']:.4f} m; " + "; ".join(
            f"{label} {row[label]['ate']:.4f} m ({row[label]['ate'] / row['before']:.0%}, {row[label]['accepted']} "
            "loops)" for label in settings))
        print("  what-if, scale 1: " + ", ".join(
            f"{sp:g} m {r['ate'] / row['before']:.0%} ({r['accepted']})"
            for sp, r in zip(SPACINGS_M, what_if[key]["sweep"], strict=True)))

    lio: dict[str, Any] = {}
    tight = OdometryNoise(**{k: v * LIO_FACTOR for k, v in dataclasses.asdict(OdometryNoise()).items()})
    for name, tag, gravity in REAL:
        found = real.get(f"{name}_{tag}")
        if found is None or tag != "fastlio2":
            continue
        stream = found
        key = f"{name}_{tag}" + (f"_gravity{gravity:g}" if gravity else "")
        lidar = stream.truth @ stream.base_T_lidar
        exact = dataclasses.replace(stream, loop_T=np.linalg.inv(lidar[stream.loops[:, 1]]) @ lidar[stream.loops[:, 0]])
        lio[key] = {"before": real_rows[key]["before"],
                    "loops_at_reference_pose": ate(exact, config(spacing=0.0, scale=1.0, gravity=gravity)),
                    f"odometry_model_x{LIO_FACTOR:g}": ate(stream, dataclasses.replace(
                        config(spacing=0.0, scale=1.0, gravity=gravity), odometry=tight))}
        got = lio[key]
        print(f"{key} what-if: loops at the reference's relative pose {got['loops_at_reference_pose']['ate']:.4f} m; "
              f"odometry model x{LIO_FACTOR:g} {got[f'odometry_model_x{LIO_FACTOR:g}']['ate']:.4f} m "
              f"(before {got['before']:.4f} m)")
    report["lio_what_if"] = lio

    report["defaults"] = dataclasses.asdict(BackendConfig().loops)
    write_bytes_atomic(args.out / "backend_loop_redundancy.json", json.dumps(report, indent=2,
                                                                             default=_json_default).encode())
    plot(report, args.out / "backend_loop_redundancy.png")
    print(f"\nwritten: {args.out}/backend_loop_redundancy.json and backend_loop_redundancy.png")
    return 0


def _json_default(value: object) -> Any:
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, float) and math.isnan(value):
        return None
    raise TypeError(f"{type(value).__name__} is not JSON serialisable")


if __name__ == "__main__":
    sys.exit(main())
