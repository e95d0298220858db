"""The back end's options: when a message becomes a node, the odometry's noise, how loops are taken, the solver.

Every option is checked when its dataclass is made: a bad value raises :class:`~lcpr_core.errors.BackendError`
(reason ``"bad option"``) naming the field, the value and what it accepts. What each option does and how its
default was chosen: docs/backend.md.
"""
from __future__ import annotations

import math
import numbers
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

from lcpr_common.params import check_fields, param

from ..errors import BackendError, PoseGraphError
from ..geometry import rotation_angle_deg
from ..loop_report import DEFAULT_LOOP_COVARIANCE
from ..posegraph import ROBUST_KERNELS, DriftModel, check_poses
from .consistency import chi2_quantile_6dof

__all__ = ["FACTORIZATIONS", "BackendConfig", "KeyframeRule", "LoopPolicy", "OdometryNoise", "SessionPolicy",
           "config_dict"]

FACTORIZATIONS = ("auto", "cholesky", "qr")
_SLACK = 1e-6  # m, rad and s: round-off allowed when a keyframe criterion is compared


def _default_sigmas() -> tuple[float, ...]:
    """x, y, z (m), roll, pitch, yaw (deg) of the detector's default loop covariance."""
    sigma = np.sqrt(np.diag(DEFAULT_LOOP_COVARIANCE))
    return tuple(round(float(v), 9) for v in (*sigma[:3], *np.degrees(sigma[3:])))


def is_real(value: object) -> bool:
    """A real number, not a bool (True is an int, but never a distance)."""
    return isinstance(value, numbers.Real) and not isinstance(value, bool)


def bad_option(message: str) -> BackendError:
    """The error refusing an option (reason ``"bad option"``)."""
    return BackendError(message, reason="bad option")


def require(ok: bool, message: str) -> None:
    """Refuse an option (BackendError, reason ``"bad option"``) unless ``ok``."""
    if not ok:
        raise bad_option(message)


def finite_non_negative(obj: object, *names: str) -> None:
    """Refuse any of ``obj``'s fields ``names`` that is not a finite number >= 0."""
    for name in names:
        value = getattr(obj, name)
        require(is_real(value) and math.isfinite(value) and value >= 0,
                f"{type(obj).__name__}.{name}={value!r}; expected a finite number >= 0")


def show(value: Any) -> str:
    """A value on one line for an error message (arrays to 4 decimals)."""
    try:
        arr = np.asarray(value, np.float64)
    except (TypeError, ValueError):
        return repr(value)
    return np.array2string(arr, precision=4, max_line_width=200, threshold=64).replace("\n", "")


def rotation_angle(r: np.ndarray) -> float:
    """The angle (rad) of a (3, 3) rotation."""
    return math.radians(float(rotation_angle_deg(r)))


@dataclass(frozen=True, kw_only=True)
class KeyframeRule:
    """When an odometry message becomes a graph node (any criterion that is due; 0 turns one off)."""

    distance: float = param(1.0, "m moved since the last graph node that makes a message a node; 0 = off", lo=0.0,
                            hi=1e6)
    # 0.2 rad, as LIO-SAM
    angle_deg: float = param(11.5, "deg turned since the last node that makes a message a node; 0 = off", lo=0.0,
                             hi=360.0)
    interval: float = param(5.0, "s since the last node that makes a message a node (standing still); 0 = off",
                            lo=0.0, hi=1e6)

    def __post_init__(self) -> None:
        check_fields(self, error=bad_option, prefix="KeyframeRule.")

    def due(self, moved: float, turned_rad: float, elapsed: float) -> bool:
        """Whether a message ``moved`` m, ``turned_rad`` and ``elapsed`` s after the last node is a node."""
        if self.distance == 0 and self.angle_deg == 0 and self.interval == 0:
            return True  # every message
        return ((self.distance > 0 and moved >= self.distance - _SLACK)  # slack: a 1 m step computed as 0.9999999
                or (self.angle_deg > 0 and turned_rad >= math.radians(self.angle_deg) - _SLACK)
                or (self.interval > 0 and elapsed >= self.interval - _SLACK))


