"""Candidate methods behind one protocol: a method registered by name is run by the detector with no other change."""
from __future__ import annotations

from collections.abc import Iterator
from typing import cast

import numpy as np
import pytest
from test_match_method import RETRIEVAL_ONLY, NoPlaceDescriber, detector, place_cloud, scan

from lcpr_core.descriptor_map import DescriptorMap, Match
from lcpr_core.detector import MATCH_METHODS, DetectorConfig, LoopDetector, MatchConfig
from lcpr_core.errors import InvalidValueError
from lcpr_core.lcpr.describer import Describer
from lcpr_core.lcpr.proposers import (
    PROPOSERS,
    DescriptorProposer,
    FusedProposer,
    KeyframeInput,
    ProposerSetup,
    ScanContextProposer,
    SearchRequest,
    method_names,
    register,
)


class NearestInTime:
    """A toy method: the eligible keyframes nearest in time, newest first (distance: seconds between them)."""

    stage = "toy_describe"

    def __init__(self, setup: ProposerSetup) -> None:
        self.map = setup.map
        self.kept = [float(t) for t in setup.map.stamps]  # a prior map's keyframes, from the map itself

    def describe(self, keyframe: KeyframeInput) -> float:
        return keyframe.stamp

    def search(self, query: float, request: SearchRequest) -> list[Match]:
        rows = range(request.eligible - 1, max(-1, request.eligible - 1 - request.match.top_k), -1)
        return [Match(id=int(self.map.ids[row]), distance=query - self.kept[row], stamp=self.kept[row], pose=None,
                      source=self.map.sources[row], rank=rank) for rank, row in enumerate(rows)]

    def add(self, query: float) -> None:
        self.kept.append(query)


@pytest.fixture
def nearest_in_time() -> Iterator[str]:
    """``nearest_in_time`` registered for one test (the registry is the process's)."""
    register("nearest_in_time")(NearestInTime)
    try:
        yield "nearest_in_time"
    finally:
        del PROPOSERS["nearest_in_time"]


def test_a_method_registered_in_another_module_is_run_by_name_under_the_detectors_exclusion_rules(nearest_in_time):
    det = detector(nearest_in_time, top_k=3, exclude_recent_s=10.0, exclude_recent_count=0)
    assert isinstance(det.proposer, NearestInTime)
    results = [det.process(scan(float(t), place_cloud(t % 3))) for t in range(20)]
    assert [c.match_stamp for c in results[15].candidates] == [5.0, 4.0, 3.0]  # newer than 10 s: excluded
    assert [c.distance for c in results[15].candidates] == [10.0, 11.0, 12.0]
    assert [c.rank for c in results[15].candidates] == [0, 1, 2]
    assert all(not r.candidates for r in results[:10]) and "toy_describe" in results[19].timings
    assert det.proposer.kept == [float(t) for t in range(20)]  # add() saw every keyframe, in order


def test_a_registered_method_searches_a_prior_maps_keyframes_from_the_start(nearest_in_time, tmp_path):
    made = detector("lcpr")
    for t in range(4):
        made.process(scan(1000.0 + t, place_cloud(t)))
    made.map.save(tmp_path / "map.npz")
    prior = DescriptorMap.load(tmp_path / "map.npz")
    det = LoopDetector(DetectorConfig(match=MatchConfig(method=nearest_in_time, top_k=2), verify=RETRIEVAL_ONLY),
                       describer=cast(Describer, NoPlaceDescriber()), prior_map=prior)
    r = det.process(scan(0.0, place_cloud(0)))  # an earlier clock: a prior session is never excluded by time
    assert [c.match_id for c in r.candidates] == [3, 2]


def test_an_unknown_method_is_refused_naming_it_and_every_registered_one(nearest_in_time):
    with pytest.raises(InvalidValueError) as refused:
        MatchConfig(method="nearest")
    assert str(refused.value) == "match.method='nearest'; accepted: lcpr, scan_context, fused, nearest_in_time"


def test_a_method_is_refused_once_its_proposer_is_unregistered():
    with pytest.raises(InvalidValueError, match="match.method='nearest_in_time'; accepted: lcpr, scan_context, fused$"):
        MatchConfig(method="nearest_in_time")


def test_a_name_already_registered_or_not_an_identifier_is_refused(nearest_in_time):
    with pytest.raises(InvalidValueError, match="'nearest_in_time' is registered already"):
        register(nearest_in_time)(NearestInTime)
    with pytest.raises(InvalidValueError, match="match.method name 'scan context'; accepted: a Python identifier"):
        register("scan context")
    assert method_names()[-1] == nearest_in_time


def test_the_built_in_methods_are_registered_in_the_order_of_match_methods():
    assert MATCH_METHODS == method_names() == ("lcpr", "scan_context", "fused")
    assert [PROPOSERS[m] for m in MATCH_METHODS] == [DescriptorProposer, ScanContextProposer, FusedProposer]


def test_fused_proposes_what_the_descriptor_and_scan_context_detectors_propose_alone_in_that_order():
    runs = {m: detector(m, top_k=3, max_distance=2.0, sc_max_distance=0.6, exclude_recent_s=2.0)
            for m in ("lcpr", "scan_context", "fused")}
    proposed = 0
    for t in range(14):
        frame = scan(float(t), place_cloud(t % 5, yaw_deg=7.0 * t))
        got = {m: [(c.match_id, c.distance) for c in det.process(frame).candidates] for m, det in runs.items()}
        first = {i for i, _ in got["lcpr"]}
        assert got["fused"] == got["lcpr"] + [(i, d) for i, d in got["scan_context"] if i not in first]
        proposed += len(got["scan_context"]) > 0
    assert proposed >= 5  # Scan Context did propose (the revisits of the five places)
    scs = {m: det.map.scan_contexts for m, det in runs.items()}
    assert scs["lcpr"] is None and scs["fused"] is not None and scs["scan_context"] is not None
    np.testing.assert_array_equal(scs["fused"].matrices(), scs["scan_context"].matrices())
