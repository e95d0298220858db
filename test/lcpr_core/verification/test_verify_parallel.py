"""Verifying a keyframe's candidates costs less without changing a verdict: threads over candidates, starts once."""
from __future__ import annotations

import math
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest

from lcpr_core.verification import GeometricVerifier, PreparedCloud, VerifierConfig
from lcpr_offline.synthetic_scenes import scattered_world, sensor_view

CONFIG = VerifierConfig(num_threads=1)


def _seen(world: np.ndarray, x: float, y: float, yaw_deg: float, seed: int) -> np.ndarray:
    return sensor_view(world, x, y, yaw_deg, seed=seed)


@pytest.fixture(scope="module")
def verifier() -> GeometricVerifier:
    return GeometricVerifier(CONFIG)


@pytest.fixture(scope="module")
def keyframe(verifier) -> tuple[PreparedCloud, list[PreparedCloud]]:
    """A query and 6 candidates: 3 views of its place (moved, turned) and 3 views of other worlds."""
    world = scattered_world(1)
    query = verifier.prepare(verifier.compact(_seen(world, 0.0, 0.0, 0.0, seed=10)))
    near = [_seen(world, dx, dy, yaw, seed=20 + k) for k, (dx, dy, yaw) in
            enumerate(((1.5, -1.0, 10.0), (-2.0, 2.0, 90.0), (3.0, 0.5, -30.0)))]
    far = [_seen(scattered_world(5 + k), 0.0, 0.0, 0.0, seed=30 + k) for k in range(3)]
    return query, [verifier.prepare(verifier.compact(c)) for c in near + far]


def same_verdict(a: object, b: object) -> bool:
    """Whether two verdicts agree field for field (arrays exactly, NaN equal to NaN)."""
    for name in ("accepted", "reason", "fitness", "rmse", "constraint", "coarse_fitness"):
        x, y = getattr(a, name), getattr(b, name)
        if x != y and not (isinstance(x, float) and math.isnan(x) and math.isnan(y)):
            return False
    return all(np.array_equal(getattr(a, n), getattr(b, n), equal_nan=True)
               for n in ("match_T_query", "covariance", "initial"))


def test_verifying_candidates_over_two_threads_gives_the_verdicts_and_poses_of_one_by_one(verifier, keyframe):
    query, matches = keyframe
    alone = [verifier.verify_prepared(query, m) for m in matches]
    assert sum(v.accepted for v in alone) >= 2 and sum(not v.accepted for v in alone) >= 3  # both kinds tested
    with ThreadPoolExecutor(2) as pool:
        for _ in range(3):  # threads interleave differently each time
            threaded = verifier.verify_all(query, matches, pool=pool)
            assert len(threaded) == len(matches)
            assert all(same_verdict(a, b) for a, b in zip(alone, threaded, strict=True)), [(a.reason, b.reason)
                                                                      for a, b in zip(alone, threaded, strict=True)]
    one_by_one = verifier.verify_all(query, matches)  # no pool
    assert all(same_verdict(a, b) for a, b in zip(alone, one_by_one, strict=True))


def test_a_start_equal_to_an_earlier_one_is_registered_once_with_the_same_verdict(verifier, keyframe, monkeypatch):
    query, matches = keyframe
    stranger = matches[-1]  # all starts are tried on a stranger: none reaches coarse_accept
    once = verifier.verify_prepared(query, stranger, initial_guess=np.eye(4))
    calls: list[np.ndarray] = []
    coarse = GeometricVerifier._coarse

    def counted(self: GeometricVerifier, q: PreparedCloud, m: PreparedCloud, T0: np.ndarray
                ) -> tuple[float, np.ndarray, np.ndarray]:
        calls.append(T0)
        return coarse(self, q, m, T0)

    monkeypatch.setattr(GeometricVerifier, "_coarse", counted)
    monkeypatch.setattr(GeometricVerifier, "starts", lambda self, q, m: [np.eye(4), np.eye(4), np.eye(4)])
    repeated = verifier.verify_prepared(query, stranger)
    assert len(calls) == 1
    assert same_verdict(once, repeated) and not repeated.accepted
