"""Typed settings of the geometric verification stage (one source for the node, lcpr_eval and the demo)."""
from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field, fields, replace
from typing import Any

from lcpr_common.params import check_fields, param

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

    voxel: float = param(0.4, "m, voxel size of the compact keyframe cloud kept in the map", lo=0.05, hi=5.0)
    # cap per keyframe after voxelisation (evenly spaced subset); thinning a 360 deg scan further leaves its
    # surfaces too sparse for the overlap test (docs/verification.md, "Raw 360-degree scans"); the fine
    # registration runs on about verify.fine_points of them
    max_points: int = param(8192, "points kept per keyframe cloud (6 bytes each)", lo=100, hi=1_000_000)
    min_range: float = param(1.0, "m: nearer points (the ego vehicle, the operator) are left out", lo=0.0)
    max_range: float = param(80.0, "m: farther points are left out (at most 327: int16 centimetres)", lo=0.0,
                             lo_open=True)

    def __post_init__(self) -> None:
        check_fields(self, error=VerificationError, prefix="verify.cloud.")
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

    enabled: bool = param(True, "register each candidate's cloud against the query's and publish verified loops "
                                "only; false = publish the nearest descriptor unchecked", dynamic=True)
    cloud: CloudConfig = field(default_factory=CloudConfig)
    registration: str = param("GICP", "small_gicp registration", choices=REGISTRATIONS, dynamic=True)
    # OpenMP threads of small_gicp; 1 is fastest beside the network on 2 cores
    num_threads: int = param(1, "registration threads", lo=1, hi=64, dynamic=True)
    processes: int = param(2, "worker processes verifying a keyframe's candidates side by side (each keeps its "
                              "own prepared clouds); 0 = in the node's process", lo=0, hi=64, dynamic=True)
    min_points: int = param(200, "fewer points (after downsampling) in either cloud: not verifiable", lo=1)
    # initial guess
    yaw_hypotheses: int = param(4, "Scan Context shifts tried as initial yaws", lo=1)
    bev_cell: float = param(1.0, "m, bird's-eye-view cell of the x/y cross-correlation", lo=0.0, lo_open=True)
    bev_extent: float = param(48.0, "m, half width of the bird's-eye view", lo=0.0, lo_open=True)
    # the views are made of an evenly spaced sample of about this many points; 0: all (the default: a sample moves
    # the x/y peaks for a small saving: docs/verification.md, "Cost")
    bev_points: int = param(0, "points the bird's-eye views are made of (an evenly spaced sample); 0 = all", lo=0)
    # with 2 more starts, see starts()
    registrations: int = param(2, "bird's-eye-view hypotheses registered at the coarse level", lo=1)
    # registration
    coarse_voxel: float = param(2.0, "m, first voxel tried for the coarse stage's clouds (rescaled to keep about "
                                     "verify.coarse_points)", lo=0.0, lo_open=True)
    coarse_points: int = param(600, "points each coarse-stage cloud keeps about (any field of view)", lo=1)
    coarse_accept: float = param(0.45, "a start whose coarse overlap reaches this ends the search over starts",
                                 lo=0.0)
    early_reject: float = param(0.8, "an overlap at the coarse pose under this times verify.min_fitness is "
                                     "rejected at once", lo=0.0)
    coarse_distance: float = param(3.0, "m, max correspondence distance of the coarse stage", lo=0.0, lo_open=True)
    fine_distance: float = param(1.0, "m, max correspondence distance of the fine stage", lo=0.0, lo_open=True)
    # a right start converges in a few; a narrow field of view needs more (verify_tune.py)
    coarse_iterations: int = param(15, "iterations of the coarse stage at most", lo=1)
    # the coarse stage stops once an iteration moves the pose less than this (small_gicp's own default is 1 mm /
    # 0.1 deg: far finer than 2 m voxels resolve; the fine stage refines the pose from there)
    coarse_epsilon_m: float = param(0.03, "m: the coarse stage stops once an iteration moves the pose less than "
                                          "this", lo=0.0)
    coarse_epsilon_deg: float = param(0.5, "deg: the coarse stage stops once an iteration turns the pose less "
                                           "than this", lo=0.0)
    max_iterations: int = param(10, "iterations of the fine stage at most (it starts from a converged coarse "
                                    "pose)", lo=1)
    fine_points: int = param(3072, "points the fine stage's clouds are resampled to, about", lo=1)
    # the overlap is estimated from an evenly spaced sample of each cloud's points (every k-th, at most about
    # this many) searched in the other's full cloud (dense surfaces; a sparse sample is unbiased); 0 reads all
    overlap_points: int = param(3072, "points of each cloud sampled (evenly) for the overlap estimate; 0 = all",
                                lo=0)
    # a sampled overlap within this of min_fitness is read again from every point: the verdict on a borderline
    # pair is the full overlap's, never a sample's
    overlap_recheck: float = param(0.03, "a sampled overlap within this of verify.min_fitness is read again from "
                                         "every point", lo=0.0)
    coarse_overlap_points: int = param(512, "points sampled for the overlap that ranks the coarse results (every "
                                            "8th point at least); 0 = all", lo=0)
    # acceptance
    inlier_distance: float = param(0.6, "m, nearest-neighbour reach of an inlier", lo=0.0, lo_open=True)
    plane_distance: float = param(0.1, "m, an inlier's distance to its neighbour's local plane at most", lo=0.0,
                                  lo_open=True)
    # benchmarks/recipes/verify_tune.py: <= 0.1 % of validation false pairs pass
    min_fitness: float = param(0.475, "overlap (0..1) a registration needs to be accepted", lo=0.0, hi=1.0,
                               dynamic=True)
    max_rmse: float = param(0.2, "m, inlier RMSE of an accepted registration at most", lo=0.0, lo_open=True)
    # fine vs coarse pose; set above the largest correction of a validation true pair (docs/verification.md)
    max_correction_m: float = param(1.0, "m the fine stage may move the pose from the coarse stage's result",
                                    lo=0.0, lo_open=True)
    max_correction_deg: float = param(5.0, "deg the fine stage may turn the pose from the coarse stage's result",
                                      lo=0.0, lo_open=True)
    # 0..1/3 point-to-plane observability (verify_tune.py); a plane, a sphere ~0
    min_constraint: float = param(0.02, "smallest per-inlier Hessian eigenvalue (rejects planes, corridors, "
                                        "sphere shells)", lo=0.0, hi=math.inf, dynamic=True)
    # free space (docs/verification.md, "Free space": chosen on validation data between its true pairs' largest
    # share and its wrong poses' smallest): a pair whose points lie in the other scan's free space beyond this
    # share, on either side, is refused as "contradicted"; 1 = never
    max_contradiction: float = param(0.05, "share (0..1) of either cloud's points that may lie where the other "
                                           "sensor's beams passed through (its free space) before the pair is "
                                           "refused as contradicted, a look-alike place; 1 = no free-space test",
                                     lo=0.0, hi=1.0, dynamic=True)
    # ambiguity (docs/verification.md, "Ambiguous poses"; chosen on validation data): a pair
    # about to be accepted whose translation part of the constraint is under ambiguity_constraint (0: never) is
    # registered from its other starts too; another pose more than ambiguity_distance m away reaching
    # ambiguity_ratio x its fitness refuses it ("ambiguous": the clouds slide along a street or a corridor)
    ambiguity_constraint: float = param(0.06, "translation constraint (0..1/3) under which a pair about to be "
                                              "accepted is also registered from its other starts (0 = never)",
                                        lo=0.0, hi=1.0, dynamic=True)
    ambiguity_ratio: float = param(0.6, "another pose reaching this share of the accepted fitness refuses the "
                                        "pair as ambiguous", lo=0.01, hi=1.0, dynamic=True)
    ambiguity_distance: float = param(5.0, "m: how far another pose must lie from the accepted one to count as "
                                           "an alternative", lo=0.1, hi=1000.0, dynamic=True)
    # covariance: inv(Hessian) * residual variance factor * inflation, floored per axis
    covariance_inflation: float = param(10.0, "factor on the registration's covariance (inverse Hessian times "
                                              "the residual variance)", lo=0.0, lo_open=True)
    min_sigma_m: float = param(0.02, "m: floor of the covariance's translation std devs", lo=0.0)
    min_sigma_deg: float = param(0.2, "deg: floor of the covariance's rotation std devs", lo=0.0)

    def __post_init__(self) -> None:
        check_fields(self, error=VerificationError, prefix="verify.")
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
