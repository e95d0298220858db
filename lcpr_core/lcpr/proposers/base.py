"""The candidate-proposer protocol and the registry of ``match.method`` names.

A proposer is what a ``match.method`` names: it keeps something of every keyframe, proposes the
map entries nearest a new keyframe, and keeps what it needs in the detector's map. The detector
(:class:`~lcpr_core.detector.LoopDetector`) drives it the same way for every method:

1. made once, with the detector's map (:class:`ProposerSetup`): a prior map's keyframes must be
   searchable from the first query, from what the map file kept for the method or rebuilt from the
   map's stored clouds;
2. per keyframe, :meth:`~CandidateProposer.describe` (what the method keeps of it), then
   :meth:`~CandidateProposer.search` (the map's rows before it, the exclusion rules already applied:
   :class:`SearchRequest`), then :meth:`~CandidateProposer.add` once the map holds the keyframe's row.

What a proposer puts in the map is saved with it (:meth:`~lcpr_core.descriptor_map.DescriptorMap.save`).
A method is one module: a class that has these members, decorated with :func:`register`.
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol, TypeVar

import numpy as np

from ...descriptor_map import DescriptorMap, Match
from ...errors import InvalidValueError

__all__ = [
    "PROPOSERS", "CandidateProposer", "KeyframeInput", "MatchSettings", "ProposerFactory", "ProposerSetup",
    "SearchRequest", "check_method", "make_proposer", "method_names", "register",
]

R = TypeVar("R")  # what a proposer keeps of one keyframe


class MatchSettings(Protocol):
    """The ``match.*`` settings a proposer reads (the detector's MatchConfig; read at every search, since
    ``top_k`` and the distances may change while a node runs)."""

    @property
    def method(self) -> str: ...

    @property
    def top_k(self) -> int: ...

    @property
    def sc_max_distance(self) -> float: ...


@dataclass(frozen=True)
class ProposerSetup:
    """What a proposer is made with: the detector's map (a prior one or a new one) and the settings at start."""

    map: DescriptorMap
    match: MatchSettings


@dataclass(frozen=True)
class KeyframeInput:
    """One keyframe as a proposer sees it."""

    descriptor: np.ndarray  # (D,) the network's
    points: np.ndarray  # N x (>=3) LiDAR cloud, sensor frame; no points when the frame had no cloud
    stamp: float
    pose: np.ndarray | None = None  # 4 x 4 world_T_base from the odometry, or None


@dataclass(frozen=True)
class SearchRequest:
    """One query's search: only the map's first ``eligible`` rows may be proposed (the rows after them are this
    session's newest keyframes, hidden by ``match.exclude_recent_s`` / ``match.exclude_recent_count``), and of
    those only the rows where ``allowed`` holds when it is given: with peer robots' keyframes in the map, this
    session's hidden keyframes are not all at its end, and a peer's keyframe is not matched with its own
    session's. The detector drops any hit outside ``allowed`` that a method proposes all the same."""

    eligible: int  # >= 1: the detector proposes nothing when no row is eligible
    match: MatchSettings  # the settings now
    max_distance: float  # descriptor L2 bound as used (match.max_distance with AUTO_DISTANCE resolved)
    allowed: np.ndarray | None = None  # (eligible,) bool: the rows that may be proposed; None = all of them


class CandidateProposer(Protocol[R]):
    """What proposes a keyframe's loop candidates (one ``match.method``)."""

    @property
    def stage(self) -> str | None:
        """The ``Result.timings`` key of :meth:`describe`'s cost; None when it costs nothing worth timing."""
        ...

    def describe(self, keyframe: KeyframeInput) -> R:
        """What this method keeps of a keyframe, made before the keyframe is searched for or stored."""
        ...

    def search(self, query: R, request: SearchRequest) -> list[Match]:
        """Up to ``request.match.top_k`` map entries among the eligible rows, best first (``Match.rank``
        counting from 0 within this list; ``Match.distance`` in the method's own measure)."""
        ...

    def add(self, query: R) -> None:
        """Keep ``query`` for the keyframe whose row the map has just added (its last row)."""
        ...


ProposerFactory = Callable[[ProposerSetup], CandidateProposer[Any]]
F = TypeVar("F", bound=ProposerFactory)

#: ``match.method`` name -> what makes its proposer, in registration order (the built-ins first)
PROPOSERS: dict[str, ProposerFactory] = {}


def register(name: str) -> Callable[[F], F]:
    """Class (or factory) decorator: make ``name`` a ``match.method`` value. A name already taken is refused."""
    if not isinstance(name, str) or not name.isidentifier():
        raise InvalidValueError(f"match.method name {name!r}; accepted: a Python identifier such as 'scan_context'")

    def add(factory: F) -> F:
        if name in PROPOSERS:
            raise InvalidValueError(f"match.method {name!r} is registered already (by {PROPOSERS[name]!r}); "
                                    f"registered: {', '.join(PROPOSERS)}")
        PROPOSERS[name] = factory
        return factory
    return add


def method_names() -> tuple[str, ...]:
    """The registered ``match.method`` names, in registration order."""
    return tuple(PROPOSERS)


def check_method(name: str) -> None:
    """Refuse a ``match.method`` that no proposer is registered under, naming it and the registered ones."""
    if name not in PROPOSERS:
        raise InvalidValueError(f"match.method={name!r}; accepted: {', '.join(PROPOSERS)}")


def make_proposer(name: str, setup: ProposerSetup) -> CandidateProposer[Any]:
    """The proposer registered under ``name``, made with ``setup``."""
    check_method(name)
    return PROPOSERS[name](setup)