@dataclass(frozen=True, kw_only=True)
class OdometryNoise:
    """Std dev of the odometry between two nodes, grown with its length ``d`` (m) and turn ``a`` (rad).

    x, y: ``translation_frac * d``; z: ``z_frac * d``; yaw: ``yaw_deg_per_m * sqrt(d)`` deg; roll,
    pitch: ``roll_pitch_deg_per_m * sqrt(d)`` deg (:class:`~lcpr_core.posegraph.DriftModel`'s form,
    a heading random walk); plus ``rotation_frac * a`` on each rotation axis, in quadrature. Steps
    shorter than 1 cm count as 1 cm (a still vehicle keeps an invertible covariance).
    """

    translation_frac: float = param(0.02, "std dev of x and y between nodes, per metre moved", lo=1e-6, hi=1.0)
    z_frac: float = param(0.01, "std dev of z between nodes, per metre moved", lo=1e-6, hi=1.0)
    yaw_deg_per_m: float = param(0.1, "yaw std dev between nodes, deg per sqrt(metre moved)", lo=1e-6, hi=100.0)
    roll_pitch_deg_per_m: float = param(0.2, "roll and pitch std dev between nodes, deg per sqrt(metre)", lo=1e-6,
                                        hi=100.0)
    rotation_frac: float = param(0.02, "extra rotation std dev between nodes, per radian turned", lo=0.0, hi=1.0)

    def __post_init__(self) -> None:
        check_fields(self, error=bad_option, prefix="OdometryNoise.")
        try:
            drift = DriftModel(translation_frac=self.translation_frac, z_frac=self.z_frac,
                               yaw_deg_per_m=self.yaw_deg_per_m, roll_pitch_deg_per_m=self.roll_pitch_deg_per_m)
        except PoseGraphError as err:
            raise BackendError(f"OdometryNoise: {err}", reason="bad option") from err
        object.__setattr__(self, "_drift", drift)

    def covariance(self, step: np.ndarray) -> np.ndarray:
        """(6, 6) diagonal covariance (x, y, z, roll, pitch, yaw) of a (4, 4) odometry step."""
        sigmas = self._drift.step_sigmas(float(np.linalg.norm(step[:3, 3])))  # type: ignore[attr-defined]
        turned = self.rotation_frac * rotation_angle(step[:3, :3])
        sigmas[3:] = np.sqrt(sigmas[3:] ** 2 + turned**2)
        return np.diag(sigmas**2)


@dataclass(frozen=True, kw_only=True)
class LoopPolicy:
    """How loops are attached, checked and weighed."""

    robust: str = param("huber", "robust kernel of loop factors", choices=ROBUST_KERNELS)
    robust_param: float = param(3.0, "the kernel's k, in whitened (Mahalanobis) units", lo=1e-3, hi=1e3)
    default_sigmas: tuple[float, ...] = param(_default_sigmas(), "std devs of a loop without a covariance: x, y, z "
                                                                  "(m), roll, pitch, yaw (deg)")
    stamp_tolerance: float = param(0.5, "s: a loop stamp farther than this from every odometry message is refused",
                                   lo=0.0, hi=60.0)
    attach_tolerance: float = param(2.5, "s: the graph node nearest to a loop stamp must be this close", lo=0.0,
                                    hi=3600.0)
    gate: float = param(0.999, "chi-square probability of the consistency check (6 dof); 1 = no check", lo=1e-6,
                        hi=1.0)
    iterations: int = param(3, "extra iSAM2 updates after a loop that moved the graph, at most", lo=0, hi=100)
    min_spacing_m: float = param(0.0, "m of travel: a loop whose both ends lie within this of an accepted loop's "
                                      "ends is skipped as redundant (fewer iSAM2 updates where a place is closed "
                                      "again and again); 0 = take every loop", lo=0.0, hi=1e6)
    covariance_scale: float = param(1.0, "every loop covariance (given or default) is multiplied by this: a "
                                         "detector whose covariances are too tight (> 1) or too loose (< 1)",
                                    lo=1e-6, hi=1e6)

    def __post_init__(self) -> None:
        check_fields(self, error=bad_option, prefix="LoopPolicy.")
        sig = tuple(self.default_sigmas)
        require(len(sig) == 6 and all(is_real(v) and math.isfinite(v) and v > 0 for v in sig),
                f"LoopPolicy.default_sigmas={sig!r}; expected 6 finite numbers > 0: x, y, z (m), roll, pitch, "
                "yaw (deg)")
        object.__setattr__(self, "default_sigmas", tuple(float(v) for v in sig))

    def default_covariance(self) -> np.ndarray:
        s = np.array(self.default_sigmas)
        s[3:] = np.radians(s[3:])
        return np.diag(s**2)

    def threshold(self) -> float:
        """The squared Mahalanobis distance above which a loop is rejected (inf: no check)."""
        return math.inf if self.gate >= 1 else chi2_quantile_6dof(self.gate)


