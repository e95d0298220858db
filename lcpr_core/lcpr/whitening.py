"""PCA whitening of LCPR descriptors, learned on training descriptors and stored in the checkpoint.

The network's 256-d descriptors use their dimensions very unevenly: on the bundled weights' 12
training cities the first 16 principal directions hold 86 % of the variance and the last 100
almost none (``benchmarks/recipes/lcpr_whitening.py`` prints both). Distances are then ruled by a few
directions that mostly separate cities, not places. Whitening (NetVLAD's post-processing,
Arandjelovic et al. 2016) centres the descriptors on the training mean, keeps the ``dims``
strongest principal directions and scales each by ``eigenvalue ** -power`` (0.5 = every kept
direction with unit variance), then normalises to unit length again. The result is turned back
into the original 256 coordinates (``U diag U^T``), so the descriptor keeps its size and every
map, topic and file stays 256-d.

The network itself is untouched (released checkpoints reproduce the authors' descriptors
exactly); a checkpoint with a ``'whitening'`` entry ({'mean', 'projection', 'power', 'dims',
'samples'}: tensors and numbers, so it loads with ``weights_only=True``) has it applied after the
network by :class:`lcpr_core.lcpr.Describer` on every inference path.

    lcpr_train train*.bag --whiten best.pth whitened.pth --out DIR    # fit on the training bags' frames
"""
from __future__ import annotations

import os
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from ..errors import CheckpointError, InputShapeError, InvalidValueError
from ..torch_files import load_checkpoint
from .checkpoint import copy_with

ENTRY = "whitening"  # the checkpoint key
DEFAULT_POWER = 0.5
DEFAULT_DIMS = 128
_EPS = 1e-12


@dataclass(frozen=True)
class Whitening:
    """y = normalise(projection @ (x - mean)); projection is D x D (rank ``dims``)."""

    mean: np.ndarray  # D float32
    projection: np.ndarray  # D x D float32
    power: float
    dims: int
    samples: int  # descriptors it was fitted on

    def __post_init__(self) -> None:
        d = self.mean.shape[0] if self.mean.ndim == 1 else -1
        if d < 1 or self.projection.shape != (d, d):
            raise InputShapeError(f"whitening mean {self.mean.shape} and projection {self.projection.shape}; "
                                  "expected (D,) and (D, D)")
        if not (np.isfinite(self.mean).all() and np.isfinite(self.projection).all()):
            raise InvalidValueError("whitening mean or projection holds NaN or inf; refit it")

    @property
    def dim(self) -> int:
        return int(self.mean.shape[0])

    def apply(self, descriptors: np.ndarray) -> np.ndarray:
        """B x D descriptors -> B x D whitened unit descriptors (float32)."""
        x = np.asarray(descriptors, np.float32)
        if x.ndim != 2 or x.shape[1] != self.dim:
            raise InputShapeError(f"descriptors of shape {x.shape}; this whitening takes B x {self.dim}")
        return unit_rows((x - self.mean) @ self.projection.T)

    def to_entry(self) -> dict[str, Any]:
        """The checkpoint entry: float32 tensors and plain numbers."""
        return {"mean": torch.from_numpy(self.mean.astype(np.float32)),
                "projection": torch.from_numpy(self.projection.astype(np.float32)),
                "power": float(self.power), "dims": int(self.dims), "samples": int(self.samples)}

    @classmethod
    def from_entry(cls, entry: object, *, source: str = "checkpoint") -> Whitening:
        if not isinstance(entry, Mapping) or not {"mean", "projection"} <= set(entry):
            raise CheckpointError(f"{source} has a '{ENTRY}' entry that is not a dict with 'mean' and 'projection'")
        try:
            return cls(mean=_array(entry["mean"]), projection=_array(entry["projection"]),
                       power=float(entry.get("power", DEFAULT_POWER)), dims=int(entry.get("dims", 0)),
                       samples=int(entry.get("samples", 0)))
        except (InputShapeError, InvalidValueError, TypeError, ValueError) as err:
            raise CheckpointError(f"{source}: its '{ENTRY}' entry cannot be used: {err}") from err


def unit_rows(x: np.ndarray) -> np.ndarray:
    """Each row scaled to unit length (float32): every descriptor post-processing ends with it."""
    return (x / np.maximum(np.linalg.norm(x, axis=1, keepdims=True), _EPS)).astype(np.float32)


def _array(value: object) -> np.ndarray:
    if isinstance(value, torch.Tensor):
        return value.detach().float().cpu().numpy()
    return np.asarray(value, np.float32)


def fit_whitening(descriptors: np.ndarray, *, power: float = DEFAULT_POWER, dims: int = DEFAULT_DIMS) -> Whitening:
    """Fit on N x D descriptors (N > ``dims``): mean, the ``dims`` strongest directions, scales."""
    x = np.asarray(descriptors, np.float64)
    if x.ndim != 2 or not np.isfinite(x).all():
        raise InputShapeError(f"descriptors of shape {x.shape} (finite: {bool(np.isfinite(x).all())}); "
                              "expected a finite N x D array")
    n, d = x.shape
    if not (isinstance(dims, int) and 1 <= dims <= d):
        raise InvalidValueError(f"dims={dims!r}; accepted: an integer in 1..{d} (the descriptor size)")
    if not 0 < power <= 1:
        raise InvalidValueError(f"power={power!r}; accepted: (0, 1] (0.5 = unit variance per direction)")
    if n <= dims:
        raise InvalidValueError(f"{n} descriptors cannot fit {dims} directions; give more than {dims}")
    mean = x.mean(axis=0)
    eigval, eigvec = np.linalg.eigh(np.cov(x - mean, rowvar=False))
    order = np.argsort(eigval)[::-1][:dims]
    lam, u = np.maximum(eigval[order], _EPS), eigvec[:, order]
    projection = (u * lam ** -power) @ u.T
    return Whitening(mean=mean.astype(np.float32), projection=projection.astype(np.float32), power=float(power),
                     dims=dims, samples=n)


def whitening_in(checkpoint: object, *, source: str) -> Whitening | None:
    """The whitening entry of a loaded checkpoint, or None when it has none (released files, state dicts)."""
    entry = checkpoint.get(ENTRY) if isinstance(checkpoint, Mapping) else None
    return None if entry is None else Whitening.from_entry(entry, source=source)


def read_whitening(path: str | os.PathLike[str]) -> Whitening | None:
    """The whitening stored in a checkpoint file (see :func:`whitening_in`)."""
    return whitening_in(load_checkpoint(path, mmap=True), source=repr(str(path)))


def write_whitened(source: str | os.PathLike[str], target: str | os.PathLike[str], whitening: Whitening) -> int:
    """Copy checkpoint ``source`` to ``target`` with ``whitening`` as its entry (atomic); returns bytes."""
    return copy_with(source, target, {ENTRY: whitening.to_entry()})
