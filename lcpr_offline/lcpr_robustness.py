"""LCPR's robustness conditions (the paper's Table III, Fig. 5, Fig. 6): how a query keyframe is perturbed.

The database keyframes are described as recorded; only the query keyframes (the paper's
database/query split, positives within 9 m) are perturbed, one condition at a time:

- yaw: the vehicle turned by k camera slots: the six images rolled by k slots together with the
  cloud rotated by the same angle (nuScenes camera yaws: 55, 110, 180, 250, 305, 360 deg);
- occlusion: each camera blacked out in turn (a zero slot, as a camera that stopped sending), all
  six at once (the LiDAR alone: what the images add), and
  a quarter of the LiDAR range image set to no return: its columns (a 90 deg sector, the full
  height), or its top or bottom quarter of rows (all the way round; the paper's "one quarter
  along the height dimension" reads either way, so both are reported);
- lighting: every query image's brightness scaled (PIL ImageEnhance.Brightness).

:func:`study_city` gives Recall@1 per condition on one rendered city, :func:`plot` draws them.
The study itself is ``benchmarks/studies/lcpr_robustness.py``.
"""
from __future__ import annotations

import argparse
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from PIL import ImageEnhance

from citysim import SynthConfig, SyntheticDrive
from lcpr_common.progress import progress_iter
from lcpr_core.atomic import save_figure
from lcpr_core.evaluation import database_query_protocol, ground_truth
from lcpr_core.lcpr.describer import Describer
from lcpr_core.lcpr.preprocess.camera import CameraInput, to_pil
from lcpr_core.lcpr.preprocess.turn import SLOT_YAWS_DEG, slot_yaw_deg, turn_frame
from lcpr_core.lcpr.training.augment import LIDAR_QUARTERS, lidar_quarter, occlude_lidar
from msg_tools.frames import NUSCENES_CAMERAS

TURNS = range(1, len(SLOT_YAWS_DEG) + 2)  # k = 1..6 camera slots: 55 .. 305 deg and the full turn
BRIGHTNESS = (0.3, 0.5, 0.7, 1.0, 1.3, 1.6)


@dataclass
class Keyframe:
    """One keyframe as recorded: camera images, LiDAR cloud and where it was taken."""

    stamp: float
    images: list[CameraInput | None]
    points: np.ndarray  # N x 3, LiDAR frame
    position: np.ndarray  # (3,)


Perturb = Callable[[Describer, Keyframe], np.ndarray]


def render(route: str, seed: int, frames: int, image_size: tuple[int, int]) -> list[Keyframe]:
    """The keyframes of a synthetic nuScenes-rig city (no camera drops: the study blacks cameras out itself)."""
    drive = SyntheticDrive(SynthConfig(rig="nuscenes", route=route, frames=frames, seed=seed, image_size=image_size,
                                       camera_drop=0.0))
    out = []
    for i in progress_iter(range(len(drive)), total=len(drive), unit="frame", desc=f"render {route}:{seed}"):
        frame = drive.frame(i)
        images: list[CameraInput | None] = [None if c is None else (c.jpeg if c.jpeg is not None else c.rgb)
                                           for c in frame.cameras]
        assert frame.pose is not None
        out.append(Keyframe(frame.stamp, images, frame.xyz, frame.pose[:3, 3].copy()))
    return out


def turned(k: int) -> Perturb:
    """The vehicle turned left by k slots: slot j now shows what slot j - k showed; the cloud turns the other way."""
    def describe(describer: Describer, kf: Keyframe) -> np.ndarray:
        return describer.describe(*turn_frame(kf.images, kf.points, k))
    return describe


def camera_out(index: int | None) -> Perturb:
    """Camera ``index`` sends nothing; None: none of them does (the LiDAR alone)."""
    def describe(describer: Describer, kf: Keyframe) -> np.ndarray:
        images = [None if index is None or i == index else im for i, im in enumerate(kf.images)]
        return describer.describe(images, kf.points)
    return describe


def lidar_quarter_out(part: str) -> Perturb:
    """A quarter of the range image set to no return: one of training's :data:`LIDAR_QUARTERS` (the sector from
    column 0); an unknown part is refused here, when the condition is built."""
    lidar_quarter(part)

    def describe(describer: Describer, kf: Keyframe) -> np.ndarray:
        cams, ranges = describer.inputs(kf.images, kf.points)  # 1 x 1 x h x w
        return describer.describe_tensors(cams, torch.from_numpy(occlude_lidar(ranges.numpy(), part)))[0]
    return describe


def brightness(factor: float) -> Perturb:
    def describe(describer: Describer, kf: Keyframe) -> np.ndarray:
        images: list[CameraInput | None] = [
            None if im is None else ImageEnhance.Brightness(to_pil(im).convert("RGB")).enhance(factor)
            for im in kf.images]
        return describer.describe(images, kf.points)
    return describe