@dataclass(frozen=True, kw_only=True)
class SessionPolicy:
    """When a new session (a restart in a prior map, another robot) is placed in the map frame.

    A loop between a session not yet placed and one that is cannot be judged against the estimate: nothing
    relates the two frames yet. Such loops wait; each says where the new session's odometry frame lies in the
    map, and two agree when that holds within their covariances and the drift between their ends (pairwise
    consistency, as PCM). The session is anchored on the largest set that agrees pairwise once it holds
    ``min_loops`` loops spanning ``min_spread_m`` of its travel. Later loops that contradict the anchor wait
    in turn; a larger agreeing set of them moves the anchor (docs/sessions.md).
    """

    min_loops: int = param(3, "loops that agree pairwise which place a new session in the map frame", lo=2, hi=1000)
    min_spread_m: float = param(10.0, "m of the new session's travel the anchoring loops must span", lo=0.0,
                                hi=1e6)
    gate: float = param(0.999, "chi-square probability (6 dof) under which two inter-session loops agree", lo=1e-6,
                        hi=0.999999)
    hold_sigma: float = param(0.01, "std dev (m and rad) holding every node of a loaded prior map at its saved "
                                    "estimate (PoseGraphBackend.load(hold=True), the node's prior_graph): "
                                    "today's run is placed in yesterday's map and does not bend it", lo=1e-6,
                              hi=1e3)
    max_waiting: int = param(200, "inter-session loops kept waiting per session (anchor evidence or "
                                  "contradiction); the oldest is dropped and counted beyond it", lo=2, hi=100000)

    def __post_init__(self) -> None:
        check_fields(self, error=bad_option, prefix="SessionPolicy.")

    def threshold(self) -> float:
        """The squared Mahalanobis distance under which two inter-session loops agree."""
        return chi2_quantile_6dof(self.gate)


