"""The paper's evaluation on hand-made features whose answers are known."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from torch import nn

from lcpr_core.vseq2pc.dataset import FeatureCache
from lcpr_core.vseq2pc.evaluate import EvalConfig, evaluate, evaluate_feature_match
from lcpr_core.vseq2pc.net import Vseq2pcNet
from lcpr_core.vseq2pc.pairs import evaluation_pairs, place_label
from lcpr_offline.vseq2pc_evaluate import main


class FirstFrame(nn.Module):
    """A 'sequence model' that returns the query frame's feature."""

    def forward(self, frames: torch.Tensor) -> torch.Tensor:
        return frames[:, 0]


class PositionDescriptor(nn.Module):
    """A 'descriptor model' that reads the position written into rows 0 and 1 of a feature (km), and
    scores a pair by minus the distance in metres: a perfect place recogniser."""

    def __init__(self) -> None:
        super().__init__()
        self.unused = nn.Parameter(torch.zeros(1))

    @staticmethod
    def _code(feature: torch.Tensor) -> torch.Tensor:
        xy = feature[:, :2, 135:225].mean(dim=2) if feature.shape[-1] == 360 else feature[:, :2].mean(dim=2)
        return torch.nn.functional.pad(1000.0 * xy, (0, 286))

    def scan_descriptor(self, slices: torch.Tensor) -> torch.Tensor:
        return self._code(slices)

    def sequence_descriptor(self, f_seq: torch.Tensor, f_img: torch.Tensor) -> torch.Tensor:
        return self._code(f_img)

    def logit(self, d_seq: torch.Tensor, d_scan: torch.Tensor) -> torch.Tensor:
        return -torch.linalg.vector_norm(d_seq - d_scan, dim=-1)


def square_drive(laps: float = 1.5, side: float = 100.0, step: float = 2.0) -> np.ndarray:
    s = np.arange(0.0, laps * 4 * side, step)
    u = (s % (4 * side)) / side
    x = np.select([u < 1, u < 2, u < 3], [u * side, side, (3 - u) * side], 0.0)
    y = np.select([u < 1, u < 2, u < 3], [0.0, (u - 1) * side, side], (4 - u) * side)
    return np.c_[x, y, np.zeros_like(x)]


NO_LIARS = np.zeros(0, np.int64)  # read-only default of position_cache


def position_cache(pos: np.ndarray, *, lie_about: np.ndarray = NO_LIARS) -> FeatureCache:
    n = len(pos)
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, :3, 3] = pos
    lidar = np.zeros((n, 12, 360), np.float32)
    lidar[:, 0], lidar[:, 1] = pos[:, :1] / 1000.0, pos[:, 1:2] / 1000.0
    camera = lidar[:, :, 135:225].copy()
    across = lie_about - 100  # half a lap (100 frames, 200 m) back: the opposite side of the square
    camera[lie_about, 0], camera[lie_about, 1] = camera[across, 0], camera[across, 1]  # claims to be there
    return FeatureCache(camera=camera, camera_valid=np.ones(n, bool), lidar=lidar, poses=poses,
                        stamps=np.arange(n) * 0.2)


@pytest.fixture(scope="module")
def oracle() -> Vseq2pcNet:
    return Vseq2pcNet.from_models(FirstFrame(), PositionDescriptor())  # type: ignore[arg-type]


def loop_queries(pos: np.ndarray, queries: np.ndarray, gap: int = 50, radius: float = 5.0) -> list[int]:
    out = []
    for q in queries:
        if any(np.hypot(*(pos[q, :2] - pos[j, :2])) <= radius for j in range(0, max(0, q - gap))):
            out.append(int(q))
    return out


def test_labels_follow_the_release_formula() -> None:
    np.testing.assert_allclose(place_label(np.array([0.0, 2.99, 10.0])), [1.0, 1.0, 0.5])
    assert place_label(np.array([3.0]))[0] == pytest.approx(1 - 1 / (1 + np.exp(7 / 1.5)))
    assert place_label(np.array([25.0]))[0] < 1e-4


