"""match.method: Scan Context proposes the candidates (alone or with the descriptor), under the same exclusion rules."""
from __future__ import annotations

from typing import cast

import numpy as np
import pytest
import torch

from lcpr_core.descriptor_map import DescriptorMap
from lcpr_core.detector import MATCH_METHODS, DetectorConfig, Frame, LoopDetector, MatchConfig
from lcpr_core.errors import InvalidValueError, MapError
from lcpr_core.lcpr.describer import Describer, Prepared, PreparedBatch, prepare_each
from lcpr_core.scan_context import ScanContextConfig, ScanContextRows, scan_context
from lcpr_core.verification import VerifierConfig

RETRIEVAL_ONLY = VerifierConfig(enabled=False)


class NoPlaceDescriber:
    """Stands in for the network with a descriptor that knows no place: a fresh random unit vector per frame."""

    weights_id = "no-place-test"

    def __init__(self) -> None:
        self.rng = np.random.default_rng(0)

    def prepare(self, images: object, points: np.ndarray) -> Prepared:
        return Prepared(torch.zeros(1), torch.zeros(1))

    def prepare_many(self, frames: list[tuple[object, np.ndarray]]) -> PreparedBatch:
        return prepare_each(self.prepare, frames)  # type: ignore[arg-type]

    def describe_tensors(self, images: torch.Tensor, ranges: torch.Tensor) -> np.ndarray:
        v = self.rng.normal(size=(len(ranges), 256)).astype(np.float32)
        return v / np.linalg.norm(v, axis=1, keepdims=True)


def place_cloud(seed: int, *, yaw_deg: float = 0.0, shift: tuple[float, float] = (0.0, 0.0)) -> np.ndarray:
    """A hand-made 360 deg scan of one place: ground and 25 boxes of the seed's sizes and positions, seen from
    the origin turned by ``yaw_deg`` and moved by ``shift`` (N x 3, sensor frame)."""
    rng = np.random.default_rng(seed)
    r, a = rng.uniform(3.0, 40.0, 3000), rng.uniform(0.0, 2 * np.pi, 3000)
    parts = [np.stack([r * np.cos(a), r * np.sin(a), np.full(3000, -1.8)], axis=1)]
    for _ in range(25):
        centre = rng.uniform(4.0, 35.0) * np.array([np.cos(t := rng.uniform(0, 2 * np.pi)), np.sin(t)])
        half, height = rng.uniform(0.5, 3.0, 2), rng.uniform(1.0, 8.0)
        u = rng.uniform(-1.0, 1.0, (300, 2))
        side = rng.integers(0, 2, 300)  # points on the faces x = +-half or y = +-half
        u[np.arange(300), side] = np.sign(u[np.arange(300), side])
        parts.append(np.c_[centre + u * half, rng.uniform(-1.8, height - 1.8, 300)])
    world = np.concatenate(parts)
    c, s = np.cos(np.radians(yaw_deg)), np.sin(np.radians(yaw_deg))
    R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return ((world - [shift[0], shift[1], 0.0]) @ R).astype(np.float32)  # the sensor frame: R^T (p - t)


def scan(t: float, cloud: np.ndarray) -> Frame:
    return Frame(stamp=t, images=[None] * 6, points=cloud, pose=np.eye(4))


def detector(method: str, *, verify: VerifierConfig = RETRIEVAL_ONLY, **match: object) -> LoopDetector:
    options: dict = {"method": method, "max_distance": 0.5, **match}
    return LoopDetector(DetectorConfig(match=MatchConfig(**options), verify=verify),
                        describer=cast(Describer, NoPlaceDescriber()))


def test_a_scan_context_detector_verifies_a_revisit_the_descriptor_cannot_see():
    places = [place_cloud(seed) for seed in range(8)]
    results = {}
    for method in ("lcpr", "scan_context"):
        det = detector(method, verify=VerifierConfig())
        for t, cloud in enumerate(places):
            det.process(scan(float(t), cloud))
        results[method] = det.process(scan(100.0, place_cloud(5, yaw_deg=40.0, shift=(0.6, -0.4))))
    assert results["lcpr"].loop is None  # a descriptor that knows no place proposes nothing under 0.5
    loop = results["scan_context"].loop
    assert loop is not None and loop.match_id == 5 and loop.verified and loop.rank == 0
    assert loop.distance < 0.2  # its Scan Context distance
    assert "scan_context" in results["scan_context"].timings


def test_a_bad_method_is_refused_naming_the_accepted_ones():
    with pytest.raises(InvalidValueError, match="match.method='sc'; accepted: lcpr, scan_context, fused"):
        MatchConfig(method="sc")
    with pytest.raises(InvalidValueError, match="sc_max_distance"):
        MatchConfig(sc_max_distance=1.5)
    assert MatchConfig().method == "lcpr" and set(MATCH_METHODS) == {"lcpr", "scan_context", "fused"}


def test_scan_context_candidates_are_never_newer_than_the_exclusion_window():
    det = detector("scan_context", top_k=100, sc_max_distance=1.0)
    cloud = place_cloud(1)  # one place all along: every eligible keyframe is a candidate
    for t in range(60):
        r = det.process(scan(float(t), cloud))
        assert all(c.match_stamp <= t - 30 for c in r.candidates)
        assert len(r.candidates) == max(0, t - 29)


