"""Network modules."""
from .lcpr import LCPR, LcprOutput

__all__ = ["LCPR", "LcprOutput"]
from .descriptor_model import DescriptorModel
from .sequence_model import SequenceModel

__all__ += ["DescriptorModel", "SequenceModel"]