def test_pairs_are_every_close_pair_far_apart_in_time_and_100_negatives_each() -> None:
    pos = square_drive()
    queries = np.arange(len(pos) - 8)
    pairs = evaluation_pairs(pos, queries, rng=np.random.default_rng(0))
    expected = {(int(q), j) for q in queries for j in range(len(pos))
                if abs(q - j) > 50 and np.hypot(*(pos[q, :2] - pos[j, :2])) < 3.0}
    got = {(int(q), int(s)) for q, s, p in zip(pairs.query, pairs.scan, pairs.positive, strict=True) if p}
    assert got == expected
    negatives = ~pairs.positive
    assert negatives.sum() == 100 * len(expected) and (pairs.distance[negatives] > 20).all()
    assert len(
        set(zip(pairs.query[negatives].tolist(), pairs.scan[negatives].tolist(), strict=True))
    ) == negatives.sum()


def test_a_perfect_recogniser_scores_max_f1_one_and_finds_every_loop(oracle: Vseq2pcNet) -> None:
    pos = square_drive()
    cache = position_cache(pos)
    result = evaluate(oracle, cache, name="oracle")
    complete = np.flatnonzero(cache.sequences()[:, 0] >= 0)
    assert result.num_loop_queries == len(loop_queries(pos, complete)) == 94  # 2nd lap + 2 frames nearing the start
    assert result.max_f1 == pytest.approx(1.0)
    assert result.recall_at == {1: 1.0, 5: 1.0, 10: 1.0}
    assert result.num_negative_pairs == 100 * result.num_positive_pairs


def test_queries_whose_camera_lies_about_the_place_are_the_misses(oracle: Vseq2pcNet) -> None:
    pos = square_drive()
    complete = np.flatnonzero(position_cache(pos).sequences()[:, 0] >= 0)
    loops = loop_queries(pos, complete)
    liars = np.array(loops[::10])  # 10 of the 94 loop queries
    result = evaluate(oracle, position_cache(pos, lie_about=liars), name="liars")
    expected = 1.0 - len(liars) / len(loops)
    assert result.recall_at[1] == pytest.approx(expected) and result.recall_at[10] == pytest.approx(expected)
    assert result.max_f1 is not None and result.max_f1 < 1.0


def test_single_frame_mode_and_the_feature_match_reference_find_every_loop_too(oracle: Vseq2pcNet) -> None:
    cache = position_cache(square_drive())
    single = evaluate(oracle, cache, name="single", config=EvalConfig(single_frame=True))
    assert single.recall_at[1] == 1.0
    reference = evaluate_feature_match(cache)  # the camera feature equals the scan's forward window here
    assert reference.recall_at[1] == 1.0 and reference.max_f1 == pytest.approx(1.0)


def test_a_shorter_sequence_repeats_its_last_frame_and_one_frame_is_the_single_frame_mode(oracle: Vseq2pcNet) -> None:
    cache = position_cache(square_drive())
    one = evaluate(oracle, cache, name="1", config=EvalConfig(sequence_length=1))
    single = evaluate(oracle, cache, name="single", config=EvalConfig(single_frame=True))
    assert one.recall_at == single.recall_at and one.max_f1 == single.max_f1
    assert evaluate(oracle, cache, name="2", config=EvalConfig(sequence_length=2)).recall_at[1] == 1.0
    with pytest.raises(ValueError, match="sequence_length=5; expected 1 to 4 frames"):
        EvalConfig(sequence_length=5)


def test_the_command_compares_untrained_with_given_weights_and_writes_json_and_png(tmp_path: Path,
                                                                                    capsys) -> None:
    from lcpr_core.vseq2pc.checkpoint import save_descriptor_weights, save_sequence_weights
    from lcpr_core.vseq2pc.initialisation import seeded_models

    cache = position_cache(square_drive(laps=1.6, side=30.0))  # 96 frames: the real networks stay quick
    cache.save(tmp_path / "cache.npz")
    seq, desc = seeded_models(7)
    save_sequence_weights(seq, tmp_path / "w" / "sequence_model.pth")
    save_descriptor_weights(desc, tmp_path / "w" / "descriptor_model.pth")
    assert main(["--cache", str(tmp_path / "cache.npz"), "--weights-dir", str(tmp_path / "w"), "--untrained",
                 "--feature-match", "--out", str(tmp_path / "eval"), "--negatives", "5"]) == 0
    printed = capsys.readouterr().out
    assert "untrained (seed 0)" in printed and "trained" in printed and "R@10" in printed
    report = json.loads((tmp_path / "eval" / "eval.json").read_text())
    assert [m["name"] for m in report["methods"]] == ["feature match (no network)", "untrained (seed 0)", "trained"]
    assert set(report["methods"][2]["recall_at"]) == {"1", "5", "10"}
    assert (tmp_path / "eval" / "pr.png").stat().st_size > 1000
