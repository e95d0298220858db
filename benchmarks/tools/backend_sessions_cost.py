"""What an inter-session loop costs the back end at thousands of nodes per session, and what anchoring costs.

    python benchmarks/tools/backend_sessions_cost.py [--nodes 2000] [--every 10] [--out out/backend_sessions_cost]

Two sessions drive the same square laps (a graph node every metre, so ``--nodes`` m each): ``a`` first, then
``b`` in an odometry frame moved by a rigid transform, drifting. Every ``--every`` nodes of ``b`` a true loop
to the nearest pose of ``a`` (5 cm, 0.5 deg) is added. Prints the median and p95 of ``add_loop`` over the
loops after ``b`` was anchored (the ordinary check and update), the anchoring solve apart, and the CPU.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from pathlib import Path

import numpy as np

from lcpr_common.cli import tool_main


def laps(nodes: int, side: float = 100.0) -> np.ndarray:
    """(nodes, 4, 4) poses 1 m apart round a square of ``side`` m, heading along the path."""
    s = np.arange(nodes, dtype=np.float64) % (4 * side)
    edge, along = (s // side).astype(int), s % side
    corners = np.array([[0, 0], [side, 0], [side, side], [0, side]], np.float64)
    dirs = np.array([[1, 0], [0, 1], [-1, 0], [0, -1]], np.float64)
    out = np.tile(np.eye(4), (nodes, 1, 1))
    out[:, :2, 3] = corners[edge] + dirs[edge] * along[:, None]
    yaw = edge * math.pi / 2
    out[:, 0, 0], out[:, 0, 1], out[:, 1, 0], out[:, 1, 1] = np.cos(yaw), -np.sin(yaw), np.sin(yaw), np.cos(yaw)
    return out


@tool_main
def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--nodes", type=int, default=2000, help="graph nodes per session (default 2000)")
    p.add_argument("--every", type=int, default=10, help="nodes of b between two inter-session loops (default 10)")
    p.add_argument("--out", type=Path, default=Path("out/backend_sessions_cost"))
    args = p.parse_args(argv)

    from lcpr_core.backend import BackendConfig, KeyframeRule, PoseGraphBackend
    from lcpr_core.geometry import so3_exp
    from lcpr_core.posegraph import DriftModel, drift_odometry
    from lcpr_core.timing import cpu_model

    truth = laps(args.nodes)
    odom_a, _ = drift_odometry(truth, model=DriftModel(seed=1))
    drifted_b, _ = drift_odometry(np.roll(truth, -37, axis=0), model=DriftModel(seed=2))
    truth_b = np.roll(truth, -37, axis=0)
    move = np.eye(4)
    move[:3, :3], move[:3, 3] = so3_exp(np.array([0.0, 0.0, 2.0])), [300.0, -120.0, 5.0]
    odom_b = move @ drifted_b
    cov = np.diag([0.05**2] * 3 + [math.radians(0.5) ** 2] * 3)
    g = PoseGraphBackend(BackendConfig(keyframes=KeyframeRule(distance=0.0, angle_deg=0.0, interval=0.0)))  # each
    for i, pose in enumerate(odom_a):
        g.add_odometry(1000.0 + i, pose, session="a")
    after: list[float] = []
    anchored_at = None
    for i, pose in enumerate(odom_b):
        g.add_odometry(9000.0 + i, pose, session="b")
        if i % args.every or i == 0:
            continue
        j = int(np.argmin(np.linalg.norm(truth[:, :3, 3] - truth_b[i, :3, 3], axis=1)))
        rel = np.linalg.inv(truth[j]) @ truth_b[i]
        was = g.anchored("b")
        tic = time.perf_counter()
        g.add_loop(9000.0 + i, 1000.0 + j, rel, cov, query_session="b", match_session="a")
        took = time.perf_counter() - tic
        if was:
            after.append(took)
        elif g.anchored("b"):
            anchored_at = i
    stats = g.stats()
    ms = np.array(after) * 1e3
    result = {"cpu": cpu_model(), "cores": os.cpu_count(), "nodes_per_session": args.nodes,
              "anchored_at_node": anchored_at, "anchor_solve_s": stats.last_anchor_s, "loops_after": len(ms),
              "add_loop_ms_p50": float(np.median(ms)) if len(ms) else None,
              "add_loop_ms_p95": float(np.percentile(ms, 95)) if len(ms) else None,
              "inter_session": stats.inter_session}
    print(f"CPU: {result['cpu']}, {result['cores']} cores; {stats.nodes} graph nodes in two sessions")
    print(f"anchored at node {anchored_at} of b; anchoring solve {stats.last_anchor_s:.3f} s")
    print(f"add_loop after anchoring ({len(ms)} loops): p50 {np.median(ms):.1f} ms, p95 "
          f"{np.percentile(ms, 95):.1f} ms")
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "backend_sessions_cost.json").write_text(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
