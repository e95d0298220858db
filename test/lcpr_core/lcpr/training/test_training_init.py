"""Fine-tuning (``lcpr_train --init``): the run starts from a trained checkpoint's network."""
from __future__ import annotations

import dataclasses

import pytest
import torch

from lcpr_core import CheckpointError
from lcpr_core.lcpr.training import Trainer, TrainingData, export_weights, open_cache
from lcpr_core.lcpr.training.config import PRESETS, checkpoint_inputs
from lcpr_core.lcpr.training.train import make_model
from lcpr_core.lcpr.whitening import ENTRY as WHITENING
from lcpr_offline.lcpr_train import build_parser, config_from_args
from training_fixtures import TINY, tiny_config, write_tiny_cache


def quiet(_: str) -> None:
    pass


@pytest.fixture
def trained(tmp_path):
    """A float16 export of a one-epoch run on the tiny data (what a bundled weights file is)."""
    data = TrainingData.from_cache(open_cache(write_tiny_cache(tmp_path / "cache")), tiny_config().split)
    Trainer(data, tiny_config(epochs=1), tmp_path / "run", progress=False, echo=quiet).fit()
    export_weights(tmp_path / "run" / "best.pth", tmp_path / "exported.pth", half=True)
    return tmp_path / "exported.pth", data


def test_a_run_with_init_starts_from_the_checkpoints_network_in_float32(trained, tmp_path):
    exported, data = trained
    state = torch.load(exported, weights_only=True)["net"]
    model = make_model(dataclasses.replace(tiny_config(), init=str(exported)))
    own = model.state_dict()
    assert all(own[k].dtype == torch.float32 for k in own if own[k].is_floating_point())
    assert all(torch.equal(own[k], v.to(own[k].dtype)) for k, v in state.items())
    fresh = make_model(tiny_config())
    assert any(not torch.equal(fresh.state_dict()[k], own[k]) for k in own if own[k].is_floating_point())

    trainer = Trainer(data, dataclasses.replace(tiny_config(epochs=1), init=str(exported)), tmp_path / "tuned",
                      progress=False, echo=quiet)
    history = trainer.fit()
    assert [h["epoch"] for h in history] == [0, 1]  # a fresh epoch count
    init = torch.load(tmp_path / "tuned" / "init.pth", weights_only=True)["net"]
    assert all(torch.equal(init[k], v.float()) for k, v in state.items())  # epoch 0 is the checkpoint
    assert WHITENING not in torch.load(tmp_path / "tuned" / "best.pth", weights_only=True)


def test_the_cli_takes_sizes_and_width_from_the_init_checkpoint_unless_a_preset_is_given(trained):
    exported, _ = trained
    config = config_from_args(build_parser().parse_args(["a.bag", "--init", str(exported)]))
    assert config.init == str(exported) and config.inputs == checkpoint_inputs(exported) == TINY
    preset = config_from_args(build_parser().parse_args(["a.bag", "--init", str(exported), "--preset", "cpu"]))
    assert preset.inputs == PRESETS["cpu"]
    assert config_from_args(build_parser().parse_args(["a.bag"])).inputs == PRESETS["cpu"]


def test_a_file_without_a_config_entry_is_the_released_configuration_for_init(tmp_path):
    torch.save({"net": {}}, tmp_path / "released.pth")
    config = config_from_args(build_parser().parse_args(["a.bag", "--init", str(tmp_path / "released.pth")]))
    assert config.inputs == PRESETS["released"]
    with pytest.raises(CheckpointError, match="has no 'config' entry"):
        checkpoint_inputs(tmp_path / "released.pth")


def test_an_init_checkpoint_of_another_width_is_refused_naming_the_mis_shaped_tensors(trained):
    exported, _ = trained
    wider = dataclasses.replace(tiny_config(), inputs=dataclasses.replace(TINY, width=0.25), init=str(exported))
    with pytest.raises(CheckpointError, match="mis-shaped"):
        make_model(wider)


