"""Geometric verification of VSeq2PC candidates: the query sequence's pseudo-cloud against the scan's cloud.

Retrieval says which scan a camera sequence shows; verification checks it with geometry. The
query's pseudo-cloud (:mod:`lcpr_core.vseq2pc.pseudo_cloud`: depth back-projected over the
sequence, stacked with odometry in the query frame's vehicle frame) is registered against each
candidate scan's compact cloud (kept by the map) with the project's
:class:`~lcpr_core.verification.GeometricVerifier` (its initial alignment and small_gicp's coarse and
fine stages), under thresholds for a depth network's error (:data:`DEPTH_VERIFIER`). Per candidate:
``verified``, ``fitness``, ``match_T_query`` (the query *camera*'s pose in the scan's LiDAR frame) and
its 6 x 6 covariance (x, y, z, roll, pitch, yaw, in the scan frame), or the reason it was refused.
:meth:`SequenceVerifier.confirm` then keeps a verified candidate only when earlier queries confirm its camera pose
(``consistency``, :mod:`lcpr_core.vseq2pc.consistency`).
"""
from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Hashable
from dataclasses import dataclass, field

import numpy as np

from ..errors import InvalidValueError, LcprError
from ..geometry import rotation_angle_deg, skew, transform_points, wrap_angle
from ..verification import (
    ACCEPTED,
    CloudConfig,
    GeometricVerifier,
    PreparedCache,
    PreparedCloud,
    Verification,
    VerifierConfig,
)
from ..verification.clouds import compact_cloud
from ..verification.verifier import inlier_share
from .consistency import ConsistencyConfig, ConsistencyGate
from .pseudo_cloud import PseudoCloudConfig
from .retrieval import SCAN_CLOUD, ScanMatch

__all__ = ["DEPTH_VERIFIER", "NOT_VERIFIED", "NO_CLOUD", "NO_CONSENSUS", "SequenceVerifier", "SequenceVerifyConfig",
           "ConsistencyConfig", "camera_pose", "consensus", "rerank", "scan_cloud",
           "support_counts"]

NO_CLOUD = "no cloud"  # the scan has no stored cloud (a map saved before clouds were kept)
NOT_VERIFIED = "not verified"  # beyond verify.top_k: not registered
PREPARED_CACHE = 256  # prepared scan clouds kept (normals, trees): candidates repeat from query to query


#: The verifier's settings for a pseudo-cloud from depth: wider inlier and plane tolerances than
#: LiDAR against LiDAR (a 10 % depth error moves a facade 1 m at 10 m), a lower two-sided overlap (the
#: camera sees 90 degrees of the scan's 360); the query cloud capped at 2500 points and the fine stage
#: at about 1024 (6 iterations): as accurate on the validation drive (citysim seed 43) and a third faster.
DEPTH_VERIFIER = VerifierConfig(
    cloud=CloudConfig(voxel=0.4, max_points=2500, min_range=1.0, max_range=50.0),
    inlier_distance=1.0, plane_distance=0.25, min_fitness=0.15, max_rmse=0.35, max_correction_m=1.5,
    max_correction_deg=6.0, early_reject=1.0, coarse_accept=0.35, min_points=150, fine_points=1024,
    max_iterations=6,
    ambiguity_constraint=0.0,  # the LiDAR pairs' ambiguity check is not measured on depth pseudo-clouds: off
    max_contradiction=1.0,  # nor is the free-space test (a camera's depth is no LiDAR's free space): off
)
NO_CONSENSUS = "no consensus"  # fewer than verify.min_support registered candidates put the camera in one place
YAW_DISAGREES = "yaw disagrees"  # the registered yaw is more than verify.max_yaw_deg from the matched slice's
LOW_QUERY_OVERLAP = "low overlap"


