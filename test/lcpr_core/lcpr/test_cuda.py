"""model.device cuda: exact and fast paths, GPU preprocessing, auto's choice, evaluation options and training.

Every test here needs torch.cuda; without a GPU they skip (the rest of the suite covers the CPU paths).
"""
from __future__ import annotations

import argparse
import copy
import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch

from lcpr_core import LCPR, Describer, ModelConfig, range_image
from lcpr_core.errors import RuntimeSetupError
from lcpr_core.lcpr.preprocess import PRESETS
from lcpr_core.lcpr.preprocess.dataset_files import find_nuscenes_keyframe
from lcpr_core.lcpr.preprocess.range_image import range_image_tensor
from lcpr_core.lcpr.runtime.choose import cosine, probe_inputs
from lcpr_core.lcpr.runtime.cuda import GPU_COSINE, GraphBackend
from lcpr_core.pretrained import default_weights

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


def test_auto_on_a_gpu_keeps_a_captured_path_within_cosine_0_9999_and_the_cpu_only_paths_are_refused_there(
        caplog: pytest.LogCaptureFixture) -> None:
    with caplog.at_level("INFO"):
        describer = Describer(ModelConfig(precision="auto", device="cuda", **NARROW))
    assert describer.path in ("fp32", "tf32", "bf16")
    assert describer.choice.cosines[describer.path] >= GPU_COSINE
    assert torch.cuda.get_device_name() in caplog.text
    with pytest.raises(RuntimeSetupError, match="CPU only"):
        Describer(ModelConfig(precision="onnx", device="cuda", **NARROW))


def test_exact_fp32_on_the_gpu_reproduces_the_reference_vectors_to_1e_5_eager_and_replayed(shared, detweights
                                                                                          ) -> None:
    ref_file = shared / "reference" / "lcpr" / "expected_seed0.npz"
    expected = np.load(ref_file)
    keys = json.loads((shared / "reference" / "lcpr" / "keys.json").read_text())
    model = LCPR().eval()
    model.load_state_dict(detweights.det_state_dict(keys, 0))
    describer = Describer(ModelConfig(precision="fp32", device="cuda"), model=model.cuda())
    assert isinstance(describer.backend, GraphBackend) and describer.backend.captured
    images, ranges = detweights.det_camera_input(2, 0), detweights.det_range_input(2, 0)
    eager = describer.backend(images, ranges)  # batch 2: the eager path
    replayed = np.concatenate([describer.backend(images[i:i + 1], ranges[i:i + 1]) for i in range(2)])  # the graph
    np.testing.assert_allclose(eager, expected["descriptor"], atol=1e-5, rtol=0)
    np.testing.assert_allclose(replayed, expected["descriptor"], atol=1e-5, rtol=0)


def test_a_graph_reserved_for_a_larger_batch_pads_smaller_batches_and_keeps_the_reference_vectors_to_1e_5(
        shared, detweights) -> None:
    expected = np.load(shared / "reference" / "lcpr" / "expected_seed0.npz")["descriptor"]
    keys = json.loads((shared / "reference" / "lcpr" / "keys.json").read_text())
    model = LCPR().eval()
    model.load_state_dict(detweights.det_state_dict(keys, 0))
    describer = Describer(ModelConfig(precision="fp32", device="cuda"), model=model.cuda())
    describer.reserve(4)
    assert isinstance(describer.backend, GraphBackend) and describer.backend.batches == (1, 4)
    images, ranges = detweights.det_camera_input(2, 0), detweights.det_range_input(2, 0)
    padded = describer.backend(images, ranges)  # 2 rows replayed in the graph of 4
    np.testing.assert_allclose(padded, expected, atol=1e-5, rtol=0)
    eager = describer.backend(images.repeat(3, 1, 1, 1, 1), ranges.repeat(3, 1, 1, 1))  # 6 rows: eager
    np.testing.assert_allclose(eager, np.concatenate([expected] * 3), atol=1e-5, rtol=0)


