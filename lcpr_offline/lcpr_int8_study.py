"""What the int8 studies (benchmarks/studies/int8_variants.py, int8_sensitivity.py) share: their options,
the fp32 reference, the calibration (training city, seed 1) and validation (seed 3) frames rendered by
:func:`.lcpr_quantize.calibration_inputs`, and quantising the convolutions whose names match a pattern."""
from __future__ import annotations

import argparse
import dataclasses
from dataclasses import dataclass

import numpy as np
import torch

from lcpr_core.errors import RuntimeSetupError
from lcpr_core.lcpr.describer import Describer, ModelConfig
from lcpr_core.lcpr.runtime.choose import cosine
from lcpr_core.lcpr.runtime.quantize import quantize
from lcpr_core.pretrained import default_weights

from .lcpr_quantize import calibration_inputs

Inputs = tuple[torch.Tensor, torch.Tensor]


def add_arguments(parser: argparse.ArgumentParser, *, weights_help: str) -> None:
    parser.add_argument("--weights", default=None, help=weights_help)
    parser.add_argument("--calibration-frames", type=int, default=48)
    parser.add_argument("--cosine-frames", type=int, default=24)
    parser.add_argument("--threads", type=int, default=2)


@dataclass
class Int8Bench:
    """torch fp32 on the configured weights, with calibration and validation frames."""

    weights: str
    base: ModelConfig
    fp32: Describer
    calibration: list[Inputs]
    validation: list[Inputs]
    expected: list[np.ndarray]  # torch fp32's descriptors of the validation frames
    refusal: str = ""  # why the runtime refused the last int8 graph ("" when it loaded)

    @classmethod
    def from_args(cls, args: argparse.Namespace) -> Int8Bench:
        weights = str(default_weights()) if args.weights is None else args.weights
        base = ModelConfig(weights=weights, threads=args.threads)
        fp32 = Describer(dataclasses.replace(base, precision="fp32"))
        calibration = calibration_inputs(fp32, seed=1, frames=args.calibration_frames)
        validation = calibration_inputs(fp32, seed=3, frames=args.cosine_frames) if args.cosine_frames else []
        return cls(weights, base, fp32, calibration, validation, [fp32.describe_tensors(*x) for x in validation])

    def describer(self, precision: str) -> Describer:
        return Describer(dataclasses.replace(self.base, precision=precision), model=self.fp32.model)

    def int8(self, pattern: str) -> Describer | None:
        """Quantise the convolutions whose names match ``pattern`` and load that graph; None when the runtime
        refuses it (further from torch fp32 on its probe input than it accepts; :attr:`refusal` says how far).
        The studies measure such variants too: a refusal is a row of their tables, not the end of the run."""
        quantize(self.fp32, self.calibration, nodes=pattern)
        try:
            describer = self.describer("int8")
        except RuntimeSetupError as err:
            self.refusal = str(err)
            return None
        self.refusal = ""
        return describer

    def cosines(self, describer: Describer | None) -> str:
        """Lowest, 10th-percentile and median cosine to torch fp32 on the validation frames ("" without any)."""
        if describer is None:
            return f"refused by the runtime: {self.refusal}"
        if not self.validation:
            return ""
        cs = np.array([cosine(describer.describe_tensors(*x), e)
                       for x, e in zip(self.validation, self.expected, strict=True)])
        return f"{cs.min():>8.5f} {np.quantile(cs, 0.1):>8.5f} {np.median(cs):>9.6f}"

    def restore_default(self) -> None:
        """Leave lcpr_quantize's default graph in place."""
        quantize(self.fp32, self.calibration)
