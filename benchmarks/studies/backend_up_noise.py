"""How the back end's measured ups are weighed, and whether one scan's error can tilt the map.

    python benchmarks/studies/backend_up_noise.py [--validation 3] [--test 7 9] [--streams out/backend_ate]
                                                  [--draws 3] [--out out/backend_up_noise]

Reads the streams cached by ``benchmarks/tools/backend_ate.py --seed S`` (KISS-ICP on a synthetic city,
the detector's loops and each keyframe's up measured from its walls). The rendered walls are exact, so a
city's ups are off by about 0.1 deg; a real scan's by up to a degree or two. Each measured up is turned
by a random angle (normal, std dev 0, 0.5, 1, 2 deg, in a random direction; ``--draws`` draws each) and
the stream replayed through the back end:

1. on the ``--validation`` city only: ``up_warmup_m`` (10, 20, 30, 60, 100 m: the travel whose ups are
   averaged into the world's up, fixed then; the default ``up_world_sigma_deg`` 0) and ``up_sigma_deg``
   (0.5, 1, 2, 5 deg, at the warm-up with the lowest worst case over noise levels and draws) over the noise
   levels, and the world's up a graph variable (``up_world_sigma_deg`` 1, 3, 10) at the defaults;
2. on the ``--test`` cities: the defaults (chosen on the validation city's own ups by
   ``backend_ate.py``), the validation setting with the lowest worst case under noise, and the world's up a
   variable of 3 deg (``backend_cost.py --variant up_world_sigma_deg=3`` gives what that costs).

Prints ATE after / before per draw, writes ``OUT/backend_up_noise.json`` and ``OUT/backend_up_noise.png``
(ATE after / before against the noise, worst draw, per city). Conclusions: docs/backend.md (Measured up
from the walls).
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from lcpr_core.backend import BackendConfig
    from lcpr_core.backend.replay import LoopStream

NOISE_DEG = (0.0, 0.5, 1.0, 2.0)
WARMUPS_M = (10.0, 20.0, 30.0, 60.0, 100.0)
UP_SIGMAS = (0.5, 1.0, 2.0, 5.0)
WORLD_SIGMAS = (1.0, 3.0, 10.0)


def noisy(ups: np.ndarray, noise_deg: float, rng: np.random.Generator) -> np.ndarray:
    """Each unit vector (NaN rows kept) turned by a normal(0, noise_deg) angle about a random perpendicular axis."""
    out = ups.copy()
    for k, u in enumerate(ups):
        if not np.isfinite(u).all():
            continue
        axis = rng.normal(size=3)
        axis -= (axis @ u) * u
        axis /= np.linalg.norm(axis)
        angle = np.radians(rng.normal(0.0, noise_deg))
        out[k] = np.cos(angle) * u + np.sin(angle) * np.cross(axis, u)
    return out


def ratios(stream: LoopStream, config: BackendConfig, noise_deg: float, draws: int) -> list[float]:
    """ATE after / before of each draw of ``noise_deg`` up noise."""
    from lcpr_core.backend.replay import replay, trajectory_error

    before = trajectory_error(stream.odometry, stream.truth).rmse
    out = []
    for d in range(draws):
        replayed = dataclasses.replace(stream, ups=noisy(stream.ups, noise_deg, np.random.default_rng(d)))
        out.append(trajectory_error(replay(replayed, config=config).trajectory, stream.truth).rmse / before)
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--validation", type=int, default=3)
    p.add_argument("--test", type=int, nargs="*", default=[7, 9])
    p.add_argument("--streams", type=Path, default=Path("out/backend_ate"))
    p.add_argument("--draws", type=int, default=3)
    p.add_argument("--out", type=Path, default=Path("out/backend_up_noise"))
    args = p.parse_args(argv)

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from lcpr_common.progress import progress_iter
    from lcpr_core.atomic import write_bytes_atomic
    from lcpr_core.backend import BackendConfig
    from lcpr_core.backend.replay import LoopStream

    def stream_of(seed: int) -> LoopStream:
        path = args.streams / f"stream_seed{seed}_1000f_1m_every5.npz"
        if not path.exists():
            raise SystemExit(f"backend_up_noise: {path} is missing; run benchmarks/tools/backend_ate.py --seed {seed}")
        return LoopStream.load(path)

    args.out.mkdir(parents=True, exist_ok=True)
    summary: dict[str, Any] = {"noise_deg": NOISE_DEG, "draws": args.draws}
    val = stream_of(args.validation)
    sweep: dict[str, dict[str, list[float]]] = {}

    def run(name: str, config: BackendConfig) -> None:
        sweep[name] = {f"{n:g}": ratios(val, config, n, args.draws) for n in NOISE_DEG}
        print(f"  {name:28s} " + "  ".join(f"{n}: " + " ".join(f"{r:.0%}" for r in v) for n, v in sweep[name].items()),
              flush=True)

    def best(names: list[str]) -> str:
        return min(names, key=lambda k: (max(max(v) for v in sweep[k].values()),
                                         float(np.mean([np.mean(v) for v in sweep[k].values()]))))

    print(f"validation city seed {args.validation}: ATE after / before per noise level (deg) and draw")
    for w in progress_iter(WARMUPS_M, total=len(WARMUPS_M), desc="warm-up", unit="setting"):
        run(f"warm-up {w:g} m, up 2 deg", BackendConfig(up_warmup_m=w, up_sigma_deg=2.0))
    warm = best(list(sweep))
    warm_m = float(warm.split()[1])
    for u in UP_SIGMAS:
        if u != 2.0:
            run(f"warm-up {warm_m:g} m, up {u:g} deg", BackendConfig(up_warmup_m=warm_m, up_sigma_deg=u))
    chosen = best(list(sweep))
    print(f"lowest worst case under noise, world's up fixed: {chosen}; defaults: warm-up "
          f"{BackendConfig().up_warmup_m:g} m, up {BackendConfig().up_sigma_deg:g} deg")
    robust = BackendConfig(up_warmup_m=warm_m, up_sigma_deg=float(chosen.split()[4]))
    for w in WORLD_SIGMAS:
        run(f"defaults, world's up a variable {w:g} deg", BackendConfig(up_world_sigma_deg=w))
    summary.update(validation=args.validation, sweep=sweep, chosen=chosen)

    defaults = BackendConfig()
    variable = dataclasses.replace(defaults, up_world_sigma_deg=3.0)
    robust_label = f"warm-up {robust.up_warmup_m:g} m, up {robust.up_sigma_deg:g} deg"
    held: dict[str, dict[str, dict[str, list[float]]]] = {}
    fig, axes = plt.subplots(1, 1 + len(args.test), figsize=(4.2 * (1 + len(args.test)), 3.6), squeeze=False)
    for ax, seed in zip(axes[0], [args.validation, *args.test], strict=True):
        stream = val if seed == args.validation else stream_of(seed)
        held[str(seed)] = {}
        configs = (("defaults", defaults), (robust_label, robust), ("world's up a variable, 3 deg", variable))
        for label, config in configs:
            rows = {f"{n:g}": ratios(stream, config, n, args.draws) for n in NOISE_DEG}
            held[str(seed)][label] = rows
            if seed != args.validation:
                print(f"city seed {seed}, {label}: " + "  ".join(
                    f"{n}: " + " ".join(f"{r:.0%}" for r in v) for n, v in rows.items()))
            ax.plot(NOISE_DEG, [100 * max(v) for v in rows.values()], marker="o", label=label)
        ax.axhline(30, color="grey", lw=0.8, ls="--")
        ax.set_title(f"city seed {seed}" + (" (validation)" if seed == args.validation else " (held out)"))
        ax.set_xlabel("noise added to each up (deg)")
        ax.set_ylabel("ATE after / before, worst draw (%)")
        ax.set_ylim(bottom=0)
    axes[0][0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(args.out / "backend_up_noise.png", dpi=110)
    summary["held_out"] = held
    write_bytes_atomic(args.out / "backend_up_noise.json", json.dumps(summary, indent=2).encode())
    print(f"written: {args.out}/backend_up_noise.json and backend_up_noise.png")
    return 0


if __name__ == "__main__":
    sys.exit(main())
