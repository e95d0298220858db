"""LCPR forward pass on a GPU: median milliseconds per frame, in one pass and averaged over the six turns.

    python benchmarks/tools/lcpr_gpu_forward.py [--device cuda:0] [--weights FILE] [--repeats 50]

Times the network as the Describer runs it on a GPU (``model.device: cuda``): one frame
(batch 1) and one turn-averaged frame (batch 6: the six camera-slot turns), in float32 and
under bfloat16 autocast, inputs already on the device, synchronised before every clock read.
Without ``--weights`` the released configuration (width 1.0, 256x704 images, 32x1056 range
image) with seeded weights; speed does not depend on the weights' values. Prints the GPU's name
and the medians; ``--device cpu`` runs it anywhere (the tests use a small network).
"""
from __future__ import annotations

import argparse
import sys
from typing import TYPE_CHECKING

from lcpr_common.cli import tool_main

if TYPE_CHECKING:  # torch and the package are imported after the arguments are read
    import torch

    from lcpr_core import LCPR


def device_name(device: torch.device) -> str:
    import torch

    from lcpr_core.lcpr.runtime.cuda import gpu_name

    return gpu_name(device) if device.type == "cuda" else f"CPU ({torch.get_num_threads()} threads)"


def median_ms(model: LCPR, batch: int, *, device: torch.device, bf16: bool, repeats: int, warmup: int = 5) -> float:
    """Median wall time of one forward pass of ``batch`` frames, in milliseconds (each pass waits for the GPU)."""
    import torch

    from lcpr_core.lcpr.runtime.choose import probe_inputs
    from lcpr_core.lcpr.training.train import autocast
    from lcpr_core.timing import median_seconds

    images, ranges = probe_inputs(model, batch=batch)
    images, ranges = images.to(device), ranges.to(device)

    def forward() -> None:
        model(images, ranges)
        if device.type == "cuda":
            torch.cuda.synchronize(device)

    with torch.inference_mode(), autocast(device, "bf16" if bf16 else "off"):
        return 1000 * median_seconds(forward, repeats=repeats, warmup=warmup)


@tool_main
def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--device", default="cuda:0")
    p.add_argument("--weights", default=None, help="an LCPR weights file (default: seeded released size)")
    p.add_argument("--repeats", type=int, default=50)
    p.add_argument("--small", action="store_true", help="a narrow network (64x192, 16x288, width 0.25), for tests")
    args = p.parse_args(argv)

    import torch

    from lcpr_core import LCPR, ModelConfig, build_model

    device = torch.device(args.device)
    if args.weights:
        model = build_model(ModelConfig(weights=args.weights, precision="fp32"))
    else:
        torch.manual_seed(0)
        model = LCPR(width=0.25, image_size=(64, 192), range_size=(16, 288)) if args.small else LCPR()
    model = model.eval().to(device)
    print(f"device: {device_name(device)}; network: width {model.width:g}, {model.num_cameras} x "
          f"{model.image_size[0]}x{model.image_size[1]} images, {model.range_size[0]}x{model.range_size[1]} range "
          f"image; median of {args.repeats} after 5 warm-up passes")
    for bf16 in (False, True):
        one = median_ms(model, 1, device=device, bf16=bf16, repeats=args.repeats)
        six = median_ms(model, 6, device=device, bf16=bf16, repeats=args.repeats)
        print(f"{'bf16' if bf16 else 'fp32'}: one pass {one:.2f} ms per frame; turn-averaged (six turns, batch 6) "
              f"{six:.2f} ms per frame")
    return 0


if __name__ == "__main__":
    sys.exit(main())
