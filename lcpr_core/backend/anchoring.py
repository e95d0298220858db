"""Placing a new session in the map frame: which inter-session loops agree with one another.

A loop between a session already in the map frame (its end ``a``) and one not yet placed (its end ``b``)
measures ``Z = X_a^-1 X_b``; with ``b``'s estimate ``E_b`` in the new session's own frame it implies the
transform ``map_T_own = X_a Z E_b^-1``. Two such loops ``i``, ``j`` agree when the relative pose they predict
between their new-session ends, ``Z_i^-1 (X_ai^-1 X_aj) Z_j``, matches the one the new session's own graph
holds, ``E_bi^-1 E_bj``, within the sum of the four covariances moved into ``b_j``'s tangent (pairwise
consistency, as PCM). The largest set of loops that agree pairwise (a maximum clique) anchors the session.
Covariances are GTSAM-order (rotation, translation), in the right tangent.
"""
from __future__ import annotations

import numpy as np

from ..geometry import invert
from .consistency import adjoint

__all__ = ["implied_transform", "invert_measurement", "max_clique", "pair_statistic"]


def invert_measurement(measured: np.ndarray, cov: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(Z^-1, its covariance)`` for ``Z`` with right-tangent covariance ``cov``: ``Ad(Z) cov Ad(Z)^T``."""
    ad = adjoint(measured)
    return invert(measured), ad @ cov @ ad.T


def implied_transform(x_a: np.ndarray, measured: np.ndarray, e_b: np.ndarray) -> np.ndarray:
    """``map_T_own = X_a Z E_b^-1``: where a loop puts the new session's own frame in the map."""
    return x_a @ measured @ invert(e_b)


def pair_statistic(*, z_i: np.ndarray, cov_i: np.ndarray, z_j: np.ndarray, cov_j: np.ndarray,
                   a_rel: np.ndarray, a_cov: np.ndarray, b_rel: np.ndarray, b_cov: np.ndarray) -> float:
    """Squared Mahalanobis distance between two loops' predictions of ``E_bi^-1 E_bj``.

    ``z_i``, ``z_j``: the loops' ``X_a^-1 X_b`` with covariances ``cov_i``, ``cov_j`` (b's tangent);
    ``a_rel = X_ai^-1 X_aj`` with ``a_cov`` (a_j's tangent) from the map's graph; ``b_rel = E_bi^-1 E_bj``
    with ``b_cov`` (b_j's tangent) from the new session's own graph.
    """
    predicted = invert(z_i) @ a_rel @ z_j
    error = invert(b_rel) @ predicted
    residual = _log(error)
    to_bj = adjoint(invert(b_rel))
    from_aj = adjoint(invert(z_j))
    total = to_bj @ cov_i @ to_bj.T + from_aj @ a_cov @ from_aj.T + b_cov + cov_j
    return float(residual @ np.linalg.solve(total, residual))


def max_clique(agree: np.ndarray) -> list[int]:
    """The largest set of indices whose pairs all agree (``agree``: N x N symmetric bool), smallest indices on
    a tie. Bron-Kerbosch with a pivot: exact, and fast at the few hundred loops a session keeps waiting."""
    n = len(agree)
    neighbours = [set(np.flatnonzero(agree[i]).tolist()) - {i} for i in range(n)]
    best: list[int] = []

    def grow(chosen: list[int], candidates: set[int], excluded: set[int]) -> None:
        nonlocal best
        if not candidates and not excluded:
            if len(chosen) > len(best) or (len(chosen) == len(best) and sorted(chosen) < sorted(best)):
                best = list(chosen)
            return
        if len(chosen) + len(candidates) < len(best):
            return
        pivot = max(candidates | excluded, key=lambda u: len(neighbours[u] & candidates))
        for v in sorted(candidates - neighbours[pivot]):
            grow([*chosen, v], candidates & neighbours[v], excluded & neighbours[v])
            candidates = candidates - {v}
            excluded = excluded | {v}

    grow([], set(range(n)), set())
    return sorted(best)


def _log(pose: np.ndarray) -> np.ndarray:
    """SE(3) log in GTSAM's (rotation, translation) order."""
    import gtsam

    return np.asarray(gtsam.Pose3.Logmap(gtsam.Pose3(np.ascontiguousarray(pose, np.float64))))
