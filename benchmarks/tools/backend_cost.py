"""Cost of the online back end (lcpr_core.backend) at 2,000 keyframes: adding a loop and updating.

    python benchmarks/tools/backend_cost.py [--nodes 2000] [--loops 60] [--seed 0] [--first-seeds 5]
        [--set NAME=VALUE ...] [--variant NAME=VALUE[,NAME=VALUE...] ...] [--rounds 1]

A drive of square laps (125 m sides, 1 m between odometry messages) with drifted odometry
(posegraph.DriftModel: its steps are 1 m +- 1.5 %, so about two messages in three become graph nodes
under the 1 m keyframe rule). Two cases, each timing ``add_loop`` whole (the
consistency check, the iSAM2 update and the extra relinearising updates):

* steady: the graph grows to ``--nodes`` nodes with a true loop every 20 m of every revisiting lap (as
  an online back end sees them), then ``--loops`` more loops are timed while driving on (20 m of
  odometry between loops, each to the same place one lap back);
* first closure: ``--nodes`` odometry messages of drift with no loop, then the one loop that closes it all
  (the most expensive update there is: every node moves), on ``--first-seeds`` seeds.

Also the cost of one odometry message (``add_odometry``: a relinearisation put off by a loop would show
there) and of one measured up (``add_up``, every ``--up-every`` messages, as the detector's keyframes
send them; those factors are in the graph the loops are timed on). Prints p50/p95 in ms (wall and CPU
time of this process) and the CPU with its load.

Variants: ``--set NAME=VALUE`` changes a BackendConfig field for every run (dotted for the nested ones:
``loops.iterations=1``, ``relinearize_translation=1.0``); each ``--variant`` (comma-separated settings, or
``default``) is one more configuration, timed back to back with the first in the same process
(``--rounds R`` repeats the whole sequence, interleaved, against a varying load). The table at the end
gives, per variant, the medians over rounds of p50/p95, and how far its final trajectory ends from the first
variant's (max position difference, m) and from the truth (RMSE, m).
"""
from __future__ import annotations

import argparse
import dataclasses
import math
import os
import sys
import time
from typing import Any

import numpy as np

from lcpr_common.cli import tool_main

SIDE_M = 125.0
STEP_M = 1.0
DT_S = 0.1
EVERY = 20  # messages (m) between loops
LOOP_COV = np.diag([0.1**2, 0.1**2, 0.05**2, math.radians(0.5) ** 2, math.radians(0.5) ** 2, math.radians(1.0) ** 2])


@dataclasses.dataclass
class Timing:
    """What one run of one variant measured (seconds; trajectory N x 4 x 4)."""

    loop_s: list[float]
    loop_cpu: list[float]
    odom_s: list[float]
    up_s: list[float]
    first_s: list[float]
    trajectory: np.ndarray
    accepted: int
    rejected: int
    nodes: int