@dataclass(frozen=True)
class SequenceVerifyConfig:
    """enabled: verify candidates (a loop must then be a verified one). top_k: the best this-many
    candidates of each query are registered (the rest stay "not verified"). keep_clouds: the map keeps
    each scan's compact cloud (``scan_cloud``) even when verification is off."""

    enabled: bool = True
    top_k: int = 10
    # min_fitness, min_support and consistency: vseq2pc_eval --verify on the validation drive (citysim seed 43, exact
    # depth: the most recall that keeps precision 1.0 with a margin; with a depth network's 5-10 % error no setting
    # publishes a right loop there, see docs/vseq2pc_verification.md)
    min_fitness: float = 0.3  # share of the pseudo-cloud on the scan's surfaces after registration (0..1)
    max_yaw_deg: float = 45.0  # registered yaw vs the retrieval's best slice (45 deg apart)
    # consensus: a verified candidate needs this many accepted registrations (itself included) that put the query
    # camera within consensus_m / consensus_deg of the same map pose (map poses of the scans); 1 = off
    min_support: int = 2
    consensus_m: float = 1.0
    consensus_deg: float = 3.0
    # temporal consistency: a verified candidate is published only when the chain of earlier queries confirms the
    # camera's map pose (lcpr_core.vseq2pc.consistency); count 1 = off
    consistency: ConsistencyConfig = field(default_factory=ConsistencyConfig)
    pseudo: PseudoCloudConfig = field(default_factory=PseudoCloudConfig)
    verifier: VerifierConfig = DEPTH_VERIFIER
    scan_cloud: CloudConfig = SCAN_CLOUD
    keep_clouds: bool = True

    def __post_init__(self) -> None:
        if isinstance(self.top_k, bool) or not isinstance(self.top_k, int) or self.top_k < 1:
            raise InvalidValueError(f"verify.top_k={self.top_k!r}; it must be a positive integer")
        if not 0.0 <= self.min_fitness <= 1.0:
            raise InvalidValueError(f"verify.min_fitness={self.min_fitness!r}; accepted: 0 <= min_fitness <= 1")
        if isinstance(self.min_support, bool) or not isinstance(self.min_support, int) or self.min_support < 1:
            raise InvalidValueError(f"verify.min_support={self.min_support!r}; it must be a positive integer")
        if not (self.consensus_m > 0 and self.consensus_deg > 0):
            raise InvalidValueError(f"verify.consensus_m={self.consensus_m!r}, verify.consensus_deg="
                                    f"{self.consensus_deg!r}; both must be > 0")
        if not 0.0 < self.max_yaw_deg <= 180.0:
            raise InvalidValueError(f"verify.max_yaw_deg={self.max_yaw_deg!r}; accepted: 0 < max_yaw_deg <= 180")


def scan_cloud(points: np.ndarray, config: SequenceVerifyConfig | None = None) -> np.ndarray:
    """What the map keeps of one scan's cloud (N x >=3, LiDAR frame): M x 3 float32 on the centimetre grid."""
    cfg = config if config is not None else SequenceVerifyConfig()
    return compact_cloud(points, cfg.scan_cloud)


def camera_pose(match_T_base: np.ndarray, covariance: np.ndarray, lidar_T_cam: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray]:
    """(match_T_cam, its covariance) from the registration's match_T_base and covariance.

    The covariance is over (x, y, z, roll, pitch, yaw) in the match (parent) frame; a fixed
    right factor moves the origin by R t_cam, so a rotation error d_theta adds d_theta x (R t_cam)
    to the translation: J = [[I, -[R t]x], [0, I]].
    """
    T = np.asarray(match_T_base, np.float64) @ np.asarray(lidar_T_cam, np.float64)
    lever = np.asarray(match_T_base, np.float64)[:3, :3] @ np.asarray(lidar_T_cam, np.float64)[:3, 3]
    J = np.eye(6)
    J[:3, 3:] = -skew(lever)
    cov = np.asarray(covariance, np.float64)
    return T, J @ cov @ J.T


def rerank(candidates: list[ScanMatch]) -> list[ScanMatch]:
    """Verified candidates first, best fitness first; then the rest in retrieval order (``rank`` stays the
    retrieval rank)."""
    verified = sorted((c for c in candidates if c.verified), key=lambda c: (-c.fitness, c.rank))
    return verified + [c for c in candidates if not c.verified]


