"""LCPR forward pass on the CPU: median time per frame, FLOPs, GFLOP/s, bf16 agreement.

    python benchmarks/lcpr_forward.py [--threads 2] [--repeats 10] [--batch 1]

Times ``LCPR().eval()`` called as ``model(images, ranges)`` under
``torch.inference_mode()`` (fp32), and again inside ``torch.autocast("cpu",
dtype=torch.bfloat16)``, next to a straightforward implementation of the same
network (benchmarks/baseline_lcpr.py) on the same weights and inputs.
"""
from __future__ import annotations

import argparse
import contextlib
import sys
from pathlib import Path

import torch
from torch.utils.flop_counter import FlopCounterMode

sys.path.insert(0, str(Path(__file__).resolve().parent))

from baseline_lcpr import baseline_forward  # noqa: E402

from lcpr_core import LCPR  # noqa: E402
from lcpr_core.timing import median_seconds  # noqa: E402


def inputs(model: LCPR, batch: int) -> tuple[torch.Tensor, torch.Tensor]:
    gen = torch.Generator().manual_seed(0)
    images, ranges = model.example_inputs(batch)
    images = torch.randn(images.shape, generator=gen).clamp_(-3, 3)
    ranges = 2 + 78 * torch.rand(ranges.shape, generator=gen)
    return images, ranges.masked_fill_(torch.rand(ranges.shape, generator=gen) < 0.1, -1.0)


def bf16() -> contextlib.AbstractContextManager:
    return torch.autocast("cpu", dtype=torch.bfloat16)


def matmul_peak(dtype: torch.dtype, n: int = 2048) -> float:
    """Achieved GFLOP/s of one large square matmul: a practical ceiling for this machine."""
    a, b = torch.randn(n, n).to(dtype), torch.randn(n, n).to(dtype)
    return 2 * n**3 / median_seconds(lambda: a @ b, repeats=5) / 1e9


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=10)
    parser.add_argument("--batch", type=int, default=1)
    parser.add_argument("--skip-baseline", action="store_true")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    model = LCPR().eval()
    images, ranges = inputs(model, args.batch)
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


if __name__ == "__main__":
    main()
