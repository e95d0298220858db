"""``match.method`` lcpr (the default): the map entries nearest the keyframe's network descriptor.

It keeps nothing beside the map: the map's FAISS index holds every keyframe's descriptor, a prior
map's included, and saves them.
"""
from __future__ import annotations

from typing import cast

import numpy as np

from ...descriptor_map import DescriptorMap, Match
from .base import KeyframeInput, ProposerSetup, SearchRequest, register


@register("lcpr")
class DescriptorProposer:
    """The ``match.top_k`` nearest descriptors (L2) under the resolved ``match.max_distance``."""

    stage = None  # the descriptor is the network's: nothing more to make

    def __init__(self, setup: ProposerSetup) -> None:
        self.map: DescriptorMap = setup.map

    def describe(self, keyframe: KeyframeInput) -> np.ndarray:
        return keyframe.descriptor

    def search(self, query: np.ndarray, request: SearchRequest) -> list[Match]:
        """Top-k entries within max_distance among the eligible rows. The excluded rows are the map's newest,
        so the index is asked for that many more hits, which are then dropped: exact however many are excluded."""
        top_k = request.match.top_k
        if request.allowed is not None:  # the rows allowed, searched as such (FAISS's selector, or exactly)
            return cast(list[Match], self.map.search(query, k=top_k, max_distance=request.max_distance,
                                                     allowed=request.allowed))
        excluded = len(self.map) - request.eligible
        # one (D,) descriptor: search returns one list of matches
        hits = cast(list[Match], self.map.search(query, k=min(top_k + excluded, len(self.map)),
                                                 max_distance=request.max_distance))
        newest_ids = set(self.map.ids[request.eligible:].tolist())
        return [h for h in hits if h.id not in newest_ids][:top_k]

    def add(self, query: np.ndarray) -> None:
        """Nothing to keep: the detector adds the descriptor to the map."""