@tool_main
def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--nodes", type=int, default=2000, help="keyframes in the graph when timing starts")
    p.add_argument("--loops", type=int, default=60, help="loops timed in the steady case")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--first-seeds", type=int, default=5, help="seeds of the first-closure case (0 = skip it)")
    p.add_argument("--set", dest="settings", action="append", default=[], metavar="NAME=VALUE",
                   help="a BackendConfig field for every variant (repeat; dotted for nested: loops.iterations=1)")
    p.add_argument("--variant", action="append", default=[], metavar="NAME=VALUE[,...]",
                   help="one more configuration timed after the first (repeat; 'default' = --set only)")
    p.add_argument("--rounds", type=int, default=1, help="times the whole sequence of variants is run, interleaved")
    p.add_argument("--up-every", type=int, default=5,
                   help="messages (m) between measured ups (add_up, the true up with 0.5 deg of noise: a detector "
                        "keyframe every 5 m); 0 = none")
    args = p.parse_args(argv)

    from lcpr_core.backend import BackendConfig
    from lcpr_core.timing import cpu_model

    common = parse_settings(args.settings)
    specs = ["default", *args.variant]
    configs = [make_config(BackendConfig, {**common, **parse_settings(_split(v))}) for v in specs]
    per_lap = int(round(4 * SIDE_M / STEP_M))
    total = int(1.6 * args.nodes) + (args.loops + 1) * EVERY
    truth, _ = square_laps(side=SIDE_M, step=STEP_M, laps=math.ceil(total / per_lap) + 1)
    truth = truth[: total + 1]
    print(f"CPU: {cpu_model()}, {os.cpu_count()} cores, load average {os.getloadavg()[0]:.2f} at the start")
    print(f"drive: {len(truth)} odometry messages 1 m apart on {SIDE_M:.0f} m squares ({per_lap} per lap)")
    results: list[list[Timing]] = [[] for _ in specs]
    for r in range(args.rounds):
        for k, (spec, config) in enumerate(zip(specs, configs, strict=True)):
            label = spec if not common else f"{spec} (+ {', '.join(args.settings)})"
            print(f"-- round {r + 1}/{args.rounds}, variant {k}: {label}", flush=True)
            res = run_variant(config, truth, per_lap=per_lap, nodes=args.nodes, loops=args.loops, seed=args.seed,
                              first_seeds=args.first_seeds, up_every=args.up_every)
            results[k].append(res)
            print(f"  steady: {len(res.loop_s)} loops timed at {args.nodes}-{res.nodes} nodes "
                  f"({res.accepted} accepted, {res.rejected} rejected in all)")
            print(f"  add_loop p50 {_ms(res.loop_s, 50)} ms, p95 {_ms(res.loop_s, 95)} ms, "
                  f"max {_ms(res.loop_s, 100)} ms "
                  f"(CPU time of this process: p50 {_ms(res.loop_cpu, 50)} ms, p95 {_ms(res.loop_cpu, 95)} ms)")
            print(f"  add_odometry p50 {_ms(res.odom_s, 50)} ms, p95 {_ms(res.odom_s, 95)} ms, "
                  f"max {_ms(res.odom_s, 100)} ms over {len(res.odom_s)} messages at >= {args.nodes} nodes")
            if res.up_s:
                print(f"  add_up p50 {_ms(res.up_s, 50)} ms, p95 {_ms(res.up_s, 95)} ms, max {_ms(res.up_s, 100)} ms "
                      f"over {len(res.up_s)} ups at >= {args.nodes} nodes")
            if res.first_s:
                print(f"  first closure at {args.nodes} nodes: p50 {_ms(res.first_s, 50)} ms, "
                      f"max {_ms(res.first_s, 100)} ms ({len(res.first_s)} seeds)")
            print(f"  load average {os.getloadavg()[0]:.2f}", flush=True)
    print(f"\nCPU: {cpu_model()}, load average {os.getloadavg()[0]:.2f} at the end; medians over {args.rounds} "
          "round(s), ms; diff: max |position - first variant's| at the end, m; ATE: RMSE against the truth, m")
    print(f"{'variant':40s} {'loop p50':>8s} {'p95':>6s} {'max':>6s} {'cpu p50':>8s} {'p95':>6s} {'odom p95':>8s} "
          f"{'max':>6s} {'first':>6s} {'diff':>8s} {'ATE':>7s}")
    ref = results[0][0].trajectory
    for spec, runs in zip(specs, results, strict=True):
        def med(key: str, q: float, runs: list[Timing] = runs) -> str:
            values = [float(np.percentile(getattr(t, key), q)) for t in runs if getattr(t, key)]
            return "n/a" if not values else f"{float(np.median(values)) * 1e3:.1f}"
        diff = max(float(np.abs(t.trajectory[:, :3, 3] - ref[:, :3, 3]).max()) for t in runs)
        ate = float(np.sqrt(np.mean(np.sum((runs[0].trajectory[:, :3, 3] - truth[:, :3, 3]) ** 2, axis=1))))
        print(f"{spec[:40]:40s} {med('loop_s', 50):>8s} {med('loop_s', 95):>6s} {med('loop_s', 100):>6s} "
              f"{med('loop_cpu', 50):>8s} {med('loop_cpu', 95):>6s} {med('odom_s', 95):>8s} {med('odom_s', 100):>6s} "
              f"{med('first_s', 50):>6s} {diff:8.4f} {ate:7.3f}")
    return 0


def run_variant(config: Any, truth: np.ndarray, *, per_lap: int, nodes: int, loops: int, seed: int,
                first_seeds: int, up_every: int = 0) -> Timing:
    """Time one configuration: the steady case, then the first closure on ``first_seeds`` seeds."""
    from lcpr_core.backend import PoseGraphBackend
    from lcpr_core.posegraph import DriftModel, drift_odometry

    stamps = 1.7e9 + DT_S * np.arange(len(truth))

    def loop(g: PoseGraphBackend, q: int, m: int) -> tuple[bool, float, float]:
        """(accepted, wall seconds, CPU seconds of this process) of one add_loop."""
        rel = np.linalg.inv(truth[m]) @ truth[q]
        tic, cpu = time.perf_counter(), time.process_time()
        ok = g.add_loop(float(stamps[q]), float(stamps[m]), rel, LOOP_COV)
        return ok, time.perf_counter() - tic, time.process_time() - cpu

    drifted, _ = drift_odometry(truth, model=DriftModel(seed=seed))
    g = PoseGraphBackend(config)
    rng = np.random.default_rng(seed)
    odom_s: list[float] = []
    up_s: list[float] = []
    loop_s: list[float] = []
    loop_cpu: list[float] = []
    n = 0
    for i in range(len(truth)):
        tic = time.perf_counter()
        g.add_odometry(float(stamps[i]), drifted[i])
        if g.stats().nodes >= nodes:
            odom_s.append(time.perf_counter() - tic)
        if up_every and i % up_every == 0:  # the LiDAR frame is the base frame here (BackendConfig's default)
            tilt = rng.normal(0.0, math.radians(0.5), 3)
            up = truth[i, :3, :3].T @ np.array([0.0, 0.0, 1.0]) + np.cross(tilt, [0.0, 0.0, 1.0])
            tic = time.perf_counter()
            g.add_up(float(stamps[i]), up)
            if g.stats().nodes >= nodes:
                up_s.append(time.perf_counter() - tic)
        if i >= per_lap and i % EVERY == 0:
            _, seconds, cpu = loop(g, i, i - per_lap)
            if g.stats().nodes >= nodes and len(loop_s) < loops:
                loop_s.append(seconds)
                loop_cpu.append(cpu)
                n = g.stats().nodes
    _, trajectory = g.trajectory()
    stats = g.stats()
    first_s: list[float] = []
    for s in range(first_seeds):
        drifted, _ = drift_odometry(truth, model=DriftModel(seed=s))
        h = PoseGraphBackend(config)
        q = 0
        while h.stats().nodes < nodes:
            h.add_odometry(float(stamps[q]), drifted[q])
            q += 1
        q -= 1
        ok, seconds, _ = loop(h, q, q % per_lap)
        first_s.append(seconds)
        print(f"  first closure, seed {s}: {'accepted' if ok else 'REJECTED'}, chi2 {h.stats().last_chi2:.1f}, "
              f"{seconds * 1e3:.1f} ms ({q - q % per_lap} m of open drift)")
    return Timing(loop_s, loop_cpu, odom_s, up_s, first_s, trajectory, stats.loops_accepted, stats.loops_rejected, n)


