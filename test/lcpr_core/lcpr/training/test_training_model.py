"""The width factor: 1.0 is the released network, narrower ones keep the names and the 256-d output."""
from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

from lcpr_core import LCPR
from lcpr_core.lcpr.models.lcpr import scaled_channels


def test_width_one_keeps_the_released_parameter_names_and_shapes(shared: Path):
    keys = json.loads((shared / "reference" / "lcpr" / "keys.json").read_text())
    state = LCPR(width=1.0).state_dict()
    assert {k: list(v.shape) for k, v in state.items()} == keys
    assert list(state) == list(keys)


def test_a_narrow_model_keeps_the_names_and_gives_unit_256_d_descriptors():
    torch.manual_seed(0)
    model = LCPR(width=0.25, num_cameras=2, image_size=(64, 128), range_size=(16, 128)).eval()
    assert list(model.state_dict()) == list(LCPR().state_dict())
    assert isinstance(model.conv1_i, torch.nn.Conv2d) and isinstance(model.layer4_l[0].conv1, torch.nn.Conv2d)
    assert model.conv1_i.out_channels == 16 and model.layer4_l[0].conv1.out_channels == 128
    assert model.netvlad_i.cluster_weights.shape == (64, 32)
    images, ranges = torch.randn(3, 2, 3, 64, 128), torch.rand(3, 1, 16, 128) * 40
    with torch.inference_mode():
        desc = model(images, ranges)
    assert desc.shape == (3, 256)
    assert torch.allclose(desc.norm(dim=1), torch.ones(3), atol=1e-5)


def test_channel_counts_round_to_multiples_of_eight():
    assert [scaled_channels(c, 1.0) for c in (64, 128, 256, 512)] == [64, 128, 256, 512]
    assert [scaled_channels(c, 0.25) for c in (64, 128, 256, 512)] == [16, 32, 64, 128]
    assert scaled_channels(64, 0.05) == 8


@pytest.mark.parametrize("width", [0, -1, 5, float("nan")])
def test_a_bad_width_is_refused_naming_the_value(width):
    with pytest.raises(ValueError, match="width="):
        LCPR(width=width)
