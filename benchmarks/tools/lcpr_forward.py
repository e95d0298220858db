"""LCPR forward pass on the CPU: median time per frame, FLOPs, GFLOP/s, bf16 agreement.

    python benchmarks/tools/lcpr_forward.py [--threads 2] [--repeats 10] [--batch 1]
    python benchmarks/tools/lcpr_forward.py --paths [--weights FILE]   # every inference path, CPU named

Times ``LCPR().eval()`` called as ``model(images, ranges)`` under
``torch.inference_mode()`` (fp32), and again inside ``torch.autocast("cpu",
dtype=torch.bfloat16)``, next to a straightforward implementation of the same
network (:mod:`lcpr_core.lcpr.models.baseline`) on the same weights and inputs.
"""
from __future__ import annotations

import argparse
import contextlib
import dataclasses
import os
import statistics
import sys
import time
from functools import partial
from typing import TYPE_CHECKING

from lcpr_common.cli import tool_main

if TYPE_CHECKING:  # torch and the package are imported after the arguments are read
    import torch


def bf16() -> contextlib.AbstractContextManager:
    import torch

    return torch.autocast("cpu", dtype=torch.bfloat16)


def matmul_peak(dtype: torch.dtype, n: int = 2048) -> float:
    """Achieved GFLOP/s of one large square matmul: a practical ceiling for this machine."""
    import torch

    from lcpr_core.timing import median_seconds

    a, b = torch.randn(n, n).to(dtype), torch.randn(n, n).to(dtype)
    return 2 * n**3 / median_seconds(lambda: a @ b, repeats=5) / 1e9


def paths(args: argparse.Namespace) -> None:
    """Every inference path of lcpr_core.lcpr.runtime, interleaved, on the released configuration."""
    from lcpr_core import Describer, ModelConfig
    from lcpr_core.lcpr.runtime.choose import cosine, probe_inputs
    from lcpr_core.timing import cpu_flags, cpu_model, median_seconds
    from lcpr_offline.lcpr_quantize import calibration_inputs, quantize

    base = ModelConfig(weights=args.weights or "", threads=args.threads)
    fp32 = Describer(dataclasses.replace(base, precision="fp32"))
    model = fp32.model
    assert model is not None
    describers = {"torch fp32": fp32, "torch bf16": Describer(dataclasses.replace(base, precision="bf16"), model=model),
                  "onnx fp32": Describer(dataclasses.replace(base, precision="onnx"), model=model)}
    calibration = calibration_inputs(fp32, seed=1, frames=args.calibration_frames)
    quantize(fp32, calibration)
    describers["int8"] = Describer(dataclasses.replace(base, precision="int8"), model=model)
    started = time.perf_counter()
    auto = Describer(dataclasses.replace(base, precision="auto"), model=model)
    auto_s = time.perf_counter() - started
    images, ranges = probe_inputs(model, args.batch)
    frames = calibration_inputs(fp32, seed=3, frames=args.cosine_frames)  # a validation city: not calibrated on
    expected = [fp32.describe_tensors(*x) for x in frames]
    times: dict[str, list[float]] = {name: [] for name in describers}
    for _ in range(args.rounds):  # interleaved: a slow minute of the machine hits every path alike
        for name, d in describers.items():
            times[name].append(median_seconds(partial(d.describe_tensors, images, ranges), repeats=args.repeats))
    ref = statistics.median(times["torch fp32"])
    source = args.weights or "seeded weights"
    print(f"LCPR inference paths, {source}, {model.num_cameras} x {model.image_size[0]} x {model.image_size[1]} "
          f"images, {model.range_size[0]} x {model.range_size[1]} range image, width {model.width}, batch "
          f"{args.batch}, {args.threads} threads")
    print(f"CPU: {cpu_model()}, {os.cpu_count()} cores; flags: {cpu_flags()}")
    print(f"median over {args.rounds} interleaved rounds of the median of {args.repeats}; cosine to torch fp32: "
          f"lowest over {len(frames)} synthetic frames of seed 3 (int8 calibrated on seed 1)")
    print(f"{'path':<12} {'ms/frame':>9} {'vs torch fp32':>14} {'cosine':>10}  runtime")
    for name, d in describers.items():
        ms = statistics.median(times[name]) / args.batch * 1e3
        cos = min(cosine(d.describe_tensors(*x), e) for x, e in zip(frames, expected, strict=True))
        print(f"{name:<12} {ms:>9.1f} {ref / statistics.median(times[name]):>13.2f}x {cos:>10.7f}  {d.runtime}")
    print(f"auto chose: {auto.path} in {auto_s:.1f} s ({auto.choice.summary() or 'memo of this process'})")


