"""What a SLAM back end gains from verified loop closures: a pose graph before and after.

Pure numpy and matplotlib, with GTSAM (an optional extra: ``pip install gtsam``)
imported only by :func:`optimize_pose_graph`.

Poses are 4 x 4 homogeneous matrices, ``world_T_body`` for a trajectory and
``a_T_b`` (frame ``b`` expressed in frame ``a``) for a relative pose.

Drift. :func:`drift_odometry` turns a ground-truth trajectory into the chain an
odometry would report: every true step ``rel_i = inv(truth[i]) @ truth[i+1]`` is
perturbed by independent zero-mean Gaussian noise and the noisy steps are composed
from ``truth[0]`` on (see :class:`DriftModel` for the noise and why it gives the
1-2 % of distance a LiDAR or wheel odometry drifts by).

Covariance order. Every 6 x 6 covariance here (odometry steps and loop constraints)
uses the ROS ``geometry_msgs/PoseWithCovariance`` order and meaning: ``(x, y, z,
roll, pitch, yaw)``, translation first, position errors and small rotation errors
(about the fixed axes) both expressed in the *parent* frame of the relative pose
``a_T_b`` (frame ``a``): the perturbed pose is ``(Exp(dtheta) @ R, t + dt)``.
GTSAM's ``Pose3`` tangent is ``(rot, trans)`` and perturbs on the right, in the
child frame: ``(R @ Exp(w), t + R @ v)``. To first order ``w = R^T dtheta`` and
``v = R^T dt``, so :func:`to_gtsam_covariance` swaps the blocks and rotates them:
``C_gtsam = J P C_ros P^T J^T`` with ``P`` the (trans, rot) -> (rot, trans)
permutation and ``J = diag(R^T, R^T)``. For a near-identity relative pose
(consecutive keyframes) this is just the block swap.

Accuracy. :func:`ate_rmse` is the RMSE of position differences. The report uses it
without alignment (``align=False``): every trajectory here starts at ``truth[0]``
and is anchored there, so an alignment would only hide drift. ``align=True`` first
applies the rigid (rotation + translation, no scale) Umeyama/Kabsch fit of the
estimate to the truth.
"""
from __future__ import annotations

import math
import numbers
import os
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from .atomic import save_figure
from .errors import PoseGraphError
from .geometry import (
    conjugate,
    heading_deg,
    nearest_rotation,
    relative,
    rotation_angle_deg,
    so3_exp,
    umeyama_rigid,
)

__all__ = [
    "DriftModel", "LoopConstraint", "drift_step", "PoseGraphConfig", "PoseGraphResult", "ROBUST_KERNELS",
    "ate_rmse", "check_covariances", "check_poses", "drift_odometry", "lidar_to_body", "optimize_pose_graph",
    "plot_trajectories",
    "relative_pose_error", "rotation_angle_deg", "rotation_error_deg", "to_gtsam_covariance", "yaw_deg",
]

#: Accepted values of :attr:`PoseGraphConfig.robust`.
ROBUST_KERNELS = ("none", "huber", "cauchy")

_MIN_STEP_M = 0.01  # noise of shorter (standing-still) steps is that of a 1 cm step: keeps covariances invertible
_ROTATION_TOL = 1e-4  # |R^T R - I| and |det R - 1| accepted in input poses


def _is_int(value: object) -> bool:
    return isinstance(value, numbers.Integral) and not isinstance(value, bool)


def _is_real(value: object) -> bool:
    return isinstance(value, numbers.Real) and not isinstance(value, bool)


