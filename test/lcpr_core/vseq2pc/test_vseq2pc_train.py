"""A tiny VSeq2PC training run: it runs, writes loadable weights in the released layouts, and resumes."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from lcpr_core.vseq2pc import Vseq2pcNet
from lcpr_core.vseq2pc.dataset import FeatureCache
from lcpr_core.vseq2pc.initialisation import seeded_models
from lcpr_core.vseq2pc.pairs import TrainPairConfig, training_pairs
from lcpr_core.vseq2pc.training import TrainConfig, lr_at, place_loss, ranking_loss, split, train
from lcpr_offline.vseq2pc_train import main


def line_cache(n: int = 48, step: float = 1.5, seed: int = 0) -> FeatureCache:
    """A drive along a line; each frame's LiDAR feature is random, its camera sees the forward 90 degrees."""
    rng = np.random.default_rng(seed)
    lidar = (rng.random((n, 12, 360)) * (rng.random((n, 12, 360)) > 0.7)).astype(np.float32)
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, 0, 3] = np.arange(n) * step
    return FeatureCache(camera=lidar[:, :, 135:225].copy(), camera_valid=np.ones(n, bool), lidar=lidar,
                        poses=poses, stamps=np.arange(n) * 0.15, source="hand-made")


def tiny(tmp_path: Path, **changes: object) -> TrainConfig:
    line_cache().save(tmp_path / "cache.npz")
    base = dict(caches=(str(tmp_path / "cache.npz"),), out=str(tmp_path / "run"), pretrain_epochs=1, epochs=1,
                batch=4, queries_per_epoch=8, val_fraction=0.25, val_negatives=2, progress=False,
                seq_base_lr=0.05)
    return TrainConfig(**{**base, **changes})  # type: ignore[arg-type]


def test_one_epoch_of_each_stage_writes_weights_that_load_and_a_history(tmp_path: Path) -> None:
    run = train(tiny(tmp_path))
    out = tmp_path / "run"
    assert [(h["stage"], h["epoch"]) for h in run.history] == [(1, 1), (2, 1)]
    assert all(np.isfinite(h["train_loss"]) for h in run.history)
    assert run.history[1]["val_max_f1"] is not None
    net = Vseq2pcNet.from_files(sequence=out / "sequence_model.pth", descriptor=out / "descriptor_model.pth")
    for name, value in net.sequence.state_dict().items():
        assert torch.equal(value, run.seq.state_dict()[name])
    assert list(torch.load(out / "descriptor_model.pth", weights_only=True)) == ["state_dict"]
    assert (out / "best_descriptor_model.pth").is_file() and (out / "curves.png").stat().st_size > 1000
    assert len(json.loads((out / "history.json").read_text())["history"]) == 2
    torch.load(out / "train_state.pt", weights_only=True)  # no pickled objects


def test_resume_continues_after_the_last_finished_epoch(tmp_path: Path) -> None:
    train(tiny(tmp_path))
    run = train(tiny(tmp_path, epochs=2, resume=True))
    assert [(h["stage"], h["epoch"]) for h in run.history] == [(1, 1), (2, 1), (2, 2)]


def test_pretraining_lowers_the_reconstruction_error_on_a_fixed_batch(tmp_path: Path) -> None:
    # every training query in one batch: each epoch is one step on the same batch
    run = train(tiny(tmp_path, pretrain_epochs=6, epochs=0, queries_per_epoch=None, batch=64,
                     seq_warmup_epochs=0.0, seq_base_lr=0.0004))
    losses = [h["train_loss"] for h in run.history]
    assert losses[-1] < losses[0]


