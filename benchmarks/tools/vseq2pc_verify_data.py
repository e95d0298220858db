"""Render a citysim KITTI-rig drive into what VSeq2PC verification is evaluated on (one .npz, no bag).

Per frame: stamp, world_T_base pose, the LiDAR structure feature (12 x 360) and the scan's compact
cloud (what a Vseq2pcMap keeps); per depth variant (the renderer's exact depth, and a depth network's
as citysim makes it: cut at 25 m, smooth relative error of 5 / 10 / 20 %), the camera feature
(12 x 90) and the frame's pseudo-cloud (:func:`lcpr_core.vseq2pc.pseudo_cloud.frame_cloud`). The
variants are made from one exact render with citysim's own depth model and seeds, so a variant equals
what ``citysim.cli --depth-range 25 --depth-noise X`` would publish.

    nice .venv/bin/python benchmarks/tools/vseq2pc_verify_data.py --seed 43 --frames 600 \
        --out out/vseq2pc_verify/val_seed43.npz
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from lcpr_common.cli import tool_main

#: variant name -> (depth range m, 0 = all; relative noise, 1 sigma); 25 m is citysim's DEPTH_RANGE
VARIANTS: dict[str, tuple[float, float]] = {
    "exact": (0.0, 0.0), "net5": (25.0, 0.05), "net10": (25.0, 0.10), "net20": (25.0, 0.20),
}


def render(seed: int, frames: int, variants: list[str]) -> dict[str, np.ndarray]:
    """The drive's frames rendered once (exact depth) and turned into every variant's features and clouds."""
    from tqdm import tqdm

    from citysim.depthnet import estimated_depth
    from citysim.drive import SynthConfig, SyntheticDrive
    from citysim.hashing import rng_for
    from lcpr_core.errors import VerificationError
    from lcpr_core.vseq2pc.preprocess import camera_feature, structure_feature
    from lcpr_core.vseq2pc.pseudo_cloud import frame_cloud
    from lcpr_core.vseq2pc.verify import SequenceVerifyConfig, scan_cloud

    cfg = SynthConfig(rig="kitti", frames=frames, seed=seed, keyframe_spacing=1.5, image_size=(620, 188),
                      depth_range=0.0, depth_noise=0.0)
    drive = SyntheticDrive(cfg)
    cam = drive.rig.cameras[0]
    lidar_T_cam = np.linalg.inv(drive.rig.lidar.base_T_lidar) @ cam.base_T_cam
    K = np.asarray(cam.K, np.float64)
    verify = SequenceVerifyConfig()
    n = len(drive)
    out: dict[str, list[np.ndarray]] = {k: [] for k in ("stamps", "poses", "lidar", "scan_counts", "scan_points")}
    per: dict[str, dict[str, list[np.ndarray]]] = {v: {"camera": [], "valid": [], "counts": [], "points": []}
                                                   for v in variants}
    for frame in tqdm(drive.frames(workers=1), total=n, desc=f"seed {seed}", unit="frame"):
        i = int(frame.extras["index"])  # type: ignore[call-overload]
        labels_pc = np.asarray(frame.cloud["label"])
        xyz = np.stack([frame.cloud[c] for c in ("x", "y", "z")], axis=1).astype(np.float64)
        out["stamps"].append(np.array(frame.stamp))
        out["poses"].append(np.asarray(frame.pose, np.float64))
        out["lidar"].append(structure_feature(xyz, labels_pc))
        cloud = scan_cloud(xyz, verify)
        out["scan_counts"].append(np.array(len(cloud)))
        out["scan_points"].append(np.round(cloud / 0.01).astype(np.int16))
        image = frame.cameras[0]
        for name in variants:
            rng_range, noise = VARIANTS[name]
            slot = per[name]
            if image is None or image.depth is None or image.labels is None:
                slot["camera"].append(np.zeros((12, 90), np.float32))
                slot["valid"].append(np.array(False))
                slot["counts"].append(np.array(0))
                continue
            depth = estimated_depth(image.depth, max_depth=rng_range, noise=noise, rng=rng_for(seed, 41, i, 0))
            slot["camera"].append(camera_feature(depth, image.labels, K, lidar_T_cam))
            slot["valid"].append(np.array(True))
            try:
                pts = frame_cloud(depth, K, lidar_T_cam, labels=image.labels, config=verify.pseudo)
            except VerificationError:
                pts = np.zeros((0, 3), np.float32)
            slot["counts"].append(np.array(len(pts)))
            slot["points"].append(np.round(pts / 0.01).astype(np.int16))
    arrays: dict[str, np.ndarray] = {
        "stamps": np.array(out["stamps"], np.float64), "poses": np.stack(out["poses"]),
        "lidar": np.stack(out["lidar"]).astype(np.float32), "scan_counts": np.array(out["scan_counts"], np.int64),
        "scan_points": np.concatenate(out["scan_points"]), "K": K, "lidar_T_cam": lidar_T_cam,
        "seed": np.array(seed), "variants": np.array(variants),
    }
    for name, slot in per.items():
        arrays[f"{name}_camera"] = np.stack(slot["camera"]).astype(np.float32)
        arrays[f"{name}_valid"] = np.array(slot["valid"], bool)
        arrays[f"{name}_counts"] = np.array(slot["counts"], np.int64)
        arrays[f"{name}_points"] = (np.concatenate(slot["points"]) if slot["points"]
                                    else np.zeros((0, 3), np.int16))
    return arrays


@tool_main
def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--seed", type=int, required=True)
    p.add_argument("--frames", type=int, required=True)
    p.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS))
    p.add_argument("--out", type=Path, required=True)
    args = p.parse_args(argv)
    from lcpr_core.atomic import atomic_path

    tic = time.perf_counter()
    arrays = render(args.seed, args.frames, args.variants)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(args.out) as tmp:
        with open(tmp, "wb") as fh:
            np.savez(fh, **arrays)  # type: ignore[arg-type]
    print(f"{args.out}: {len(arrays['stamps'])} frames, {time.perf_counter() - tic:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