def test_init_and_imagenet_together_are_refused_by_name():
    with pytest.raises(ValueError, match="imagenet='r18.pth' and init='w.pth'"):
        dataclasses.replace(tiny_config(), inputs=dataclasses.replace(TINY, width=1.0), imagenet="r18.pth",
                            init="w.pth")


def v(r: float, f: float) -> dict:
    """A validation point of the recipes' rules: mean Recall@1 and mean max F1."""
    return {"mean_recall@1": r, "mean_max_f1": f}


def test_the_finetune_recipe_adopts_only_a_point_of_max_f1_at_no_real_cost_in_recall():
    from lcpr_core.lcpr.training.recipe_rules import adopt_finetuned

    bundled = v(0.963, 0.887)
    assert adopt_finetuned(v(0.955, 0.900), bundled)
    assert not adopt_finetuned(v(0.990, 0.894), bundled)  # max F1 up less than a point
    assert not adopt_finetuned(v(0.950, 0.950), bundled)  # Recall@1 down more than a point


def test_lidar_only_weights_become_the_lidar_only_default_only_with_a_point_of_max_f1():
    from lcpr_core.lcpr.training.recipe_rules import adopt_lidar_only

    bundled = v(0.900, 0.800)
    assert adopt_lidar_only(v(0.895, 0.811), bundled)
    assert not adopt_lidar_only(v(0.990, 0.805), bundled)  # max F1 up less than a point
    assert not adopt_lidar_only(v(0.880, 0.900), bundled)  # Recall@1 down more than a point


def test_the_finetune_corpus_links_every_bag_and_refuses_a_seed_the_corpus_has(tmp_path):
    from pathlib import Path

    from lcpr_offline.lcpr_recipe import extend_corpus

    corpus = tmp_path / "corpus"
    for name in ("train_grid_s1", "val_grid_s3", "train_k00_s41"):
        (corpus / f"{name}.bag").mkdir(parents=True)
    bags = extend_corpus(corpus, tmp_path / "out", [])
    assert [Path(b).name for b in bags] == ["train_grid_s1.bag", "train_k00_s41.bag"]
    assert (tmp_path / "out" / "val_grid_s3.bag").resolve() == (corpus / "val_grid_s3.bag").resolve()
    with pytest.raises(SystemExit, match="41 is already a city"):
        extend_corpus(corpus, tmp_path / "out2", [41])


def test_a_recipe_reuses_a_report_only_when_it_was_made_after_and_with_the_same_weights(tmp_path):
    import json
    import os

    from lcpr_core.lcpr.training.recipe_rules import reusable_report

    ours, other = tmp_path / "ours.pth", tmp_path / "other.pth"
    for w in (ours, other):
        w.write_bytes(b"w")
        os.utime(w, (1_000, 1_000))
    report = tmp_path / "report.json"
    report.write_text(json.dumps({"settings": {"model": {"weights": str(ours)}}}))
    os.utime(report, (2_000, 2_000))
    assert reusable_report(report, ours)
    assert not reusable_report(report, other)  # left in the folder by another weights file
    os.utime(ours, (3_000, 3_000))
    assert not reusable_report(report, ours)  # the weights changed since
    assert not reusable_report(tmp_path / "missing.json", ours)


def test_the_recipes_refuse_a_corpus_without_its_cities_and_stages_that_do_not_rise(tmp_path):
    import json

    from lcpr_offline.lcpr_recipe import check_stages, require_corpus, trained_epochs

    (tmp_path / "val_grid_s3.bag").mkdir()
    with pytest.raises(SystemExit, match=r"missing \['val_k00_s45', 'test_grid_s7'"):
        require_corpus(tmp_path)
    check_stages([10, 20])
    with pytest.raises(SystemExit, match=r"--stages \[20, 10\]: must rise"):
        check_stages([20, 10])
    assert trained_epochs(tmp_path) == 0
    (tmp_path / "history.json").write_text(json.dumps([{"epoch": 0}, {"epoch": 7}]))
    assert trained_epochs(tmp_path) == 7