def test_scan_context_exclusion_by_count_adds_to_exclusion_by_time():
    det = detector("scan_context", top_k=100, exclude_recent_s=0.0, exclude_recent_count=5)
    cloud = place_cloud(1)
    for t in range(20):
        r = det.process(scan(float(t), cloud))
    assert len(r.candidates) == 19 - 5 and max(c.match_id for c in r.candidates) == 13


def test_a_prior_maps_keyframes_are_found_by_scan_context_from_their_stored_clouds():
    prior = detector("lcpr", verify=VerifierConfig())  # verification on: the map keeps each keyframe's cloud
    for t in range(4):
        prior.process(scan(1000.0 + t, place_cloud(t)))
    config = DetectorConfig(match=MatchConfig(method="scan_context"), verify=RETRIEVAL_ONLY)
    det = LoopDetector(config, describer=cast(Describer, NoPlaceDescriber()), prior_map=prior.map)
    r = det.process(scan(0.0, place_cloud(2, yaw_deg=-25.0)))  # an earlier clock: never excluded by time
    assert r.loop is not None and r.loop.match_id == 2 and r.keyframe_id == 4


def test_fused_proposes_the_descriptors_candidates_then_scan_contexts_without_repeats():
    det = detector("fused", top_k=3, max_distance=2.0)
    for t in range(6):
        det.process(scan(float(t), place_cloud(t)))
    r = det.process(scan(100.0, place_cloud(4, yaw_deg=10.0)))
    ids = [c.match_id for c in r.candidates]
    assert len(ids) == len(set(ids)) and 3 < len(ids) <= 6
    assert [c.rank for c in r.candidates] == list(range(len(ids)))
    assert all(c.distance <= 2.0 for c in r.candidates[:3])  # the descriptor's (L2) come first
    assert ids[3] == 4 if 4 not in ids[:3] else 4 not in ids[3:]  # Scan Context's best: the revisited place


def test_scan_context_rows_search_only_the_rows_asked_and_skip_empty_ones():
    rows = ScanContextRows(ScanContextConfig(candidates=2))
    for seed in range(3):
        rows.add(scan_context(place_cloud(seed)))
    rows.add(None)  # a row without a scan context
    rows.add(scan_context(place_cloud(1)))
    query = scan_context(place_cloud(1, yaw_deg=30.0))
    assert [row for row, _ in rows.search(query, rows=5, k=5)][:2] in ([1, 4], [4, 1])
    assert 4 not in [row for row, _ in rows.search(query, rows=4, k=5)]
    assert 3 not in [row for row, _ in rows.search(query, rows=5, k=5)]
    elsewhere = scan_context(place_cloud(7))
    assert rows.search(elsewhere, rows=5, k=5) and rows.search(elsewhere, rows=5, k=5, max_distance=0.05) == []


def test_a_saved_map_keeps_the_scan_contexts_of_the_raw_scans_and_a_new_detector_uses_them(tmp_path):
    made = detector("scan_context", verify=VerifierConfig())  # the clouds kept are compact: voxelised, capped
    clouds = [place_cloud(t) for t in range(4)]
    for t, cloud in enumerate(clouds):
        made.process(scan(1000.0 + t, cloud))
    path = tmp_path / "map.npz"
    made.map.save(path)
    loaded = DescriptorMap.load(path)
    assert loaded.scan_contexts is not None
    raw = np.stack([scan_context(c) for c in clouds])
    np.testing.assert_array_equal(loaded.scan_contexts.matrices(), raw)  # the raw scans', not the compact clouds'
    compact = loaded.clouds.get(int(loaded.ids[0]))
    assert compact is not None and not np.array_equal(scan_context(compact), raw[0])
    det = LoopDetector(DetectorConfig(match=MatchConfig(method="scan_context", top_k=3), verify=RETRIEVAL_ONLY),
                       describer=cast(Describer, NoPlaceDescriber()), prior_map=loaded)
    assert det.map.scan_contexts is not None
    np.testing.assert_array_equal(det.map.scan_contexts.matrices(), raw)
    r = det.process(scan(0.0, place_cloud(2, yaw_deg=-25.0)))
    assert r.loop is not None and r.loop.match_id == 2
    det.map.save(path)  # the new keyframe's row joins them
    saved = DescriptorMap.load(path).scan_contexts
    assert saved is not None and len(saved) == 5


def test_a_map_made_without_scan_contexts_saves_none_and_bad_ones_are_refused(tmp_path):
    made = detector("lcpr", verify=VerifierConfig())
    made.process(scan(1000.0, place_cloud(0)))
    path = tmp_path / "map.npz"
    made.map.save(path)
    assert DescriptorMap.load(path).scan_contexts is None
    with np.load(path) as npz:
        arrays = {k: npz[k] for k in npz.files}
    arrays["scan_contexts"] = np.zeros((1, 20, 60), np.float32)  # without the record of what made them
    np.savez(tmp_path / "bad.npz", **arrays)
    with pytest.raises(MapError, match="holds scan_contexts but its header has no 'scan_context' record"):
        DescriptorMap.load(tmp_path / "bad.npz")
