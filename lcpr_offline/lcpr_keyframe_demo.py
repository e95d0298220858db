"""Descriptor demo on a real nuScenes keyframe: describe it, time it, show its yaw robustness.

    lcpr_demo [--data DIR] [--weights FILE] [--out DIR]
"""
from __future__ import annotations

import argparse
import dataclasses
import logging
import sys
from pathlib import Path

import numpy as np
import torch

from lcpr_common.shared_data import shared_path
from lcpr_core.lcpr.describer import Describer, ModelConfig
from lcpr_core.lcpr.preprocess import NUSCENES_CAMERAS, range_image
from lcpr_core.lcpr.preprocess.dataset_files import find_nuscenes_keyframe
from lcpr_core.lcpr.preprocess.turn import turn_frame
from lcpr_core.points import rotate_z
from lcpr_core.pretrained import SEEDED, command_weights, describe_weights
from lcpr_core.timing import median_seconds

log = logging.getLogger("lcpr_demo")


def default_data_dir() -> Path:
    """../shared/data/nuscenes_sample (see lcpr_common.shared_data for where ../shared is looked for)."""
    return shared_path("data", "nuscenes_sample")


def cosine(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.dot(a.astype(np.float64), b) / (np.linalg.norm(a) * np.linalg.norm(b)))


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, default=None, help="folder with one nuScenes keyframe")
    parser.add_argument("--weights", default="",
                        help="LCPR checkpoint or state dict (default: the bundled trained weights)")
    parser.add_argument("--seeded", action="store_true", help="random weights (testing only), as --weights seeded")
    parser.add_argument("--imagenet", default="", help="torchvision resnet18 state dict for initialisation")
    parser.add_argument("--seed", type=int, default=0, help="seed of the random initialisation")
    parser.add_argument("--threads", type=int, default=2, help="torch threads (default 2)")
    parser.add_argument("--repeats", type=int, default=5, help="timed runs per measurement")
    parser.add_argument("--out", type=Path, default=Path("out"), help="where the figure is written")
    return parser.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s", stream=sys.stdout)
    data = args.data or default_data_dir()
    try:
        files = find_nuscenes_keyframe(data)
    except FileNotFoundError as err:
        print(f"lcpr_demo: {err}; pass --data DIR", file=sys.stderr)
        return 2
    images, points = files.read()
    weights = SEEDED if args.seeded else command_weights(args.weights, imagenet=args.imagenet)
    config = ModelConfig(weights=weights, imagenet=args.imagenet, seed=args.seed, threads=args.threads)
    fp32 = Describer(config)
    bf16 = Describer(dataclasses.replace(config, precision="bf16"), model=fp32.model)
    pil = Describer(dataclasses.replace(config, decode="pil"), model=fp32.model)  # the released pipeline
    loaded = fp32.config.weights
    described = (describe_weights(loaded) if loaded or not args.imagenet
                 else f"ImageNet ResNet blocks from {args.imagenet}, the rest random: NOT a trained model")

    print(f"\nLCPR descriptor demo on {data}")
    print(f"  weights: {described}")
    print(f"  cloud: {len(points)} points; cameras: {', '.join(NUSCENES_CAMERAS)} ({len(images)} JPEGs)")

    cams, ranges = fp32.inputs(images, points)
    desc = fp32.describe_tensors(cams, ranges)[0]
    print(f"\nDescriptor: {desc.shape[0]}-d, finite: {bool(np.isfinite(desc).all())}, "
          f"norm {np.linalg.norm(desc):.6f}, filled range pixels {(ranges > 0).float().mean().item():.1%}")

    r = args.repeats
    t_cam = median_seconds(lambda: fp32.inputs(images, points), repeats=r)
    t_cam_pil = median_seconds(lambda: pil.inputs(images, points), repeats=r)
    t_rng = median_seconds(lambda: range_image(points), repeats=r)
    t_fp32 = median_seconds(lambda: fp32.describe_tensors(cams, ranges), repeats=r)
    t_bf16 = median_seconds(lambda: bf16.describe_tensors(cams, ranges), repeats=r)
    print(f"\nTimes (median of {r}, {torch.get_num_threads()} threads):")
    print(f"  preprocessing (6 JPEG decodes + resize + range image): {t_cam * 1e3:7.1f} ms, decoder "
          f"{fp32.cameras.decoder} (PIL, the released pipeline: {t_cam_pil * 1e3:.1f} ms); range image alone "
          f"{t_rng * 1e3:.1f} ms")
    print(f"  network fp32: {t_fp32 * 1e3:7.1f} ms    bf16 (autocast): {t_bf16 * 1e3:7.1f} ms")

    changes = yaw_and_degradation(fp32, images, points, desc)
    changes["bf16 instead of fp32"] = bf16.describe_tensors(cams, ranges)[0]
    changes[f"decoder {fp32.cameras.decoder} instead of PIL (the released pipeline)"] = pil.describe(images, points)
    print("\nHow far the descriptor moves (1 - cosine; 0 = unchanged):")
    for label, other in changes.items():
        print(f"  {label:<68} {max(0.0, 1.0 - cosine(desc, other)):.2e}")

    figure = args.out / "demo_keyframe.png"
    plot_inputs(cams[0], ranges[0, 0], figure)
    print(f"\nFigure of the network inputs: {figure}")
    if not loaded:
        print("Note: with random weights the similarities show the network's structure (yaw invariance), "
              "not place recognition; drop --seeded for the trained weights.")
    return 0


