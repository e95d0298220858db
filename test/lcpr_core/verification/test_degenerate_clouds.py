"""Clouds no registration can pin down are refused while being prepared: a reason, never an exception or a search."""
from __future__ import annotations

import functools

import numpy as np
import pytest

from lcpr_core.verification import REJECT_REASONS, GeometricVerifier, VerifierConfig
from lcpr_core.verification.processes import CloudRef, VerifierProcesses
from lcpr_offline.synthetic_scenes import scattered_world, sensor_view

CONFIG = VerifierConfig(num_threads=1)
RNG = np.random.default_rng(7)
DEGENERATE = {  # name: (raw cloud, the reason it is refused with)
    "a ground plane": (np.c_[RNG.uniform(-30, 30, (5000, 2)), RNG.normal(0.0, 0.01, 5000)], "degenerate"),
    "a wall": (np.c_[RNG.uniform(-30, 30, 5000), np.full(5000, 4.0), RNG.uniform(-2, 6, 5000)], "degenerate"),
    "a long line": (np.c_[np.linspace(-79, 79, 5000), np.zeros(5000), np.ones(5000)], "degenerate"),
    "a single spot": (RNG.normal(0.0, 0.05, (5000, 3)) + (5.0, 5.0, 0.0), "too few points"),
    "fewer points than verify.min_points": (RNG.uniform(-10, 10, (150, 3)), "too few points"),
    "no points": (np.zeros((0, 3)), "too few points"),
    "only non-finite points": (np.full((100, 3), np.nan), "too few points"),
}


@pytest.fixture(scope="module")
def place() -> np.ndarray:
    return sensor_view(scattered_world(1), 0.0, 0.0, 0.0, seed=10)


@pytest.mark.parametrize("name", list(DEGENERATE))
def test_a_degenerate_cloud_is_refused_before_any_search_on_either_side(name, place, monkeypatch):
    raw, reason = DEGENERATE[name]
    verifier = GeometricVerifier(CONFIG)

    def never(*_: object, **__: object) -> None:
        raise AssertionError("a degenerate cloud reached a search or a registration")

    for stage in ("starts", "_coarse", "_fine", "_overlap"):
        monkeypatch.setattr(verifier, stage, never)
    for query, match in ((raw, place), (place, raw)):
        v = verifier.verify(query, match)
        assert not v.accepted and v.reason == reason and reason in REJECT_REASONS
    assert verifier.prepare(verifier.compact(raw)).refusal == reason


def test_a_real_scene_is_not_refused_while_being_prepared(place):
    verifier = GeometricVerifier(CONFIG)
    assert verifier.prepare(verifier.compact(place)).refusal == ""


def test_worker_processes_answer_a_degenerate_cloud_with_its_reason_not_an_exception(place):
    verifier = GeometricVerifier(CONFIG)
    clouds = {"place": verifier.compact(place), "plane": verifier.compact(DEGENERATE["a ground plane"][0]),
              "empty": np.zeros((0, 3))}
    ref = {k: CloudRef(k, functools.partial(clouds.__getitem__, k)) for k in clouds}
    with VerifierProcesses(CONFIG, processes=2) as pool:
        verdicts = pool.verify([(ref["place"], ref["plane"]), (ref["plane"], ref["place"]),
                                (ref["place"], ref["empty"])])
        assert pool.fallbacks == 0
    assert [getattr(v, "reason", v) for v in verdicts] == ["degenerate", "degenerate", "too few points"]
