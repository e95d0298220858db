"""The VSeq2PC scan database: exact batched search, exclusion rules, FAISS prefilter, files, the map API."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from lcpr_core import MapError, MapSchemaError
from lcpr_core.vseq2pc import DATABASE_SCHEMA_VERSION, ScanDatabase, SearchConfig, SequenceBatch, Vseq2pcMap, Vseq2pcNet

N = 240


@pytest.fixture(scope="module")
def net() -> Vseq2pcNet:
    return Vseq2pcNet.seeded(0)


@pytest.fixture(scope="module")
def slices() -> np.ndarray:
    return np.random.default_rng(1).random((N, 8, 288), dtype=np.float32)


@pytest.fixture(scope="module")
def queries() -> np.ndarray:
    return np.random.default_rng(2).random((4, 288), dtype=np.float32)


def brute_force(net: Vseq2pcNet, q: np.ndarray, slices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(Q, N) max-slice logits and best slices, one (query, slice) pair at a time through the head."""
    logits = np.empty((len(q), len(slices), 8), np.float32)
    with torch.no_grad():
        for i in range(len(q)):
            for j in range(len(slices)):
                d_seq = torch.from_numpy(q[i]).expand(8, -1)
                logits[i, j] = net.descriptor.logit(d_seq, torch.from_numpy(slices[j])).numpy()
    return logits.max(axis=2), logits.argmax(axis=2)


def database(slices: np.ndarray, stamps: np.ndarray | None = None) -> ScanDatabase:
    db = ScanDatabase(weights_id="w")
    db.add(slices, stamps=np.arange(len(slices), dtype=float) if stamps is None else stamps)
    return db


def test_the_batched_pass_ranks_every_scan_as_the_head_does_pair_by_pair(net, slices, queries) -> None:
    db = database(slices)
    found = db.search(queries, net.descriptor, config=SearchConfig(k=7, exclude_recent_s=None, chunk_scans=50))
    ref_logits, ref_best = brute_force(net, queries, slices)
    for i, matches in enumerate(found):
        order = np.argsort(-ref_logits[i], kind="stable")[:7]
        assert [m.row for m in matches] == order.tolist()
        assert [m.rank for m in matches] == list(range(7))
        np.testing.assert_allclose([m.logit for m in matches], ref_logits[i, order], atol=1e-5)
        assert [m.slice for m in matches] == ref_best[i, order].tolist()
        assert all(0 < m.probability < 1 for m in matches)


def test_scans_newer_than_the_time_window_are_never_returned(net, slices, queries) -> None:
    stamps = np.arange(N, dtype=float)
    for shuffled in (False, True):
        order = np.random.default_rng(3).permutation(N) if shuffled else np.arange(N)
        db = database(slices[order], stamps[order])
        found = db.search(queries, net.descriptor, config=SearchConfig(k=N, exclude_recent_s=30.0),
                          stamps=[100.0, 200.0, 29.0, 500.0])
        assert {m.stamp for m in found[0]} == set(np.arange(71.0))
        assert len(found[1]) == 171 and max(m.stamp for m in found[1]) == 170.0
        assert found[2] == []
        assert len(found[3]) == N


def test_a_frame_gap_excludes_the_query_row_the_rows_before_it_and_everything_after(net, slices, queries) -> None:
    db = database(slices)
    config = SearchConfig(k=N, exclude_recent_s=None, exclude_recent_rows=50)
    found = db.search(queries[:2], net.descriptor, config=config, rows=[120, 40])
    assert sorted(m.row for m in found[0]) == list(range(70))  # 120 - row > 50
    assert found[1] == []


