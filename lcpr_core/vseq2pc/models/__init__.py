"""VSeq2PC's two networks: the sequence model (masked transformer) and the descriptor model (RINet towers + head)."""
from .descriptor_model import DescriptorModel
from .sequence_model import SequenceModel

__all__ = ["DescriptorModel", "SequenceModel"]
