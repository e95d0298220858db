"""Keyframe clouds: compacted, kept in the descriptor map, saved with it, and used by the detector to verify loops."""
from __future__ import annotations

import dataclasses
import json
import re
from typing import Any, cast

import numpy as np
import pytest
from test_verification import pose, pose_error, scene, view

from lcpr_core.descriptor_map import SCHEMA_VERSION, DescriptorMap, MapConfig, Match
from lcpr_core.detector import DetectorConfig, Frame, LoopDetector, MatchConfig
from lcpr_core.errors import MapError, VerificationError
from lcpr_core.lcpr.describer import Describer, Prepared, prepare_each
from lcpr_core.verification import REJECT_REASONS, CloudConfig, CloudStore, VerifierConfig, compact_cloud
from lcpr_core.verification.processes import CloudRef

CONFIG = VerifierConfig(num_threads=1)  # see test_verification.CONFIG
DIM = 16


def on_grid(xyz: np.ndarray) -> bool:
    """Every coordinate is a whole number of centimetres as float32 (what the int16 store holds)."""
    cm = np.round(xyz.astype(np.float64) / 0.01)
    return bool(np.array_equal((cm.astype(np.float32) * np.float32(0.01)).astype(np.float32), xyz))


def rows(xyz: np.ndarray) -> np.ndarray:
    """The rows of a cloud in a canonical order (compaction does not promise an order)."""
    return xyz[np.lexsort(xyz.T[::-1])]


@pytest.fixture(scope="module")
def raw_cloud() -> np.ndarray:
    return view(scene(1), pose(5.0, -3.0, 20.0), seed=10)


# ---------------------------------------------------------------------- compact clouds
def test_a_compact_cloud_keeps_at_most_max_points_float32_points_on_the_centimetre_grid(raw_cloud):
    c = compact_cloud(raw_cloud, CloudConfig(max_points=3072))
    assert c.dtype == np.float32 and c.ndim == 2 and c.shape[1] == 3
    assert len(c) == 3072  # 12 k points in ~9 k voxels: capped
    assert on_grid(c)
    small = compact_cloud(raw_cloud, CloudConfig(max_points=500))
    assert 0 < len(small) <= 500


def test_a_compact_cloud_is_spread_over_the_whole_scan_not_its_first_rows(raw_cloud):
    c = compact_cloud(raw_cloud, CloudConfig(max_points=500)).astype(np.float64)
    angles = np.degrees(np.arctan2(c[:, 1], c[:, 0]))
    assert np.histogram(angles, bins=8, range=(-180, 180))[0].min() > 0


def test_points_outside_the_range_limits_and_non_finite_points_are_dropped():
    directions = np.array([[1.0, 0, 0], [0, 1.0, 0], [-1.0, 0, 0], [0, -1.0, 0], [0.6, 0.8, 0], [0, 0.6, 0.8]])
    kept = directions[:4] * np.array([[2.0], [40.0], [79.0], [10.0]])
    dropped = np.concatenate([directions[4:] * np.array([[0.5], [81.0]]), [[200.0, 5.0, 1.0]]])
    junk = np.array([[np.nan, 1.0, 1.0], [5.0, np.inf, 0.0], [-np.inf, 3.0, 2.0]])
    c = compact_cloud(np.concatenate([kept, dropped, junk]))
    assert np.array_equal(rows(c), rows(kept.astype(np.float32)))


def test_compact_cloud_refuses_clouds_of_the_wrong_shape():
    with pytest.raises(VerificationError, match=re.escape("(10, 2)")):
        compact_cloud(np.zeros((10, 2)))
    assert compact_cloud(np.zeros((0, 3))).shape == (0, 3)


def test_a_stored_cloud_reads_back_bit_identical_to_the_compact_cloud(raw_cloud):
    c = compact_cloud(raw_cloud)
    store = CloudStore()
    store.add(7, c)
    back = store.get(7)
    assert back is not None
    assert back.dtype == np.float32 and back.tobytes() == c.tobytes()


def test_compacting_a_stored_cloud_again_changes_at_most_one_percent_of_its_points(raw_cloud):
    """Centroids of centimetre-rounded centroids: a few points merge or move by a centimetre, no more."""
    store = CloudStore()
    store.add(0, compact_cloud(raw_cloud))
    stored = store.get(0)
    assert stored is not None
    again = compact_cloud(stored)
    assert len(stored) - len(again) <= 0.01 * len(stored)
    stored_rows = {tuple(r) for r in stored.tolist()}
    same = float(np.mean([tuple(r) in stored_rows for r in again.tolist()]))
    assert same >= 0.99, f"only {same:.1%} of the re-compacted points are stored points"


