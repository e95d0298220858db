"""DescriptorMap: adding, searching, time-window exclusion, saving and loading."""
from __future__ import annotations

import json
import os
from pathlib import Path
from typing import TypeGuard

import numpy as np
import pytest

from lcpr_core import descriptor_map
from lcpr_core.descriptor_map import DescriptorMap, MapConfig, Match
from lcpr_core.errors import MapError, MapSchemaError

DIM = 16


def unit(rng: np.random.Generator, n: int, dim: int = DIM) -> np.ndarray:
    x = rng.standard_normal((n, dim)).astype(np.float32)
    return x / np.linalg.norm(x, axis=1, keepdims=True)


def brute_force(
    db: np.ndarray, q: np.ndarray, k: int, allowed: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    d = np.linalg.norm(db.astype(np.float64) - q.astype(np.float64), axis=1)
    if allowed is not None:
        d = np.where(allowed, d, np.inf)
    order = np.argsort(d, kind="stable")[:k]
    order = order[np.isfinite(d[order])]
    return order, d[order]


def single(hits: list[Match] | list[list[Match]]) -> TypeGuard[list[Match]]:
    """The result of one (D,) query: a flat list of matches."""
    return all(isinstance(h, Match) for h in hits)


def batched(results: list[Match] | list[list[Match]]) -> TypeGuard[list[list[Match]]]:
    """The result of a (Q, D) batch: one list of matches per query."""
    return all(isinstance(r, list) for r in results)


def filled_map(n: int = 300, *, seed: int = 0, index: str = "flat") -> tuple[DescriptorMap, np.ndarray]:
    rng = np.random.default_rng(seed)
    x = unit(rng, n)
    m = DescriptorMap(MapConfig(dim=DIM, index=index))
    poses = np.c_[np.arange(n, dtype=float), -np.arange(n, dtype=float), np.zeros(n)]
    poses[::7] = np.nan
    sources = [f"bag{i % 3}" for i in range(n)]
    m.add(x, stamps=np.arange(n) * 0.5, poses=poses, sources=sources)
    return m, x


def test_ids_are_assigned_consecutively_from_zero() -> None:
    m, _ = filled_map(10)
    assert m.ids.tolist() == list(range(10))
    assert len(m) == 10
    new = m.add(np.ones(DIM, np.float32), stamps=100.0)
    assert new.tolist() == [10]


def test_exact_search_matches_numpy_brute_force() -> None:
    m, x = filled_map(300)
    queries = unit(np.random.default_rng(1), 25)
    results = m.search(queries, k=7)
    assert len(results) == 25
    assert batched(results)
    for q, hits in zip(queries, results, strict=True):
        order, dist = brute_force(x, q, 7)
        assert [h.id for h in hits] == order.tolist()
        np.testing.assert_allclose([h.distance for h in hits], dist, atol=1e-5)
        assert [h.rank for h in hits] == list(range(7))


def test_a_single_query_returns_a_flat_list_of_matches_with_metadata() -> None:
    m, x = filled_map(30)
    hits = m.search(x[8], k=3)
    assert isinstance(hits[0], Match)
    top = hits[0]
    assert (top.id, top.stamp, top.source, top.rank) == (8, 4.0, "bag2", 0)
    assert top.distance == pytest.approx(0.0, abs=1e-3)
    assert top.pose == (8.0, -8.0, 0.0)
    nan_pose = m.search(x[7], k=1)
    assert single(nan_pose) and nan_pose[0].pose is None  # row 7 was given a NaN pose


def test_k_larger_than_the_map_returns_every_entry() -> None:
    m, _ = filled_map(5)
    assert len(m.search(np.ones(DIM, np.float32), k=20)) == 5
    assert DescriptorMap(MapConfig(dim=DIM)).search(np.ones(DIM, np.float32)) == []


def test_max_distance_drops_far_hits() -> None:
    m, x = filled_map(100)
    hits = m.search(x[0], k=10, max_distance=1.0)
    assert single(hits)
    _, dist = brute_force(x, x[0], 10)
    assert len(hits) == int((dist <= 1.0).sum())
    assert all(h.distance <= 1.0 for h in hits)


@pytest.mark.parametrize(("index", "exact_rows"), [("flat", 16384), ("hnsw", 16384), ("hnsw", 0)])
def test_entries_newer_than_exclude_after_are_never_returned(
    index: str, exact_rows: int, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(descriptor_map, "_EXACT_FALLBACK_ROWS", exact_rows)  # 0: use the faiss selector
    m, x = filled_map(300, index=index)
    q = x[250]
    hits = m.search(q, k=10, exclude_after=60.0)  # stamps are 0.5 * row
    assert single(hits)
    assert hits and all(h.stamp <= 60.0 for h in hits)
    order, _ = brute_force(x, q, 10, allowed=m.stamps <= 60.0)
    assert [h.id for h in hits] == order.tolist()
    assert m.search(q, k=10, exclude_after=-1.0) == []


@pytest.mark.parametrize("exact_rows", [16384, 0])
def test_exclusion_is_correct_when_stamps_are_not_monotonic(exact_rows: int, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(descriptor_map, "_EXACT_FALLBACK_ROWS", exact_rows)
    rng = np.random.default_rng(3)
    x = unit(rng, 400)
    stamps = rng.permutation(400).astype(float)
    for index in ("flat", "hnsw"):
        m = DescriptorMap(MapConfig(dim=DIM, index=index))
        m.add(x[:200], stamps=stamps[:200])
        m.add(x[200:], stamps=stamps[200:])
        allowed = stamps <= 150.0
        for q in x[::40]:
            hits = m.search(q, k=5, exclude_after=150.0)
            assert single(hits)
            order, _ = brute_force(x, q, 5, allowed=allowed)
            assert [h.id for h in hits] == order.tolist()


def test_each_query_of_a_batch_can_have_its_own_window() -> None:
    m, x = filled_map(200)
    windows = np.array([10.0, 50.0, 99.5])
    results = m.search(x[[150, 160, 199]], k=4, exclude_after=windows)
    assert batched(results)
    for w, hits in zip(windows, results, strict=True):
        assert len(hits) == 4 and all(h.stamp <= w for h in hits)


def test_hnsw_finds_the_exact_neighbour_on_easy_data() -> None:
    m, x = filled_map(500, index="hnsw")
    noisy = x[::10] + 0.01 * unit(np.random.default_rng(5), 50)
    results = m.search(noisy, k=1)
    assert batched(results)
    assert [r[0].id for r in results] == list(range(0, 500, 10))


def test_a_saved_map_loads_back_with_the_same_ids_and_metadata(tmp_path: Path) -> None:
    m, x = filled_map(50)
    path = tmp_path / "map.npz"
    m.save(path)
    back = DescriptorMap.load(path)
    assert back.config == m.config
    np.testing.assert_array_equal(back.ids, m.ids)
    np.testing.assert_array_equal(back.stamps, m.stamps)
    np.testing.assert_array_equal(back.poses, m.poses)
    np.testing.assert_array_equal(back.descriptors, x)
    assert back.sources == m.sources
    loaded_hits, saved_hits = back.search(x[3], k=5), m.search(x[3], k=5)
    assert single(loaded_hits) and single(saved_hits)
    assert [h.id for h in loaded_hits] == [h.id for h in saved_hits]


def test_a_saved_map_keeps_which_weights_made_it_and_an_old_file_loads_as_unknown(tmp_path: Path) -> None:
    m, _ = filled_map(5)
    m.weights_id = "0123456789abcdef"
    m.save(tmp_path / "map.npz")
    assert DescriptorMap.load(tmp_path / "map.npz").weights_id == "0123456789abcdef"
    with np.load(tmp_path / "map.npz") as z:
        arrays = dict(z)
    header = json.loads(str(arrays["header"].item()))
    del header["weights_id"]  # as maps saved before the field existed
    arrays["header"] = np.array(json.dumps(header))
    np.savez(tmp_path / "old.npz", **arrays)
    assert DescriptorMap.load(tmp_path / "old.npz").weights_id == ""


def test_ids_continue_after_the_largest_loaded_id(tmp_path: Path) -> None:
    m = DescriptorMap(MapConfig(dim=DIM))
    m.add(unit(np.random.default_rng(0), 3), stamps=[0.0, 1.0, 2.0], ids=[4, 9, 40])
    m.save(tmp_path / "m.npz")
    back = DescriptorMap.load(tmp_path / "m.npz")
    assert back.add(unit(np.random.default_rng(1), 2), stamps=[3.0, 4.0]).tolist() == [41, 42]


def test_a_map_saved_as_hnsw_reloads_as_hnsw_unless_expect_says_flat(tmp_path: Path) -> None:
    m, _ = filled_map(40, index="hnsw")
    m.save(tmp_path / "h.npz")
    assert DescriptorMap.load(tmp_path / "h.npz").config.index == "hnsw"
    assert DescriptorMap.load(tmp_path / "h.npz", expect=MapConfig(dim=DIM)).config.index == "flat"


@pytest.mark.parametrize("expect", [MapConfig(dim=32), MapConfig(dim=DIM, descriptor_tag="other")])
def test_a_map_of_another_dim_or_model_is_refused_and_left_untouched(tmp_path: Path, expect: MapConfig) -> None:
    m, _ = filled_map(20)
    path = tmp_path / "map.npz"
    m.save(path)
    before, mtime = path.read_bytes(), os.stat(path).st_mtime_ns
    with pytest.raises(MapSchemaError) as err:
        DescriptorMap.load(path, expect=expect)
    assert f"{DIM}-d 'lcpr'" in str(err.value) and f"{expect.dim}-d {expect.descriptor_tag!r}" in str(err.value)
    assert str(path) in str(err.value)
    assert path.read_bytes() == before and os.stat(path).st_mtime_ns == mtime


@pytest.mark.parametrize("content", [b"", b"not a zip file at all", None])
def test_a_corrupt_or_truncated_file_is_refused_with_map_error(tmp_path: Path, content: bytes | None) -> None:
    path = tmp_path / "bad.npz"
    if content is None:  # a real map cut in half
        filled_map(50)[0].save(path)
        content = path.read_bytes()[: path.stat().st_size // 2]
    path.write_bytes(content)
    with pytest.raises(MapError, match="bad.npz"):
        DescriptorMap.load(path)
    assert path.read_bytes() == content


def test_an_npz_that_is_not_a_map_is_refused(tmp_path: Path) -> None:
    np.savez(tmp_path / "other.npz", a=np.zeros(3))
    with pytest.raises(MapError, match="lacks header"):
        DescriptorMap.load(tmp_path / "other.npz")
    with pytest.raises(MapError, match="does not exist"):
        DescriptorMap.load(tmp_path / "missing.npz")


def test_a_failing_save_leaves_the_old_file_intact(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    path = tmp_path / "map.npz"
    filled_map(20)[0].save(path)
    before = path.read_bytes()

    def broken_savez(*args: object, **kwargs: object) -> None:
        raise RuntimeError("disk went away")

    monkeypatch.setattr(np, "savez", broken_savez)
    with pytest.raises(RuntimeError, match="disk went away"):
        filled_map(40, seed=1)[0].save(path)
    assert path.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["map.npz"]  # no temporary left behind


def test_a_save_into_an_unwritable_directory_raises_map_error(tmp_path: Path) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("x")
    with pytest.raises(MapError, match="cannot save"):
        filled_map(5)[0].save(blocker / "map.npz")


@pytest.mark.parametrize(
    ("bad", "shape"),
    [(np.zeros((3, 8), np.float32), "(3, 8)"), (np.zeros((2, 3, DIM), np.float32), "(2, 3, 16)"),
     (np.zeros(5), "(5,)")],
)
def test_descriptors_of_the_wrong_shape_are_refused_naming_the_shape(bad: np.ndarray, shape: str) -> None:
    m = DescriptorMap(MapConfig(dim=DIM))
    with pytest.raises(MapError) as err:
        m.add(bad, stamps=np.zeros(len(bad)))
    assert shape in str(err.value) and f"(N, {DIM})" in str(err.value)
    with pytest.raises(MapError, match=r"shape \(3, 8\)"):
        m.search(np.zeros((3, 8), np.float32))


def test_non_finite_or_integer_descriptors_and_mismatched_metadata_are_refused() -> None:
    m = DescriptorMap(MapConfig(dim=DIM))
    x = np.zeros((2, DIM), np.float32)
    with pytest.raises(MapError, match="NaN or inf"):
        m.add(np.where(np.eye(2, DIM) > 0, np.nan, x), stamps=[0.0, 1.0])
    with pytest.raises(MapError, match="dtype int64"):
        m.add(np.zeros((2, DIM), np.int64), stamps=[0.0, 1.0])
    with pytest.raises(MapError, match=r"stamps of shape \(3,\)"):
        m.add(x, stamps=[0.0, 1.0, 2.0])
    with pytest.raises(MapError, match=r"poses of shape \(2, 2\)"):
        m.add(x, stamps=[0.0, 1.0], poses=np.zeros((2, 2)))
    m.add(x, stamps=[0.0, 1.0])
    with pytest.raises(MapError, match=r"ids \[1\] are already in the map"):
        m.add(x, stamps=[2.0, 3.0], ids=[7, 1])
    assert len(m) == 2


def test_bad_configs_name_the_accepted_values() -> None:
    with pytest.raises(MapError, match="index='ivf'; accepted: flat, hnsw"):
        MapConfig(index="ivf")
    with pytest.raises(MapError, match="dim=0"):
        MapConfig(dim=0)
