"""LCPR reproduces the authors' released network on their deterministic parity vectors."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from conftest import reference_seed, reference_sets
from lcpr_core import LCPR

TOL = 1e-5


@pytest.fixture(scope="module")
def keys(shared: Path) -> dict[str, list[int]]:
    return json.loads((shared / "reference" / "lcpr" / "keys.json").read_text())


def test_the_model_has_the_released_parameter_names_and_shapes(keys):
    state = LCPR().state_dict()
    assert list(state) == list(keys)
    assert {k: list(v.shape) for k, v in state.items()} == keys


@pytest.mark.parametrize("ref_file", reference_sets("lcpr"), ids=lambda p: p.stem)
def test_descriptors_match_the_released_code(ref_file: Path, keys, detweights):
    seed = reference_seed(ref_file)
    expected = np.load(ref_file)
    batch = expected["descriptor"].shape[0]
    model = LCPR().eval()
    model.load_state_dict(detweights.det_state_dict(keys, seed))
    assert sum(p.numel() for p in model.parameters()) == int(expected["params"])

    images = detweights.det_camera_input(batch, seed)
    ranges = detweights.det_range_input(batch, seed)
    assert images.double().sum().item() == pytest.approx(float(expected["camera_input_sum"]), rel=1e-9)
    assert ranges.double().sum().item() == pytest.approx(float(expected["range_input_sum"]), rel=1e-9)

    # Sub-descriptors are read with forward hooks on netvlad_i / netvlad_l, as a user
    # of the released code would; the reference recorded them on its last forward,
    # the yaw-shifted one.
    captured: dict[str, torch.Tensor] = {}
    hooks = [
        getattr(model, name).register_forward_hook(lambda m, i, o, name=name: captured.__setitem__(name, o))
        for name in ("netvlad_i", "netvlad_l")
    ]
    with torch.inference_mode():
        descriptor = model(images, ranges)
        shifted = model(images.roll(1, dims=1), ranges.roll(ranges.shape[-1] // 6, dims=3))
    for hook in hooks:
        hook.remove()

    np.testing.assert_allclose(descriptor.numpy(), expected["descriptor"], atol=TOL, rtol=0)
    np.testing.assert_allclose(shifted.numpy(), expected["descriptor_yaw_shifted"], atol=TOL, rtol=0)
    np.testing.assert_allclose(captured["netvlad_i"].numpy(), expected["camera_subdescriptor"], atol=TOL, rtol=0)
    np.testing.assert_allclose(captured["netvlad_l"].numpy(), expected["lidar_subdescriptor"], atol=TOL, rtol=0)
    np.testing.assert_allclose(np.linalg.norm(descriptor.numpy(), axis=1), 1.0, atol=1e-6)


def test_describe_returns_the_sub_descriptors_the_hooks_see(keys, detweights):
    model = LCPR().eval()
    model.load_state_dict(detweights.det_state_dict(keys, 0))
    images, ranges = detweights.det_camera_input(1, 0), detweights.det_range_input(1, 0)
    seen: dict[str, torch.Tensor] = {}
    model.netvlad_l.register_forward_hook(lambda m, i, o: seen.setdefault("l", o))
    with torch.inference_mode():
        out = model.describe(images, ranges)
    torch.testing.assert_close(out.lidar, seen["l"])
    torch.testing.assert_close(out.descriptor, model(images, ranges))


def test_bf16_autocast_stays_within_cosine_0_9999_of_fp32(keys, detweights):
    model = LCPR().eval()
    model.load_state_dict(detweights.det_state_dict(keys, 0))
    images, ranges = detweights.det_camera_input(1, 0), detweights.det_range_input(1, 0)
    with torch.inference_mode():
        fp32 = model(images, ranges)
        with torch.autocast("cpu", dtype=torch.bfloat16):
            bf16 = model(images, ranges).float()
    assert torch.nn.functional.cosine_similarity(fp32, bf16).item() >= 0.9999