# ============================================================================ drift
@dataclass(frozen=True)
class DriftModel:
    """Independent Gaussian noise on each odometry step of length ``d`` metres.

    Per step, standard deviations (translation in the step's start body frame):

    * x, y (forward, left): ``translation_frac * d`` m; z: ``z_frac * d`` m, so each
      step is off by ~1.5 % of its length, what an odometry's own covariance claims;
    * yaw: ``yaw_deg_per_m * sqrt(d)`` deg; roll, pitch: ``roll_pitch_deg_per_m * sqrt(d)``
      deg: the heading is a random walk whose std dev after L metres is
      ``yaw_deg_per_m * sqrt(L)`` (the unit is really deg per sqrt(metre); with 1 m
      steps it is the per-step std dev).

    The heading random walk dominates the drift: a heading off by ``theta`` moves every
    later position sideways by ``theta`` per metre, so on a straight road the position
    error grows faster than the distance (~``L^1.5``); translation noise alone would only
    give ``translation_frac * sqrt(L)`` metres. With the defaults a straight drive (1 m
    steps) ends on average about 0.7-1 % of its length off after 100 m, 1-1.3 % after
    200-300 m, ~2 % after 500 m and ~2.5 % after 1 km: the 1-2 % of distance LiDAR or
    wheel-inertial odometry drifts by over the few hundred metres between revisits. On a
    compact loop the error grows more slowly (a heading error swings the rest of the path
    about the point where it arose, by at most the loop's size). Steps shorter than 1 cm
    get the noise of a 1 cm step, so that standing still keeps an invertible covariance.
    """

    translation_frac: float = 0.015
    z_frac: float = 0.005
    yaw_deg_per_m: float = 0.1
    roll_pitch_deg_per_m: float = 0.01
    seed: int = 0

    def __post_init__(self) -> None:
        for name in ("translation_frac", "z_frac", "yaw_deg_per_m", "roll_pitch_deg_per_m"):
            value = getattr(self, name)
            if not _is_real(value) or not (math.isfinite(value) and value > 0):
                raise PoseGraphError(
                    f"DriftModel {name}={value!r}; expected a finite number > 0 (zero noise gives singular covariances)"
                )
        if not _is_int(self.seed) or self.seed < 0:
            raise PoseGraphError(f"DriftModel seed={self.seed!r}; expected an integer >= 0")

    def step_sigmas(self, length: float) -> np.ndarray:
        """(6,) std devs of one step of ``length`` metres: x, y, z (m), roll, pitch, yaw (rad)."""
        d = max(float(length), _MIN_STEP_M)
        rp = math.radians(self.roll_pitch_deg_per_m) * math.sqrt(d)
        return np.array([
            self.translation_frac * d, self.translation_frac * d, self.z_frac * d,
            rp, rp, math.radians(self.yaw_deg_per_m) * math.sqrt(d),
        ])


def drift_odometry(truth: np.ndarray, *, model: DriftModel = DriftModel()) -> tuple[np.ndarray, np.ndarray]:
    """A drifted odometry chain of ``truth`` (N, 4, 4) world_T_body and its step covariances.

    Returns ``(drifted, step_covariances)``: drifted (N, 4, 4) starts at ``truth[0]`` and
    composes the noisy steps ``(Exp(dtheta) @ R_i, t_i + dt)`` of the true steps
    ``rel_i = inv(truth[i]) @ truth[i + 1]``; step_covariances (N - 1, 6, 6) are the
    diagonal covariances the noise was drawn from, in the (x, y, z, roll, pitch, yaw)
    order of the module docstring. The same ``model.seed`` gives the same chain.
    """
    poses = check_poses(truth, "truth")
    if not isinstance(model, DriftModel):
        raise PoseGraphError(f"model={model!r}; expected a DriftModel")
    n = len(poses)
    rng = np.random.default_rng(model.seed)
    drifted = np.empty_like(poses)  # (N, 4, 4)
    drifted[0] = poses[0]
    covs = np.zeros((max(n - 1, 0), 6, 6))  # (N-1, 6, 6)
    for i in range(n - 1):
        noisy, sigmas = drift_step(relative(poses[i], poses[i + 1]), model=model, rng=rng)
        drifted[i + 1] = drifted[i] @ noisy
        covs[i] = np.diag(sigmas**2)
    return drifted, covs


