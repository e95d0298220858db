"""small_gicp (what the verifier uses) against kiss-icp's registration, on the same pairs and starts.

    python benchmarks/tools/registration_compare.py [--pairs 60] [--out out/registration_compare]

Pairs: true revisits of a synthetic nuScenes-rig drive (city seed 3, exact ground truth)
and of ``livox_hku/walk_loop`` (ground truth: its odometry poses, see verify_real.py). kiss-icp comes with
the ``compare`` extra (``pip install -e .[compare]``).
Both libraries refine the same compact clouds from the same start: the true relative
pose perturbed by a seeded offset (up to 1.5 m and 15 deg of yaw). Reported per library:
the share of pairs that end within 0.3 m / 2 deg, the median error of those, and the median
time of one registration (this CPU, 1 thread each). small_gicp runs GICP coarse (2 m voxels,
3 m correspondences) then fine (the compact cloud, 1 m), as the verifier does; kiss-icp
aligns the query points to a voxel hash map of the match (0.5 m voxels, 20 points each)
with its robust point-to-point ICP, coarse (3 m, kernel 1 m) then fine (1 m, kernel 0.3 m).
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from lcpr_common.cli import tool_main

if TYPE_CHECKING:  # the package (and torch with it) is imported after the arguments are read
    from lcpr_core.verification import GeometricVerifier, PreparedCloud
    from lcpr_offline.verification_pairs import Scans

OK_M, OK_DEG = 0.3, 2.0


def perturb(T: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    yaw = math.radians(rng.uniform(-15, 15))
    c, s = math.cos(yaw), math.sin(yaw)
    D = np.eye(4)
    D[:2, :2] = [[c, -s], [s, c]]
    D[:2, 3] = rng.uniform(-1.5, 1.5, 2) / math.sqrt(2)
    out = D @ T
    u, _, vt = np.linalg.svd(out[:3, :3])  # pose files carry ~1e-6 of non-orthogonality; Sophus refuses it
    out[:3, :3] = u @ vt
    return out


def small_gicp_register(verifier: GeometricVerifier, q: PreparedCloud, m: PreparedCloud, start: np.ndarray
                        ) -> np.ndarray:
    _, T, _ = verifier._coarse(q, m, start)
    return verifier._fine(q, m, T, start).T


def kiss_register(q_xyz: np.ndarray, m_xyz: np.ndarray, start: np.ndarray) -> np.ndarray:
    from kiss_icp.mapping import VoxelHashMap
    from kiss_icp.registration import Registration

    voxel_map = VoxelHashMap(voxel_size=0.5, max_distance=200.0, max_points_per_voxel=20)
    voxel_map.add_points(np.ascontiguousarray(m_xyz, np.float64))
    reg = Registration(max_num_iterations=100, convergence_criterion=1e-4, max_num_threads=1)
    points = np.ascontiguousarray(q_xyz, np.float64)
    T = reg.align_points_to_map(points, voxel_map, start, max_correspondance_distance=3.0, kernel=1.0)
    return reg.align_points_to_map(points, voxel_map, T, max_correspondance_distance=1.0, kernel=0.3)


def compare(name: str, seq: Scans, truth_poses: np.ndarray, pairs: np.ndarray, verifier: GeometricVerifier,
            seed: int) -> dict[str, dict[str, float | None]]:
    """Both libraries on every pair from the same perturbed start: share within 0.3 m / 2 deg, errors, time."""
    from tqdm import tqdm

    from lcpr_offline.verification_pairs import PreparedScans, pose_error

    rng = np.random.default_rng(seed)
    prepared = PreparedScans(verifier, seq)
    rows: dict[str, list[tuple[float, float, float]]] = {"small_gicp": [], "kiss-icp": []}
    for q, m in tqdm(pairs, desc=name, unit="pair"):
        Q, M = prepared[q], prepared[m]
        truth = np.linalg.inv(truth_poses[m]) @ truth_poses[q]
        start = perturb(truth, rng)
        for lib, run in (("small_gicp", lambda Q=Q, M=M, start=start: small_gicp_register(verifier, Q, M, start)),
                         ("kiss-icp", lambda Q=Q, M=M, start=start: kiss_register(Q.xyz, M.xyz, start))):
            tic = time.perf_counter()
            T = run()
            seconds = time.perf_counter() - tic
            err_m, err_deg = pose_error(T, truth)
            rows[lib].append((err_m, err_deg, seconds))
    out = {}
    for lib, r in rows.items():
        a = np.array(r)
        ok = (a[:, 0] <= OK_M) & (a[:, 1] <= OK_DEG)
        out[lib] = {"pairs": len(a), "within_0.3m_2deg": float(ok.mean()),
                    "median_err_m_of_those": float(np.median(a[ok, 0])) if ok.any() else None,
                    "median_err_deg_of_those": float(np.median(a[ok, 1])) if ok.any() else None,
                    "median_ms": float(np.median(a[:, 2]) * 1000)}
        print(f"  {name:22s} {lib:10s} {json.dumps(out[lib])}")
    return out


@tool_main
def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", type=Path, default=None, help="the livox_hku folder (default: ../shared/data/livox_hku)")
    p.add_argument("--pairs", type=int, default=60, help="pairs per data set (evenly spaced)")
    p.add_argument("--out", type=Path, default=Path("out/registration_compare"))
    args = p.parse_args(argv)

    from lcpr_common.shared_data import shared_path
    from lcpr_core.revisits import revisit_pairs
    from lcpr_core.timing import cpu_model
    from lcpr_core.verification import GeometricVerifier
    from lcpr_offline.verification_pairs import SyntheticLidar, true_pairs
    from msg_tools.convert.scan_folder import ScanFolder

    data = args.data or shared_path("data", "livox_hku")
    print(f"CPU: {cpu_model()}")
    verifier = GeometricVerifier()
    results = {}
    syn = SyntheticLidar("nuscenes", 3, 160)
    pairs = revisit_pairs(syn.poses[:, :3, 3], syn.stamps, radius=9.0, min_time_gap=30.0)
    pairs = pairs[np.linspace(0, len(pairs) - 1, min(args.pairs, len(pairs))).round().astype(np.int64)]
    results["synthetic"] = compare("synthetic seed 3", syn, syn.poses, pairs, verifier, 0)
    walk = ScanFolder(data / "walk_loop")
    odom = ScanFolder(data / "walk_loop", poses_file="odom_poses.txt")
    pairs = true_pairs(walk)
    pairs = pairs[np.linspace(0, len(pairs) - 1, min(args.pairs, len(pairs))).round().astype(np.int64)]
    results["walk_loop"] = compare("livox walk_loop", walk, odom.poses, pairs, verifier, 1)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "results.json").write_text(json.dumps(results, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
