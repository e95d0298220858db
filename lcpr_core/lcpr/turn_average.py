"""A descriptor averaged over the rig's camera-slot turns, when the weights file asks for it.

LCPR is meant to be yaw-invariant, but a trained network is only nearly so: the range image's
convolutions see a seam at its first column and the six cameras are not evenly spaced, so the
same place seen after a turn (a revisit driven the other way, a robot that turned on the spot)
gets a somewhat different descriptor. Averaging makes the descriptor invariant by construction:
the frame is described as seen after each of the six whole-slot turns of
:mod:`lcpr_core.lcpr.preprocess.turn` (cameras rolled by k slots, range image columns by the
slot's angle), each descriptor post-processed as usual (whitening, unit length), and the six
averaged and normalised again. It costs six network passes per frame, run as one batch.

It is a property of a weights file, like its whitening: a checkpoint with ``'turn_average':
True`` is described this way by :class:`lcpr_core.lcpr.Describer` on every inference path
(``model.turn_average: false`` turns it off), and maps record it through ``weights_id``.
``benchmarks/recipes/lcpr_turn_average.py`` chose it for the bundled weights on the validation cities.
"""
from __future__ import annotations

import os
from collections.abc import Mapping

import numpy as np
import torch

from ..errors import CheckpointError, InputShapeError
from .checkpoint import copy_with, load_checkpoint
from .preprocess.turn import SLOT_YAWS_DEG, turn_inputs
from .whitening import unit_rows

ENTRY = "turn_average"  # the checkpoint key: True when the file's descriptors are averaged over turns
TURNS = len(SLOT_YAWS_DEG) + 1  # the nuScenes rig's six camera slots: turns by 0 .. 5 slots


def turned_batch(images: torch.Tensor, ranges: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """B x C x 3 x H x W, B x 1 x h x w -> the same frames after each turn, turn-major: TURNS*B rows."""
    if images.shape[1] != TURNS:
        raise InputShapeError(f"turn averaging needs the {TURNS}-camera rig its slot turns are defined for; "
                              f"got {images.shape[1]} cameras (set model.turn_average: false)")
    turned = [turn_inputs(images, ranges, k) for k in range(TURNS)]
    return torch.cat([t[0] for t in turned]), torch.cat([t[1] for t in turned])


def average_turns(descriptors: np.ndarray, batch: int) -> np.ndarray:
    """TURNS*B x D unit descriptors (turn-major, as :func:`turned_batch`) -> B x D unit averages."""
    x = np.asarray(descriptors, np.float32)
    if x.ndim != 2 or x.shape[0] != TURNS * batch:
        raise InputShapeError(f"descriptors of shape {x.shape}; expected {TURNS * batch} x D ({TURNS} turns of "
                              f"{batch} frames)")
    return unit_rows(x.reshape(TURNS, batch, -1).mean(axis=0))


def turn_average_in(checkpoint: object, *, source: str) -> bool:
    """Whether a loaded checkpoint asks for turn averaging (False for files without the entry)."""
    value = checkpoint.get(ENTRY, False) if isinstance(checkpoint, Mapping) else False
    if not isinstance(value, bool):
        raise CheckpointError(f"{source} has a '{ENTRY}' entry {value!r}; accepted: True or False")
    return value


def read_turn_average(path: str | os.PathLike[str]) -> bool:
    """Whether a checkpoint file asks for turn averaging (see :func:`turn_average_in`)."""
    return turn_average_in(load_checkpoint(path, mmap=True), source=repr(str(path)))


def write_turn_average(source: str | os.PathLike[str], target: str | os.PathLike[str], *, on: bool) -> int:
    """Copy checkpoint ``source`` to ``target`` with its ``'turn_average'`` entry set to ``on`` (atomic);
    returns bytes."""
    return copy_with(source, target, {ENTRY: bool(on)})


__all__ = ["ENTRY", "TURNS", "average_turns", "read_turn_average", "turn_average_in", "turned_batch",
           "write_turn_average"]