def drift_step(rel: np.ndarray, *, model: DriftModel, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """One true step ``rel`` (4, 4) as the odometry reports it, ``(Exp(dtheta) @ R, t + dt)``, and the (6,) std
    devs its noise was drawn with (:func:`drift_odometry`, one step at a time: a stream drifts the same way)."""
    sigmas = model.step_sigmas(float(np.linalg.norm(rel[:3, 3])))
    noise = rng.standard_normal(6) * sigmas  # (x, y, z, roll, pitch, yaw)
    noisy = rel.copy()
    noisy[:3, :3] = so3_exp(noise[3:]) @ rel[:3, :3]
    noisy[:3, 3] += noise[:3]
    return noisy, sigmas


# ============================================================================ pose graph
@dataclass(frozen=True)
class LoopConstraint:
    """A verified loop closure: the relative pose of keyframe ``query`` seen from ``match``."""

    query: int  # trajectory index of the later keyframe
    match: int  # trajectory index of the earlier keyframe
    match_T_query: np.ndarray  # (4, 4): query body frame expressed in the match body frame
    covariance: np.ndarray  # (6, 6), (x, y, z, roll, pitch, yaw) in the match frame; see the module docstring

    def __post_init__(self) -> None:
        for name in ("query", "match"):
            value = getattr(self, name)
            if not _is_int(value) or value < 0:
                raise PoseGraphError(f"LoopConstraint {name}={value!r}; expected a trajectory index >= 0")
        if self.query == self.match:
            raise PoseGraphError(f"LoopConstraint query = match = {self.query}; expected two different keyframes")
        object.__setattr__(self, "query", int(self.query))
        object.__setattr__(self, "match", int(self.match))
        pose = check_poses(self.match_T_query, "LoopConstraint match_T_query", single=True)
        cov = check_covariances(self.covariance, "LoopConstraint covariance", single=True)
        pose.flags.writeable = False
        cov.flags.writeable = False
        object.__setattr__(self, "match_T_query", pose)
        object.__setattr__(self, "covariance", cov)


@dataclass(frozen=True)
class PoseGraphConfig:
    """How :func:`optimize_pose_graph` weighs loops and anchors the graph."""

    robust: str = "cauchy"  # m-estimator on loop factors: "none", "huber" or "cauchy"
    robust_param: float = 1.0  # the kernel's k, in units of the loop's whitened (Mahalanobis) residual
    prior_sigma: float = 1e-3  # std dev (m and rad) of the prior holding node 0 at odometry[0]
    max_iterations: int = 100  # Levenberg-Marquardt iterations at most

    def __post_init__(self) -> None:
        if self.robust not in ROBUST_KERNELS:
            raise PoseGraphError(f"PoseGraphConfig robust={self.robust!r}; expected one of {', '.join(ROBUST_KERNELS)}")
        for name in ("robust_param", "prior_sigma"):
            value = getattr(self, name)
            if not _is_real(value) or not (math.isfinite(value) and value > 0):
                raise PoseGraphError(f"PoseGraphConfig {name}={value!r}; expected a finite number > 0")
        if not _is_int(self.max_iterations) or self.max_iterations < 1:
            raise PoseGraphError(f"PoseGraphConfig max_iterations={self.max_iterations!r}; expected an integer >= 1")


@dataclass(frozen=True)
class PoseGraphResult:
    optimized: np.ndarray  # (N, 4, 4) world_T_body
    iterations: int  # Levenberg-Marquardt iterations run
    initial_error: float  # graph error (0.5 * sum of squared whitened residuals, robustified) at the odometry
    final_error: float  # the same at the optimum


def optimize_pose_graph(
    odometry: np.ndarray,
    step_covariances: np.ndarray,
    loops: Sequence[LoopConstraint],
    *,
    config: PoseGraphConfig = PoseGraphConfig(),
) -> PoseGraphResult:
    """Optimise the odometry chain (N, 4, 4) with loop constraints in GTSAM.

    The graph: a ``PriorFactorPose3`` holding node 0 at ``odometry[0]`` (isotropic
    ``config.prior_sigma``), a ``BetweenFactorPose3`` per odometry step with
    ``step_covariances`` (N - 1, 6, 6), and one per loop (``match`` -> ``query``,
    measured ``match_T_query``), its Gaussian noise wrapped in ``noiseModel.Robust``
    with the chosen m-estimator. Covariances are converted with
    :func:`to_gtsam_covariance`. Levenberg-Marquardt starts from the odometry.
    """
    poses = check_poses(odometry, "odometry")
    n = len(poses)
    covs = check_covariances(step_covariances, "step_covariances")
    if covs.shape[0] != n - 1:
        raise PoseGraphError(
            f"step_covariances of shape {covs.shape}; expected ({n - 1}, 6, 6), one per step of the {n} odometry poses"
        )
    if not isinstance(config, PoseGraphConfig):
        raise PoseGraphError(f"config={config!r}; expected a PoseGraphConfig")
    loops = list(loops)
    for k, loop in enumerate(loops):
        if not isinstance(loop, LoopConstraint):
            raise PoseGraphError(f"loops[{k}] is a {type(loop).__name__}; expected a LoopConstraint")
        for name in ("query", "match"):
            index = getattr(loop, name)
            if index >= n:
                raise PoseGraphError(f"loops[{k}].{name}={index}; expected an index into the {n} poses (0..{n - 1})")
    try:
        import gtsam
    except ImportError as exc:
        raise PoseGraphError(
            f"gtsam is not installed ({exc}); pose-graph optimisation needs it: pip install gtsam"
        ) from exc

    def pose3(matrix: np.ndarray) -> Any:
        m = np.array(matrix, np.float64)
        m[:3, :3] = nearest_rotation(m[:3, :3])
        return gtsam.Pose3(m)

    def gaussian(cov: np.ndarray, rel: np.ndarray) -> Any:
        return gtsam.noiseModel.Gaussian.Covariance(to_gtsam_covariance(cov, rel[:3, :3]))

    graph = gtsam.NonlinearFactorGraph()
    initial = gtsam.Values()
    for i in range(n):
        initial.insert(i, pose3(poses[i]))
    graph.add(gtsam.PriorFactorPose3(0, pose3(poses[0]), gtsam.noiseModel.Isotropic.Sigma(6, config.prior_sigma)))
    for i in range(n - 1):
        rel = relative(poses[i], poses[i + 1])
        graph.add(gtsam.BetweenFactorPose3(i, i + 1, pose3(rel), gaussian(covs[i], rel)))
    m_estimators = gtsam.noiseModel.mEstimator
    make_kernel = {"huber": m_estimators.Huber.Create, "cauchy": m_estimators.Cauchy.Create}.get(config.robust)
    for loop in loops:
        noise = gaussian(loop.covariance, loop.match_T_query)
        if make_kernel is not None:
            noise = gtsam.noiseModel.Robust.Create(make_kernel(config.robust_param), noise)
        graph.add(gtsam.BetweenFactorPose3(loop.match, loop.query, pose3(loop.match_T_query), noise))

    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(int(config.max_iterations))
    optimizer = gtsam.LevenbergMarquardtOptimizer(graph, initial, params)
    result = optimizer.optimize()
    optimized = np.stack([result.atPose3(i).matrix() for i in range(n)])  # (N, 4, 4)
    return PoseGraphResult(
        optimized=optimized, iterations=int(optimizer.iterations()),
        initial_error=float(graph.error(initial)), final_error=float(graph.error(result)),
    )


def to_gtsam_covariance(covariance: np.ndarray, rotation: np.ndarray) -> np.ndarray:
    """(6, 6) ROS-order covariance of a relative pose with rotation ``rotation`` (3, 3) -> GTSAM's.

    ROS: (x, y, z, roll, pitch, yaw) in the parent frame; GTSAM: (rot, trans) in the
    child frame (see the module docstring): ``J P C P^T J^T``, ``J = diag(R^T, R^T)``.
    """
    cov = check_covariances(covariance, "covariance", single=True)
    r = np.asarray(rotation, np.float64)
    if r.shape != (3, 3) or not np.isfinite(r).all():
        raise PoseGraphError(f"rotation of shape {r.shape}; expected a finite (3, 3) rotation matrix")
    swapped = np.block([[cov[3:, 3:], cov[3:, :3]], [cov[:3, 3:], cov[:3, :3]]])
    j = np.zeros((6, 6))
    j[:3, :3] = j[3:, 3:] = r.T
    out = j @ swapped @ j.T
    return 0.5 * (out + out.T)


# ============================================================================ errors
def ate_rmse(estimate: np.ndarray, truth: np.ndarray, *, align: bool = False) -> float:
    """Absolute trajectory error: RMSE (m) of the position differences.

    ``estimate`` and ``truth``: (N, 4, 4) poses or (N, 3) positions. With
    ``align=True`` the estimate is first moved by the rigid (no scale) transform that
    fits it best to the truth (Umeyama); the report uses ``align=False``.
    """
    est = _positions(estimate, "estimate")
    ref = _positions(truth, "truth")
    if est.shape != ref.shape:
        raise PoseGraphError(f"estimate of {len(est)} and truth of {len(ref)} poses; expected the same number")
    if len(est) == 0:
        raise PoseGraphError("empty trajectories; expected at least one pose")
    if align:
        rot, shift = umeyama_rigid(est, ref)
        est = est @ rot.T + shift
    return float(np.sqrt(((est - ref) ** 2).sum(axis=1).mean()))


def yaw_deg(pose: np.ndarray) -> float:
    """Heading (deg, -180..180] of a (4, 4) pose or (3, 3) rotation: atan2(R[1, 0], R[0, 0])."""
    m = np.asarray(pose, np.float64)
    if m.shape not in ((4, 4), (3, 3)) or not np.isfinite(m).all():
        raise PoseGraphError(f"pose of shape {m.shape}; expected a finite (4, 4) pose or (3, 3) rotation")
    return heading_deg(m)


def rotation_error_deg(estimate_T: np.ndarray, truth_T: np.ndarray) -> float:
    """Angle (deg, 0..180) of the rotation between two (4, 4) poses: |log(R_truth^T R_estimate)|."""
    est = check_poses(estimate_T, "estimate_T", single=True)
    ref = check_poses(truth_T, "truth_T", single=True)
    return float(rotation_angle_deg(ref[:3, :3].T @ est[:3, :3]))


def relative_pose_error(estimate_T: np.ndarray, truth_T: np.ndarray) -> tuple[float, float]:
    """(translation error m, |yaw error| deg) of an estimated (4, 4) relative pose.

    Translation: ``|t_estimate - t_truth|``; yaw: the heading of ``inv(truth_T) @ estimate_T``.
    """
    est = check_poses(estimate_T, "estimate_T", single=True)
    ref = check_poses(truth_T, "truth_T", single=True)
    err = ref[:3, :3].T @ est[:3, :3]
    return float(np.linalg.norm(est[:3, 3] - ref[:3, 3])), abs(heading_deg(err))


def lidar_to_body(match_T_query_lidar: np.ndarray, body_T_lidar: np.ndarray) -> np.ndarray:
    """The relative pose between two LiDAR frames as the one between their body frames (4, 4).

    ``match_T_query_body = body_T_lidar @ match_T_query_lidar @ inv(body_T_lidar)``.
    """
    rel = check_poses(match_T_query_lidar, "match_T_query_lidar", single=True)
    ext = check_poses(body_T_lidar, "body_T_lidar", single=True)
    return conjugate(ext, rel)


# ============================================================================ plot
def plot_trajectories(
    truth: np.ndarray,
    drifted: np.ndarray,
    corrected: np.ndarray,
    path: str | os.PathLike[str],
    *,
    loops: Sequence[tuple[int, int] | LoopConstraint] = (),
    title: str = "Pose-graph optimisation with loop closures",
) -> None:
    """Top view (x, y) of the truth, the drifted odometry and the optimised trajectory.

    Each loop ``(query, match)`` is a thin line between the two keyframes' true
    positions (a long line: a wrong loop). The legend gives each estimate's ATE
    (:func:`ate_rmse`, no alignment). Written as PNG, atomically.
    """
    gt = _positions(truth, "truth")
    est = {"drifted odometry": _positions(drifted, "drifted"), "optimised": _positions(corrected, "corrected")}
    for name, xyz in est.items():
        if xyz.shape != gt.shape:
            raise PoseGraphError(f"{name} trajectory of {len(xyz)} poses; expected {len(gt)} like the truth")
    pairs: list[tuple[int, int]] = []
    for k, loop in enumerate(loops):
        q, m = (loop.query, loop.match) if isinstance(loop, LoopConstraint) else tuple(loop)
        if not (_is_int(q) and _is_int(m) and 0 <= q < len(gt) and 0 <= m < len(gt)):
            raise PoseGraphError(f"loops[{k}]={loop!r}; expected a (query, match) pair of indices 0..{len(gt) - 1}")
        pairs.append((int(q), int(m)))

    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.collections import LineCollection
    from matplotlib.figure import Figure

    fig = Figure(figsize=(7, 7), dpi=100)
    FigureCanvasAgg(fig)  # Agg without touching pyplot's global backend
    ax = fig.add_subplot(1, 1, 1)
    ax.plot(gt[:, 0], gt[:, 1], "-", color="k", lw=2, label="ground truth")
    for (name, xyz), color in zip(est.items(), ("tab:red", "tab:blue"), strict=False):
        ax.plot(xyz[:, 0], xyz[:, 1], "-", color=color, lw=1.3, label=f"{name}: ATE {ate_rmse(xyz, gt):.2f} m")
    if pairs:
        segs = np.stack([gt[[q for q, _ in pairs], :2], gt[[m for _, m in pairs], :2]], axis=1)  # (L, 2, 2)
        ax.add_collection(LineCollection(list(segs), colors="tab:green", lw=0.6, alpha=0.7, zorder=0))
        ax.plot([], [], color="tab:green", lw=0.6, label=f"loop closures ({len(pairs)})")
    if len(gt):
        ax.plot(*gt[0, :2], "k^", ms=8, label="start")
    ax.set(xlabel="x [m]", ylabel="y [m]", title=title)
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(alpha=0.3)
    ax.legend(loc="best", fontsize=8)
    save_figure(fig, path)


# ============================================================================ helpers
def check_poses(poses: Any, name: str, *, single: bool = False) -> np.ndarray:
    """A float64 copy of (N, 4, 4) poses (or one (4, 4) pose) with rigid-transform checks."""
    expected = "(4, 4)" if single else "(N, 4, 4)"
    try:
        arr = np.array(poses, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise PoseGraphError(f"{name} cannot be read as numbers ({exc}); expected {expected} poses") from exc
    if arr.shape[-2:] != (4, 4) or arr.ndim != (2 if single else 3):
        raise PoseGraphError(f"{name} of shape {arr.shape}; expected {expected} homogeneous poses")
    if arr.size == 0:
        raise PoseGraphError(f"{name} of shape {arr.shape} is empty; expected at least one pose")
    stack = arr.reshape(-1, 4, 4)
    bad = np.flatnonzero(~np.isfinite(stack).all(axis=(1, 2)))
    if len(bad):
        where = "" if single else f" at pose {bad[0]}"
        raise PoseGraphError(f"{name} holds NaN or inf{where}; expected finite poses")
    rows = np.abs(stack[:, 3] - np.array([0.0, 0.0, 0.0, 1.0])).max(axis=1) if len(stack) else np.zeros(0)
    rot = stack[:, :3, :3]
    ortho = np.abs(np.swapaxes(rot, 1, 2) @ rot - np.eye(3)).max(axis=(1, 2)) if len(stack) else np.zeros(0)
    det = np.abs(np.linalg.det(rot) - 1.0) if len(stack) else np.zeros(0)
    bad = np.flatnonzero((rows > _ROTATION_TOL) | (ortho > _ROTATION_TOL) | (det > _ROTATION_TOL))
    if len(bad):
        where = "" if single else f" pose {bad[0]}"
        raise PoseGraphError(
            f"{name}{where} is not a rigid transform (bottom row {stack[bad[0], 3].tolist()}, "
            f"|R^T R - I| = {ortho[bad[0]]:.2g}, det R = {np.linalg.det(rot[bad[0]]):.6g}); "
            "expected a rotation matrix and bottom row [0, 0, 0, 1]"
        )
    return arr


def check_covariances(covs: Any, name: str, *, single: bool = False) -> np.ndarray:
    """A float64 copy of (K, 6, 6) covariances (or one (6, 6)): finite, symmetric, positive definite."""
    try:
        arr = np.array(covs, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise PoseGraphError(f"{name} cannot be read as numbers ({exc}); expected 6 x 6 covariances") from exc
    expected = "(6, 6)" if single else "(K, 6, 6)"
    if arr.shape[-2:] != (6, 6) or arr.ndim != (2 if single else 3):
        raise PoseGraphError(
            f"{name} of shape {arr.shape}; expected {expected} covariances (x, y, z, roll, pitch, yaw)"
        )
    stack = arr.reshape(-1, 6, 6)
    for k, c in enumerate(stack):
        where = "" if single else f"[{k}]"
        if not np.isfinite(c).all():
            raise PoseGraphError(f"{name}{where} holds NaN or inf; expected a finite covariance")
        scale = max(float(np.abs(c).max()), 1e-300)
        if np.abs(c - c.T).max() > 1e-9 * scale:
            raise PoseGraphError(f"{name}{where} is not symmetric; expected a symmetric positive definite covariance")
        try:
            np.linalg.cholesky(c)
        except np.linalg.LinAlgError:
            raise PoseGraphError(
                f"{name}{where} with eigenvalues {np.round(np.linalg.eigvalsh(c), 12).tolist()} is not positive "
                "definite; expected a symmetric positive definite covariance"
            ) from None
    return arr


def _positions(traj: Any, name: str) -> np.ndarray:
    """(N, 3) positions of (N, 4, 4) poses or (N, 3) positions, finite."""
    arr = np.asarray(traj, dtype=np.float64)
    if arr.ndim == 3 and arr.shape[1:] == (4, 4):
        arr = arr[:, :3, 3]
    elif not (arr.ndim == 2 and arr.shape[1] == 3):
        raise PoseGraphError(f"{name} of shape {arr.shape}; expected (N, 4, 4) poses or (N, 3) positions")
    if not np.isfinite(arr).all():
        first = np.flatnonzero(~np.isfinite(arr).all(axis=1))[0]
        raise PoseGraphError(f"{name} holds NaN or inf at pose {first}; expected finite positions")
    return arr
