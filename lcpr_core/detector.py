"""LCPR's detector, by the import path every module and user takes (``../shared/spec/interfaces.md``)::

    from lcpr_core.detector import LoopDetector, DetectorConfig, Frame

The code lives in LCPR's folder (:mod:`lcpr_core.lcpr.detector`); this module is its one public door, and
an import contract (setup.cfg) keeps every other module from importing the folder's file directly.
"""
from .lcpr.detector import (
    MATCH_METHODS,
    PEER_REFUSALS,
    REASONS,
    Candidate,
    DescribedBatch,
    DetectorConfig,
    Frame,
    KeyframeConfig,
    LoopDetector,
    MatchConfig,
    PeerKeyframe,
    PeerKeyframeError,
    Result,
    SensorConfig,
    decode_peer_keyframe,
    encode_peer_keyframe,
)

__all__ = ["MATCH_METHODS", "REASONS", "Candidate", "DescribedBatch", "DetectorConfig", "Frame", "KeyframeConfig",
           "LoopDetector", "MatchConfig", "PEER_REFUSALS", "PeerKeyframe", "PeerKeyframeError", "Result",
           "SensorConfig", "decode_peer_keyframe", "encode_peer_keyframe"]
