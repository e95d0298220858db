"""The exported ONNX graph of an LCPR: where it is cached and when it must be exported again.

A graph is named by a hash (:func:`graph_key`) of everything that shapes it: the weights file's
bytes (or the seed / ImageNet file of an untrained model), the architecture and input sizes, the
graph kind (``fp32``, ``int8``), whether it computes one frame's six turns itself
(:class:`~lcpr_core.lcpr.turn_average.TurnedNetwork`) and the torch and opset versions that export it. A changed
checkpoint therefore gets a new file; a stale one is never used. Graphs sit next to the weights
(``<weights>.<kind>-<hash>.onnx``) when that folder is writable, else in the user cache
(``$XDG_CACHE_HOME/lcpr_loop_closure``). Files are written atomically.
"""
from __future__ import annotations

import hashlib
import json
import logging
import os
import tempfile
import warnings
from pathlib import Path
from typing import TYPE_CHECKING

import torch

from ...errors import RuntimeSetupError

if TYPE_CHECKING:
    from ..config import ModelConfig
    from ..models import LCPR
    from ..turn_average import TurnedNetwork

log = logging.getLogger(__name__)

OPSET = 17
# The TorchScript exporter: 1 s for a narrow LCPR where torch.export (dynamo=True) takes 10-20 s, same graph
# to 1e-7; torch is pinned (setup.py), and a torch without it fails here with the reason.
FORMAT = 1  # bump when the export itself changes (names, dynamic axes)
KINDS = ("fp32", "int8")
_digests: dict[tuple[str, int, int], str] = {}


def file_digest(path: str | os.PathLike[str]) -> str:
    """sha256 of a file's bytes, remembered per (path, size, mtime) for this process."""
    stat = os.stat(path)
    key = (str(Path(path).resolve()), stat.st_size, stat.st_mtime_ns)
    if key not in _digests:
        h = hashlib.sha256()
        with open(path, "rb") as f:
            for chunk in iter(lambda: f.read(1 << 20), b""):
                h.update(chunk)
        _digests[key] = h.hexdigest()
    return _digests[key]


def graph_turns(model: LCPR | TurnedNetwork) -> tuple[int, ...]:
    """The turns the graph of ``model`` computes per frame: () for one pass, a TurnedNetwork's turns."""
    from ..turn_average import TurnedNetwork

    return model.turns if isinstance(model, TurnedNetwork) else ()


def graph_key(config: ModelConfig, kind: str = "fp32", *, turns: tuple[int, ...] = ()) -> str:
    """16 hex digits naming the graph of ``config`` (resolved: sizes as the weights fix them); ``turns``: those
    a :class:`~lcpr_core.lcpr.turn_average.TurnedNetwork` computes (one frame in, a row per turn out)."""
    if kind not in KINDS:
        raise RuntimeSetupError(f"graph kind {kind!r}; accepted: {', '.join(KINDS)}")
    preset = config.range_preset
    source: dict[str, object] = ({"weights": file_digest(config.weights)} if config.weights else
                                 {"imagenet": file_digest(config.imagenet)} if config.imagenet else
                                 {"seed": config.seed})
    fields = {"format": FORMAT, "opset": OPSET, "torch": torch.__version__.split("+")[0], "kind": kind,
              "width": config.width, "num_cameras": config.num_cameras, "image_size": list(config.image_size),
              "range_size": [preset.height, preset.width], **source}
    if turns:  # absent for the one-pass graph, whose names stay those of earlier versions
        fields["turns"] = list(turns)
    return hashlib.sha256(json.dumps(fields, sort_keys=True).encode()).hexdigest()[:16]


def cache_dir() -> Path:
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "lcpr_loop_closure"


def _writable(folder: Path) -> bool:
    return folder.is_dir() and os.access(folder, os.W_OK)


def onnx_path(config: ModelConfig, kind: str = "fp32", *, turns: tuple[int, ...] = ()) -> Path:
    """Where the graph of ``config`` is (when it exists) or is to be written (``turns``: see graph_key)."""
    key = graph_key(config, kind, turns=turns)
    places = []
    if config.weights:
        weights = Path(config.weights)
        places.append(weights.with_name(f"{weights.name}.{kind}-{key}.onnx"))
    places.append(cache_dir() / f"lcpr-{kind}-{key}.onnx")
    for place in places:
        if place.is_file():
            return place
    for place in places:
        if _writable(place.parent) or place.parent == cache_dir():
            return place
    return places[-1]


def export_onnx(model: LCPR | TurnedNetwork, path: str | os.PathLike[str]) -> Path:
    """Export ``model`` (fp32, batch dimension dynamic) to ``path`` atomically."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    images, ranges = model.example_inputs(1)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
    os.close(fd)
    was_training = model.training
    model.eval()
    try:
        with warnings.catch_warnings(), torch.no_grad():
            warnings.simplefilter("ignore")  # the TorchScript exporter's deprecation notice
            torch.onnx.export(model, (images.cpu(), ranges.cpu()), tmp, input_names=["images", "ranges"],
                              output_names=["descriptor"], opset_version=OPSET, dynamo=False,
                              dynamic_axes={"images": {0: "batch"}, "ranges": {0: "batch"},
                                            "descriptor": {0: "batch"}})
        os.chmod(tmp, 0o644)
        os.replace(tmp, path)
    except Exception as err:
        raise RuntimeSetupError(f"exporting LCPR to ONNX at {str(path)!r} failed: {err}") from err
    finally:
        model.train(was_training)
        if os.path.exists(tmp):
            os.unlink(tmp)
    log.info("LCPR: exported the network to %s", path)
    return path


def exported_graph(config: ModelConfig, model: LCPR | TurnedNetwork) -> Path:
    """The fp32 graph of ``config``, exported from ``model`` (on the CPU) when not cached yet."""
    path = onnx_path(config, "fp32", turns=graph_turns(model))
    if not path.is_file():
        device = next(model.parameters()).device
        export_onnx(model.cpu(), path)
        model.to(device)
    return path