def forward(args: argparse.Namespace) -> None:
    """The released configuration's forward pass with seeded weights: fp32, bf16 and the straightforward way."""
    import torch
    from torch.utils.flop_counter import FlopCounterMode

    from lcpr_core import LCPR
    from lcpr_core.lcpr.models.baseline import baseline_forward
    from lcpr_core.lcpr.runtime.choose import probe_inputs
    from lcpr_core.timing import median_seconds

    torch.manual_seed(0)
    model = LCPR().eval()
    images, ranges = probe_inputs(model, args.batch)
    b = args.batch

    with torch.inference_mode():
        with FlopCounterMode(display=False) as counter:
            model(images, ranges)
        gflop = counter.get_total_flops() / 1e9 / b
        ours = model(images, ranges)
        with bf16():
            ours_bf16 = model(images, ranges).float()
        rows = [("LCPR fp32", median_seconds(lambda: model(images, ranges), repeats=args.repeats))]
        with bf16():
            rows.append(("LCPR bf16 autocast", median_seconds(lambda: model(images, ranges), repeats=args.repeats)))
        if not args.skip_baseline:
            base = baseline_forward(model, images, ranges)
            rows.append(("straightforward fp32", median_seconds(lambda: baseline_forward(model, images, ranges),
                                                               repeats=args.repeats)))
    print(f"LCPR forward, released configuration ({model.num_cameras} x 3 x {model.image_size[0]} x "
          f"{model.image_size[1]} images, 1 x {model.range_size[0]} x {model.range_size[1]} range image), "
          f"batch {b}, {torch.get_num_threads()} threads, median of {args.repeats}")
    print(f"FLOPs per frame: {gflop:.1f} GFLOP (multiply-add = 2, counted by torch.utils.flop_counter)")
    peak32, peak16 = matmul_peak(torch.float32), matmul_peak(torch.bfloat16)
    print(f"machine ceiling (2048^2 matmul): fp32 {peak32:.0f} GFLOP/s, bf16 {peak16:.0f} GFLOP/s "
          f"-> {gflop / peak32 * 1e3:.0f} ms / {gflop / peak16 * 1e3:.0f} ms per frame at best")
    print(f"{'variant':<22} {'ms/frame':>10} {'GFLOP/s':>9}")
    for name, seconds in rows:
        print(f"{name:<22} {seconds / b * 1e3:>10.1f} {gflop * b / seconds:>9.1f}")
    cos = torch.nn.functional.cosine_similarity(ours, ours_bf16).min().item()
    print(f"bf16 vs fp32 cosine (min over batch): {cos:.6f}")
    if not args.skip_baseline:
        base_ms = rows[2][1]
        print(f"max |LCPR fp32 - straightforward fp32|: {(ours - base).abs().max().item():.2e}")
        print(f"speed-up over straightforward fp32: fp32 {base_ms / rows[0][1]:.2f}x, bf16 {base_ms / rows[1][1]:.2f}x")



@tool_main
def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=10)
    parser.add_argument("--batch", type=int, default=1)
    parser.add_argument("--skip-baseline", action="store_true")
    parser.add_argument("--paths", action="store_true",
                        help="compare the inference paths (torch fp32/bf16, ONNX Runtime fp32/int8, auto) instead")
    parser.add_argument("--weights", default=None, help="--paths: a weights file (default: seeded released size)")
    parser.add_argument("--rounds", type=int, default=5, help="--paths: interleaved rounds")
    parser.add_argument("--calibration-frames", type=int, default=32, help="--paths: int8 calibration frames")
    parser.add_argument("--cosine-frames", type=int, default=8, help="--paths: frames for the cosine column")
    args = parser.parse_args(argv)

    import torch

    torch.set_num_threads(args.threads)
    if args.paths:
        paths(args)
    else:
        forward(args)


if __name__ == "__main__":
    sys.exit(main())
