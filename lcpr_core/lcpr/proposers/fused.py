"""``match.method`` fused: the descriptor's candidates, then Scan Context's that are not among them.

Up to 2 x ``match.top_k`` candidates; it keeps and saves what both of its parts keep.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ...descriptor_map import Match
from .base import KeyframeInput, ProposerSetup, SearchRequest, register
from .descriptor import DescriptorProposer
from .scan_context import ScanContextProposer


@dataclass(frozen=True)
class FusedQuery:
    """What fused keeps of a keyframe: each part's."""

    descriptor: np.ndarray
    scan_context: np.ndarray


@register("fused")
class FusedProposer:
    """:class:`DescriptorProposer`'s list, then :class:`ScanContextProposer`'s entries not in it."""

    stage = ScanContextProposer.stage  # the descriptor costs nothing more

    def __init__(self, setup: ProposerSetup) -> None:
        self.descriptor = DescriptorProposer(setup)
        self.scan_context = ScanContextProposer(setup)

    def describe(self, keyframe: KeyframeInput) -> FusedQuery:
        return FusedQuery(self.descriptor.describe(keyframe), self.scan_context.describe(keyframe))

    def search(self, query: FusedQuery, request: SearchRequest) -> list[Match]:
        hits = self.descriptor.search(query.descriptor, request)
        seen = {h.id for h in hits}
        return hits + [h for h in self.scan_context.search(query.scan_context, request) if h.id not in seen]

    def add(self, query: FusedQuery) -> None:
        self.descriptor.add(query.descriptor)
        self.scan_context.add(query.scan_context)