def test_a_keyframe_costs_at_most_six_bytes_a_point_and_sixteen_of_bookkeeping():
    cfg = CloudConfig()
    store = CloudStore()
    assert store.nbytes == 0
    for i, seed in enumerate((1, 2, 3)):
        c = compact_cloud(view(scene(seed), pose(0.0, 0.0, 0.0), seed=seed), cfg)
        before = store.nbytes
        store.add(i, c)
        assert store.nbytes - before == 6 * len(c) + 16 <= 6 * cfg.max_points + 16
    assert len(store) == 3 and 2 in store and 3 not in store


def test_the_cloud_store_refuses_a_second_cloud_for_a_keyframe_and_knows_what_it_lacks(raw_cloud):
    store = CloudStore()
    store.add(1, compact_cloud(raw_cloud))
    with pytest.raises(VerificationError, match="keyframe 1 already has a cloud"):
        store.add(1, compact_cloud(raw_cloud))
    assert store.get(2) is None
    store.add(2, np.zeros((0, 3), np.float32))  # a keyframe without points keeps an empty cloud
    empty = store.get(2)
    assert empty is not None and empty.shape == (0, 3) and len(store) == 2


# ---------------------------------------------------------------------- map files
def map_with_clouds(n: int = 5) -> DescriptorMap:
    rng = np.random.default_rng(3)
    m = DescriptorMap(MapConfig(dim=DIM))
    ids = m.add(rng.normal(size=(n, DIM)).astype(np.float32), stamps=np.arange(n, dtype=np.float64),
                poses=rng.normal(size=(n, 3)), sources="run1")
    world = scene(1)
    for i in ids[:-1]:
        m.clouds.add(int(i), compact_cloud(view(world, pose(2.0 * i, 0.0, 10.0 * i), seed=int(i))))
    m.clouds.add(int(ids[-1]), np.zeros((0, 3), np.float32))  # a keyframe that had no points
    return m


def test_a_map_saved_and_loaded_has_the_same_clouds_bit_for_bit(tmp_path):
    m = map_with_clouds()
    m.save(tmp_path / "map.npz")
    loaded = DescriptorMap.load(tmp_path / "map.npz")
    assert len(loaded.clouds) == len(m.clouds) == 5
    for i in m.ids.tolist():
        loaded_cloud, saved_cloud = loaded.clouds.get(i), m.clouds.get(i)
        assert loaded_cloud is not None and saved_cloud is not None
        assert loaded_cloud.tobytes() == saved_cloud.tobytes()
    empty = loaded.clouds.get(4)
    assert empty is not None and empty.shape == (0, 3)
    assert loaded.clouds.nbytes == m.clouds.nbytes
    assert np.array_equal(loaded.descriptors, m.descriptors) and loaded.ids.tolist() == m.ids.tolist()
    with np.load(tmp_path / "map.npz") as npz:
        header = json.loads(str(npz["header"]))
        assert header["schema_version"] == SCHEMA_VERSION == 3 and header["clouds"] == 5
        assert npz["cloud_points"].dtype == np.int16


def test_a_map_without_clouds_saves_and_loads_with_an_empty_store(tmp_path):
    m = DescriptorMap(MapConfig(dim=DIM))
    m.add(np.ones((2, DIM), np.float32), stamps=[0.0, 1.0])
    m.save(tmp_path / "map.npz")
    loaded = DescriptorMap.load(tmp_path / "map.npz")
    assert len(loaded) == 2 and len(loaded.clouds) == 0


def write_version_1(path, n: int = 3) -> np.ndarray:
    """A map file as schema version 1 wrote it: no cloud arrays."""
    rng = np.random.default_rng(4)
    descriptors = rng.normal(size=(n, DIM)).astype(np.float32)
    header = {"format": "lcpr_core.descriptor_map", "schema_version": 1, "dim": DIM, "model": "lcpr",
              "index": "flat", "count": n, "sources": ["old"]}
    with open(path, "wb") as fh:
        np.savez(fh, header=np.array(json.dumps(header)), descriptors=descriptors,
                 ids=np.arange(10, 10 + n, dtype=np.int64), stamps=np.arange(n, dtype=np.float64),
                 poses=np.full((n, 3), np.nan), source_codes=np.zeros(n, np.int32))
    return descriptors


