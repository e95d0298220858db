"""A global initial alignment of two clouds that needs no odometry and no yaw guess (KISS-Matcher).

    found = global_alignment(query_xyz, match_xyz, config=GlobalAlignConfig())
    if found.valid: verifier.verify_prepared(q, m, initial_guess=found.match_T_query)

KISS-Matcher (Lim et al., ICRA 2025; ``pip install kiss-matcher``) voxelises both clouds, matches
FPFH features computed on them, prunes the correspondences by their pairwise consistency (max
clique) and solves the pose with graduated non-convexity: a start from anywhere, any turn. It is
a *start* for small_gicp's registration (coarse, then fine), not a verdict: on a wrong candidate it
still returns a pose.

The defaults were chosen on validation pairs only (true revisits of ``livox_hku/walk_loop`` and
``campus`` whose query is in the first half, :func:`lcpr_offline.verification_pairs.split_pairs`
"validation"), by benchmarks/studies/global_registration.py ``--tune``; docs/studies/global_registration.md
has the measurements. Its cost (docs/studies/global_registration.md; the FPFH of both clouds is most of it)
makes it a fallback for the best-ranked candidate whose usual starts failed, not a start for every candidate.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np

from ..errors import VerificationError

METHODS: tuple[str, ...] = ("kiss_matcher",)


@dataclass(frozen=True)
class GlobalAlignConfig:
    """Settings of :func:`global_alignment`; radii scale with the voxel (KISS-Matcher's own convention)."""

    method: str = "kiss_matcher"
    voxel: float = 0.8  # m: both clouds voxelised to this before the features (compact clouds are 0.4 m)
    normal_gain: float = 3.0  # normal radius = normal_gain * voxel
    fpfh_gain: float = 4.0  # FPFH radius = fpfh_gain * voxel
    max_points: int = 2000  # more points at ``voxel``: voxelised coarser, radii growing with it (see _voxel_for)
    max_correspondences: int = 5000  # feature matches kept before pruning
    min_inliers: int = 5  # a solution with fewer final inliers is not valid
    use_quatro: bool = False  # Quatro: rotation about z only; a handheld sensor tilts, so off by default

    def __post_init__(self) -> None:
        if self.method not in METHODS:
            raise VerificationError(f"global_align.method={self.method!r}; accepted: {', '.join(METHODS)}")
        for name in ("voxel", "normal_gain", "fpfh_gain"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) \
                    or value <= 0:
                raise VerificationError(f"global_align.{name}={value!r}; accepted: a finite number > 0")
        if self.fpfh_gain <= self.normal_gain:
            raise VerificationError(f"global_align.fpfh_gain={self.fpfh_gain!r} <= normal_gain={self.normal_gain!r}; "
                                    "accepted: fpfh_gain > normal_gain (FPFH reaches past the normals it uses)")
        for name, low in (("max_points", 100), ("max_correspondences", 3), ("min_inliers", 3)):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < low:
                raise VerificationError(f"global_align.{name}={value!r}; accepted: an integer >= {low}")
        if not isinstance(self.use_quatro, bool):
            raise VerificationError(f"global_align.use_quatro={self.use_quatro!r}; accepted: True or False")


@dataclass(frozen=True)
class GlobalAlignment:
    """A global start: ``match_T_query`` maps query points into the match frame (p_match = T @ p_query)."""

    match_T_query: np.ndarray  # 4 x 4 float64 (identity when nothing was solved)
    inliers: int  # final (translation) inliers of the solver
    valid: bool  # the solver converged with at least ``min_inliers`` inliers
    seconds: float
    voxel: float = math.nan  # m, the voxel the features were made at (``voxel`` or coarser, see ``max_points``)


def global_alignment(query_xyz: np.ndarray, match_xyz: np.ndarray, *,
                     config: GlobalAlignConfig | None = None) -> GlobalAlignment:
    """Align ``query_xyz`` to ``match_xyz`` (N x (>=3) each, own frames) from no initial guess."""
    cfg = config if config is not None else GlobalAlignConfig()
    tic = time.perf_counter()
    q, m = (_xyz(p, name) for p, name in ((query_xyz, "query_xyz"), (match_xyz, "match_xyz")))
    if min(len(q), len(m)) < 3:
        return GlobalAlignment(np.eye(4), 0, False, time.perf_counter() - tic)
    try:
        import kiss_matcher
    except ImportError as err:
        raise VerificationError("global_align.method='kiss_matcher' needs the kiss-matcher package: "
                                "pip install kiss-matcher") from err
    voxel = max(_voxel_for(q, cfg), _voxel_for(m, cfg))  # one voxel for both: their features must compare
    matcher = kiss_matcher.KISSMatcher(kiss_matcher.KISSMatcherConfig(
        voxel_size=voxel, use_voxel_sampling=True, use_quatro=cfg.use_quatro,
        num_max_corr=cfg.max_correspondences, normal_r_gain=cfg.normal_gain, fpfh_r_gain=cfg.fpfh_gain))
    solution = matcher.estimate(q, m)
    T = np.eye(4)
    T[:3, :3] = np.asarray(solution.rotation, np.float64)
    T[:3, 3] = np.asarray(solution.translation, np.float64).reshape(3)
    inliers = int(matcher.get_num_final_inliers())
    valid = bool(solution.valid) and inliers >= cfg.min_inliers and bool(np.isfinite(T).all())
    if not np.isfinite(T).all():
        T = np.eye(4)
    return GlobalAlignment(T, inliers, valid, time.perf_counter() - tic, voxel)


def _voxel_for(xyz: np.ndarray, cfg: GlobalAlignConfig) -> float:
    """``cfg.voxel``, or a coarser voxel that leaves about ``cfg.max_points`` of the cloud.

    Why: the features' cost grows with the points and their neighbours; a 360 deg scan keeps several
    thousand points at the voxel that suits a 70 deg Livox view, and a cap keeps its cost near a Livox pair's
    with the same starts found (docs/studies/global_registration.md, "Parameters"); a narrow Livox cloud stays
    as it is. Surface points scale with 1 / voxel^2, so one rescaled voxel lands close.
    Above ~1 m KISS-Matcher clamps its noise bounds and prints a warning to stdout.
    """
    import small_gicp

    count = small_gicp.voxelgrid_sampling(xyz, cfg.voxel, num_threads=1).size()
    if count <= cfg.max_points:
        return cfg.voxel
    return cfg.voxel * math.sqrt(count / cfg.max_points)


def _xyz(points: np.ndarray, name: str) -> np.ndarray:
    """The finite x, y, z rows of an N x (>=3) array as contiguous float64, or VerificationError naming it."""
    a = np.asarray(points)
    if a.ndim != 2 or a.shape[1] < 3 or a.dtype.kind not in "fiu":
        raise VerificationError(f"{name} of shape {a.shape} and dtype {a.dtype}; accepted: N x (>=3) numbers")
    xyz = a[:, :3].astype(np.float64)
    return np.ascontiguousarray(xyz[np.isfinite(xyz).all(axis=1)])
