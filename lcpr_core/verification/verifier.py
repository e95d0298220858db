"""Geometric verification of loop candidates: register the two keyframe clouds, accept on the evidence.

    verifier = GeometricVerifier(VerifierConfig())
    v = verifier.verify(query_xyz, match_xyz)      # N x 3 each, in their own LiDAR frames
    if v.accepted: use v.match_T_query, v.covariance

``match_T_query`` maps points of the query keyframe's LiDAR frame into the match
keyframe's LiDAR frame (p_match = T @ p_query). ``covariance`` is 6 x 6 over
(x, y, z, roll, pitch, yaw), translation first and expressed in the match (parent)
frame as in geometry_msgs/PoseWithCovariance: ``(Exp(d_rot) R, t + d_t)``.
``lcpr_core.posegraph.to_gtsam_covariance`` turns it into GTSAM's (rotation,
translation) child-frame tangent.

Registration is small_gicp's (GICP on voxel-downsampled clouds, per-point covariances
from 10 neighbours): see docs/verification.md for the comparison with kiss-icp that chose it.
"""
from __future__ import annotations

import math
import time
from collections import OrderedDict
from collections.abc import Hashable, Iterator, Sequence
from concurrent.futures import Executor
from dataclasses import dataclass, field, replace
from typing import Any, Generic, TypeVar

import numpy as np
import small_gicp

from ..errors import VerificationError
from ..geometry import rotation_angle_deg, transform_points
from ..points import finite_xyz
from .clouds import compact_cloud
from .config import VerifierConfig
from .free_space import FreeSpace
from .initial import BevMatcher, Hypothesis, polar_context, yaw_candidates
from .neighbours import Neighbours

ACCEPTED = "accepted"
REJECT_REASONS: tuple[str, ...] = (
    "too few points", "low overlap", "high residual", "large correction", "degenerate", "contradicted", "ambiguous",
    "failed",
)
_ROS_ORDER = [3, 4, 5, 0, 1, 2]  # small_gicp's (rotation, translation) tangent -> (x, y, z, roll, pitch, yaw)
_NEIGHBOURS = 10
_COARSE_STRIDE = 8  # every 8th point estimates the overlap of a coarse result
V = TypeVar("V")
_Search = tuple[np.ndarray, np.ndarray, np.ndarray]  # points in the other cloud's frame, their nearest rows, within
_BEV_QUERY_CACHE = 24  # query BEV spectra kept per prepared cloud (~120 KiB each), then forgotten at once


@dataclass
class PreparedCloud:
    """A compact cloud with what registration needs, built once per keyframe and query."""

    xyz: np.ndarray  # M x 3 float64
    cloud: small_gicp.PointCloud | None  # None: too few points to register
    tree: small_gicp.KdTree | None
    context: np.ndarray  # Scan Context for the yaw guess
    normals: np.ndarray  # M x 3 unit normals (smallest principal axis of each point's neighbourhood)
    coarse: small_gicp.PointCloud | None = None  # about verify.coarse_points points, for the coarse stage
    coarse_tree: small_gicp.KdTree | None = None
    fine: small_gicp.PointCloud | None = None  # about verify.fine_points points (or ``cloud``), for the fine stage
    fine_tree: small_gicp.KdTree | None = None
    # why no pair with this cloud can be verified, found while preparing it ("too few points", "degenerate"); ""
    refusal: str = ""
    _bev: BevMatcher | None = field(default=None, repr=False)
    _free: FreeSpace | None = field(default=None, repr=False)
    _near: Neighbours | None = field(default=None, repr=False)
    # its BEV spectra as a query, by (matcher key, yaw): its candidates' yaw guesses often repeat
    _bev_query: dict[tuple[tuple[float, float, int], float], tuple[np.ndarray, float]] = field(
        default_factory=dict, repr=False)

    def __len__(self) -> int:
        return len(self.xyz)

    def bev(self, config: VerifierConfig) -> BevMatcher:
        if self._bev is None:
            self._bev = BevMatcher(self.bev_xyz(config), cell=config.bev_cell, extent=config.bev_extent,
                                   max_offset=config.bev_extent / 2.0)
        return self._bev

    def neighbours(self) -> Neighbours:
        """The search for its nearest point within a reach (every test's question of this cloud)."""
        if self._near is None:
            self._near = Neighbours(self.xyz)
        return self._near

    def free_space(self) -> FreeSpace:
        """What this cloud says is empty, seen from its origin (the sensor)."""
        if self._free is None:
            self._free = FreeSpace(self.xyz)
        return self._free

    def bev_xyz(self, config: VerifierConfig) -> np.ndarray:
        """The points its bird's-eye views are made of: every k-th, about ``bev_points`` (all when 0)."""
        return self.xyz[::_stride(len(self.xyz), config.bev_points)]

    def locate_in(self, match: BevMatcher, yaw: float, config: VerifierConfig) -> Hypothesis:
        """This cloud, as the query turned by ``yaw``, located in ``match``'s view (its spectrum kept for reuse)."""
        key = (match.key, yaw)
        spectrum = self._bev_query.get(key)
        xyz = self.bev_xyz(config)
        if spectrum is None:
            if len(self._bev_query) >= _BEV_QUERY_CACHE:
                self._bev_query.clear()
            spectrum = self._bev_query[key] = match.query_spectrum(xyz, yaw)
        return match.locate(xyz, yaw, spectrum=spectrum)