def test_a_version_1_map_loads_with_an_empty_cloud_store_and_saves_as_the_current_version(tmp_path):
    descriptors = write_version_1(tmp_path / "v1.npz")
    loaded = DescriptorMap.load(tmp_path / "v1.npz")
    assert len(loaded) == 3 and len(loaded.clouds) == 0 and loaded.clouds.get(10) is None
    assert loaded.ids.tolist() == [10, 11, 12] and loaded.sources == ["old"] * 3
    hits = loaded.search(descriptors[1], k=1)
    assert isinstance(hits[0], Match) and hits[0].id == 11
    loaded.clouds.add(11, np.array([[1.0, 2.0, 3.0]], np.float32))
    loaded.save(tmp_path / "v2.npz")
    again = DescriptorMap.load(tmp_path / "v2.npz")
    cloud = again.clouds.get(11)
    assert len(again.clouds) == 1 and cloud is not None and np.array_equal(cloud, [[1.0, 2.0, 3.0]])


def tampered(tmp_path, **changes) -> str:
    """A saved map with some arrays replaced (or, given None, removed)."""
    map_with_clouds().save(tmp_path / "good.npz")
    with np.load(tmp_path / "good.npz") as npz:
        arrays = {k: npz[k] for k in npz.files}
    for key, value in changes.items():
        if value is None:
            del arrays[key]
        else:
            arrays[key] = value(arrays[key]) if callable(value) else value
    path = tmp_path / "bad map.npz"
    with open(path, "wb") as fh:
        np.savez(fh, **arrays)
    return str(path)


@pytest.mark.parametrize("changes, says", [
    ({"cloud_counts": lambda c: c + np.eye(1, len(c), 1, dtype=c.dtype)[0]}, "cloud_counts add up to"),
    ({"cloud_counts": lambda c: c[::-1] * 0 - 1}, "cloud_counts add up to"),
    ({"cloud_counts": lambda c: c[:-1]}, "cloud_counts"),
    ({"cloud_ids": lambda i: np.zeros_like(i)}, "cloud_ids repeat"),
    ({"cloud_points": lambda p: p.astype(np.float32)}, "expected P x 3 int16"),
    ({"cloud_ids": None}, "not all of cloud_ids"),
], ids=["counts one too many", "negative counts", "counts short", "ids repeat", "float points", "ids missing"])
def test_a_map_with_inconsistent_clouds_is_refused_naming_the_file(tmp_path, changes, says):
    path = tampered(tmp_path, **changes)
    with pytest.raises(MapError, match=re.escape(path) + ".*" + re.escape(says)):
        DescriptorMap.load(path)


# ---------------------------------------------------------------------- the detector verifies with the clouds
class KeyedDescriber:
    """Stands in for the network: the first "image" names the descriptor to return."""

    weights_id = "keyed-test"

    def __init__(self, table: dict[str, np.ndarray]) -> None:
        self.table = table

    def inputs(self, images, points):
        return list(images), None

    def prepare(self, images, points):
        return Prepared(*self.inputs(images, points))

    def prepare_many(self, frames):
        return prepare_each(self.prepare, frames)

    def describe_tensors(self, images, ranges):
        return self.table[images[0]][None]


def descriptors() -> dict[str, np.ndarray]:
    """'A': place A; 'R': its revisit, 0.3 away; the look-alike B is given 'R' itself (nearer than A)."""
    rng = np.random.default_rng(8)
    a = rng.normal(size=256)
    a /= np.linalg.norm(a)
    noise = rng.normal(size=256)
    r = a + 0.3 * noise / np.linalg.norm(noise)
    return {"A": a.astype(np.float32), "R": (r / np.linalg.norm(r)).astype(np.float32)}


PLACE_A, PLACE_B = pose(10.0, 5.0, 30.0), pose(300.0, -40.0, -60.0)
REVISIT = PLACE_A @ pose(1.5, -1.0, 25.0)  # 1.8 m away, turned by 25 degrees
TRUTH = np.linalg.inv(PLACE_A) @ REVISIT  # the revisit's LiDAR frame in place A's


@pytest.fixture(scope="module")
def worlds() -> dict[str, np.ndarray]:
    return {"A": scene(1) + [10.0, 5.0, 0.0], "B": scene(2) + [300.0, -40.0, 0.0]}


def keyframe(t: float, key: str, world: np.ndarray, world_T_base: np.ndarray, seed: int) -> Frame:
    images = cast(Any, [key] * 6)  # not images: KeyedDescriber reads the key
    return Frame(stamp=t, images=images, points=view(world, world_T_base, seed=seed), pose=world_T_base)