def test_frames_prepared_together_on_the_gpu_equal_each_frame_prepared_alone(shared: Path) -> None:
    pytest.importorskip("torchvision.io", reason="torchvision (nvJPEG) not importable here")
    gpu = Describer(ModelConfig(device="cuda", decode="nvjpeg", precision="fp32", **NARROW))
    frames = [find_nuscenes_keyframe(shared / "data" / name).read() for name in ("nuscenes_sample", "nuscenes_sample2")]
    broken = list(frames[1][0])
    broken[3] = broken[3][: len(broken[3]) // 2]  # truncated: only this frame's camera 3 is left out
    frames.append((broken, frames[1][1]))
    batch = gpu.prepare_many(frames)
    assert batch.images.is_cuda and batch.images.shape[:2] == (3, 6)
    assert batch.failed[0] == {} and batch.failed[1] == {} and set(batch.failed[2]) == {3}
    for b, (images, points) in enumerate(frames):
        alone = gpu.prepare(images, points)
        # nvJPEG may decode a batch on another backend than a frame's six: a grey level here and there
        assert float((batch.images[b:b + 1] - alone.images).abs().mean()) <= 0.01
        assert torch.equal(batch.ranges[b:b + 1], alone.ranges)
    many = gpu.describe_tensors(batch.images, batch.ranges)
    one = np.concatenate([gpu.describe_tensors(p.images, p.ranges) for p in (gpu.prepare(*f) for f in frames)])
    assert float((many * one).sum(axis=1).min()) >= 0.9999


def test_a_failed_graph_capture_leaves_the_eager_path_with_a_warning(monkeypatch, caplog) -> None:
    def broken(*_: object, **__: object) -> Any:
        raise RuntimeError("capture refused")

    monkeypatch.setattr(torch.cuda, "graph", broken)
    with caplog.at_level("WARNING"):
        gpu = Describer(ModelConfig(precision="fp32", device="cuda", **NARROW))
    assert gpu.model is not None
    cpu = Describer(ModelConfig(precision="fp32", **NARROW), model=copy.deepcopy(gpu.model).cpu())
    assert cpu.model is not None
    assert isinstance(gpu.backend, GraphBackend) and not gpu.backend.captured
    assert "capture refused" in caplog.text
    images, ranges = probe_inputs(cpu.model)
    assert cosine(gpu.describe_tensors(images, ranges), cpu.describe_tensors(images, ranges)) >= 0.99999


def test_the_gpu_frame_path_decodes_with_nvjpeg_and_keeps_the_descriptor_of_the_cpu_reference_path(
        shared: Path) -> None:
    pytest.importorskip("torchvision.io", reason="torchvision (nvJPEG) not importable here")
    weights = default_weights()
    assert weights is not None
    gpu = Describer(ModelConfig(weights=str(weights), device="cuda"))
    reference = Describer(ModelConfig(weights=str(weights), precision="fp32", decode="pil"))
    assert gpu.cameras.decoder == "nvjpeg"
    for name in ("nuscenes_sample", "nuscenes_sample2"):
        images, points = find_nuscenes_keyframe(shared / "data" / name).read()
        prepared = gpu.prepare(images, points)
        assert prepared.images.is_cuda and prepared.ranges.is_cuda and not prepared.failed
        assert float(np.dot(gpu.describe(images, points), reference.describe(images, points))) >= 0.9999


def test_the_gpu_range_image_equals_the_cpu_one_on_a_real_sweep(shared: Path) -> None:
    _, points = find_nuscenes_keyframe(shared / "data" / "nuscenes_sample").read()
    gpu = range_image_tensor(torch.from_numpy(points).cuda(), preset=PRESETS["nuscenes_lidar_top"])
    differ = int((gpu.cpu().numpy() != range_image(points)).sum())
    assert differ <= 5  # the device's atan2 / asin may differ from libm's in the last bit at a pixel border


def test_a_corrupt_jpeg_on_the_gpu_path_leaves_only_its_camera_empty(shared: Path) -> None:
    pytest.importorskip("torchvision.io", reason="torchvision (nvJPEG) not importable here")
    images, points = find_nuscenes_keyframe(shared / "data" / "nuscenes_sample").read()
    gpu = Describer(ModelConfig(device="cuda", decode="nvjpeg", **NARROW))
    broken = list(images)
    broken[2] = images[2][: len(images[2]) // 2]  # truncated
    broken[4] = b"\xff\xd8\xff\xe0" + bytes(1000) + b"\xff\xd9"  # a header and nothing decodable
    prepared = gpu.prepare(broken, points)
    assert set(prepared.failed) >= {2} and set(prepared.failed) <= {2, 4}
    assert float(prepared.images[0, 2].abs().sum()) == 0 and float(prepared.images[0, 0].abs().sum()) > 0


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
