"""The training loop on tiny hand-made data: a step learns, checkpoints load, resume counts on."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from lcpr_core import ModelConfig, build_model
from lcpr_core.lcpr.checkpoint import trained_lidar_only
from lcpr_core.lcpr.describer import Describer, checkpoint_config
from lcpr_core.lcpr.training import Trainer, TrainingData, export_weights, open_cache
from lcpr_core.lcpr.training.mining import Triplet
from training_fixtures import TINY, tiny_config, write_tiny_cache


@pytest.fixture
def data(tmp_path) -> TrainingData:
    return TrainingData.from_cache(open_cache(write_tiny_cache(tmp_path / "cache")), tiny_config().split)


def quiet(_: str) -> None:
    pass


def test_a_few_steps_on_one_batch_decrease_the_triplet_loss(data, tmp_path):
    trainer = Trainer(data, tiny_config(lr=1e-3), tmp_path / "run", progress=False, echo=quiet)
    split = data.split
    q = int(split.train[0])
    batch = [Triplet(query=q, positive=int(split.positives(q)[0]), negatives=tuple(split.negatives(q)[:3].tolist()))]
    trainer.model.train()
    losses = [trainer.step(batch) for _ in range(6)]
    assert losses[-1] < losses[0]


def test_training_writes_loadable_released_format_checkpoints_and_a_curve(data, tmp_path):
    out = tmp_path / "run"
    history = Trainer(data, tiny_config(epochs=1), out, progress=False, echo=quiet).fit()
    assert [h["epoch"] for h in history] == [0, 1]
    assert {"recall@1", "recall@5", "recall@10"} <= set(history[1]) and history[1]["loss"] is not None
    for name in ("init.pth", "last.pth", "best.pth", "curve.png", "history.json"):
        assert (out / name).is_file(), name
    ckpt = torch.load(out / "best.pth", weights_only=True)
    assert {"epoch", "net", "scheduler", "config"} <= set(ckpt) and ckpt["epoch"] == 1
    model = build_model(ModelConfig(weights=str(out / "best.pth")))  # width and sizes from the file
    assert model.width == TINY.width and model.image_size == TINY.image_size and model.num_cameras == 2
    assert model.range_size == TINY.range_size
    assert all(torch.equal(model.state_dict()[k], v) for k, v in ckpt["net"].items())


def test_resume_continues_the_epoch_count_and_history(data, tmp_path):
    out = tmp_path / "run"
    Trainer(data, tiny_config(epochs=1), out, progress=False, echo=quiet).fit()
    lr_after_one = torch.load(out / "last.pth", weights_only=True)["optimizer"]["param_groups"][0]["lr"]
    again = Trainer(data, tiny_config(epochs=2), out, progress=False, echo=quiet)
    history = again.fit(resume=True)
    assert [h["epoch"] for h in history] == [0, 1, 2]
    assert again.epoch == 2 and torch.load(out / "last.pth", weights_only=True)["epoch"] == 2
    assert history[2]["lr"] == pytest.approx(lr_after_one)


def test_resume_refuses_a_run_of_another_width(data, tmp_path):
    out = tmp_path / "run"
    Trainer(data, tiny_config(epochs=1), out, progress=False, echo=quiet).fit()
    wider = dataclasses.replace(tiny_config(epochs=2), inputs=dataclasses.replace(TINY, width=0.25))
    with pytest.raises(Exception, match="width"):
        Trainer(data, wider, out, progress=False, echo=quiet).fit(resume=True)


def test_the_checkpoint_config_roundtrips_into_the_describer_and_a_float16_export(data, tmp_path):
    out = tmp_path / "run"
    trainer = Trainer(data, tiny_config(epochs=1), out, progress=False, echo=quiet)
    trainer.fit()
    entry = checkpoint_config(out / "best.pth")
    assert entry == {"width": 0.125, "num_cameras": 2, "image_size": [32, 64], "range_size": [8, 64],
                     "lidar": "nuscenes_lidar_top"}
    describer = Describer(ModelConfig(weights=str(out / "best.pth")))
    assert describer.config.image_size == (32, 64) and describer.config.range_preset.width == 64
    assert describer.config.width == 0.125
    small = tmp_path / "small.pth"
    export_weights(out / "best.pth", small)
    payload = torch.load(small, weights_only=True)
    assert "optimizer" not in payload and payload["net"]["conv1_i.weight"].dtype == torch.float16
    half = build_model(ModelConfig(weights=str(small)))
    full = build_model(ModelConfig(weights=str(out / "best.pth")))
    images, ranges = data.inputs([0, 5])
    with torch.inference_mode():
        assert np.allclose(half(images, ranges).numpy(), full(images, ranges).numpy(), atol=2e-2)
    assert checkpoint_config(tmp_path / "run" / "init.pth") == entry


def test_a_time_budget_cuts_the_epoch_short_and_stops_there(data, tmp_path):
    config = dataclasses.replace(tiny_config(), optim=dataclasses.replace(tiny_config().optim, epochs=5,
                                                                           time_budget_s=1e-6))
    said: list[str] = []
    history = Trainer(data, config, tmp_path / "run", progress=False, echo=said.append).fit()
    assert [h["epoch"] for h in history] == [0, 1]
    assert history[1]["cut_short"] and history[1]["trained"] == 0 and history[1]["loss"] is None
    assert any("time budget" in line and "during epoch 1" in line for line in said)


def test_a_generous_time_budget_changes_nothing(data, tmp_path):
    config = dataclasses.replace(tiny_config(), optim=dataclasses.replace(tiny_config().optim, epochs=2,
                                                                           time_budget_s=1e6))
    history = Trainer(data, config, tmp_path / "run", progress=False, echo=quiet).fit()
    assert [h["epoch"] for h in history] == [0, 1, 2]
    assert not any(h.get("cut_short") for h in history) and history[2]["trained"] == history[2]["tuples"]


def test_bf16_autocast_trains_and_describes_close_to_float32(data, tmp_path):
    fp32 = Trainer(data, tiny_config(), tmp_path / "a", progress=False, echo=quiet)
    bf16 = Trainer(data, dataclasses.replace(tiny_config(), amp="bf16"), tmp_path / "b", progress=False, echo=quiet)
    samples = np.arange(len(data))
    a, b = fp32.describe(samples), bf16.describe(samples)  # same seed: the same initial weights
    assert not np.array_equal(a, b)  # bf16 really ran
    cos = np.sum(a * b, axis=1) / np.linalg.norm(a, axis=1) / np.linalg.norm(b, axis=1)
    assert cos.min() > 0.99
    history = bf16.fit()
    assert history[1]["loss"] is not None and np.isfinite(history[1]["loss"])


def test_an_unknown_amp_mode_is_refused_by_name():
    with pytest.raises(ValueError, match="amp='fp8'.*off, bf16"):
        dataclasses.replace(tiny_config(), amp="fp8")


def test_the_cli_builds_the_time_budget_and_amp_into_the_config():
    from lcpr_offline.lcpr_train import build_parser, config_from_args

    args = build_parser().parse_args(["a.bag", "--time-budget", "300", "--amp", "bf16", "--cache-workers", "4"])
    config = config_from_args(args)
    assert config.optim.time_budget_s == 300 and config.amp == "bf16" and args.cache_workers == 4


def run_tool(name: str, *args: str) -> str:
    """Run ``benchmarks/tools/NAME.py`` as a user does (the venv's python, the installed package); its stdout."""
    import subprocess
    import sys
    from pathlib import Path

    script = Path(__file__).resolve().parents[4] / "benchmarks" / "tools" / f"{name}.py"
    done = subprocess.run([sys.executable, str(script), *args], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    return done.stdout


def test_the_gpu_forward_tool_prints_medians_for_both_precisions_and_batches():
    out = run_tool("lcpr_gpu_forward", "--device", "cpu", "--small", "--repeats", "1")
    assert "width 0.25, 6 x 64x192 images" in out
    for line in ("fp32: one pass", "bf16: one pass"):
        assert line in out and "turn-averaged (six turns, batch 6)" in out


def test_the_evaluation_table_prints_one_line_per_report_in_name_order(tmp_path):
    import json

    for name, r1 in (("eval_b", 0.5), ("eval_a", 0.25)):
        (tmp_path / name).mkdir()
        methods = [{"name": "LCPR", "online": {"recall_at": {"1": r1}, "max_f1": 0.8, "max_f1_threshold": 0.7}},
                   {"name": "Scan Context", "online": None}]
        (tmp_path / name / "report.json").write_text(json.dumps({"methods": methods}))
    assert run_tool("eval_table", str(tmp_path)).splitlines() == [
        "eval_a LCPR: R@1 0.250 max F1 0.800 thr 0.7 | Scan Context: R@1 nan max F1 0.000 thr None",
        "eval_b LCPR: R@1 0.500 max F1 0.800 thr 0.7 | Scan Context: R@1 nan max F1 0.000 thr None",
    ]


def test_lidar_only_training_never_shows_the_network_a_camera_and_marks_its_weights(data, tmp_path):
    config = dataclasses.replace(tiny_config(epochs=1), lidar_only=True)
    trainer = Trainer(data, config, tmp_path / "run", progress=False, echo=quiet)
    assert trainer.data.lidar_only and not data.lidar_only  # the config decides
    images, _ = trainer.data.inputs(data.split.train[:3])
    assert not images.any()
    with_cameras, _ = data.inputs(data.split.train[:3])
    assert with_cameras.any()
    trainer.fit()
    export_weights(tmp_path / "run" / "best.pth", tmp_path / "lidar.pth")
    assert trained_lidar_only(tmp_path / "lidar.pth") and trained_lidar_only(tmp_path / "run" / "best.pth")
    Trainer(data, tiny_config(epochs=1), tmp_path / "plain", progress=False, echo=quiet).fit()
    assert not trained_lidar_only(tmp_path / "plain" / "best.pth")


def test_whitening_of_lidar_only_weights_is_fitted_on_frames_without_cameras(data, tmp_path, monkeypatch):
    from lcpr_core.lcpr.training import whiten

    Trainer(data, dataclasses.replace(tiny_config(epochs=1), lidar_only=True), tmp_path / "run", progress=False,
            echo=quiet).fit()
    seen: list[bool] = []
    real = whiten.describe_samples

    def spy(model, described, *args, **kwargs):
        seen.append(described.lidar_only)
        return real(model, described, *args, **kwargs)

    monkeypatch.setattr(whiten, "describe_samples", spy)
    whiten.whiten_checkpoint(tmp_path / "run" / "best.pth", tmp_path / "w.pth", data, dims=8, progress=False)
    assert seen == [True] and trained_lidar_only(tmp_path / "w.pth")


def test_the_cli_builds_lidar_only_training_and_the_sensor_augmentations():
    from lcpr_offline.lcpr_train import build_parser, config_from_args

    args = build_parser().parse_args(["a.bag", "--lidar-only", "--augment-lidar-fov", "0.3",
                                      "--augment-lidar-sparse", "0.2"])
    config = config_from_args(args)
    assert config.lidar_only and config.augment.lidar_fov == 0.3 and config.augment.lidar_sparse == 0.2
    assert not config_from_args(build_parser().parse_args(["a.bag"])).lidar_only