def conditions() -> dict[str, dict[str, Perturb | None]]:
    """Study -> condition -> how a query is described (None: as recorded)."""
    return {
        "yaw": {f"{slot_yaw_deg(k):g}": (None if k == TURNS[-1] else turned(k)) for k in TURNS},
        "occlusion": {"none": None, **{f"{name} out": camera_out(i) for i, name in enumerate(NUSCENES_CAMERAS)},
                      "all cameras out": camera_out(None),
                      **{f"LiDAR 1/4 {part} out": lidar_quarter_out(part) for part in LIDAR_QUARTERS}},
        "lighting": {f"{f:g}": (None if f == 1.0 else brightness(f)) for f in BRIGHTNESS},
    }


STUDIES = ("yaw", "occlusion", "lighting")


def study_city(describer: Describer, keyframes: list[Keyframe], *, name: str,
               studies: Sequence[str] = STUDIES) -> dict[str, dict[str, float]]:
    """Study -> condition -> Recall@1 of one city (database/query protocol, positives within 9 m)."""
    stamps = np.array([kf.stamp for kf in keyframes])
    gt = ground_truth(stamps, np.stack([kf.position for kf in keyframes]), radius=9.0, exclude_recent_s=30.0)
    base = np.stack([describer.describe(kf.images, kf.points)
                     for kf in progress_iter(keyframes, total=len(keyframes), unit="kf", desc=f"{name}: describe")])
    queries = gt.queries
    print(f"{name}: {len(keyframes)} keyframes, {len(gt.database)} database, {len(queries)} queries", flush=True)
    out: dict[str, dict[str, float]] = {}
    for study, conds in conditions().items():
        if study not in studies:
            continue
        out[study] = {}
        for label, perturb in conds.items():
            desc = base.copy()
            if perturb is not None:
                for q in progress_iter(queries.tolist(), total=len(queries), unit="q", desc=f"{name}: {label}"):
                    desc[q] = perturb(describer, keyframes[q])
            result = database_query_protocol(gt, descriptors=desc)
            assert result is not None, f"{name} has no revisit"
            out[study][label] = float(result.recall_at[1])
            print(f"  {study:9s} {label:>20s}: Recall@1 {out[study][label]:.3f}", flush=True)
    return out


def plot(results: dict[str, dict[str, dict[str, float]]], path: Path, *, weights: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(16, 4.5))
    for city, studies in results.items():
        yaw = studies.get("yaw", {})
        axes[0].plot([float(k) for k in yaw], list(yaw.values()), marker="o", label=city)
        light = studies.get("lighting", {})
        axes[2].plot([float(k) for k in light], list(light.values()), marker="o", label=city)
    occl_labels = list(next(iter(results.values())).get("occlusion", {}))
    width = 0.8 / max(len(results), 1)
    for j, (city, studies) in enumerate(results.items()):
        axes[1].bar(np.arange(len(occl_labels)) + j * width, [studies["occlusion"][k] for k in occl_labels],
                    width=width, label=city)
    axes[1].set_xticks(np.arange(len(occl_labels)) + width * (len(results) - 1) / 2)
    axes[1].set_xticklabels([k.replace(" out", "").replace("CAM_", "") for k in occl_labels], rotation=45, ha="right",
                            fontsize=8)
    for ax, title, xlabel in zip(axes, ("yaw of the query (Fig. 6)", "occlusion (Table III)", "brightness (Fig. 5)"),
                                 ("vehicle turned (deg)", "", "brightness factor"), strict=True):
        ax.set_title(title)
        ax.set_xlabel(xlabel)
        ax.set_ylabel("Recall@1")
        ax.set_ylim(0, 1)
        ax.grid(alpha=0.3)
        if ax.has_data():
            ax.legend(fontsize=8)
    fig.suptitle(f"LCPR ({weights}), synthetic cities {', '.join(results)}: only the queries perturbed")
    save_figure(fig, path, dpi=100)
    plt.close(fig)


def parse_city(text: str) -> tuple[str, int, int | None]:
    """``ROUTE:SEED[:FRAMES]`` -> (route, seed, keyframes or None for ``--frames``)."""
    route, _, spec = text.partition(":")
    seed, *rest = spec.split(":")
    if route not in ("grid", "kitti00") or not seed.isdigit() or len(rest) > 1 or not all(r.isdigit() for r in rest):
        raise argparse.ArgumentTypeError(f"city {text!r}; expected ROUTE:SEED[:FRAMES] with ROUTE grid or kitti00, "
                                         "e.g. grid:7 or kitti00:21:900")
    return route, int(seed), (int(rest[0]) if rest else None)