class LruCache(Generic[V]):
    """The last ``size`` values by key, the least recently used dropped first."""

    def __init__(self, size: int) -> None:
        self.size = size
        self._items: OrderedDict[Hashable, V] = OrderedDict()

    def __len__(self) -> int:
        return len(self._items)

    def __iter__(self) -> Iterator[Hashable]:
        return iter(self._items)  # keys, least recently used first

    def __contains__(self, key: Hashable) -> bool:  # a look that does not count as a use
        return key in self._items

    def get(self, key: Hashable) -> V | None:
        hit = self._items.get(key)
        if hit is not None:
            self._items.move_to_end(key)
        return hit

    def put(self, key: Hashable, value: V) -> V:
        self._items[key] = value
        self._items.move_to_end(key)
        if len(self._items) > self.size:
            self._items.popitem(last=False)
        return value

    def discard(self, key: Hashable) -> None:
        self._items.pop(key, None)

    def clear(self) -> None:
        self._items.clear()


class PreparedCache(LruCache[PreparedCloud]):
    """The last ``size`` prepared clouds by key: consecutive queries share most candidates, and preparing a cloud
    (voxels, normals, trees) costs as much as registering it."""


@dataclass(frozen=True)
class Verification:
    """The verdict on one pair. ``fitness`` in [0, 1]; ``reason`` is "accepted" or why not."""

    accepted: bool
    reason: str
    match_T_query: np.ndarray  # 4 x 4 float64 (the best registration, also when rejected; identity if none ran)
    fitness: float  # overlap: the mean of both clouds' inlier shares (see _overlap)
    rmse: float = math.inf  # m, of the query's inliers
    covariance: np.ndarray = field(default_factory=lambda: np.full((6, 6), np.nan))
    correction_m: float = math.nan  # how far the fine stage moved from the coarse pose it started from
    correction_deg: float = math.nan
    constraint: float = 0.0  # point-to-plane observability of the inliers, 0 (degenerate) .. 1/3 (_constraint)
    translation_constraint: float = 0.0  # its translation part alone, 0 .. 1/3 (gates the "ambiguous" test)
    # fitness of the best other pose (> ambiguity_distance away) when the ambiguity test ran, else nan
    alternative_fitness: float = math.nan
    # the larger share of either cloud's points lying in the other's free space at the pose, when the test ran
    contradiction: float = math.nan
    initial: np.ndarray = field(default_factory=lambda: np.eye(4))  # the initial guess the result came from
    coarse_fitness: float = 0.0  # overlap estimated at the best coarse pose (the early-reject test)
    seconds: float = 0.0

    @property
    def information(self) -> np.ndarray:
        """6 x 6 inverse of ``covariance`` (same order), for back ends that take information matrices."""
        return np.linalg.inv(self.covariance)


@dataclass(frozen=True)
class _Registered:
    T: np.ndarray
    fitness: float
    rmse: float
    H: np.ndarray
    error: float
    inliers: int
    initial: np.ndarray
    coarse: np.ndarray  # the coarse stage's pose the fine stage started from
    constraint: float  # see _constraint
    translation_constraint: float
    # the evidence's two sampled searches at T ((points, nearest rows, within reach): query in the match, match in
    # the query) when sampled as the free-space test samples them (overlap_points), for it to reuse
    searches: tuple[_Search, _Search] | None = None


