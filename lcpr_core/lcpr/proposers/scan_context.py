"""``match.method`` scan_context: the map entries whose Scan Context (of the keyframe's raw cloud) is nearest.

Scan Contexts (:class:`~lcpr_core.scan_context.ScanContextRows`) are kept row-aligned in the map
(``DescriptorMap.scan_contexts``), so a saved map keeps them. A prior map's are taken from its file
when they were made as these are, else rebuilt from its stored compact clouds (a keyframe without a
cloud is never proposed by Scan Context).
"""
from __future__ import annotations

import logging

import numpy as np

from ...descriptor_map import DescriptorMap, Match
from ...scan_context import ScanContextConfig, ScanContextRows
from .base import KeyframeInput, ProposerSetup, SearchRequest, register

log = logging.getLogger(__name__)

SC_CANDIDATES_PER_K = 5  # ring-key nearest neighbours compared in full, per candidate wanted


@register("scan_context")
class ScanContextProposer:
    """The ``match.top_k`` nearest Scan Contexts under ``match.sc_max_distance`` (distance: theirs, 0..1)."""

    stage = "scan_context"

    def __init__(self, setup: ProposerSetup) -> None:
        self.map: DescriptorMap = setup.map
        self.rows = prior_scan_contexts(setup.map, top_k=setup.match.top_k, method=setup.match.method)

    def describe(self, keyframe: KeyframeInput) -> np.ndarray:
        return self.rows.describe(keyframe.points)

    def search(self, query: np.ndarray, request: SearchRequest) -> list[Match]:
        match = request.match
        found = self.rows.search(query, rows=request.eligible, k=match.top_k, max_distance=match.sc_max_distance,
                                 allowed=request.allowed)
        if not found:
            return []
        sources = self.map.sources
        out = []
        for rank, (row, distance) in enumerate(found):
            p = self.map.poses[row]
            pose = None if np.isnan(p).all() else (float(p[0]), float(p[1]), float(p[2]))
            out.append(Match(id=int(self.map.ids[row]), distance=distance, stamp=float(self.map.stamps[row]),
                             pose=pose, source=sources[row], rank=rank))
        return out

    def add(self, query: np.ndarray) -> None:
        self.rows.add(query)


def prior_scan_contexts(descriptor_map: DescriptorMap, *, top_k: int, method: str) -> ScanContextRows:
    """Scan Context rows for the map's existing keyframes: those the map file kept when they were made as these
    are, else rebuilt from the stored compact clouds; the map holds them from here on, so a saved map keeps them.
    ``method``: the ``match.method`` named in the log."""
    config = ScanContextConfig(candidates=SC_CANDIDATES_PER_K * top_k)
    kept = descriptor_map.scan_contexts
    if kept is not None and len(kept) == len(descriptor_map) and kept.config.describing() == config.describing():
        rows = kept.with_config(config)
        log.info("match.method %s: the prior map's %d Scan Contexts loaded", method, len(rows))
    else:
        rows, missing = ScanContextRows(config), 0
        for kf in descriptor_map.ids.tolist():
            xyz = descriptor_map.clouds.get(int(kf))
            missing += xyz is None
            rows.add(None if xyz is None else rows.describe(xyz))
        if len(descriptor_map):
            log.info("match.method %s: Scan Contexts of the prior map's %d keyframes rebuilt from their clouds "
                     "(%d have none and are never proposed by it)", method, len(descriptor_map), missing)
    descriptor_map.scan_contexts = rows
    return rows
