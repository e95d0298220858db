"""Keyframe pairs with a known answer, on which the verifier's thresholds are chosen and measured.

True revisits and far pairs of a scan folder (the Livox Avia sets: ``livox_hku/walk_loop`` and
``campus``, poses from a SLAM system) and of a synthetic drive (exact poses), the validation / test
split of a set by query keyframe, and each scan's prepared compact cloud made once. Shared by the
threshold recipe (benchmarks/recipes/verify_tune.py), the measuring tools (verify_real.py,
verify_cost.py, registration_compare.py) and the tests, so all of them score the same pairs.
"""
from __future__ import annotations

from typing import Protocol

import numpy as np
from tqdm import tqdm

from citysim import SynthConfig, SyntheticDrive
from lcpr_core.posegraph import relative_pose_error, rotation_angle_deg, rotation_error_deg
from lcpr_core.revisits import revisit_pairs
from lcpr_core.scan_context import ScanContextConfig, _all_shifts, scan_context
from lcpr_core.verification import GeometricVerifier, PreparedCloud
from msg_tools.convert.scan_folder import ScanFolder

#: A true revisit: the two keyframes closer than this (m) ...
TRUE_RADIUS = 3.0
#: ... more than this apart in time (s) ...
TRUE_GAP_S = 30.0
#: ... and turned by less than this (deg) against each other.
TRUE_ROT_DEG = 30.0
#: A far pair: the two keyframes farther apart than this (m); the verifier must accept none.
FAR_M = 20.0


class Scans(Protocol):
    """A sequence of scans with their poses (N x 4 x 4, the LiDAR in the world): a scan folder or a synthetic
    drive's LiDAR."""

    @property
    def poses(self) -> np.ndarray: ...

    def points(self, i: int) -> np.ndarray: ...


def true_pairs(seq: ScanFolder) -> np.ndarray:
    """(query, match) rows of the true revisits of a scan folder (TRUE_RADIUS, TRUE_GAP_S, TRUE_ROT_DEG)."""
    pairs = revisit_pairs(seq.poses[:, :3, 3], seq.stamps, radius=TRUE_RADIUS, min_time_gap=TRUE_GAP_S)
    rel = np.einsum("nji,njk->nik", seq.poses[pairs[:, 1], :3, :3], seq.poses[pairs[:, 0], :3, :3])
    return pairs[rotation_angle_deg(rel) < TRUE_ROT_DEG]


def far_pairs(seq: ScanFolder, *, sample: int, hard: int, seed: int, before: int | None = None
              ) -> tuple[np.ndarray, np.ndarray]:
    """(random sample, hardest by Scan Context) of pairs (query, match) more than FAR_M apart.

    The hardest: per query, the ``hard`` older far keyframes whose Scan Context is nearest (what a
    retrieval stage proposes). ``before``: only queries before that keyframe (the random sample is
    drawn among them).
    """
    P = seq.poses[:, :3, 3]
    d = np.linalg.norm(P[:, None] - P[None], axis=-1)
    if before is not None:
        d[before:] = 0.0
    q, m = np.nonzero(np.triu(d > FAR_M, 1).T)  # q > m
    all_far = np.stack([q, m], axis=1)
    rng = np.random.default_rng(seed)
    random = all_far[rng.choice(len(all_far), size=min(sample, len(all_far)), replace=False)]
    cfg = ScanContextConfig()
    contexts = [scan_context(seq.points(i), config=cfg) for i in tqdm(range(len(seq)), desc="scan contexts",
                                                                      leave=False)]
    hardest = []
    for i in range(len(seq)):
        others = np.flatnonzero(d[i] > FAR_M)
        others = others[others < i]
        if len(others) == 0:
            continue
        dist = np.array([_all_shifts(contexts[i], contexts[j]).min() for j in others])
        hardest += [(i, int(j)) for j in others[np.argsort(dist)[:hard]]]
    return random, np.array(hardest, np.int64).reshape(-1, 2)


def split_at(name: str, seq: ScanFolder) -> int:
    """The query keyframe that splits a set's pairs into validation (queries before it) and test.

    campus: half its keyframes. walk_loop: its revisits all come at the end of the walk,
    so the median query keyframe of its true pairs (the first half of the return).
    """
    if name == "walk_loop":
        return int(np.median(true_pairs(seq)[:, 0]))
    return len(seq) // 2


def split_pairs(pairs: np.ndarray, at: int, split: str) -> np.ndarray:
    """Pairs of one split: "validation" = query keyframe before ``at``, "test" = the rest, "all"."""
    if split == "all":
        return pairs
    first = pairs[:, 0] < at
    return pairs[first] if split == "validation" else pairs[~first]


def pose_error(estimate: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    """(translation m, full rotation angle deg): a handheld sensor tilts, so not only yaw counts."""
    return relative_pose_error(estimate, truth)[0], rotation_error_deg(estimate, truth)


class PreparedScans:
    """The prepared compact clouds of a sequence's scans (``seq.points(i)``), each made once: pairs share scans."""

    def __init__(self, verifier: GeometricVerifier, seq: Scans) -> None:
        self.verifier, self.seq = verifier, seq
        self._cache: dict[int, PreparedCloud] = {}

    def __getitem__(self, i: int) -> PreparedCloud:
        if i not in self._cache:
            self._cache[i] = self.verifier.prepare(self.verifier.compact(self.seq.points(i)))
        return self._cache[i]


class SyntheticLidar:
    """LiDAR clouds and poses of a synthetic drive (cameras rendered tiny: only the cloud is used)."""

    def __init__(self, rig: str, seed: int, frames: int) -> None:
        self.drive = SyntheticDrive(SynthConfig(rig=rig, frames=frames, seed=seed, image_size=(64, 32)))
        base_T_lidar = self.drive.rig.lidar.base_T_lidar
        self.poses = np.stack([self.drive.pose(i) @ base_T_lidar for i in range(len(self.drive))])
        self.stamps = np.asarray(self.drive.keyframes.stamps, np.float64)
        self._cache: dict[int, np.ndarray] = {}

    def __len__(self) -> int:
        return len(self.poses)

    def points(self, i: int) -> np.ndarray:
        if i not in self._cache:
            self._cache[i] = self.drive.frame(i).xyz
        return self._cache[i]


def synthetic_pairs(seq: SyntheticLidar, *, far_random: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """(true, far) pairs of a synthetic drive: true within 9 m and >= 30 s apart (the demo's rule), far a
    seeded random sample of ``far_random`` pairs more than FAR_M apart."""
    P = seq.poses[:, :3, 3]
    true = revisit_pairs(P, seq.stamps, radius=9.0, min_time_gap=30.0)
    d = np.linalg.norm(P[:, None] - P[None], axis=-1)
    q, m = np.nonzero(np.tril(d > FAR_M, -1))
    rng = np.random.default_rng(seed)
    far = np.stack([q, m], 1)[rng.choice(len(q), size=min(far_random, len(q)), replace=False)]
    return true, far
