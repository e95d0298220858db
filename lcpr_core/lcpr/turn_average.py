"""A descriptor averaged over the rig's camera-slot turns, when the weights file asks for it.

LCPR is meant to be yaw-invariant, but a trained network is only nearly so: the range image's
convolutions see a seam at its first column and the six cameras are not evenly spaced, so the
same place seen after a turn (a revisit driven the other way, a robot that turned on the spot)
gets a somewhat different descriptor. Averaging makes the descriptor invariant by construction:
the frame is described as seen after each of the six whole-slot turns of
:mod:`lcpr_core.lcpr.preprocess.turn` (cameras rolled by k slots, range image columns by the
slot's angle), each descriptor post-processed as usual (whitening, unit length), and the six
averaged and normalised again. It costs six network passes per frame, run as one batch; on the CPU
:class:`TurnedNetwork` runs them with the camera stem (the layers that see each image alone) computed
once per frame instead of six times, which is the same arithmetic.

It is a property of a weights file, like its whitening: a checkpoint with ``'turn_average':
True`` is described this way by :class:`lcpr_core.lcpr.Describer` on every inference path
(``model.turn_average: false`` turns it off), and maps record it through ``weights_id``.
``benchmarks/recipes/lcpr_turn_average.py`` chose it for the bundled weights on the validation cities.
"""
from __future__ import annotations

import os
from collections.abc import Mapping, Sequence

import numpy as np
import torch
from torch import nn

from ..errors import CheckpointError, InputShapeError, InvalidValueError
from ..torch_files import load_checkpoint
from .checkpoint import copy_with
from .models import LCPR
from .preprocess.turn import SLOT_YAWS_DEG, range_columns, slot_yaw_deg, turn_inputs
from .whitening import unit_rows

ENTRY = "turn_average"  # the checkpoint key: True when the file's descriptors are averaged over turns
TURNS = len(SLOT_YAWS_DEG) + 1  # the nuScenes rig's six camera slots: turns by 0 .. 5 slots


def _require_rig(cameras: int, found: str) -> None:
    """InputShapeError unless there are TURNS cameras; ``found`` says where the count came from ("... {} ...")."""
    if cameras != TURNS:
        raise InputShapeError(f"turn averaging needs the {TURNS}-camera rig its slot turns are defined for; "
                              f"{found.format(cameras)} (set model.turn_average: false)")


def turned_batch(images: torch.Tensor, ranges: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """B x C x 3 x H x W, B x 1 x h x w -> the same frames after each turn, turn-major: TURNS*B rows."""
    _require_rig(images.shape[1], "got {} cameras")
    turned = [turn_inputs(images, ranges, k) for k in range(TURNS)]
    return torch.cat([t[0] for t in turned]), torch.cat([t[1] for t in turned])


class TurnedNetwork(nn.Module):
    """One frame in, the raw descriptors of its six turns out (as the LCPR on :func:`turned_batch`'s rows).

    The camera stem (:meth:`~lcpr_core.lcpr.models.LCPR.camera_stem`: conv1_i to layer1_i) sees each
    camera image alone, and a turn only rolls the cameras, so it runs once on the frame's six images and
    its features are rolled for each turn; the rest of the network (from the first fusion with the
    LiDAR branch on) runs per turn, as one batch. Same arithmetic as the full batch of six turns (the
    descriptors agree to float rounding); the stem is about 40 % of the camera branch's multiply-adds,
    and sharing it cut the six-turn network's CPU work by 16 % in ONNX Runtime (bundled weights).
    The LiDAR branch is not shared: its convolutions zero-pad the range image's ends, so they do not
    commute with the column roll.

    ``turns`` (ascending, default all six) restricts the output to those turns, len(turns)*B rows, so that
    several single-threaded runners can each take a share of a frame's turns (:mod:`.runtime.backends`).
    """

    def __init__(self, model: LCPR, *, turns: Sequence[int] = tuple(range(TURNS))) -> None:
        super().__init__()
        _require_rig(model.num_cameras, "the network has {} cameras")
        chosen = tuple(int(k) for k in turns)
        if not chosen or list(chosen) != sorted(set(chosen)) or not all(0 <= k < TURNS for k in chosen):
            raise InvalidValueError(f"turns={tuple(turns)}; accepted: ascending distinct turns out of 0 .. "
                                    f"{TURNS - 1}, e.g. (0, 1, 2)")
        self.model = model
        #: the turns computed, in output order
        self.turns = chosen
        width = model.range_size[1]
        #: range image columns each of those turns rolls (turn 0: none)
        self.range_shifts = tuple(range_columns(slot_yaw_deg(k), width) if k else 0 for k in chosen)
        self.train(model.training)  # the wrapper is in the mode of the network it wraps (eval for inference)

    def example_inputs(self, batch: int = 1) -> tuple[torch.Tensor, torch.Tensor]:
        """Zero inputs of one frame per row: B x N x 3 x H x W and B x 1 x h x w."""
        return self.model.example_inputs(batch)

    def forward(self, images: torch.Tensor, ranges: torch.Tensor) -> torch.Tensor:
        """B x N x 3 x H x W images, B x 1 x h x w ranges -> T*B x 256 unit descriptors, turn-major (T turns)."""
        b, n = images.shape[:2]
        want = (n, 3, *self.model.image_size)
        if images.dim() != 5 or n != TURNS or tuple(images.shape[1:]) != want:
            raise InputShapeError(f"images have shape {tuple(images.shape)}; expected B x {TURNS} x 3 x "
                                  f"{self.model.image_size[0]} x {self.model.image_size[1]}")
        if tuple(ranges.shape) != (b, 1, *self.model.range_size):
            raise InputShapeError(f"ranges have shape {tuple(ranges.shape)}; expected {b} x 1 x "
                                  f"{self.model.range_size[0]} x {self.model.range_size[1]}")
        stem = self.model.camera_stem(images)  # (B*N) x C1 x H/4 x W/4
        stem = stem.reshape(b, n, *stem.shape[1:])  # B x N x C1 x H/4 x W/4
        cams = torch.cat([torch.roll(stem, k, dims=1) if k else stem for k in self.turns])  # T*B x N x ...
        cams = cams.flatten(0, 1).contiguous(memory_format=torch.channels_last)  # T*B*N x C1 x H/4 x W/4
        rngs = torch.cat([torch.roll(ranges, s, dims=-1) if s else ranges for s in self.range_shifts])
        return self.model.describe_from_stem(cams, rngs, n).descriptor


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


__all__ = ["ENTRY", "TURNS", "TurnedNetwork", "average_turns", "read_turn_average", "turn_average_in", "turned_batch",
           "write_turn_average"]