def first_session(worlds) -> list[Frame]:
    return [keyframe(0.0, "A", worlds["A"], PLACE_A, 1), keyframe(5.0, "R", worlds["B"], PLACE_B, 2)]


def revisit(worlds, t: float) -> Frame:
    return keyframe(t, "R", worlds["A"], REVISIT, 3)


def make_detector(verify: VerifierConfig = CONFIG, prior_map: DescriptorMap | None = None) -> LoopDetector:
    return LoopDetector(DetectorConfig(match=MatchConfig(max_distance=1.0), verify=verify),
                        describer=cast(Describer, KeyedDescriber(descriptors())), prior_map=prior_map)


def check_verified_revisit(result) -> None:
    by_match = {c.match_id: c for c in result.candidates}
    assert set(by_match) == {0, 1}
    assert result.candidates[0].match_id == 1  # the look-alike is the nearer descriptor ...
    lookalike, true = by_match[1], by_match[0]
    assert not lookalike.verified and lookalike.verification in REJECT_REASONS  # ... but the LiDAR says no
    assert true.verified and true.verification == "accepted", true.verification
    assert 0.0 <= true.fitness <= 1.0 and true.covariance.shape == (6, 6)
    loop = result.loop
    assert loop is not None and loop.match_id == 0 and loop.query_id == result.keyframe_id
    err_m, err_deg = pose_error(loop.match_T_query, TRUTH)
    assert err_m <= 0.05 and err_deg <= 0.5, (err_m, err_deg)


def test_the_true_revisit_is_verified_and_the_look_alike_place_is_not(worlds):
    det = make_detector()
    for f in first_session(worlds):
        assert det.process(f).loop is None
    result = det.process(revisit(worlds, 40.0))
    assert result.keyframe_id == 2 and result.verification
    check_verified_revisit(result)
    assert {"compact", "verify"} <= set(result.timings)
    assert len(det.map.clouds) == 3 and det.map.clouds.nbytes <= 3 * (6 * CONFIG.cloud.max_points + 16)


def test_with_verification_off_the_loop_is_the_nearest_descriptor_as_before(worlds):
    det = make_detector(VerifierConfig(enabled=False))
    for f in first_session(worlds):
        det.process(f)
    result = det.process(revisit(worlds, 40.0))
    assert not result.verification
    loop = result.loop
    assert loop is not None and loop.match_id == 1 and loop.rank == 0  # the look-alike, unverified
    assert all(c.verification == "off" and not c.verified and c.match_T_query is None for c in result.candidates)


def test_a_saved_and_reloaded_map_still_verifies_against_the_old_sessions_clouds(tmp_path, worlds):
    old = make_detector()
    for f in first_session(worlds):
        old.process(f)
    old.map.save(tmp_path / "map.npz")
    det = make_detector(prior_map=DescriptorMap.load(tmp_path / "map.npz"))
    result = det.process(revisit(worlds, 0.0))  # a new clock: the old session is never excluded by time
    assert result.keyframe_id == 2
    check_verified_revisit(result)


def test_a_map_from_a_session_without_verification_gives_no_cloud_and_no_loop(tmp_path, worlds):
    old = make_detector(VerifierConfig(enabled=False))
    for f in first_session(worlds):
        old.process(f)
    det = make_detector(prior_map=old.map)
    result = det.process(revisit(worlds, 0.0))
    assert [c.verification for c in result.candidates] == ["no cloud", "no cloud"]
    assert result.loop is None


@pytest.mark.parametrize("processes", [0, 2])
def test_a_registration_that_raises_fails_that_candidate_keeps_the_keyframe_and_says_why(worlds, monkeypatch,
                                                                                       processes):
    det = make_detector(dataclasses.replace(CONFIG, processes=processes))
    for f in first_session(worlds):
        det.process(f)

    def broken(query, match, **options):
        raise RuntimeError("registration blew up")

    def lost(*args: Any, **kwargs: Any) -> CloudRef:  # over worker processes: the match cloud cannot be had
        def load() -> np.ndarray:
            raise RuntimeError("registration blew up")
        return CloudRef(("lost", args), load)

    monkeypatch.setattr(det.verifier, "verify_prepared", broken)  # in this process
    monkeypatch.setattr(det, "_match_cloud", lost)
    result = det.process(revisit(worlds, 40.0))
    assert result.keyframe_id == 2 and len(det.map) == 3 and len(det.map.clouds) == 3
    assert [c.verification for c in result.candidates] == ["failed", "failed"] and result.loop is None
    assert len(result.errors) == 2 and all("RuntimeError: registration blew up" in e for e in result.errors)