class GeometricVerifier:
    """Checks a loop candidate against the LiDAR: registration + acceptance + relative pose."""

    def __init__(self, config: VerifierConfig | None = None) -> None:
        self.config = config if config is not None else VerifierConfig()

    # -- clouds --------------------------------------------------------------------------
    def compact(self, points: np.ndarray) -> np.ndarray:
        """What a keyframe keeps of its cloud (see :func:`compact_cloud`)."""
        return compact_cloud(points, self.config.cloud)

    def prepare(self, compact_xyz: np.ndarray) -> PreparedCloud:
        """Covariances, k-d trees, normals and polar context of a compact cloud (M x 3)."""
        xyz = np.ascontiguousarray(np.asarray(compact_xyz, np.float64).reshape(-1, 3))
        cfg = self.config
        threads = cfg.num_threads
        refusal = _refusal(xyz, cfg)
        if refusal:  # seen before any search: no tree, no normals, no registration
            return PreparedCloud(xyz=xyz, cloud=None, tree=None, context=polar_context(xyz), normals=np.zeros_like(xyz),
                                 refusal=refusal)
        cloud = small_gicp.PointCloud(xyz)
        tree = small_gicp.KdTree(cloud, num_threads=threads)
        resample = len(xyz) > 1.4 * cfg.fine_points
        if resample:  # the full cloud is only searched (the overlap): no covariances, which only GICP reads
            small_gicp.estimate_normals(cloud, tree, num_neighbors=_NEIGHBOURS, num_threads=threads)
        else:
            small_gicp.estimate_normals_covariances(cloud, tree, num_neighbors=_NEIGHBOURS, num_threads=threads)
        normals = np.asarray(cloud.normals())[:, :3]
        fine, fine_tree = cloud, tree
        if resample:
            fine, fine_tree = self._resampled(cloud, cfg.cloud.voxel, cfg.fine_points)
        coarse, coarse_tree = self._resampled(fine, cfg.coarse_voxel, cfg.coarse_points)
        if min(coarse.size(), fine.size()) < _NEIGHBOURS:  # a stage's clouds too small for their covariances
            return PreparedCloud(xyz=xyz, cloud=None, tree=None, context=polar_context(xyz), normals=normals,
                                 refusal="too few points")
        return PreparedCloud(xyz=xyz, cloud=cloud, tree=tree, context=polar_context(xyz), normals=normals,
                             coarse=coarse, coarse_tree=coarse_tree, fine=fine, fine_tree=fine_tree)

    def _resampled(self, cloud: small_gicp.PointCloud, voxel: float, points: int
                   ) -> tuple[small_gicp.PointCloud, small_gicp.KdTree]:
        """The cloud voxelised to about ``points`` points (starting from ``voxel``), with its tree and covariances.

        Surface points scale with 1 / voxel^2, so one rescaled resampling lands close. A fixed
        voxel would leave a narrow-field sensor (a Livox sees ~70 deg) a few hundred points,
        too few for GICP's local covariances, and a 360 deg sensor thousands, which only cost time.
        """
        cfg = self.config
        out = small_gicp.voxelgrid_sampling(cloud, voxel)  # single thread: deterministic
        ratio = out.size() / points
        if not 0.7 <= ratio <= 1.4:
            out = small_gicp.voxelgrid_sampling(cloud, max(voxel * math.sqrt(ratio), cfg.cloud.voxel))
        tree = small_gicp.KdTree(out, num_threads=cfg.num_threads)
        small_gicp.estimate_covariances(out, tree, num_neighbors=_NEIGHBOURS, num_threads=cfg.num_threads)
        return out, tree

    # -- verification ----------------------------------------------------------------------
    def verify(self, query_xyz: np.ndarray, match_xyz: np.ndarray, initial_guess: np.ndarray | None = None
               ) -> Verification:
        """Verify two raw clouds (N x (>=3), each in its own LiDAR frame); see the module docstring."""
        q, m = (self.prepare(self.compact(finite_xyz(p, error=VerificationError, name=name)))
                for p, name in ((query_xyz, "query_xyz"), (match_xyz, "match_xyz")))
        return self.verify_prepared(q, m, initial_guess=initial_guess)

    def verify_prepared(self, query: PreparedCloud, match: PreparedCloud, *,
                        initial_guess: np.ndarray | None = None) -> Verification:
        tic = time.perf_counter()
        cfg = self.config
        refusal = query.refusal or match.refusal  # the cheapest stage: seen while preparing either cloud
        if not refusal and (min(len(query), len(match)) < cfg.min_points or query.tree is None or match.tree is None):
            refusal = "too few points"  # a cloud prepared under other settings
        if refusal:
            return Verification(False, refusal, np.eye(4), 0.0, seconds=time.perf_counter() - tic)
        if initial_guess is not None:
            starts = [_rigid(initial_guess)]
        else:
            starts = self.starts(query, match)
        coarse = []  # (overlap at the coarse pose, T, T0)
        for k, T0 in enumerate(starts):
            if any(np.array_equal(T0, earlier) for earlier in starts[:k]):  # e.g. a zero yaw's start is identity
                continue  # registration is deterministic: the same start gives the same result
            coarse.append(self._coarse(query, match, T0))
            if coarse[-1][0] >= cfg.coarse_accept:  # clearly the place: the other starts cannot do better
                break
        coarse.sort(key=lambda c: -c[0])
        early = coarse[0][0]
        if early < cfg.early_reject * cfg.min_fitness:  # far from acceptable already: skip the fine stage
            return Verification(False, "low overlap", coarse[0][1], early, initial=coarse[0][2],
                                coarse_fitness=early, seconds=time.perf_counter() - tic)
        best = self._fine(query, match, coarse[0][1], coarse[0][2])
        verdict = self._judge(best)
        if verdict.accepted and cfg.max_contradiction < 1.0:
            contradiction = self.contradiction(query, match, best.T, searches=best.searches)
            verdict = replace(verdict, contradiction=contradiction)
            if contradiction > cfg.max_contradiction:
                verdict = replace(verdict, accepted=False, reason="contradicted")
        if verdict.accepted and best.translation_constraint < cfg.ambiguity_constraint:
            other = self._alternative(query, match, coarse, best.T)
            verdict = replace(verdict, alternative_fitness=other)
            if other >= cfg.ambiguity_ratio * best.fitness:
                verdict = replace(verdict, accepted=False, reason="ambiguous")
        return replace(verdict, coarse_fitness=early, seconds=time.perf_counter() - tic)

    def contradiction(self, query: PreparedCloud, match: PreparedCloud, match_T_query: np.ndarray, *,
                      searches: tuple[_Search, _Search] | None = None) -> float:
        """The larger of the two clouds' shares of points that lie in the other's free space at the pose.

        Each share is taken over an evenly spaced sample of about ``overlap_points`` points, among those
        falling in directions the other sensor saw; a point within ``inlier_distance`` of the other's points
        lies on a surface both saw and never counts against the pair (see :mod:`.free_space`). ``searches``:
        those samples' neighbour searches at this pose, already made by the evidence (query side, match side).
        """
        cfg = self.config
        if searches is None:
            T, sample = match_T_query, cfg.overlap_points
            q_in_m = transform_points(query.xyz[::_stride(len(query), sample)], T)
            m_in_q = transform_points(match.xyz[::_stride(len(match), sample)], np.linalg.inv(T))
            searches = (q_in_m, *_near(q_in_m, match, cfg)), (m_in_q, *_near(m_in_q, query, cfg))
        shares = []
        for seen_by, (points, _, near) in zip((match, query), searches, strict=True):
            bad, seen = seen_by.free_space().contradicting(points, excused=near)
            shares.append(bad / seen if seen else 0.0)
        return max(shares)

    def _alternative(self, query: PreparedCloud, match: PreparedCloud,
                     coarse: list[tuple[float, np.ndarray, np.ndarray]], T: np.ndarray) -> float:
        """Fitness of the best pose more than ``ambiguity_distance`` from ``T`` that registration reaches from the
        other starts (0 when none does): a weakly constrained translation may have slid onto a look-alike.

        The starts that the search over starts skipped (and, after an initial guess, the usual starts) are
        registered at the coarse level; the best of the results far from ``T`` is refined like the result was.
        """
        cfg = self.config
        tried = [c[2] for c in coarse]
        for T0 in self.starts(query, match):
            if not any(np.array_equal(T0, earlier) for earlier in tried):
                coarse = [*coarse, self._coarse(query, match, T0)]
                tried.append(T0)
        far = [c for c in coarse if c[0] > 0.0 and _distance(c[1], T) > cfg.ambiguity_distance]
        if not far:
            return 0.0
        found = max(far, key=lambda c: c[0])
        other = self._fine(query, match, found[1], found[2])
        if not np.isfinite(other.T).all() or _distance(other.T, T) <= cfg.ambiguity_distance:
            return 0.0  # it came back to the result
        return other.fitness

    def verify_all(self, query: PreparedCloud, matches: Sequence[PreparedCloud], *,
                   pool: Executor | None = None) -> list[Verification]:
        """:meth:`verify_prepared` of ``query`` against each of ``matches``, in their order; over ``pool``'s
        threads when given (each pair is independent: the same verdicts as one by one)."""
        if pool is None or len(matches) < 2:
            return [self.verify_prepared(query, m) for m in matches]
        return list(pool.map(lambda m: self.verify_prepared(query, m), matches))

    def starts(self, query: PreparedCloud, match: PreparedCloud) -> list[np.ndarray]:
        """Initial guesses: the best BEV hypotheses, the best yaw with no offset, and identity.

        A revisit is usually within a few metres, most often facing the same way; with a
        narrow field of view (a Livox sees ~70 deg) the polar context's yaw and the
        bird's-eye view's x/y peak can both be wrong where no motion at all is close enough.
        """
        found = self.hypotheses(query, match)
        zero = [Hypothesis(h.yaw, 0.0, 0.0, 0.0).matrix() for h in found[:1]]
        return [h.matrix() for h in found] + zero + [np.eye(4)]

    def hypotheses(self, query: PreparedCloud, match: PreparedCloud) -> list[Hypothesis]:
        """The ``registrations`` best initial guesses (yaw from the polar contexts, x/y from the BEV)."""
        cfg = self.config
        bev = match.bev(cfg)
        found = [query.locate_in(bev, yaw, cfg) for yaw in yaw_candidates(query.context, match.context,
                                                                     cfg.yaw_hypotheses)]
        found.sort(key=lambda h: -h.score)
        return found[: cfg.registrations]

    def _coarse(self, query: PreparedCloud, match: PreparedCloud, T0: np.ndarray) -> tuple[float, np.ndarray,
                                                                                           np.ndarray]:
        """(overlap of the full clouds at the result, pose, start) of a registration of the coarse clouds
        from ``T0``."""
        cfg = self.config
        assert query.coarse is not None and match.coarse is not None
        r = small_gicp.align(match.coarse, query.coarse, match.coarse_tree, init_T_target_source=T0,
                             registration_type=cfg.registration, num_threads=cfg.num_threads,
                             max_iterations=cfg.coarse_iterations, max_correspondence_distance=cfg.coarse_distance,
                             translation_epsilon=cfg.coarse_epsilon_m,
                             rotation_epsilon=math.radians(cfg.coarse_epsilon_deg))
        T = np.asarray(r.T_target_source, np.float64)
        if not np.isfinite(T).all():
            return -1.0, T0, T0
        return self._overlap(query, match, T, points=cfg.coarse_overlap_points, least_stride=_COARSE_STRIDE)[0], T, T0

    def _fine(self, query: PreparedCloud, match: PreparedCloud, start: np.ndarray, T0: np.ndarray) -> _Registered:
        cfg = self.config
        assert query.fine is not None and match.fine is not None
        fine = small_gicp.align(match.fine, query.fine, match.fine_tree, init_T_target_source=start,
                                registration_type=cfg.registration, num_threads=cfg.num_threads,
                                max_iterations=cfg.max_iterations, max_correspondence_distance=cfg.fine_distance)
        T = np.asarray(fine.T_target_source, np.float64)
        fitness, rmse, constraint, searches = 0.0, math.inf, (0.0, 0.0), None
        if np.isfinite(T).all():
            fitness, rmse, constraint, searches = self._evidence(query, match, T, cfg.overlap_points)
            sampled = max(_stride(len(query), cfg.overlap_points), _stride(len(match), cfg.overlap_points)) > 1
            if sampled and abs(fitness - cfg.min_fitness) < cfg.overlap_recheck:  # borderline: read every point
                fitness, rmse, constraint, _ = self._evidence(query, match, T, 0)
        return _Registered(T, fitness, rmse, np.asarray(fine.H, np.float64), float(fine.error), int(fine.num_inliers),
                           T0, start, min(constraint), constraint[0], searches)

    def _evidence(self, query: PreparedCloud, match: PreparedCloud, T: np.ndarray, points: int
                  ) -> tuple[float, float, tuple[float, float], tuple[_Search, _Search]]:
        """(overlap, RMSE, (translation, rotation) constraint, the two searches) at ``T`` from samples of about
        ``points`` points (0: every point)."""
        cfg = self.config
        q_in_m = transform_points(query.xyz[::_stride(len(query), points)], T)
        query_side = (q_in_m, *_near(q_in_m, match, cfg))  # one search: the overlap and the constraint share it
        fitness, rmse, match_side = self._overlap(query, match, T, points=points, query_side=query_side)
        _, idx, near = query_side
        return fitness, rmse, _constraint(q_in_m[near], match.normals[idx[near]]), (query_side, match_side)

    def _overlap(self, query: PreparedCloud, match: PreparedCloud, T: np.ndarray, *, points: int = 0,
                 least_stride: int = 1, query_side: _Search | None = None) -> tuple[float, float, _Search]:
        """(overlap, RMSE, the match side's search) after alignment; overlap = the mean of both directions'
        inlier shares.

        A point is an inlier when its nearest neighbour in the other cloud is within
        ``inlier_distance`` and it lies within ``plane_distance`` of that neighbour's local
        plane: independent of how densely either sensor sampled the surface. RMSE is
        the point-to-plane RMSE of the query's inliers. Each cloud's share is estimated from
        an evenly spaced sample of its points (every k-th: at most about ``points``, 0 for all,
        and k at least ``least_stride``) searched in the other's full cloud: the sample may be
        sparse, the surfaces it is tested against may not. ``query_side`` passes the query's
        sampled points in the match frame and their neighbour search when the caller has them.
        """
        cfg = self.config
        if query_side is None:
            q_in_m = transform_points(query.xyz[::_stride(len(query), points, least_stride)], T)
            query_side = (q_in_m, *_near(q_in_m, match, cfg))
        m_in_q = transform_points(match.xyz[::_stride(len(match), points, least_stride)], np.linalg.inv(T))
        match_side = (m_in_q, *_near(m_in_q, query, cfg))
        share_q, d_q = _inliers(*query_side, match, cfg)
        share_m, _ = _inliers(*match_side, query, cfg)
        rmse = float(np.sqrt(np.mean(d_q ** 2))) if len(d_q) else math.inf
        return 0.5 * (share_q + share_m), rmse, match_side

    def _judge(self, best: _Registered) -> Verification:
        cfg = self.config
        delta = np.linalg.inv(best.coarse) @ best.T  # the registration's own consistency, not a guess's accuracy
        correction_m = float(np.linalg.norm(delta[:3, 3]))
        correction_deg = float(rotation_angle_deg(delta[:3, :3]))
        constraint = best.constraint
        covariance = self._covariance(best)
        common: dict[str, Any] = dict(
            match_T_query=best.T, fitness=best.fitness, rmse=best.rmse, covariance=covariance,
            correction_m=correction_m, correction_deg=correction_deg, constraint=constraint,
            translation_constraint=best.translation_constraint, initial=best.initial)
        reason = ACCEPTED
        if not np.isfinite(best.T).all():
            reason = "failed"
        elif best.fitness < cfg.min_fitness:
            reason = "low overlap"
        elif best.rmse > cfg.max_rmse:
            reason = "high residual"
        elif correction_m > cfg.max_correction_m or correction_deg > cfg.max_correction_deg:
            reason = "large correction"
        elif constraint < cfg.min_constraint or not np.isfinite(covariance).all():
            reason = "degenerate"
        return Verification(reason == ACCEPTED, reason, **common)

    def _covariance(self, r: _Registered) -> np.ndarray:
        """inv(H) scaled by the residual variance factor and the inflation, floored; (x, y, z, roll, pitch, yaw)."""
        cfg = self.config
        try:
            cov = np.linalg.inv(r.H)
        except np.linalg.LinAlgError:
            return np.full((6, 6), np.nan)
        factor = 2.0 * r.error / max(3 * r.inliers - 6, 1)
        cov = cov * factor * cfg.covariance_inflation
        cov = cov[np.ix_(_ROS_ORDER, _ROS_ORDER)]  # small_gicp perturbs on the right (query frame) ...
        J = np.kron(np.eye(2), r.T[:3, :3])  # ... rotate both blocks into the match frame
        cov = J @ cov @ J.T
        floor = np.array([cfg.min_sigma_m] * 3 + [math.radians(cfg.min_sigma_deg)] * 3) ** 2
        sigma2 = np.diag(cov).copy()
        bump = np.maximum(floor - sigma2, 0.0)
        return cov + np.diag(bump)


