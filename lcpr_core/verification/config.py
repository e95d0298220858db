"""Typed settings of the geometric verification stage (one source for the node, lcpr_eval and the demo)."""
from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field, fields, replace
from typing import Any

from ..errors import VerificationError

REGISTRATIONS: tuple[str, ...] = ("GICP", "PLANE_ICP", "VGICP")


@dataclass(frozen=True)
class CloudConfig:
    """How a keyframe's cloud is kept: voxel-downsampled, capped, quantised to int16 centimetres.

    Bytes per keyframe: 6 * (points kept) <= 6 * max_points (48 KiB at the default 8192; a 70 deg
    Livox keeps 1-3 thousand points, a 360 deg 64-beam scan reaches the cap),
    plus 16 bytes of bookkeeping. Points farther than ``max_range`` or nearer than
    ``min_range`` (straight-line distance from the sensor) are left out.
    """

    voxel: float = 0.4  # m, voxel-grid downsampling (centroid per voxel)
    # cap per keyframe after voxelisation (evenly spaced subset); thinning a 360 deg scan further leaves its
    # surfaces too sparse for the overlap test (raw KITTI scans from the true pose: overlap 0.25-0.46 at 3072,
    # 0.47-0.67 at 8192); the fine registration runs on about verify.fine_points of them
    max_points: int = 8192
    min_range: float = 1.0  # m: drops the ego vehicle / operator
    max_range: float = 80.0  # m (<= 327 m: int16 centimetres)

    def __post_init__(self) -> None:
        _positive(self, "voxel", "max_points", "max_range")
        if not 0.0 <= self.min_range < self.max_range:
            raise VerificationError(f"cloud min_range={self.min_range!r}, max_range={self.max_range!r}; "
                                    "accepted: 0 <= min_range < max_range")
        if self.max_range > 327.0:
            raise VerificationError(f"cloud max_range={self.max_range!r} m; accepted: <= 327 (int16 centimetres)")