class SequenceVerifier:
    """Registers query pseudo-clouds against scan clouds; keeps the prepared scans of recent candidates.

    Not thread-safe (the detector's worker owns it).
    """

    def __init__(self, config: SequenceVerifyConfig | None = None) -> None:
        self.config = config if config is not None else SequenceVerifyConfig()
        self.verifier = GeometricVerifier(self.config.verifier)
        self._prepared = PreparedCache(PREPARED_CACHE)
        self._gate: ConsistencyGate | None = None

    def prepare_query(self, points: np.ndarray) -> PreparedCloud:
        """The accumulated pseudo-cloud (N x 3, query vehicle frame), compacted and prepared once per query."""
        return self.verifier.prepare(self.verifier.compact(points))

    def _scan(self, scan_id: int, cloud: np.ndarray) -> PreparedCloud:
        hit = self._prepared.get(scan_id)
        return hit if hit is not None else self._prepared.put(scan_id, self.verifier.prepare(cloud))

    def verify_all(self, query: PreparedCloud, candidates: list[ScanMatch], clouds: Callable[[ScanMatch],
                   np.ndarray | None], *, lidar_T_cam: np.ndarray, errors: list[str] | None = None) -> list[ScanMatch]:
        """The best ``top_k`` candidates registered (the rest "not verified"), checked for consensus, re-ranked:
        verified first (best fitness first), then by retrieval rank."""
        top = self.config.top_k
        out = [self.verify(query, c, clouds(c), lidar_T_cam=lidar_T_cam, errors=errors) if i < top
               else dataclasses.replace(c, verification=NOT_VERIFIED) for i, c in enumerate(candidates)]
        return rerank(consensus(out, self.config))

    def forget(self) -> None:
        """Drop the prepared scans (the map or the settings changed)."""
        self._prepared.clear()

    def confirm(self, odom_T_base: np.ndarray | None, candidates: list[ScanMatch], *, lidar_T_cam: np.ndarray
                ) -> list[ScanMatch]:
        """The query's verified candidates that the earlier queries confirm (``verify.consistency``), re-ranked;
        the others turn "inconsistent". Call it for every query in stream order, those without candidates too."""
        return self.confirm_all(odom_T_base, candidates, lidar_T_cam=lidar_T_cam)[0]

    def confirm_all(self, odom_T_base: np.ndarray | None, candidates: list[ScanMatch], *, lidar_T_cam: np.ndarray,
                    key: Hashable = None) -> tuple[list[ScanMatch], list[tuple[Hashable, list[ScanMatch]]]]:
        """:meth:`confirm`, and the earlier queries (by their ``key``) whose loop this query's loop confirms late
        (``verify.consistency_backfill``), their candidates re-ranked with the confirmed one verified."""
        L = np.asarray(lidar_T_cam, np.float64).reshape(4, 4)
        if self._gate is None or not np.array_equal(self._gate.lidar_T_cam, L):
            self._gate = ConsistencyGate(self.config.consistency, lidar_T_cam=L)
        admitted, late = self._gate.admit_all(odom_T_base, candidates, key=key)
        return rerank(admitted), [(k, rerank(c)) for k, c in late]

    def restart(self) -> None:
        """A new session: odometry does not chain across it, the consistency history is dropped."""
        if self._gate is not None:
            self._gate.reset()

    def verify(self, query: PreparedCloud, candidate: ScanMatch, cloud: np.ndarray | None, *,
               lidar_T_cam: np.ndarray, errors: list[str] | None = None) -> ScanMatch:
        """The candidate with its verdict. A registration that raises counts as "failed" (its cause is
        appended to ``errors``)."""
        if cloud is None:
            return dataclasses.replace(candidate, verification=NO_CLOUD)
        cfg = self.config
        try:
            match = self._scan(candidate.id, cloud)
            yaw = math.radians(candidate.relative_yaw_deg)  # the camera looked along this direction of the scan
            vcfg = self.verifier.config  # the query's BEV spectrum for this yaw is kept for its other candidates
            guess = query.locate_in(match.bev(vcfg), yaw, vcfg).matrix() if match.tree is not None else np.eye(4)
            v = self.verifier.verify_prepared(query, match, initial_guess=guess)
            if v.reason in (ACCEPTED, "low overlap") and match.tree is not None:
                share = query_overlap(query, match, v.match_T_query, self.verifier.config)
                turn = abs(math.degrees(wrap_angle(math.atan2(v.match_T_query[1, 0], v.match_T_query[0, 0]) - yaw)))
                reason = v.reason
                if v.accepted and share < cfg.min_fitness:
                    reason = LOW_QUERY_OVERLAP
                elif v.accepted and turn > cfg.max_yaw_deg:
                    reason = YAW_DISAGREES
                v = dataclasses.replace(v, fitness=share, accepted=reason == ACCEPTED, reason=reason)
        except (LcprError, ValueError, RuntimeError, np.linalg.LinAlgError) as err:
            if errors is not None:
                errors.append(f"verification against scan {candidate.id}: {type(err).__name__}: {err}")
            v = Verification(False, "failed", np.eye(4), 0.0)
        return with_verdict(candidate, v, lidar_T_cam)