def test_the_command_line_trains_and_reports(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    line_cache().save(tmp_path / "cache.npz")
    code = main(["--cache", str(tmp_path / "cache.npz"), "--out", str(tmp_path / "cli"), "--pretrain-epochs", "0",
                 "--epochs", "1", "--batch", "4", "--queries-per-epoch", "4", "--no-progress"])
    assert code == 0 and "stage 2 epoch 1" in capsys.readouterr().out
    assert main(["--cache", str(tmp_path / "missing.npz"), "--out", str(tmp_path / "x")]) == 2


def test_pairs_losses_and_schedule_follow_the_release() -> None:
    pos = np.c_[np.arange(100) * 1.5, np.zeros(100), np.zeros(100)]
    pairs = training_pairs(pos, np.arange(0, 60, 7), np.arange(100), config=TrainPairConfig(negatives=3),
                           rng=np.random.default_rng(0))
    assert len(pairs) == 9 * 4
    grouped = pairs.distance.reshape(9, 4)
    assert (grouped[:, 0] < 3).all() and (grouped[:, 1:] > 20).all()
    perfect = place_loss(torch.tensor([20.0, -20.0]), torch.tensor([0.0, 1.0]), torch.tensor([1.0, 0.0]), margin=0.2)
    assert float(perfect) < 1e-6
    hinge = place_loss(torch.tensor([-20.0]), torch.tensor([0.01]), torch.tensor([0.0]), margin=0.2)
    assert float(hinge) == pytest.approx((0.2 - 0.1) ** 2, abs=1e-6)
    assert lr_at(0, base=1.0, warmup_steps=4, total_steps=12) == 0.25
    assert lr_at(4, base=1.0, warmup_steps=4, total_steps=12) == 1.0
    assert lr_at(12, base=1.0, warmup_steps=4, total_steps=12) == pytest.approx(0.0)
    seq, _ = seeded_models(0)
    with torch.no_grad():
        f = seq.eval()(torch.from_numpy(line_cache().camera[:4][None]))
    inside = float(((f > 0) & (f < 1)).float().mean())
    assert inside > 0.3  # the training init starts largely inside the clamp (PyTorch's default: ~0.1 %)


def test_drives_trained_together_keep_their_own_sequences_and_never_pair_as_positives() -> None:
    a, b = line_cache(40, seed=1), line_cache(30, seed=2)  # both start at the origin
    train_part, val = split([a, b], 0.25)
    assert val is not None
    assert len(train_part.positions) == 70 and len(train_part.scans) == 30 + 22
    assert train_part.queries.max() < 70 and set(train_part.queries) & set(range(40, 70))
    for q in train_part.queries:  # every sequence stays inside its drive
        frames = train_part.sequences[q]
        assert (frames < 40).all() if q < 40 else (frames >= 40).all()
    assert torch.equal(train_part.camera[45], torch.from_numpy(b.camera[5]))
    pairs = training_pairs(train_part.positions, train_part.queries, train_part.scans,
                           config=TrainPairConfig(negatives=2), rng=np.random.default_rng(0))
    same_drive = (pairs.query < 40) == (pairs.scan < 40)
    assert (same_drive[pairs.positive]).all() and (pairs.label[~same_drive] < 1e-6).all()
    assert set(val.queries) == {q for q in val.queries if (30 <= q < 40) or q >= 40 + 22}


def test_the_command_line_takes_several_drives(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    line_cache(seed=1).save(tmp_path / "a.npz")
    line_cache(seed=2).save(tmp_path / "b.npz")
    code = main(["--cache", str(tmp_path / "a.npz"), str(tmp_path / "b.npz"), "--out", str(tmp_path / "cli"),
                 "--pretrain-epochs", "0", "--epochs", "1", "--batch", "4", "--queries-per-epoch", "4",
                 "--no-progress", "--no-in-batch"])
    assert code == 0
    config = json.loads((tmp_path / "cli" / "history.json").read_text())["config"]
    assert len(config["caches"]) == 2 and config["in_batch"] is False


def test_the_straight_through_clamp_changes_the_gradients_and_not_the_values() -> None:
    seq, _ = seeded_models(0)
    with torch.no_grad():
        seq.decoder.head.bias.fill_(-5.0)  # every output cell below 0: clamped
    frames = torch.rand(2, 4, 12, 90)
    grads, outputs = [], []
    for straight_through in (False, True):
        seq.straight_through_clamp = straight_through
        seq.zero_grad()
        torch.manual_seed(0)  # the same training-time token mask
        out = seq.train()(frames)
        out.sum().backward()
        outputs.append(out.detach())
        assert seq.decoder.head.bias.grad is not None
        grads.append(float(seq.decoder.head.bias.grad.abs().sum()))
    assert torch.equal(outputs[0], outputs[1]) and float(outputs[0].abs().max()) == 0.0
    assert grads[0] == 0.0 and grads[1] > 0.0


def test_the_ranking_term_is_zero_when_positives_lead_by_far_and_large_when_a_negative_leads() -> None:
    logits = torch.tensor([[9.0, -9.0, -9.0], [-9.0, 9.0, 0.0]])
    positive = torch.tensor([[True, False, False], [True, False, False]])
    negative = torch.tensor([[False, True, True], [False, True, False]])  # row 2's third scan has no label
    per_row = [ranking_loss(logits[i : i + 1], positive[i : i + 1], negative[i : i + 1]).item() for i in range(2)]
    assert per_row[0] == pytest.approx(np.log1p(2 * np.exp(-18.0)), abs=1e-6)
    assert per_row[1] == pytest.approx(18.0, abs=1e-6)  # log(e^-9 + e^9) - (-9), the unlabelled scan ignored
    assert ranking_loss(logits, positive, negative).item() == pytest.approx(np.mean(per_row), abs=1e-6)
    assert ranking_loss(logits, positive, torch.zeros_like(negative)).item() == 0.0  # no row has both


def test_hard_negatives_come_from_the_band_beyond_20_m_when_the_query_has_any_there() -> None:
    positions = np.zeros((200, 3))
    positions[:, 0] = np.arange(200) * 1.5  # a line: frame i is 1.5 i metres on
    pairs = training_pairs(positions, np.array([0, 100]), np.arange(200), rng=np.random.default_rng(0),
                           config=TrainPairConfig(negatives=20, negative_max_radius=40.0))
    negatives = pairs.distance[~pairs.positive]
    assert len(negatives) == 40 and negatives.min() > 20.0 and negatives.max() <= 40.0
    with pytest.raises(ValueError, match="negative_max_radius=15"):
        TrainPairConfig(negative_max_radius=15.0)


def test_a_run_with_the_ranking_term_picks_its_best_epoch_by_validation_recall(tmp_path: Path) -> None:
    there = line_cache(n=80, seed=3)
    back = np.r_[np.arange(80), np.arange(79, -1, -1)]  # out and back along the same line: revisits
    FeatureCache(camera=there.camera[back], camera_valid=there.camera_valid[back], lidar=there.lidar[back],
                 poses=there.poses[back], stamps=np.arange(160) * 0.15, source="there and back"
                 ).save(tmp_path / "val.npz")
    run = train(tiny(tmp_path, val_cache=str(tmp_path / "val.npz"), ranking_weight=1.0, select="recall_at_1",
                     epochs=2))
    rows = [h for h in run.history if h["stage"] == 2]
    assert all(np.isfinite(h["train_loss"]) and h["val_recall_at_1"] is not None for h in rows)
    assert run.best_f1 == max(h["val_recall_at_1"] for h in rows)
    with pytest.raises(ValueError, match="select='recall_at_1' needs val_cache"):
        tiny(tmp_path, select="recall_at_1")
    with pytest.raises(ValueError, match="select='best'"):
        tiny(tmp_path, select="best")


def test_one_pass_of_the_shared_tower_equals_two_in_eval_mode_and_mixes_the_batch_statistics_in_training() -> None:
    torch.manual_seed(0)
    _, desc = seeded_models(0)
    f_seq, f_img = torch.rand(3, 12, 90), torch.rand(3, 12, 90)
    slices = torch.rand(16, 12, 360) * 2.0  # scans unlike the camera features: their batch statistics differ
    desc.eval()
    d_seq, d_scan = desc.descriptors(f_seq, f_img, slices)
    assert torch.allclose(d_seq, desc.sequence_descriptor(f_seq, f_img), atol=1e-6)
    assert torch.allclose(d_scan, desc.scan_descriptor(slices), atol=1e-6)
    desc.train()
    mixed = desc.descriptors(f_seq, f_img, slices)[0]
    apart = desc.sequence_descriptor(f_seq, f_img)
    assert not torch.allclose(mixed, apart, atol=1e-3)


def test_a_run_with_mixed_batch_norm_ranking_and_reconstruction_trains_and_validates(tmp_path: Path) -> None:
    run = train(tiny(tmp_path, mixed_batch_norm=True, ranking_weight=0.5, reconstruction_weight=2.0))
    assert all(np.isfinite(h["train_loss"]) for h in run.history)
    assert run.history[-1]["val_max_f1"] is not None


@pytest.mark.parametrize("name", ["ranking_weight", "reconstruction_weight"])
def test_a_negative_loss_weight_is_refused_naming_it(tmp_path: Path, name: str) -> None:
    with pytest.raises(ValueError, match=f"{name}=-1"):
        tiny(tmp_path, **{name: -1.0})