def yaw_and_degradation(
    describer: Describer, images: list[bytes], points: np.ndarray, desc: np.ndarray
) -> dict[str, np.ndarray]:
    """Descriptors of the keyframe seen turned, degraded, and (for contrast) from 10 m away."""
    slot_deg = 360.0 / len(images)
    rolled = images[-1:] + images[:-1]  # the vehicle turned left by one camera slot
    moved = points.copy()
    moved[:, 1] -= 10.0  # LIDAR_TOP y is forward: the vehicle 10 m further on
    return {
        f"vehicle turned {slot_deg:.0f} deg (cloud rotated, cameras rolled a slot)":
            describer.describe(rolled, rotate_z(points, -slot_deg)),
        "vehicle turned 55 deg (nuScenes camera spacing; not a pixel shift)":
            describer.describe(*turn_frame(images, points, 1)),
        "CAM_FRONT blacked out (a camera that stopped sending)": describer.describe([None, *images[1:]], points),
        "for contrast: the cloud seen from 10 m further on": describer.describe(images, moved),
    }


def plot_inputs(cams: torch.Tensor, ranges: torch.Tensor, path: Path) -> None:
    """The six normalised camera inputs as a panorama strip above the range image."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from lcpr_core.atomic import save_figure
    from lcpr_core.lcpr.preprocess import IMAGENET_MEAN, IMAGENET_STD

    mean, std = torch.tensor(IMAGENET_MEAN).view(3, 1, 1), torch.tensor(IMAGENET_STD).view(3, 1, 1)
    strip = torch.cat([(c * std + mean).clamp(0, 1) for c in cams], dim=2).permute(1, 2, 0).numpy()
    fig, (top, bottom) = plt.subplots(2, 1, figsize=(16, 4.5), height_ratios=[1.5, 1])
    top.imshow(strip)
    top.set_title(" | ".join(NUSCENES_CAMERAS), fontsize=9)
    top.axis("off")
    shown = np.ma.masked_less(ranges.numpy(), 0)
    im = bottom.imshow(shown, cmap="turbo", aspect="auto", interpolation="nearest")
    bottom.set_title("range image (m), blank = no return")
    fig.colorbar(im, ax=bottom, fraction=0.02)
    save_figure(fig, path, dpi=90)
    plt.close(fig)


if __name__ == "__main__":
    sys.exit(main())