@dataclass(frozen=True)
class VerifierConfig:
    """Registration and acceptance of one query/candidate pair.

    Pipeline: initial yaw hypotheses from the Scan Context column shift
    (``yaw_hypotheses`` best shifts), each completed with an x/y offset from a
    bird's-eye-view cross-correlation (``bev_cell``); the best
    ``registrations`` hypotheses (then the best yaw with no offset, then identity) are
    registered with small_gicp (GICP by default) on clouds downsampled to about
    ``coarse_points`` points, in turn until one reaches an overlap of ``coarse_accept``; the
    best of them (largest overlap) again on clouds of about ``fine_points`` points,
    unless its overlap at the coarse pose is already under
    ``early_reject * min_fitness`` ("low overlap" at once: the common case of a wrong
    candidate; benchmarks/recipes/verify_tune.py chose it to turn away at most 2 % of validation true pairs);
    the result is accepted when all of:

    - the overlap (share of each cloud's points whose nearest neighbour in the other
      cloud is within ``inlier_distance`` and that lie within ``plane_distance`` of that
      neighbour's local plane; the mean of the two shares) is at least ``min_fitness``;
      each share is estimated from an evenly spaced sample of about ``overlap_points``
      points searched in the other's full cloud, and read from every point when the
      estimate lies within ``overlap_recheck`` of ``min_fitness``;
    - the inlier RMSE is at most ``max_rmse``;
    - the fine stage (full compact clouds) moved the pose at most ``max_correction_m`` /
      ``max_correction_deg`` away from the coarse stage's result it started from: the two
      levels agree on one pose. The initial guess may be far off (a narrow field of view, a
      repetitive scene); how far the coarse stage travelled from it is not judged;
    - the registration is well constrained: the smallest eigenvalue of the point-to-plane
      information of the inliers (translation and rotation blocks, normalised; 0..1/3) is
      at least ``min_constraint`` (a plane, a corridor, a sphere shell give ~0);
    - the pose is not contradicted by free space: at most ``max_contradiction`` of either cloud's points
      lie where the other sensor's beams passed through (nearer than its nearest return in their
      direction; :mod:`.free_space`). A look-alike place registered on the part it shares puts the parts
      that differ there; the same place, rightly aligned, almost none (a passing car, sampling);
    - the pose is not ambiguous: when the translation block alone has a smallest eigenvalue
      under ``ambiguity_constraint`` (a street whose walls run along it constrains the pose across
      the street only), the best result of the other starts is refined too, and a pose more than
      ``ambiguity_distance`` away that reaches ``ambiguity_ratio`` x the fitness refuses the pair
      (the clouds could slide along the street onto a wrong pose that fits about as well).

    Thresholds default to values chosen on validation drives (see benchmarks/recipes/verify_tune.py),
    never on the drives docs/verification.md reports as held out.
    """

    enabled: bool = True
    cloud: CloudConfig = field(default_factory=CloudConfig)
    registration: str = "GICP"
    num_threads: int = 1  # OpenMP threads of small_gicp; 1 is fastest beside the network on 2 cores
    processes: int = 2  # worker processes verifying a keyframe's candidates side by side (0: in the caller's)
    min_points: int = 200  # fewer points (after downsampling) in either cloud: not verifiable
    # initial guess
    yaw_hypotheses: int = 4  # Scan Context shifts tried
    bev_cell: float = 1.0  # m, bird's-eye-view cell of the x/y cross-correlation
    bev_extent: float = 48.0  # m, half width of the bird's-eye view
    # the views are made of an evenly spaced sample of about this many points; 0: all (the default: a sample moves
    # the x/y peaks, which won and lost walk_loop pairs alike)
    bev_points: int = 0
    registrations: int = 2  # BEV hypotheses registered at the coarse level (with 2 more starts, see starts())
    # registration
    coarse_voxel: float = 2.0  # m, first voxel tried for the coarse stage's clouds ...
    coarse_points: int = 600  # ... rescaled so that each keeps about this many points (any field of view)
    coarse_accept: float = 0.45  # a start whose coarse overlap reaches this ends the search over starts
    early_reject: float = 0.8  # overlap at the coarse pose under early_reject * min_fitness: rejected at once
    coarse_distance: float = 3.0  # m, max correspondence distance of the coarse stage
    fine_distance: float = 1.0  # m, of the fine stage
    coarse_iterations: int = 15  # a right start converges in a few; a narrow field of view needs more (verify_tune.py)
    # the coarse stage stops once an iteration moves the pose less than this (small_gicp's own default is 1 mm /
    # 0.1 deg: far finer than 2 m voxels resolve; the fine stage refines the pose from there)
    coarse_epsilon_m: float = 0.03
    coarse_epsilon_deg: float = 0.5
    max_iterations: int = 10  # of the fine stage (it starts from a converged coarse pose)
    fine_points: int = 3072  # the fine stage registers clouds resampled to about this many
    # the overlap is estimated from an evenly spaced sample of each cloud's points (every k-th, at most about
    # this many) searched in the other's full cloud (dense surfaces; a sparse sample is unbiased); 0 reads all
    overlap_points: int = 3072
    # a sampled overlap within this of min_fitness is read again from every point: the verdict on a borderline
    # pair is the full overlap's (walk_loop pairs at 0.475-0.479 fell 0.005 under min_fitness from a sample)
    overlap_recheck: float = 0.03
    coarse_overlap_points: int = 512  # the same for ranking the coarse results (every 8th point at least)
    # acceptance
    inlier_distance: float = 0.6  # m, nearest-neighbour reach of an inlier
    plane_distance: float = 0.1  # m, its distance to the neighbour's local plane
    min_fitness: float = 0.475  # benchmarks/recipes/verify_tune.py: <= 0.1 % of validation false pairs pass
    max_rmse: float = 0.2  # m
    max_correction_m: float = 1.0  # fine vs coarse pose; validation true pairs moved <= 0.7 m, 1.7 deg
    max_correction_deg: float = 5.0
    min_constraint: float = 0.02  # 0..1/3 point-to-plane observability (verify_tune.py); a plane, a sphere ~0
    # free space (docs/verification.md; chosen on the validation city seed 3, the KITTI scans and the Livox validation
    # halves: their true pairs reach 0.016, their wrong poses 0.096 at least): a pair whose points lie in the other
    # scan's free space beyond this share, on either side, is refused as "contradicted"; 1 = never
    max_contradiction: float = 0.05
    # ambiguity (docs/verification.md; chosen on the validation city seed 3 and the Livox validation halves): a pair
    # about to be accepted whose translation part of the constraint is under ambiguity_constraint (0: never) is
    # registered from its other starts too; another pose more than ambiguity_distance m away reaching
    # ambiguity_ratio x its fitness refuses it ("ambiguous": the clouds slide along a street or a corridor)
    ambiguity_constraint: float = 0.06
    ambiguity_ratio: float = 0.6
    ambiguity_distance: float = 5.0
    # covariance: inv(Hessian) * residual variance factor * inflation, floored per axis
    covariance_inflation: float = 10.0
    min_sigma_m: float = 0.02
    min_sigma_deg: float = 0.2

    def __post_init__(self) -> None:
        if self.registration not in REGISTRATIONS:
            raise VerificationError(f"verify.registration={self.registration!r}; accepted: {', '.join(REGISTRATIONS)}")
        _positive(self, "num_threads", "min_points", "yaw_hypotheses", "bev_cell", "bev_extent", "registrations",
                  "coarse_voxel", "coarse_points", "fine_points", "coarse_distance", "fine_distance",
                  "coarse_iterations", "max_iterations", "inlier_distance", "plane_distance", "max_rmse",
                  "max_correction_m", "max_correction_deg", "covariance_inflation", "ambiguity_distance",
                  "ambiguity_ratio")
        _non_negative(self, "coarse_accept", "early_reject", "min_constraint", "ambiguity_constraint",
                      "min_sigma_m", "min_sigma_deg",
                      "coarse_epsilon_m", "coarse_epsilon_deg", "overlap_recheck")
        for name in ("overlap_points", "coarse_overlap_points", "bev_points"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 0:
                raise VerificationError(f"verify.{name}={value!r}; accepted: an integer >= 0 (0: every point)")
        if isinstance(self.processes, bool) or not isinstance(self.processes, int) or not 0 <= self.processes <= 64:
            raise VerificationError(f"verify.processes={self.processes!r}; accepted: an integer 0..64 (0: verify in "
                                    "the detector's own process)")
        if isinstance(self.max_contradiction, bool) or not 0.0 <= self.max_contradiction <= 1.0:
            raise VerificationError(f"verify.max_contradiction={self.max_contradiction!r}; accepted: 0 <= "
                                    "max_contradiction <= 1 (1 = no free-space test)")
        if not 0.0 <= self.min_fitness <= 1.0:
            raise VerificationError(f"verify.min_fitness={self.min_fitness!r}; accepted: 0 <= min_fitness <= 1")
        if self.bev_extent / self.bev_cell > 1024:
            raise VerificationError(f"verify.bev_extent / verify.bev_cell = {self.bev_extent / self.bev_cell:.0f} "
                                    "cells; accepted: at most 1024 (a larger view is slower, not better)")


def with_settings(config: VerifierConfig, items: Sequence[str]) -> VerifierConfig:
    """``config`` with numeric fields set from "NAME=VALUE" items (benchmarks compare settings back to back)."""
    numeric = {f.name for f in fields(VerifierConfig)} - {"enabled", "cloud", "registration"}
    values: dict[str, Any] = {}  # Any: the fields are of several types
    for item in items:
        name, sep, text = (part.strip() for part in item.partition("="))
        try:
            value: int | float = int(text) if text.lstrip("-").isdigit() else float(text)
        except ValueError:
            value = math.nan
        if not sep or name not in numeric or value != value:
            raise VerificationError(f"setting {item!r}; accepted: NAME=NUMBER, NAME one of "
                                    f"{', '.join(sorted(numeric))}")
        values[name] = value
    return replace(config, **values)


def _positive(obj: object, *names: str) -> None:
    for name in names:
        value = getattr(obj, name)
        if isinstance(value, bool) or not value > 0:
            raise VerificationError(f"verify.{name}={value!r}; it must be > 0")


def _non_negative(obj: object, *names: str) -> None:
    for name in names:
        value = getattr(obj, name)
        if isinstance(value, bool) or not value >= 0:
            raise VerificationError(f"verify.{name}={value!r}; it must be >= 0")
