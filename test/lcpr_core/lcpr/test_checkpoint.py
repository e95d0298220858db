"""Weights load from the released checkpoint layout and plain state dicts, never running code."""
from __future__ import annotations

import logging
import pickle
import stat
import zipfile
from typing import Any

import pytest
import torch

from lcpr_core import LCPR, CheckpointError, ModelConfig, build_model, init_from_imagenet, load_weights
from lcpr_core.atomic import save_torch
from lcpr_core.lcpr.checkpoint import save_checkpoint

SMALL: dict[str, Any] = dict(num_cameras=2, image_size=(64, 128), range_size=(16, 256))


def states_equal(a: torch.nn.Module, b: torch.nn.Module) -> bool:
    return all(torch.equal(x, y) for x, y in zip(a.state_dict().values(), b.state_dict().values(), strict=True))


def test_a_released_format_checkpoint_roundtrips(tmp_path):
    source = LCPR()
    path = tmp_path / "lcpr.pth"
    save_checkpoint(source, path, epoch=7)
    payload = torch.load(path, weights_only=True)
    assert set(payload) >= {"epoch", "net", "scheduler"} and payload["epoch"] == 7
    assert states_equal(load_weights(LCPR(), path), source)


def test_a_plain_state_dict_and_a_data_parallel_prefix_load(tmp_path):
    source = LCPR()
    torch.save(source.state_dict(), tmp_path / "plain.pt")
    torch.save({"module." + k: v for k, v in source.state_dict().items()}, tmp_path / "dp.pt")
    assert states_equal(load_weights(LCPR(), tmp_path / "plain.pt"), source)
    assert states_equal(load_weights(LCPR(), tmp_path / "dp.pt"), source)


def test_a_mismatched_file_lists_missing_unexpected_and_misshaped_keys(tmp_path):
    state = LCPR().state_dict()
    del state["eca.conv.weight"]
    state["extra.weight"] = torch.zeros(1)
    state["conv_l.weight"] = torch.zeros(32, 1, 1, 1)
    torch.save({"net": state}, tmp_path / "bad.pth")
    with pytest.raises(CheckpointError) as info:
        load_weights(LCPR(), tmp_path / "bad.pth")
    text = str(info.value)
    assert "1 missing: eca.conv.weight" in text
    assert "1 unexpected: extra.weight" in text
    assert "conv_l.weight: file (32, 1, 1, 1) vs model (64, 1, 1, 1)" in text


class Payload:
    def __reduce__(self):
        return (print, ("this must never run",))


def test_a_file_that_would_run_code_is_refused(tmp_path, capsys):
    path = tmp_path / "evil.pth"
    with open(path, "wb") as fh:
        pickle.dump({"net": Payload()}, fh)
    with pytest.raises(CheckpointError, match="could run code|not a readable"):
        load_weights(LCPR(), path)
    assert "this must never run" not in capsys.readouterr().out


def test_missing_and_garbage_files_are_refused_with_their_path(tmp_path):
    with pytest.raises(CheckpointError, match="does not exist"):
        load_weights(LCPR(), tmp_path / "nope.pth")
    (tmp_path / "junk.pth").write_bytes(b"\x00junk")
    with pytest.raises(CheckpointError, match="junk.pth"):
        load_weights(LCPR(), tmp_path / "junk.pth")


def test_imagenet_weights_initialise_both_branches(tmp_path):
    model = LCPR(**SMALL)
    resnet = {}
    for prefix, lcpr_prefix in (("conv1.", "conv1_i."), ("bn1.", "bn1_i."), ("layer1.", "layer1_i."),
                                ("layer2.", "layer2_i."), ("layer3.", "layer3_i."), ("layer4.", "layer4_i.")):
        for k, v in model.state_dict().items():
            if k.startswith(lcpr_prefix):
                resnet[prefix + k[len(lcpr_prefix):]] = torch.full_like(v, 0.5) if v.is_floating_point() else v
    resnet["fc.weight"] = torch.zeros(1000, 512)
    torch.save(resnet, tmp_path / "resnet18.pth")
    init_from_imagenet(model, tmp_path / "resnet18.pth")
    assert isinstance(model.layer3_l[0].conv1, torch.nn.Conv2d)
    assert isinstance(model.layer3_i[0].conv1, torch.nn.Conv2d)
    assert torch.all(model.layer3_l[0].conv1.weight == 0.5)
    assert torch.all(model.layer3_i[0].conv1.weight == 0.5)
    assert not torch.all(model.conv_l.weight == 0.5)


def test_the_default_model_is_seeded_and_says_so(caplog):
    with caplog.at_level(logging.WARNING):
        a = build_model(ModelConfig(seed=3))
    b = build_model(ModelConfig(seed=3))
    assert states_equal(a, b)
    assert not states_equal(a, build_model(ModelConfig(seed=4)))
    assert "seeded random initialisation (seed 3)" in caplog.text
    assert not a.training


def test_model_sizes_are_constructor_options():
    model = LCPR(**SMALL).eval()
    images, ranges = model.example_inputs(batch=2)
    with torch.inference_mode():
        out = model(images.normal_(), ranges.uniform_(1, 50))
    assert out.shape == (2, 256)
    with pytest.raises(ValueError, match="expected B x 2 x 3 x 64 x 128"):
        model(torch.zeros(1, 6, 3, 64, 128), ranges[:1])


def test_torch_files_are_written_whole_with_records_named_after_no_temporary_file(tmp_path):
    size = save_torch({"net": {"w": torch.ones(3)}}, tmp_path / "ship.pth", shared=True)
    assert size == (tmp_path / "ship.pth").stat().st_size
    assert all(n.startswith("archive/") for n in zipfile.ZipFile(tmp_path / "ship.pth").namelist())
    assert stat.S_IMODE((tmp_path / "ship.pth").stat().st_mode) == 0o644
    assert torch.equal(torch.load(tmp_path / "ship.pth", weights_only=True)["net"]["w"], torch.ones(3))
    assert [p.name for p in tmp_path.iterdir()] == ["ship.pth"]  # no temporary file left behind
