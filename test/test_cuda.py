"""model.device cuda: descriptors, auto's choice, evaluation options and a training step on a GPU.

Every test here needs torch.cuda; without a GPU they skip (the rest of the suite covers the CPU paths).
"""
from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch

from lcpr_core import LCPR, Describer, ModelConfig
from lcpr_core.errors import RuntimeSetupError
from lcpr_core.lcpr.runtime.choose import cosine, probe_inputs

pytestmark = pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA GPU on this machine")

NARROW: dict[str, Any] = dict(width=0.25, image_size=(64, 192), range_size=(16, 264))


def test_cuda_fp32_descriptors_agree_with_the_cpu_to_a_cosine_of_0_9999() -> None:
    cpu = Describer(ModelConfig(precision="fp32"))
    gpu = Describer(ModelConfig(precision="fp32", device="cuda"))
    assert cpu.model is not None
    images, ranges = probe_inputs(cpu.model, batch=2)
    assert cosine(gpu.describe_tensors(images, ranges), cpu.describe_tensors(images, ranges)) >= 0.9999


def test_cuda_bf16_stays_close_to_the_cpu() -> None:
    cpu = Describer(ModelConfig(precision="fp32"))
    gpu = Describer(ModelConfig(precision="bf16", device="cuda"))
    assert cpu.model is not None
    images, ranges = probe_inputs(cpu.model)
    assert cosine(gpu.describe_tensors(images, ranges), cpu.describe_tensors(images, ranges)) >= 0.999


def test_auto_on_a_gpu_is_torch_fp32_and_the_cpu_only_paths_are_refused_there() -> None:
    assert Describer(ModelConfig(precision="auto", device="cuda", **NARROW)).path == "fp32"
    with pytest.raises(RuntimeSetupError, match="CPU only"):
        Describer(ModelConfig(precision="onnx", device="cuda", **NARROW))


def test_lcpr_eval_takes_the_device_from_its_flag() -> None:
    from lcpr_ros.evaluate import parse_args

    args = parse_args(["a.bag", "--device", "cuda:0"])
    assert isinstance(args, argparse.Namespace) and args.device == "cuda:0"


def test_one_training_step_on_the_gpu_changes_the_weights(tmp_path: Path) -> None:
    torch.manual_seed(0)
    model = LCPR(**NARROW).cuda().train()
    before = [p.detach().clone() for p in model.parameters()]
    images, ranges = probe_inputs(model, batch=3)
    desc = model(images.cuda(), ranges.cuda())
    loss = torch.relu((desc[0] - desc[1]).norm() - (desc[0] - desc[2]).norm() + 0.5)
    loss.backward()
    torch.optim.Adam(model.parameters(), lr=1e-3).step()
    assert any(not torch.equal(b, p.detach()) for b, p in zip(before, model.parameters(), strict=True))
    assert np.isfinite(loss.item())


def test_training_inputs_normalised_on_the_gpu_equal_the_cpu_ones() -> None:
    from lcpr_core.lcpr.training.dataset import to_model_inputs

    rng = np.random.default_rng(0)
    images = rng.integers(0, 256, size=(2, 6, 32, 64, 3), dtype=np.uint8)
    cameras = np.array([[True] * 6, [True, False, True, True, True, True]])
    ranges = rng.uniform(-1, 50, size=(2, 8, 64)).astype(np.float16)
    cpu = to_model_inputs(images, cameras, ranges)
    gpu = to_model_inputs(images, cameras, ranges, device="cuda")
    assert gpu[0].is_cuda and gpu[1].is_cuda
    for a, b in zip(cpu, gpu, strict=True):
        assert torch.allclose(a, b.cpu(), atol=1e-6)


def test_bf16_autocast_training_step_on_the_gpu(tmp_path: Path) -> None:
    import dataclasses

    from lcpr_core.lcpr.training import Trainer, TrainingData, open_cache
    from training_fixtures import tiny_config, write_tiny_cache

    config = dataclasses.replace(tiny_config(), device="cuda", amp="bf16")
    data = TrainingData.from_cache(open_cache(write_tiny_cache(tmp_path / "cache")), config.split)
    history = Trainer(data, config, tmp_path / "run", progress=False, echo=lambda _: None).fit()
    assert history[1]["loss"] is not None and np.isfinite(history[1]["loss"])
