"""LCPR's network modules (VSeq2PC's live in lcpr_core.vseq2pc.models)."""
from .lcpr import LCPR, LcprOutput

__all__ = ["LCPR", "LcprOutput"]