def support_counts(candidates: list[ScanMatch], config: SequenceVerifyConfig) -> list[int]:
    """Per candidate: how many verified candidates (itself included) put the query camera within consensus_m /
    consensus_deg of its map pose (world_T_scan @ match_T_query); 0 for an unverified one, 1 without a map pose."""
    placed = {}
    for i, c in enumerate(candidates):
        if c.verified and c.pose is not None and c.match_T_query is not None:
            placed[i] = np.asarray(c.pose, np.float64) @ c.match_T_query
    out = []
    for i, c in enumerate(candidates):
        if not c.verified:
            out.append(0)
            continue
        support = 1
        if i in placed:
            inv = np.linalg.inv(placed[i])
            for j, T in placed.items():
                if j != i:
                    d = inv @ T
                    support += int(np.linalg.norm(d[:3, 3]) <= config.consensus_m
                                   and rotation_angle_deg(d[:3, :3]) <= config.consensus_deg)
        out.append(support)
    return out


def consensus(candidates: list[ScanMatch], config: SequenceVerifyConfig) -> list[ScanMatch]:
    """Accepted candidates keep ``verified`` only when at least ``min_support`` accepted ones (themselves included)
    put the query camera at one map pose (:func:`support_counts`): neighbouring scans of a true place agree, a
    look-alike street elsewhere seldom finds as many witnesses."""
    if config.min_support <= 1:
        return candidates
    return [c if not c.verified or n >= config.min_support else
            dataclasses.replace(c, verified=False, verification=NO_CONSENSUS)
            for c, n in zip(candidates, support_counts(candidates, config), strict=True)]


def query_overlap(query: PreparedCloud, match: PreparedCloud, match_T_query: np.ndarray, config: VerifierConfig
                  ) -> float:
    """The share of the query's points within ``inlier_distance`` of a scan point and ``plane_distance`` of its
    local plane at ``match_T_query``: how much of what the camera saw the scan explains (the scan's own share
    is small by nature: the camera sees 90 of its 360 degrees)."""
    if match.tree is None or len(query) == 0 or not np.isfinite(match_T_query).all():
        return 0.0
    pts = transform_points(query.xyz, np.asarray(match_T_query, np.float64))  # N x 3 in the scan frame
    return inlier_share(pts, match, config)


def with_verdict(candidate: ScanMatch, v: Verification, lidar_T_cam: np.ndarray) -> ScanMatch:
    """A candidate carrying a registration's verdict, its pose and covariance moved to the camera."""
    registered = np.isfinite(v.match_T_query).all() and v.reason not in ("too few points", "failed")
    pose, cov = None, None
    if registered:
        pose, cov = camera_pose(v.match_T_query, v.covariance, lidar_T_cam)
        if not np.isfinite(cov).all():
            cov = None
    fitness = float(v.fitness) if math.isfinite(v.fitness) else 0.0
    return dataclasses.replace(candidate, verified=bool(v.accepted), fitness=fitness, match_T_query=pose,
                               covariance=cov, verification=v.reason)
