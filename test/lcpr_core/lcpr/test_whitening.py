"""Descriptor whitening: the fit, its checkpoint entry, the describer applying it, lcpr_train --whiten."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from lcpr_core.errors import CheckpointError, InputShapeError, InvalidValueError
from lcpr_core.lcpr.checkpoint import save_checkpoint
from lcpr_core.lcpr.describer import Describer, ModelConfig
from lcpr_core.lcpr.training import TrainingData, export_weights, open_cache
from lcpr_core.lcpr.training.cache import cache_meta
from lcpr_core.lcpr.training.recipe_rules import choose_whitening
from lcpr_core.lcpr.training.recipe_scores import online_ranking
from lcpr_core.lcpr.training.train import make_model
from lcpr_core.lcpr.whitening import ENTRY, Whitening, fit_whitening, read_whitening, write_whitened
from lcpr_offline.lcpr_train import main as lcpr_train
from training_fixtures import TINY, tiny_config, write_tiny_cache


def anisotropic(n: int = 400, d: int = 16, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    basis, _ = np.linalg.qr(rng.normal(size=(d, d)))
    return 0.3 + (rng.normal(size=(n, d)) * np.logspace(0, -3, d)) @ basis.T


def test_whitening_gives_the_kept_directions_unit_variance_and_drops_the_rest():
    x = anisotropic()
    w = fit_whitening(x, power=0.5, dims=6)
    y = (x - w.mean) @ w.projection.T
    eig = np.sort(np.linalg.eigvalsh(np.cov(y, rowvar=False)))[::-1]
    assert np.allclose(eig[:6], 1.0, atol=1e-3) and np.allclose(eig[6:], 0.0, atol=1e-6)
    out = w.apply(x[:5])
    assert out.shape == (5, 16) and out.dtype == np.float32
    assert np.allclose(np.linalg.norm(out, axis=1), 1.0, atol=1e-5)


def test_a_smaller_power_flattens_the_spectrum_less():
    x = anisotropic()
    ratios = []
    for power in (0.25, 0.5):
        w = fit_whitening(x, power=power, dims=4)
        eig = np.sort(np.linalg.eigvalsh(np.cov((x - w.mean) @ w.projection.T, rowvar=False)))[::-1]
        ratios.append(eig[0] / eig[3])
    assert ratios[0] > 1.5 and ratios[1] == pytest.approx(1.0, abs=1e-3)


@pytest.mark.parametrize(("kwargs", "named"), [
    ({"dims": 0}, "dims=0"), ({"dims": 17}, "dims=17"), ({"power": 0.0, "dims": 4}, "power=0.0"),
    ({"power": 1.5, "dims": 4}, "power=1.5"),
])
def test_options_outside_their_ranges_are_refused_by_name(kwargs, named):
    with pytest.raises(InvalidValueError, match=named):
        fit_whitening(anisotropic(), **kwargs)


def test_too_few_or_malformed_descriptors_are_refused():
    with pytest.raises(InvalidValueError, match="3 descriptors cannot fit 8 directions"):
        fit_whitening(anisotropic(n=3), dims=8)
    with pytest.raises(InputShapeError, match="finite"):
        fit_whitening(np.full((20, 4), np.nan), dims=2)
    with pytest.raises(InputShapeError, match="B x 16"):
        fit_whitening(anisotropic(), dims=4).apply(np.zeros((2, 8)))


@pytest.fixture
def checkpoint(tmp_path) -> Path:
    path = tmp_path / "tiny.pth"
    save_checkpoint(make_model(tiny_config()), path, extra={"config": TINY.model_entry()})
    return path


def fitted(d: int = 256) -> Whitening:
    return fit_whitening(anisotropic(n=400, d=d), dims=32)


def test_a_whitened_checkpoint_roundtrips_loads_without_code_and_survives_the_float16_export(checkpoint, tmp_path):
    w = fitted()
    target = tmp_path / "whitened.pth"
    write_whitened(checkpoint, target, w)
    payload = torch.load(target, weights_only=True)
    assert set(payload[ENTRY]) == {"mean", "projection", "power", "dims", "samples"}
    back = read_whitening(target)
    assert back is not None and back.dims == 32 and back.samples == 400
    assert np.array_equal(back.projection, w.projection) and np.array_equal(back.mean, w.mean)
    assert read_whitening(checkpoint) is None
    small = tmp_path / "small.pth"
    export_weights(target, small)
    exported = torch.load(small, weights_only=True)
    assert exported["net"]["conv1_i.weight"].dtype == torch.float16
    assert exported[ENTRY]["projection"].dtype == torch.float32
    again = read_whitening(small)
    assert again is not None and np.array_equal(again.projection, w.projection)


def test_a_checkpoint_in_torchs_legacy_format_is_read_too(checkpoint, tmp_path):
    payload = torch.load(checkpoint, weights_only=True)
    payload[ENTRY] = fitted().to_entry()
    legacy = tmp_path / "legacy.pth"
    torch.save(payload, legacy, _use_new_zipfile_serialization=False)  # cannot be memory-mapped
    back = read_whitening(legacy)
    assert back is not None and back.dims == 32


def test_a_malformed_whitening_entry_is_refused_naming_the_file(checkpoint, tmp_path):
    payload = torch.load(checkpoint, weights_only=True)
    payload[ENTRY] = {"mean": torch.zeros(256), "projection": torch.zeros(256, 8)}
    bad = tmp_path / "bad.pth"
    torch.save(payload, bad)
    with pytest.raises(CheckpointError, match="bad.pth.*whitening"):
        read_whitening(bad)


def test_the_describer_whitens_when_the_file_has_it_unless_the_config_says_not(checkpoint, tmp_path):
    w = fitted()
    target = tmp_path / "whitened.pth"
    write_whitened(checkpoint, target, w)
    data = TrainingData.from_cache(open_cache(write_tiny_cache(tmp_path / "cache")), tiny_config().split)
    images, ranges = data.inputs([0, 3, 7])
    plain = Describer(ModelConfig(weights=str(checkpoint), precision="fp32"))
    raw = plain.describe_tensors(images, ranges)
    assert plain.whitening is None
    white = Describer(ModelConfig(weights=str(target), precision="fp32"))
    assert np.allclose(white.describe_tensors(images, ranges), w.apply(raw), atol=1e-5)
    off = Describer(ModelConfig(weights=str(target), precision="fp32", whitening=False))
    assert off.whitening is None and np.allclose(off.describe_tensors(images, ranges), raw, atol=1e-6)
    assert off.weights_id == plain.weights_id != white.weights_id  # maps tell the two descriptor spaces apart


def test_lcpr_train_whiten_fits_on_every_frame_of_the_bags_and_writes_the_target(checkpoint, tmp_path, capsys):
    bag = tmp_path / "drive.bag"
    bag.mkdir()
    (bag / "metadata.yaml").write_text("stand-in: the cache below is up to date for it\n")
    cache = write_tiny_cache(tmp_path / "cache")
    (cache / "meta.json").write_text(json.dumps(cache_meta([bag], TINY) | {"samples": 24}))
    target = tmp_path / "whitened.pth"
    code = lcpr_train([str(bag), "--whiten", str(checkpoint), str(target), "--cache", str(cache),
                       "--whiten-dims", "16", "--quiet"])
    assert code == 0
    w = read_whitening(target)
    assert w is not None and w.samples == 24 and w.dims == 16 and w.power == 0.5
    assert "whitening fitted on 24 frames (16 of 256 directions, power 0.5)" in capsys.readouterr().out


def test_lcpr_train_whiten_refuses_a_checkpoint_without_sizes(tmp_path, capsys):
    plain = tmp_path / "plain.pth"
    torch.save(make_model(tiny_config()).state_dict(), plain)
    bag = tmp_path / "drive.bag"
    bag.mkdir()
    code = lcpr_train([str(bag), "--whiten", str(plain), str(tmp_path / "t.pth"), "--out", str(tmp_path)])
    assert code == 2 and "has no 'config' entry" in capsys.readouterr().err


def test_the_recipe_rule_takes_the_best_max_f1_within_one_point_of_recall_or_nothing():
    def v(r: float, f: float) -> dict:
        return {"mean_recall@1": r, "mean_max_f1": f}

    assert choose_whitening({"none": v(0.90, 0.70), "a": v(0.895, 0.80), "b": v(0.85, 0.90)}) == "a"
    assert choose_whitening({"none": v(0.90, 0.70), "a": v(0.88, 0.80)}) == "none"
    assert choose_whitening({"none": v(0.90, 0.70), "a": v(0.95, 0.69)}) == "none"


def test_the_recipe_ranking_never_offers_a_keyframe_newer_than_the_exclusion():
    stamps = np.arange(10) * 10.0
    desc = np.random.default_rng(0).normal(size=(10, 4))
    ids, dist = online_ranking(desc, stamps, exclude_recent_s=30.0, k=3)
    assert (ids[:3] == -1).all() and np.isinf(dist[:3]).all()
    for i in range(3, 10):
        valid = ids[i][ids[i] >= 0]
        assert len(valid) == min(3, i - 2) and (stamps[valid] <= stamps[i] - 30.0).all()
        assert np.all(np.diff(dist[i][: len(valid)]) >= 0)
