"""Building the backend a ModelConfig names; ``precision="auto"`` measures the exact paths once.

``auto`` times torch fp32, torch bf16 autocast and ONNX Runtime fp32 on this CPU (a warm-up and
a few forward passes each, on a fixed probe input) and keeps the fastest whose descriptor has a
cosine of at least :data:`EXACT_COSINE` to torch fp32. The choice is logged with the CPU model,
because it differs between machines: bf16 wins on CPUs with fast bf16 dot products and loses on
others. On a GPU, ``auto`` times fp32, tf32 and bf16, each replayed
from a CUDA graph of the describer's batch (:mod:`.cuda`), and keeps the fastest within
:data:`~.cuda.GPU_COSINE` of exact fp32, logged with the GPU's name.
An explicit ``onnx`` or ``int8`` is checked against torch fp32 on the probe before use.

The model raced may be a :class:`~lcpr_core.lcpr.turn_average.TurnedNetwork` (the describer's on the
CPU for weights that average six turns): one frame in, its six turns' descriptors out, the camera
stem shared by the turns. Every candidate then runs that network, and its exported graph is cached
under a key of its own (:func:`.onnx_cache.graph_key` with its ``turns``). On two or more threads ``auto``
also races :data:`SPLIT`: the turns shared out to as many single-threaded ONNX Runtime sessions as threads,
run side by side, which avoids the intra-op synchronisation of small convolutions on few cores.

``config.runtime`` says what runs an exported graph: ``onnxruntime``, ``openvino``, or ``auto``.
With ``auto``, the int8 graph is timed in both (when OpenVINO is installed) and the faster kept, as the
winner differs between CPUs. The exact fp32 graph runs in ONNX Runtime under ``auto``: OpenVINO is not
faster there, and not worth the start time of compiling twice (docs/studies/inference_paths.md,
"Which runtime runs a graph").
"""
from __future__ import annotations

import dataclasses
import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from functools import partial
from typing import TYPE_CHECKING

import numpy as np
import torch

from ...errors import RuntimeSetupError
from ...timing import cpu_model, median_seconds
from .backends import Backend, OpenVinoBackend, OrtBackend, SplitBackend, TorchBackend
from .cuda import GPU_COSINE, GraphBackend, gpu_name
from .numerics import CUDA_PRECISIONS
from .onnx_cache import exported_graph, graph_key, graph_turns, onnx_path

if TYPE_CHECKING:
    from pathlib import Path

    from ..config import ModelConfig
    from ..models import LCPR
    from ..turn_average import TurnedNetwork

log = logging.getLogger(__name__)

EXACT_COSINE = 0.99999  # what "exact" means for auto and for an exported graph
INT8_COSINE = 0.99  # an int8 graph further than this from fp32 on the probe is refused as broken
AUTO_CANDIDATES = ("fp32", "bf16", "onnx")
#: auto's extra candidate for a TurnedNetwork on two or more threads: the exported graph split by turns into
#: as many single-threaded ONNX Runtime sessions as threads (at most six), run side by side (backends.SplitBackend)
SPLIT = "onnx-split"
_chosen: dict[tuple[str, str, int], str] = {}  # (graph key, device, threads or batch) -> what auto chose here


def probe_inputs(model: LCPR | TurnedNetwork, batch: int = 1) -> tuple[torch.Tensor, torch.Tensor]:
    """A fixed, frame-like input: clamped normal images, ranges 2-80 m with 10 % no-return."""
    gen = torch.Generator().manual_seed(0)
    images, ranges = model.example_inputs(batch)
    images = torch.randn(images.shape, generator=gen).clamp_(-3, 3)
    ranges = 2 + 78 * torch.rand(ranges.shape, generator=gen)
    return images, ranges.masked_fill_(torch.rand(ranges.shape, generator=gen) < 0.1, -1.0)


