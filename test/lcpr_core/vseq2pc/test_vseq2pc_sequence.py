"""Online query sequences agree with the offline table and with preprocess.sequence_indices."""
from __future__ import annotations

import numpy as np
import pytest

from lcpr_core.errors import InputShapeError
from lcpr_core.vseq2pc import SequenceBatch, SequenceBuilder
from lcpr_core.vseq2pc.preprocess import sequence_indices
from lcpr_core.vseq2pc.sequence import SequenceConfig, sequence_table


def drive(n: int, seed: int = 0) -> np.ndarray:
    """A wiggly path with irregular steps (0 to 2.5 m, some standing still)."""
    rng = np.random.default_rng(seed)
    steps = rng.uniform(0.0, 2.5, n) * (rng.random(n) > 0.1)
    heading = np.cumsum(rng.normal(0, 0.2, n))
    xy = np.cumsum(np.stack([steps * np.cos(heading), steps * np.sin(heading)], axis=1), axis=0)
    return np.c_[xy, rng.normal(0, 0.3, n)]  # z must not count


def features(n: int) -> np.ndarray:
    return np.arange(n, dtype=np.float32)[:, None, None] * np.ones((1, 12, 90), np.float32)


def feed(builder: SequenceBuilder, positions: np.ndarray, valid: np.ndarray | None = None
         ) -> tuple[list[SequenceBatch], list[int]]:
    feats = features(len(positions))
    batches, emitted_at = [], []
    for i, p in enumerate(positions):
        ok = valid is None or valid[i]
        batch = builder.push(feats[i] if ok else None, stamp=100.0 + i, pose=p)
        if batch is not None:
            batches.append(batch)
            emitted_at.extend([i] * len(batch))
    return batches, emitted_at


def test_the_builder_picks_the_frames_the_offline_table_and_sequence_indices_pick() -> None:
    pos = drive(300)
    table = sequence_table(pos)
    batches, emitted_at = feed(SequenceBuilder(), pos)
    indices = np.concatenate([b.indices for b in batches])
    complete = np.flatnonzero(table[:, 0] >= 0)
    np.testing.assert_array_equal(indices, table[complete])
    for q in complete[::7]:
        assert sequence_indices(pos[:, :2], int(q)) == table[q].tolist()
    assert sequence_indices(pos[:, :2], int(complete[-1]) + 1) is None
    # each query comes out exactly when its last member arrives, with that frame's data
    np.testing.assert_array_equal(emitted_at, indices[:, -1])
    frames = np.concatenate([b.frames for b in batches])
    assert frames.shape == (len(indices), 4, 12, 90) and frames.dtype == np.float32
    np.testing.assert_array_equal(frames[:, :, 0, 0], indices.astype(np.float32))
    stamps = np.concatenate([b.stamps for b in batches])
    np.testing.assert_array_equal(stamps, 100.0 + indices)
    np.testing.assert_array_equal(np.concatenate([b.query_poses for b in batches])[:, :3, 3], pos[indices[:, 0]])


def test_frames_without_a_camera_feature_are_never_members_but_count_for_distance() -> None:
    pos = np.c_[np.arange(60) * 1.0, np.zeros(60), np.zeros(60)]  # 1 m per frame on a line
    valid = np.ones(60, bool)
    valid[[5, 6, 15]] = False
    table = sequence_table(pos, valid)
    assert table[0].tolist() == [0, 7, 10, 16]  # 5 and 6 missing -> 7; 15 missing -> 16
    assert (table[~valid] == -1).all()
    batches, _ = feed(SequenceBuilder(), pos, valid)
    indices = np.concatenate([b.indices for b in batches])
    np.testing.assert_array_equal(indices, table[table[:, 0] >= 0])


def test_nothing_comes_out_before_the_vehicle_has_driven_15_m() -> None:
    builder = SequenceBuilder()
    for i in range(15):
        assert builder.push(features(1)[0], stamp=float(i), pose=np.array([float(i), 0.0])) is None
    assert builder.pending == 15
    batch = builder.push(features(1)[0], stamp=15.0, pose=np.array([15.0, 0.0]))
    assert batch is not None and batch.indices.tolist() == [[0, 5, 10, 15]]
    assert batch.query_indices.tolist() == [0] and batch.query_stamps.tolist() == [0.0]


def test_query_spacing_thins_the_queries_but_not_the_members() -> None:
    pos = np.c_[np.arange(80) * 1.0, np.zeros(80)]
    batches, _ = feed(SequenceBuilder(SequenceConfig(min_query_spacing_m=10.0)), pos)
    indices = np.concatenate([b.indices for b in batches])
    assert indices[:, 0].tolist() == list(range(0, 65, 10))
    assert indices[0].tolist() == [0, 5, 10, 15]


def test_bad_frames_and_settings_are_refused() -> None:
    builder = SequenceBuilder()
    with pytest.raises(InputShapeError, match="12 x 90"):
        builder.push(np.zeros((12, 360)), stamp=0.0, pose=np.eye(4))
    with pytest.raises(InputShapeError, match="pose"):
        builder.push(None, stamp=0.0, pose=np.zeros(5))
    builder.push(None, stamp=0.0, pose=np.eye(4), index=4)
    with pytest.raises(ValueError, match="not after"):
        builder.push(None, stamp=0.1, pose=np.eye(4), index=4)
    with pytest.raises(ValueError, match="ascending"):
        SequenceConfig(offsets=(10.0, 5.0))
