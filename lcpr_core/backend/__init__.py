"""The pose-graph back end: any odometry plus verified loop closures -> a corrected trajectory.

    g = PoseGraphBackend(BackendConfig(base_T_lidar=T))   # T: base frame -> the loops' LiDAR frame
    g.add_odometry(stamp, world_T_base)                     # every odometry message, in stamp order
    g.add_loop(query_stamp, match_stamp, match_T_query, covariance)   # False: rejected as inconsistent
    g.pose(stamp), g.trajectory(), g.map_T_odom(), g.stats(), g.save(path), PoseGraphBackend.load(path)
    g.add_odometry(t, pose, session="b"); g.add_loop(..., query_session="b", match_session="a")  # sessions
    g.anchored("b"), g.map_T_odom("b"), PoseGraphBackend.load(path, hold=True)   # a prior map (docs/sessions.md)

A SLAM consumer of the detectors, not a part of them: it imports only the core's shared layers (geometry,
errors, the pose-graph and loop-report conversions), and neither the detectors nor the evaluation import it
(the import contracts in setup.cfg hold both). Its rooms: the graph (:mod:`.graph`), its options
(:mod:`.config`), its file (:mod:`.graph_file`), the consistency check (:mod:`.consistency`), its sessions
(:mod:`.session`) and how a new one is placed (:mod:`.placing`, :mod:`.anchoring`), a recorded
drive replayed through it (:mod:`.replay`) and KISS-ICP odometry to feed it (:mod:`.lidar_odometry`).
How it is built and what it measures: docs/backend.md. GTSAM is an optional extra (``pip install gtsam``).
"""
from __future__ import annotations

from .config import (
    FACTORIZATIONS,
    BackendConfig,
    KeyframeRule,
    LoopPolicy,
    OdometryNoise,
    SessionPolicy,
    config_dict,
)
from .consistency import chi2_quantile_6dof
from .graph import (
    BAD_SESSION,
    BAD_STAMP,
    DEFAULT_SESSION,
    LOOP_COVARIANCE,
    LOOP_POSE,
    LOOP_SAME_NODE,
    LOOP_SESSION,
    ODOM_ORDER,
    ODOM_POSE,
    PRIOR_MISMATCH,
    UP_VECTOR,
    BackendStats,
    PoseGraphBackend,
)
from .graph_file import GRAPH_SCHEMA, GRAPH_VERSION
from .session import LOOP_AHEAD, LOOP_OLD, LOOP_UNKNOWN, MAX_SESSION_NAME

__all__ = [
    "BackendConfig", "BackendStats", "GRAPH_SCHEMA", "GRAPH_VERSION", "KeyframeRule", "LoopPolicy", "OdometryNoise",
    "PoseGraphBackend", "SessionPolicy", "chi2_quantile_6dof", "config_dict", "DEFAULT_SESSION", "MAX_SESSION_NAME",
    # the solver choices, and the reasons an input is refused under (BackendError.reason, BackendStats.refused)
    "FACTORIZATIONS", "BAD_STAMP", "LOOP_AHEAD", "LOOP_COVARIANCE", "LOOP_OLD", "LOOP_POSE", "LOOP_SAME_NODE",
    "LOOP_UNKNOWN", "ODOM_ORDER", "ODOM_POSE", "UP_VECTOR", "BAD_SESSION", "LOOP_SESSION", "PRIOR_MISMATCH",
]