def cosine(a: np.ndarray, b: np.ndarray) -> float:
    """The smallest row-wise cosine between two B x D arrays."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    num = (a * b).sum(1)
    den = np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1)
    return float((num / np.maximum(den, 1e-30)).min())


@dataclass
class Choice:
    """What ``auto`` measured: ms per frame and cosine to torch fp32 per candidate, and the winner."""

    backend: Backend
    ms: dict[str, float] = field(default_factory=dict)
    cosines: dict[str, float] = field(default_factory=dict)
    failed: dict[str, str] = field(default_factory=dict)  # candidate -> why it could not run

    def summary(self) -> str:
        parts = [f"{n} {self.ms[n]:.1f} ms (cos {self.cosines[n]:.7f})" for n in self.ms]
        parts += [f"{n}: {why}" for n, why in self.failed.items()]
        return "; ".join(parts)


def _build(name: str, config: ModelConfig, model: LCPR | TurnedNetwork, *, batch: int = 1) -> Backend:
    cuda = torch.device(config.device).type == "cuda"
    if name in CUDA_PRECISIONS:
        if cuda and config.cuda_graph:
            return GraphBackend(model, device=config.device, precision=name, batch=batch)
        return TorchBackend(model, device=config.device, precision=name)
    if torch.device(config.device).type != "cpu":
        raise RuntimeSetupError(f"model.precision={name!r} runs on the CPU only; with model.device="
                                f"{config.device!r} accepted: auto, fp32, tf32, bf16")
    if name == "onnx":
        return _graph_backend(exported_graph(config, model), config, name)
    if name == "int8":
        path = onnx_path(config, "int8")
        if not path.is_file():
            weights = f" --weights {config.weights}" if config.weights else ""
            raise RuntimeSetupError(f"model.precision='int8' needs the int8 graph of these weights at {str(path)!r}; "
                                    f"make it once with: lcpr_quantize{weights} (accepted without it: auto, fp32, "
                                    "bf16, onnx)")
        return _graph_backend(path, config, name)
    raise RuntimeSetupError(f"model.precision={name!r}; accepted: auto, fp32, bf16, onnx, int8")


def _split_shares(config: ModelConfig, model: LCPR | TurnedNetwork) -> list[tuple[int, ...]]:
    """The turns each single-threaded session of the SPLIT candidate takes; [] where it does not apply (not
    a TurnedNetwork of all six turns, one thread, or OpenVINO asked for)."""
    from ..turn_average import TURNS, TurnedNetwork

    threads = config.threads or torch.get_num_threads()
    if not isinstance(model, TurnedNetwork) or model.turns != tuple(range(TURNS)) or threads < 2 \
            or config.runtime == "openvino":
        return []
    return [tuple(int(k) for k in share) for share in np.array_split(np.arange(TURNS), min(threads, TURNS))]


def _build_split(config: ModelConfig, model: LCPR | TurnedNetwork) -> Backend:
    """The SPLIT candidate: a graph per share of the turns, each in a one-thread ONNX Runtime session."""
    from ..turn_average import TurnedNetwork

    shares = _split_shares(config, model)
    if not shares or not isinstance(model, TurnedNetwork):
        raise RuntimeSetupError(f"{SPLIT} needs a TurnedNetwork of all six turns and at least two threads")
    parts: list[Backend] = [OrtBackend(exported_graph(config, TurnedNetwork(model.model, turns=share)), threads=1)
                            for share in shares]
    return SplitBackend(parts, name="onnx")


def _graph_backend(path: Path, config: ModelConfig, name: str) -> Backend:
    """An exported graph in the runtime ``config.runtime`` names (``auto`` here: ONNX Runtime)."""
    if config.runtime == "openvino":
        return OpenVinoBackend(path, threads=config.threads, name=name)
    return OrtBackend(path, threads=config.threads, name=name)


def choose_backend(config: ModelConfig, model: LCPR | TurnedNetwork, *, batch: int = 1,
                   repeats: int = 3) -> Choice:
    """The backend ``config.precision`` asks for (``auto``: measured here, see the module doc).

    ``batch``: the rows one frame makes (1, or 6 with turn averaging): what a GPU path captures.
    """
    reference = TorchBackend(model, device=config.device)
    if config.precision == "auto" and torch.device(config.device).type == "cuda":
        return _choose_cuda(config, model, reference, batch=batch)
    if config.precision not in ("auto", "onnx", "int8"):  # torch itself: nothing to check, no probe pass
        return Choice(_build(config.precision, config, model, batch=batch))
    images, ranges = probe_inputs(model)
    expected = reference(images, ranges)
    if config.precision != "auto":
        if config.precision == "int8" and config.runtime == "auto":
            backend: Backend = _fastest_int8(config, model, images, ranges, repeats=repeats)
        else:
            backend = _build(config.precision, config, model)
        cos = cosine(backend(images, ranges), expected)
        floor = EXACT_COSINE if config.precision == "onnx" else INT8_COSINE
        if cos < floor:
            where = getattr(backend, "path", "the exported graph")
            raise RuntimeSetupError(f"{where} gives descriptors at cosine {cos:.6f} to the torch model "
                                    f"(at least {floor} expected): delete it to export it again")
        log.info("LCPR: %s path in %s, cosine %.7f to torch fp32 on the probe input", config.precision,
                 backend.runtime, cos)
        return Choice(backend)
    memo = (graph_key(config, turns=graph_turns(model)), config.device, torch.get_num_threads())

    def build(name: str) -> Backend:
        if name == "fp32":
            return reference
        return _build_split(config, model) if name == SPLIT else _build(name, config, model)

    if memo in _chosen:  # measured once per process: a second detector or node takes the same path
        return Choice(build(_chosen[memo]))
    choice = Choice(reference)
    names = AUTO_CANDIDATES + ((SPLIT,) if _split_shares(config, model) else ())
    best = _race(choice, names, build, images, ranges, expected, floor=EXACT_COSINE, repeats=repeats, warmup=0)
    _chosen[memo] = best or "fp32"
    log.info("LCPR: precision auto chose %s on %s (%d threads): %s", best, cpu_model(), torch.get_num_threads(),
             choice.summary())
    return choice


def _race(choice: Choice, names: Sequence[str], build: Callable[[str], Backend], images: torch.Tensor,
          ranges: torch.Tensor, expected: np.ndarray, *, floor: float, repeats: int, warmup: int) -> str | None:
    """Time each candidate on the probe input, recording ms and cosine to ``expected`` (or why it failed) in
    ``choice``; the fastest at least ``floor`` close becomes ``choice.backend``. Returns its name, or None.
    A candidate that is the reference itself (``choice.backend`` on entry) has cosine 1 without computing it."""
    reference = choice.backend
    best = None
    for name in names:
        try:
            backend = build(name)
            out = backend(images, ranges)
            choice.cosines[name] = 1.0 if backend is reference else cosine(out, expected)
            choice.ms[name] = 1000 * median_seconds(partial(backend, images, ranges), repeats=repeats, warmup=warmup)
        except (RuntimeSetupError, RuntimeError) as err:  # a GPU out of memory included
            choice.failed[name] = str(err)
            continue
        if choice.cosines[name] >= floor and (best is None or choice.ms[name] < choice.ms[best]):
            best, choice.backend = name, backend
    return best


def _choose_cuda(config: ModelConfig, model: LCPR | TurnedNetwork, reference: TorchBackend, *, batch: int,
                 repeats: int = 20) -> Choice:
    """auto on a GPU: the fastest of fp32, tf32 and bf16 (CUDA graphs of ``batch``) within GPU_COSINE of fp32."""
    memo = (graph_key(config, turns=graph_turns(model)), config.device, batch)
    if memo in _chosen:
        return Choice(_build(_chosen[memo], config, model, batch=batch))
    images, ranges = probe_inputs(model, batch=batch)
    images, ranges = images.to(config.device), ranges.to(config.device)
    expected = reference(images, ranges)
    choice = Choice(reference)
    best = _race(choice, CUDA_PRECISIONS, lambda name: _build(name, config, model, batch=batch), images, ranges,
                 expected, floor=GPU_COSINE, repeats=repeats, warmup=2)
    _chosen[memo] = best or "fp32"
    log.info("LCPR: precision auto chose %s on %s (batch %d): %s", best, gpu_name(config.device), batch,
             choice.summary())
    return choice


def _fastest_int8(config: ModelConfig, model: LCPR | TurnedNetwork, images: torch.Tensor, ranges: torch.Tensor, *,
                  repeats: int) -> Backend:
    """The int8 graph in whichever of ONNX Runtime and OpenVINO runs it faster here (measured, logged).

    ONNX Runtime comes with the package: its failure (or a missing graph) is raised. OpenVINO may be
    absent or refuse a graph; then ONNX Runtime runs it without being timed.
    """
    candidates: dict[str, Backend] = {"onnxruntime": _build("int8", dataclasses.replace(config, runtime="onnxruntime"),
                                                            model)}
    try:
        candidates["openvino"] = _build("int8", dataclasses.replace(config, runtime="openvino"), model)
    except RuntimeSetupError as err:
        log.info("LCPR: int8 in openvino not measured: %s", err)
        return candidates["onnxruntime"]
    ms: dict[str, float] = {}
    for runtime, backend in candidates.items():
        backend(images, ranges)  # the first pass compiles and allocates: not timed
        ms[runtime] = 1000 * median_seconds(partial(backend, images, ranges), repeats=repeats, warmup=0)
    best = min(ms, key=ms.__getitem__)
    log.info("LCPR: int8 runs in %s on %s (%d threads): %s", best, cpu_model(), torch.get_num_threads(),
             ", ".join(f"{r} {v:.1f} ms" for r, v in ms.items()))
    return candidates[best]