def test_the_prefilter_scores_the_scans_nearest_by_min_slice_distance(net, slices, queries) -> None:
    db = database(slices)
    exact = db.search(queries, net.descriptor, config=SearchConfig(k=10, exclude_recent_s=None))
    whole = db.search(queries, net.descriptor, config=SearchConfig(k=10, exclude_recent_s=None, prefilter=N))
    assert [[m.row for m in r] for r in whole] == [[m.row for m in r] for r in exact]
    m = 25
    approx = db.search(queries, net.descriptor, config=SearchConfig(k=10, exclude_recent_s=None, prefilter=m))
    d2 = ((slices[None] - queries[:, None, None]) ** 2).sum(axis=3).min(axis=2)  # (Q, N)
    for i, matches in enumerate(approx):
        nearest = set(np.argsort(d2[i], kind="stable")[:m].tolist())
        assert len(matches) == 10 and {x.row for x in matches} <= nearest
        logits = [x.logit for x in matches]
        assert logits == sorted(logits, reverse=True)
    # with exclusion, the prefilter only looks at allowed scans
    db_t = database(slices)
    cut = db_t.search(queries, net.descriptor, config=SearchConfig(k=5, exclude_recent_s=30.0, prefilter=10),
                      stamps=100.0)
    assert all(x.stamp <= 70.0 for r in cut for x in r)


def test_a_saved_database_loads_back_identical_and_checks_its_weights(tmp_path: Path, slices) -> None:
    db = ScanDatabase(weights_id="abc")
    poses = np.tile(np.eye(4), (3, 1, 1))
    poses[:, 0, 3] = [1.0, 2.0, 3.0]
    db.add(slices[:3], stamps=[1.0, 2.0, 3.0], poses=poses)
    db.add(slices[3], stamps=4.0, ids=10)
    db.save(tmp_path / "map.npz")
    back = ScanDatabase.load(tmp_path / "map.npz", expect_weights_id="abc")
    np.testing.assert_array_equal(back.descriptors, slices[:4])
    np.testing.assert_array_equal(back.ids, [0, 1, 2, 10])
    np.testing.assert_array_equal(back.stamps, [1, 2, 3, 4])
    np.testing.assert_array_equal(back.poses[:3], poses)
    assert np.isnan(back.poses[3]).all()
    with np.load(tmp_path / "map.npz", allow_pickle=False) as npz:  # no pickled objects inside
        assert json.loads(str(npz["header"]))["schema_version"] == DATABASE_SCHEMA_VERSION
    with pytest.raises(MapSchemaError, match="descriptor weights 'abc'"):
        ScanDatabase.load(tmp_path / "map.npz", expect_weights_id="other")
    with pytest.raises(MapError, match="does not exist"):
        ScanDatabase.load(tmp_path / "none.npz")


def test_bad_inputs_are_refused_with_the_accepted_forms(net, slices) -> None:
    db = database(slices[:5])
    with pytest.raises(MapError, match=r"expected float \(n, 8, 288\)"):
        db.add(np.zeros((2, 4, 288), np.float32), stamps=[0.0, 1.0])
    with pytest.raises(MapError, match="unique, unused"):
        db.add(slices[:1], stamps=9.0, ids=3)
    with pytest.raises(ValueError, match="prefilter"):
        SearchConfig(prefilter=0)
    with pytest.raises(ValueError, match="expected"):
        db.search(np.zeros(100, np.float32), net.descriptor)


def test_the_map_describes_labelled_clouds_and_answers_sequence_batches(net) -> None:
    rng = np.random.default_rng(4)
    vmap = Vseq2pcMap(net, config=SearchConfig(k=10, exclude_recent_s=30.0))
    for i in range(6):
        points = rng.uniform(-40, 40, (2000, 3))
        labels = rng.choice([40, 48, 50, 70, 72, 80], size=2000)
        assert vmap.add_scan(points, labels, stamp=10.0 * i, pose=np.eye(4)) == i
    batch = SequenceBatch(frames=rng.random((2, 4, 12, 90), dtype=np.float32), indices=np.zeros((2, 4), np.int64),
                          stamps=np.array([[45.0] * 4, [60.0] * 4]), poses=np.tile(np.eye(4), (2, 4, 1, 1)))
    found = vmap.query(batch)
    assert [sorted(m.id for m in r) for r in found] == [[0, 1], [0, 1, 2, 3]]  # stamps <= query - 30 s
    assert all(m.pose is not None and m.pose.shape == (4, 4) for r in found for m in r)
    with pytest.raises(MapSchemaError):
        Vseq2pcMap(Vseq2pcNet.seeded(1), vmap.database)