def _split(spec: str) -> list[str]:
    return [] if spec.strip() in ("", "default") else [part for part in spec.split(",") if part.strip()]


def parse_settings(items: list[str]) -> dict[str, str]:
    """``NAME=VALUE`` strings -> {name: value} (SystemExit naming a malformed one)."""
    out: dict[str, str] = {}
    for item in items:
        name, sep, value = item.partition("=")
        if not sep or not name.strip():
            raise SystemExit(f"backend_cost: setting {item!r}; expected NAME=VALUE (e.g. loops.iterations=1)")
        out[name.strip()] = value.strip()
    return out


def make_config(kind: Any, settings: dict[str, str]) -> Any:
    """A frozen config dataclass of type ``kind`` with ``settings`` (dotted names reach nested dataclasses)."""
    fields = {f.name: f for f in dataclasses.fields(kind)}
    direct: dict[str, Any] = {}
    nested: dict[str, dict[str, str]] = {}
    default = kind()
    for name, value in settings.items():
        head, _, rest = name.partition(".")
        if head not in fields:
            raise SystemExit(f"backend_cost: unknown setting {name!r} of {kind.__name__}; "
                             f"expected one of {', '.join(sorted(fields))}")
        if rest:
            nested.setdefault(head, {})[rest] = value
        else:
            direct[head] = _convert(value, getattr(default, head), name)
    for head, sub in nested.items():
        direct[head] = make_config(type(getattr(default, head)), sub)
    return kind(**direct)


def _convert(text: str, like: Any, name: str) -> Any:
    """``text`` as the type of the default ``like`` (bool, int, float, str, tuple of floats)."""
    try:
        if isinstance(like, bool):
            if text.lower() not in ("true", "false", "1", "0"):
                raise ValueError(text)
            return text.lower() in ("true", "1")
        if isinstance(like, int):
            return int(text)
        if isinstance(like, float):
            return float(text)
        if isinstance(like, tuple):
            return tuple(float(v) for v in text.split(":"))
    except ValueError:
        raise SystemExit(f"backend_cost: {name}={text!r}; expected a {type(like).__name__} "
                         "(tuples: values separated by ':')") from None
    if isinstance(like, str):
        return text
    raise SystemExit(f"backend_cost: {name} is a {type(like).__name__}; only numbers, booleans, strings and "
                     "tuples can be set here")


def square_laps(*, side: float, step: float, laps: int) -> tuple[np.ndarray, int]:
    """Counter-clockwise laps of a square from (0, 0) facing +x; (poses (N, 4, 4), poses per lap)."""
    per_lap = int(round(4 * side / step))
    poses = np.tile(np.eye(4), (laps * per_lap + 1, 1, 1))
    for i in range(len(poses)):
        s = (i * step) % (4 * side)
        k = min(int(s // side), 3)
        u = s - k * side
        corner = np.array([(0.0, 0.0), (side, 0.0), (side, side), (0.0, side)][k])
        heading = np.array([(1.0, 0.0), (0.0, 1.0), (-1.0, 0.0), (0.0, -1.0)][k])
        c, s_ = math.cos(k * math.pi / 2), math.sin(k * math.pi / 2)
        poses[i, :2, :2] = [[c, -s_], [s_, c]]
        poses[i, :2, 3] = corner + heading * u
    return poses, per_lap


def _ms(values: list[float], q: float) -> str:
    return "n/a" if not values else f"{float(np.percentile(values, q)) * 1e3:.1f}"


if __name__ == "__main__":
    sys.exit(main())
