"""One keyframe, stage by stage: six nuScenes JPEGs + a LiDAR sweep -> a descriptor, on the CPU and the GPU.

    python benchmarks/tools/keyframe_pipeline.py [--data DIR ...] [--devices cpu cuda] [--repeats 20] [--out DIR]
                                                 [--preprocessing-only]

For each device (``cuda`` only where torch sees one) and each network (the released size with
seeded weights, one pass; the bundled weights, whitened and averaged over six turns), prints the
median milliseconds of each stage as the Describer runs it:

- preprocessing: ``Describer.prepare``, the six images and the sweep to the network's inputs (on the CPU the
  pool threads work on the images while the calling thread makes the range image);
- decode, resize + normalise: on the CPU (turbo) each pool thread decodes, resizes and normalises one image
  into its slot, so these stages overlap and are given as thread CPU time per keyframe (``cpu ms``), beside
  the wall time of all six cameras together; on a GPU (nvjpeg) each stage's wall time: the six JPEGs to
  pixels, then pixels to the N x 3 x H x W input on the GPU;
- range image: the sweep to the h x w range image (on the GPU there);
- network: the forward pass(es) in the path ``precision: auto`` chose (named; with the bundled weights on the
  CPU the six turns share the camera stem, :class:`lcpr_core.lcpr.turn_average.TurnedNetwork`);
- post-processing: whitening and turn averaging;
- end to end: ``Describer.describe`` on the raw frame (decode to descriptor).

The CPU figures also give the process CPU time of one preprocessing (all threads) and the load average
before and after, since wall times on a shared machine follow its load.
Beside them, on the CPU, the released PIL pipeline's preprocessing in the same run (and the speed-up),
and on every device the descriptor's cosine to the reference path (PIL decode, exact fp32 on the
CPU). Real keyframes: ../shared/data/nuscenes_sample and nuscenes_sample2 by default. Every
figure names the CPU and GPU it was measured on; ``--out`` also writes them as JSON.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
from collections.abc import Callable
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from lcpr_common.cli import tool_main

if TYPE_CHECKING:  # torch and the package are imported after the arguments are read
    import torch

    from lcpr_core import Describer, ModelConfig

NETWORKS = ("released", "bundled")


def median_ms(fn: Callable[[], object], *, device: torch.device, repeats: int, warmup: int = 2) -> float:
    """Median wall time of ``fn()`` in ms, the GPU drained before each clock read."""
    import torch

    from lcpr_core.timing import median_seconds

    def run() -> None:
        fn()
        if device.type == "cuda":
            torch.cuda.synchronize(device)

    return 1000 * median_seconds(run, repeats=repeats, warmup=warmup)


def network_config(network: str, device: str) -> ModelConfig:
    """The released size with seeded weights, or the bundled weights (whitened, turn-averaged)."""
    from lcpr_core import ModelConfig
    from lcpr_core.pretrained import default_weights

    if network == "released":
        return ModelConfig(device=device)  # 256 x 704 images, 32 x 1056 range image, width 1.0
    weights = default_weights()
    if weights is None:
        raise SystemExit("keyframe_pipeline: the bundled weights are not installed (weights/*.pth)")
    return ModelConfig(weights=str(weights), device=device)


def stages(describer: Describer, images: list[bytes], points: np.ndarray, *, repeats: int,
           network: bool = True) -> tuple[dict[str, float], dict[str, float]]:
    """Median wall ms of each stage of one keyframe, and on the CPU median thread CPU ms per stage (module doc)."""
    import torch

    from lcpr_core.lcpr.turn_average import average_turns

    device = torch.device(describer.config.device)
    cams = describer.cameras
    timed: dict[str, float] = {}
    cpu: dict[str, float] = {}
    timed["preprocessing"] = median_ms(lambda: describer.prepare(images, points), device=device, repeats=repeats)
    if device.type == "cpu" and cams.decoder == "turbo":
        timed["cameras"] = median_ms(lambda: cams(images), device=device, repeats=repeats)
        cpu = preprocessing_cpu_ms(describer, images, points, repeats=repeats)
    elif device.type == "cpu":  # pil: one image after another on this thread
        timed["cameras"] = median_ms(lambda: cams(images), device=device, repeats=repeats)
    else:
        timed["decode"] = median_ms(lambda: cams.decode(images), device=device, repeats=repeats)
        pixels, _ = cams.decode(images)
        timed["resize + normalise"] = median_ms(lambda: cams.assemble(pixels, len(images)), device=device,
                                                repeats=repeats)
    timed["range image"] = median_ms(lambda: describer.range_tensor(points), device=device, repeats=repeats)
    if not network:
        return timed, cpu
    prepared = describer.prepare(images, points)
    batch = (prepared.images, prepared.ranges)
    timed["network"] = median_ms(lambda: describer.network_outputs(*batch), device=device, repeats=repeats)
    raw = describer.network_outputs(*batch)

    def post() -> np.ndarray:
        out = describer.postprocess(raw)
        return average_turns(out, 1) if describer.turn_average else out

    timed["post-processing"] = median_ms(post, device=device, repeats=repeats)
    timed["end to end"] = median_ms(lambda: describer.describe(images, points), device=device, repeats=repeats)
    return timed, cpu


def preprocessing_cpu_ms(describer: Describer, images: list[bytes], points: np.ndarray, *, repeats: int
                         ) -> dict[str, float]:
    """Median CPU ms per keyframe: decode and resize + normalise summed over the pool threads' images, the
    range image on the calling thread, and the whole process during one ``prepare`` (all threads)."""
    import time

    cams = describer.cameras
    rows: list[dict[str, float]] = []
    for _ in range(repeats):
        cams.profile = []
        t_process = time.process_time()
        t_thread = time.thread_time()
        describer.range_tensor(points)
        range_cpu = time.thread_time() - t_thread
        describer.prepare(images, points)
        row = {"range image": range_cpu, "process (one prepare)": time.process_time() - t_process - range_cpu}
        for stage, seconds in cams.profile:
            row[stage] = row.get(stage, 0.0) + seconds
        rows.append(row)
    cams.profile = None
    return {k: 1000 * float(np.median([r.get(k, 0.0) for r in rows])) for k in rows[0]}


@tool_main
def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", type=Path, nargs="+", default=None, help="folders each holding one nuScenes keyframe")
    p.add_argument("--devices", nargs="+", default=None, help="default: cpu, and cuda where torch sees a GPU")
    p.add_argument("--networks", nargs="+", choices=NETWORKS, default=list(NETWORKS))
    p.add_argument("--repeats", type=int, default=20)
    p.add_argument("--out", type=Path, default=None, help="write the figures as JSON here")
    p.add_argument("--preprocessing-only", action="store_true",
                   help="time only the preprocessing stages (exact fp32 network, no precision measurement, no "
                        "network or descriptor figures): a minute where the whole run takes several")
    args = p.parse_args(argv)

    import torch

    from lcpr_common.shared_data import shared_path
    from lcpr_core import Describer
    from lcpr_core.atomic import write_bytes_atomic
    from lcpr_core.lcpr.preprocess.dataset_files import find_nuscenes_keyframe
    from lcpr_core.lcpr.preprocess.decode import jpeg_backend
    from lcpr_core.lcpr.runtime.cuda import gpu_name
    from lcpr_core.timing import cpu_model
    from lcpr_offline.lcpr_keyframe_demo import cosine

    folders = args.data or [shared_path("data", "nuscenes_sample"), shared_path("data", "nuscenes_sample2")]
    devices = args.devices or (["cpu", "cuda"] if torch.cuda.is_available() else ["cpu"])
    frames = [find_nuscenes_keyframe(folder).read() for folder in folders]
    print(f"CPU: {cpu_model()}, {torch.get_num_threads()} torch threads; torch {torch.__version__}; "
          f"load average {os.getloadavg()[0]:.2f}; JPEG decoder {jpeg_backend()}")
    for device in devices:
        if device.startswith("cuda"):
            print(f"GPU ({device}): {gpu_name(device)}")
    results: list[dict[str, Any]] = []
    for network in args.networks:
        reference = Describer(dataclasses.replace(network_config(network, "cpu"), decode="pil", precision="fp32"))
        expected = [None if args.preprocessing_only else reference.describe(images, points)
                    for images, points in frames]
        for device in devices:
            config = network_config(network, device)
            if args.preprocessing_only:
                config = dataclasses.replace(config, precision="fp32")
            describer = Describer(config)
            cfg = describer.config
            print(f"\n{network} network ({cfg.image_size[0]}x{cfg.image_size[1]} images, width {cfg.width:g}"
                  f"{', six turns' if describer.turn_average else ''}) on {device}: precision {describer.path}, "
                  f"decoder {describer.cameras.decoder}; median of {args.repeats} (ms)")
            if describer.choice.ms:  # what precision auto measured at start
                print(f"  auto: {describer.choice.summary()}")
            for (images, points), folder, want in zip(frames, folders, expected, strict=True):
                timed, cpu = stages(describer, images, points, repeats=args.repeats,
                                    network=not args.preprocessing_only)
                row: dict[str, Any] = {"network": network, "device": device, "keyframe": Path(folder).name,
                                       "precision": describer.path, "decoder": describer.cameras.decoder,
                                       "ms": timed, "cpu_ms": cpu, "load_average": os.getloadavg()[0],
                                       "cosine_to_reference": None if want is None else
                                       cosine(describer.describe(images, points), want)}
                name = Path(folder).name
                line = "  ".join(f"{k} {v:.2f}" for k, v in timed.items())
                if want is not None:
                    line += f"  | cosine to the PIL + exact fp32 CPU path {row['cosine_to_reference']:.7f}"
                print(f"  {name}: {line}")
                if cpu:
                    print(f"  {'':{len(name)}}  cpu ms: " + "  ".join(f"{k} {v:.2f}" for k, v in cpu.items()))
                if device == "cpu":
                    pil = Describer(dataclasses.replace(cfg, decode="pil"), model=describer.model)
                    ms = median_ms(partial(pil.prepare, images, points), device=torch.device("cpu"),
                                   repeats=max(5, args.repeats // 4))
                    fast = timed["preprocessing"]
                    row["pil_preprocessing_ms"] = ms
                    print(f"  {'':{len(name)}}  preprocessing {fast:.2f} (PIL, the released pipeline, "
                          f"{ms:.2f}: {ms / fast:.1f}x); load average {row['load_average']:.2f}")
                results.append(row)
    if args.out:
        args.out.mkdir(parents=True, exist_ok=True)
        meta = {"cpu": cpu_model(), "threads": torch.get_num_threads(), "torch": torch.__version__,
                "jpeg_decoder": jpeg_backend(), "load_average_end": os.getloadavg()[0],
                "gpu": gpu_name("cuda") if torch.cuda.is_available() else None}
        write_bytes_atomic(args.out / "keyframe_pipeline.json",
                           json.dumps({"meta": meta, "rows": results}, indent=1).encode())
    return 0


if __name__ == "__main__":
    sys.exit(main())
