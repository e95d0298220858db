"""The stable import path of LCPR's detector (``../shared/spec/interfaces.md``)::

    from lcpr_core.detector import LoopDetector, DetectorConfig, Frame

The code lives in :mod:`lcpr_core.lcpr.detector` (LCPR's folder); this module only re-exports it.
"""
from .lcpr.detector import (
    REASONS,
    Candidate,
    DetectorConfig,
    Frame,
    LoopDetector,
    MatchConfig,
    Result,
    SensorConfig,
)

__all__ = ["REASONS", "Candidate", "DetectorConfig", "Frame", "LoopDetector", "MatchConfig", "Result", "SensorConfig"]
