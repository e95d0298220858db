"""Inference paths for LCPR behind one call: torch fp32 / bf16, an exported fp32 / int8 graph (ORT, OpenVINO).

:func:`choose_backend` turns a :class:`~lcpr_core.lcpr.config.ModelConfig`'s ``precision`` into a
callable ``(images, ranges) -> B x 256`` (see :mod:`.backends`); ``"auto"`` measures the exact
candidates once on this machine (:mod:`.choose`). Exported graphs are cached next to the weights
under a hash of everything that shapes them (:mod:`.onnx_cache`); int8 graphs are made offline
(:mod:`.quantize`; the ``lcpr_quantize`` command is :mod:`lcpr_offline.lcpr_quantize`). Nothing here imports
the describer: a configuration is a :class:`~lcpr_core.lcpr.config.ModelConfig`.
"""
from ...timing import cpu_model
from .backends import Backend, OpenVinoBackend, OrtBackend, SplitBackend, TorchBackend
from .choose import EXACT_COSINE, Choice, choose_backend
from .onnx_cache import export_onnx, graph_key, onnx_path

__all__ = ["Backend", "TorchBackend", "OrtBackend", "OpenVinoBackend", "SplitBackend", "choose_backend", "Choice",
           "EXACT_COSINE", "cpu_model", "export_onnx", "graph_key", "onnx_path"]
