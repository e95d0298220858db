"""What proposes a keyframe's loop candidates: one module per ``match.method``, registered by name.

    lcpr          descriptor.DescriptorProposer     the nearest network descriptors (the default)
    scan_context  scan_context.ScanContextProposer  the nearest Scan Contexts of the raw clouds
    fused         fused.FusedProposer               the descriptor's, then Scan Context's not among them

The protocol and the registry are in :mod:`.base`. A new method is one module whose class is
decorated with ``@register("name")``, imported before a detector is configured with that name
(the built-ins are imported here, in the order of :func:`method_names`).
"""
from .base import (
    PROPOSERS,
    CandidateProposer,
    KeyframeInput,
    MatchSettings,
    ProposerFactory,
    ProposerSetup,
    SearchRequest,
    check_method,
    make_proposer,
    method_names,
    register,
)
from .descriptor import DescriptorProposer
from .fused import FusedProposer
from .scan_context import ScanContextProposer

#: the built-in match.method names, in registration order (a plug-in registered later is not among them)
BUILT_IN_METHODS = method_names()

__all__ = [
    "BUILT_IN_METHODS", "PROPOSERS", "CandidateProposer", "DescriptorProposer", "FusedProposer", "KeyframeInput",
    "MatchSettings", "ProposerFactory", "ProposerSetup", "ScanContextProposer", "SearchRequest", "check_method",
    "make_proposer", "method_names", "register",
]