def _refusal(xyz: np.ndarray, cfg: VerifierConfig) -> str:
    """Why no registration of this cloud (M x 3) can be accepted, seen before any search; "" when none.

    Fewer than ``min_points`` points: "too few points". All of them within a slab a quarter of
    ``plane_distance`` thick (the smallest principal spread of a plane, a line or a point): "degenerate",
    as the point-to-plane constraint would find after registering it; no scan of a place is that flat.
    """
    if len(xyz) < max(cfg.min_points, _NEIGHBOURS):
        return "too few points"
    centred = xyz - xyz.mean(axis=0)
    spread = float(np.sqrt(max(np.linalg.eigvalsh(centred.T @ centred / len(xyz))[0], 0.0)))
    return "degenerate" if spread < cfg.plane_distance / 4.0 else ""


def _distance(a: np.ndarray, b: np.ndarray) -> float:
    """m between the translations of two 4 x 4 poses."""
    return float(np.linalg.norm(a[:3, 3] - b[:3, 3]))


def _stride(count: int, points: int, least: int = 1) -> int:
    """Every k-th of ``count`` points leaves at most about ``points`` (0: all), k >= ``least``."""
    return max(least, -(-count // points) if points > 0 else 1)


def _near(points: np.ndarray, target: PreparedCloud, cfg: VerifierConfig) -> tuple[np.ndarray, np.ndarray]:
    """(nearest target row of each point, whether it lies within ``inlier_distance``)."""
    return target.neighbours().nearest(points, reach=cfg.inlier_distance, threads=cfg.num_threads)


def inlier_share(points: np.ndarray, target: PreparedCloud, config: VerifierConfig) -> float:
    """The share of ``points`` (N x 3, in ``target``'s frame) that are inliers of ``target``: a nearest neighbour
    within ``inlier_distance`` and its local plane within ``plane_distance``."""
    return _inliers(points, *_near(points, target, config), target, config)[0]


def _inliers(points: np.ndarray, idx: np.ndarray, near: np.ndarray, target: PreparedCloud, cfg: VerifierConfig
             ) -> tuple[float, np.ndarray]:
    """(share of ``points`` that are inliers of ``target``, their point-to-plane distances)."""
    plane = np.abs(np.einsum("ij,ij->i", points[near] - target.xyz[idx[near]], target.normals[idx[near]]))
    good = plane <= cfg.plane_distance
    return float(good.sum()) / max(len(points), 1), plane[good]


def _constraint(points: np.ndarray, normals: np.ndarray) -> tuple[float, float]:
    """How well aligned points and their neighbours' normals pin down the translation and the rotation,
    (translation, rotation), each 0 .. 1/3.

    Point-to-plane analysis: with n the neighbour's normal and p the point (centred on
    the points' centroid, scaled by their RMS radius), the smallest eigenvalue of
    mean(n n^T) (translation) and of mean((p x n)(p x n)^T) (rotation). A plane leaves a
    translation free, a sphere shell or a cylinder a rotation: both give ~0.
    """
    if len(points) < 6:
        return 0.0, 0.0
    p = points - points.mean(axis=0)
    p /= max(float(np.sqrt((p ** 2).sum(axis=1).mean())), 1e-9)
    pn = np.cross(p, normals)
    return (float(np.linalg.eigvalsh(normals.T @ normals / len(normals)).min()),
            float(np.linalg.eigvalsh(pn.T @ pn / len(normals)).min()))


def _rigid(guess: object) -> np.ndarray:
    """A 4 x 4 rigid transform, or VerificationError naming what is wrong with it."""
    try:
        T = np.asarray(guess, np.float64)
    except (TypeError, ValueError) as err:
        raise VerificationError(f"initial_guess {guess!r} is not a 4 x 4 array of numbers") from err
    if T.shape != (4, 4) or not np.isfinite(T).all():
        raise VerificationError(f"initial_guess of shape {T.shape} is not a finite 4 x 4 transform")
    R = T[:3, :3]
    if (not np.allclose(R.T @ R, np.eye(3), atol=1e-4) or np.linalg.det(R) <= 0
            or not np.allclose(T[3], (0.0, 0.0, 0.0, 1.0))):
        raise VerificationError("initial_guess is not a rigid transform (rotation block not orthonormal with "
                                "determinant +1, or last row not 0 0 0 1)")
    return T
