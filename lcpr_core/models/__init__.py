"""Network modules."""
from .lcpr import LCPR, LcprOutput

__all__ = ["LCPR", "LcprOutput"]