@dataclass(frozen=True, kw_only=True)
class BackendConfig:
    """Everything :class:`PoseGraphBackend` is configured with."""

    base_T_lidar: np.ndarray = field(default_factory=lambda: np.eye(4), compare=False)  # (4, 4)
    keyframes: KeyframeRule = field(default_factory=KeyframeRule)
    odometry: OdometryNoise = field(default_factory=OdometryNoise)
    loops: LoopPolicy = field(default_factory=LoopPolicy)
    sessions: SessionPolicy = field(default_factory=SessionPolicy)
    prior_sigma: float = 1e-3  # std dev (m and rad) of the prior holding the first node at its odometry
    relinearize_threshold: float = 0.1  # rad: iSAM2 relinearises a node whose rotation update exceeds this
    # m: ... or whose translation update exceeds this (looser is cheaper but costs ATE: the translation's
    # linearisation point matters on a drifting odometry; docs/backend.md)
    relinearize_translation: float = 0.1
    # m, rad: the online reads (newest node, the check's ends) stop back-substituting below a clique whose update
    # is under this (GTSAM's wildfire; 0.001 its default, no better in ATE: docs/backend.md); trajectory(),
    # nodes() and save() solve fully
    wildfire_threshold: float = 0.01
    # iSAM2's factorisation: cholesky (faster), qr (robust), or auto: Cholesky until it declares the graph
    # indeterminate, then QR for good (the graph rebuilt once from its factors; see graph.PoseGraphBackend._new_isam)
    factorization: str = "auto"
    level_sigma_deg: float = param(0.0, "deg: std dev of a level prior on every graph node (a ground vehicle level "
                                        "on average, or an IMU's gravity; removes the tilt loops cannot see); 0 = "
                                        "off", lo=0.0, hi=90.0)
    gravity_sigma_deg: float = param(0.0, "deg: std dev holding every graph node's roll and pitch to the "
                                          "odometry's, for an odometry that measures gravity (FAST-LIO2, LIO-SAM, "
                                          "Point-LIO: 0.5); 0 = off (KISS-ICP and other LiDAR-only odometry drift "
                                          "in tilt)", lo=0.0, hi=90.0)
    # inside a Huber kernel (add_up)
    up_sigma_deg: float = param(2.0, "deg: std dev of a keyframe's up measured from its walls (up_topic; Huber "
                                     "kernel): holds the roll and pitch loops cannot see, on slopes too; 0 = ignored",
                                lo=0.0, hi=90.0)
    # the ups measured within it, carried by the odometry, are averaged into the world's up (fixed at the first
    # measurement beyond it); short, so that the odometry's drift stays out of it
    up_warmup_m: float = param(10.0, "m of travel from the first node whose measured ups, averaged, set the world's "
                                     "up", lo=0.0, hi=1e6)
    # a variable joined to every node makes add_loop's p95 3-4 times dearer at 2,000 nodes
    up_world_sigma_deg: float = param(0.0, "deg: > 0 makes the world's up a graph variable held to the warm-up's "
                                           "mean with this std dev and refined by every up (noisy ups tilt the map "
                                           "less; add_loop p95 several times dearer); 0 = fixed at the warm-up's "
                                           "mean", lo=0.0, hi=90.0)

    def __post_init__(self) -> None:
        try:
            ext = check_poses(self.base_T_lidar, "BackendConfig.base_T_lidar", single=True)
        except PoseGraphError as err:
            raise BackendError(f"{err} (got {show(self.base_T_lidar)})", reason="bad option") from err
        ext.flags.writeable = False
        object.__setattr__(self, "base_T_lidar", ext)
        for name, kind in (("keyframes", KeyframeRule), ("odometry", OdometryNoise), ("loops", LoopPolicy),
                           ("sessions", SessionPolicy)):
            require(isinstance(getattr(self, name), kind),
                    f"BackendConfig.{name}={getattr(self, name)!r}; expected a {kind.__name__}")
        for name in ("prior_sigma", "relinearize_threshold", "relinearize_translation"):
            value = getattr(self, name)
            require(is_real(value) and math.isfinite(value) and value > 0,
                    f"BackendConfig.{name}={value!r}; expected a finite number > 0")
        check_fields(self, error=bad_option, prefix="BackendConfig.")
        finite_non_negative(self, "wildfire_threshold")
        require(self.factorization in FACTORIZATIONS,
                f"BackendConfig.factorization={self.factorization!r}; expected one of {', '.join(FACTORIZATIONS)}")


def config_dict(config: BackendConfig) -> dict[str, Any]:
    """A JSON-ready summary of a config (reports, benchmarks)."""
    out: dict[str, Any] = {name: asdict(getattr(config, name))
                           for name in ("keyframes", "odometry", "loops", "sessions")}
    out.update(base_T_lidar=np.asarray(config.base_T_lidar).tolist(), prior_sigma=config.prior_sigma,
               relinearize_threshold=config.relinearize_threshold,
               relinearize_translation=config.relinearize_translation, wildfire_threshold=config.wildfire_threshold,
               factorization=config.factorization,
               level_sigma_deg=config.level_sigma_deg,
               gravity_sigma_deg=config.gravity_sigma_deg, up_sigma_deg=config.up_sigma_deg,
               up_warmup_m=config.up_warmup_m, up_world_sigma_deg=config.up_world_sigma_deg)
    return out
