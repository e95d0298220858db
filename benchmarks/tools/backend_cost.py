"""Cost of the online back end (lcpr_core.backend) at 2,000 keyframes: adding a loop and updating.

    python benchmarks/tools/backend_cost.py [--nodes 2000] [--loops 60] [--seed 0]

A drive of square laps (125 m sides, 1 m between odometry messages) with drifted odometry
(posegraph.DriftModel: its steps are 1 m +- 1.5 %, so about two messages in three become graph nodes
under the 1 m keyframe rule). Two cases, each timing ``add_loop`` whole (the
consistency check, the iSAM2 update and the extra relinearising updates):

* steady: the graph grows to ``--nodes`` nodes with a true loop every 20 m of every revisiting lap (as
  an online back end sees them), then ``--loops`` more loops are timed while driving on (20 m of
  odometry between loops, each to the same place one lap back);
* first closure: ``--nodes`` odometry messages of drift with no loop, then the one loop that closes it all
  (the most expensive update there is: every node moves), on 5 seeds.

Also the cost of one odometry message (``add_odometry``). Prints p50/p95 in ms and the CPU.
"""
from __future__ import annotations

import argparse
import math
import os
import sys
import time

import numpy as np

SIDE_M = 125.0
STEP_M = 1.0
DT_S = 0.1
EVERY = 20  # messages (m) between loops
LOOP_COV = np.diag([0.1**2, 0.1**2, 0.05**2, math.radians(0.5) ** 2, math.radians(0.5) ** 2, math.radians(1.0) ** 2])


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--nodes", type=int, default=2000, help="keyframes in the graph when timing starts")
    p.add_argument("--loops", type=int, default=60, help="loops timed in the steady case")
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)

    from lcpr_core.backend import BackendConfig, PoseGraphBackend
    from lcpr_core.posegraph import DriftModel, drift_odometry
    from lcpr_core.timing import cpu_model

    per_lap = int(round(4 * SIDE_M / STEP_M))
    total = int(1.6 * args.nodes) + (args.loops + 1) * EVERY
    truth, _ = square_laps(side=SIDE_M, step=STEP_M, laps=math.ceil(total / per_lap) + 1)
    truth = truth[: total + 1]
    print(f"CPU: {cpu_model()}, {os.cpu_count()} cores, load average {os.getloadavg()[0]:.2f} at the start")
    print(f"drive: {len(truth)} odometry messages 1 m apart on {SIDE_M:.0f} m squares ({per_lap} per lap)")

    def loop(g: PoseGraphBackend, stamps: np.ndarray, q: int, m: int) -> tuple[bool, float, float]:
        """(accepted, wall seconds, CPU seconds of this process) of one add_loop."""
        rel = np.linalg.inv(truth[m]) @ truth[q]
        tic, cpu = time.perf_counter(), time.process_time()
        ok = g.add_loop(float(stamps[q]), float(stamps[m]), rel, LOOP_COV)
        return ok, time.perf_counter() - tic, time.process_time() - cpu

    # -- steady
    drifted, _ = drift_odometry(truth, model=DriftModel(seed=args.seed))
    stamps = 1.7e9 + DT_S * np.arange(len(truth))
    g = PoseGraphBackend(BackendConfig())
    odom_s: list[float] = []
    steady_s: list[float] = []
    steady_cpu: list[float] = []
    accepted = nodes = 0
    for i in range(len(truth)):
        tic = time.perf_counter()
        g.add_odometry(float(stamps[i]), drifted[i])
        odom_s.append(time.perf_counter() - tic)
        if i >= per_lap and i % EVERY == 0:
            ok, seconds, cpu = loop(g, stamps, i, i - per_lap)
            accepted += ok
            if g.stats().nodes >= args.nodes and len(steady_s) < args.loops:
                steady_s.append(seconds)
                steady_cpu.append(cpu)
                nodes = g.stats().nodes
    print(f"steady: {len(steady_s)} loops timed at {args.nodes}-{nodes} nodes "
          f"({g.stats().loops_accepted} accepted, {g.stats().loops_rejected} rejected in all)")
    print(f"  add_loop p50 {_ms(steady_s, 50)} ms, p95 {_ms(steady_s, 95)} ms, max {_ms(steady_s, 100)} ms "
          f"(CPU time of this process: p50 {_ms(steady_cpu, 50)} ms, p95 {_ms(steady_cpu, 95)} ms)")
    print(f"  add_odometry p50 {_ms(odom_s, 50)} ms, p95 {_ms(odom_s, 95)} ms over {len(odom_s)} messages")

    # -- the first closure after a long open drift
    first_s: list[float] = []
    for seed in range(5):
        drifted, _ = drift_odometry(truth, model=DriftModel(seed=seed))
        g = PoseGraphBackend(BackendConfig())
        q = 0
        while g.stats().nodes < args.nodes:
            g.add_odometry(float(stamps[q]), drifted[q])
            q += 1
        q -= 1
        ok, seconds, _ = loop(g, stamps, q, q % per_lap)
        first_s.append(seconds)
        print(f"  first closure, seed {seed}: {'accepted' if ok else 'REJECTED'}, "
              f"chi2 {g.stats().last_chi2:.1f}, {seconds * 1e3:.1f} ms ({q - q % per_lap} m of open drift)")
    print(f"load average {os.getloadavg()[0]:.2f} at the end")
    print(f"first closure at {args.nodes} nodes: p50 {_ms(first_s, 50)} ms, max {_ms(first_s, 100)} ms")
    return 0


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
