"""Building an LCPR from a config and turning raw sensor data into descriptors."""
from __future__ import annotations

import dataclasses
import functools
import logging
import os
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ..errors import CheckpointError, DeviceError, InvalidValueError
from ..fingerprint import tensors_id
from ..pretrained import WEIGHTS_NAMES, resolve_weights
from ..torch_files import load_checkpoint
from .checkpoint import init_from_imagenet, load_weights
from .config import (  # noqa: F401 - PRECISIONS, RUNTIMES: importable from here too, beside ModelConfig
    CHECKPOINT_FIELDS,
    PRECISIONS,
    RUNTIMES,
    ModelConfig,
)
from .models import LCPR
from .preprocess import CUSTOM, range_image
from .preprocess.camera import CameraInput
from .preprocess.cameras import CameraPreprocessor
from .preprocess.range_image import points_array, range_images_tensor
from .runtime import Backend, Choice, choose_backend
from .turn_average import TURNS, TurnedNetwork, average_turns, turn_average_in, turned_batch
from .whitening import Whitening, whitening_in

log = logging.getLogger(__name__)


def checkpoint_config(path: str | os.PathLike[str]) -> dict[str, Any] | None:
    """The 'config' entry of a checkpoint (width, sizes, preset), or None for files without one.

    Released checkpoints and plain state dicts have none (they are the released
    configuration). Read with ``weights_only=True`` and a memory map, so it is cheap.
    """
    file = Path(path)
    if not file.is_file():
        raise CheckpointError(f"weights file {str(file)!r} does not exist")
    try:
        obj = load_checkpoint(file, mmap=True)
    except CheckpointError:
        return None  # load_weights reports what is wrong with the file
    entry = obj.get("config") if isinstance(obj, Mapping) else None
    if entry is None:
        return None
    if not isinstance(entry, Mapping) or not set(entry) <= set(CHECKPOINT_FIELDS):
        raise CheckpointError(f"{str(file)!r} has a 'config' entry {entry!r}; accepted keys: "
                              f"{', '.join(CHECKPOINT_FIELDS)}")
    return dict(entry)


def resolve_config(config: ModelConfig) -> ModelConfig:
    """``config`` with width, camera count and input sizes taken from its weights file's 'config' entry.

    The file wins: its network only loads at its own width and was trained at its own
    sizes. Fields the caller set to something else than the default are logged. A
    ``lidar = "custom"`` geometry is the caller's sensor and stays (its range image takes the
    file's size).
    """
    if config.weights in WEIGHTS_NAMES:  # "bundled" / "seeded" -> the file / no file
        config = dataclasses.replace(config, weights=resolve_weights(config.weights))
    if not config.weights:
        return config
    entry = checkpoint_config(config.weights)
    if not entry:
        return config
    values: dict[str, Any] = {}
    for key, value in entry.items():
        if key in ("image_size", "range_size"):
            value = tuple(int(v) for v in value)
        values[key] = value
    if config.lidar == CUSTOM and "lidar" in values:
        log.info("LCPR: %s was trained with LiDAR preset %r; using the custom model.lidar_geometry at its range "
                 "image size", config.weights, values.pop("lidar"))
    defaults = ModelConfig()
    for key, value in values.items():
        given = getattr(config, key)
        if given != value and given != getattr(defaults, key):
            log.warning("LCPR: %s=%r replaced by %r from %s", key, given, value, config.weights)
    return dataclasses.replace(config, **values)


def build_model(config: ModelConfig = ModelConfig()) -> LCPR:
    """An LCPR in eval mode with weights from the config, saying in the log where they came from.

    A weights file with a 'config' entry (written by ``lcpr_train``) fixes the width and
    input sizes (:func:`resolve_config`).
    """
    config = resolve_config(config)
    preset = config.range_preset
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(config.seed)
        model = LCPR(
            num_cameras=config.num_cameras,
            image_size=config.image_size,
            range_size=(preset.height, preset.width),
            width=config.width,
        )
    if config.weights:
        load_weights(model, config.weights)
    elif config.imagenet:
        init_from_imagenet(model, config.imagenet)
        log.warning("LCPR: ResNet blocks from ImageNet (%s), the rest random; not a trained place model",
                    config.imagenet)
    else:
        log.warning("LCPR: no weights given, using a seeded random initialisation (seed %d); "
                    "descriptors are not those of a trained network", config.seed)
    return model.to(config.device).eval()


@dataclass
class Prepared:
    """One frame's network inputs and the cameras whose images could not be used."""

    images: torch.Tensor  # 1 x N x 3 x H x W, on the model's device
    ranges: torch.Tensor  # 1 x 1 x h x w
    failed: dict[int, str] = field(default_factory=dict)  # camera slot -> why its image was left out


@dataclass
class PreparedBatch:
    """Several frames' network inputs and, per frame, the cameras whose images could not be used."""

    images: torch.Tensor  # B x N x 3 x H x W, on the model's device
    ranges: torch.Tensor  # B x 1 x h x w
    failed: list[dict[int, str]]  # per frame: camera slot -> why its image was left out


def prepare_each(prepare: Callable[[Sequence[CameraInput | None], np.ndarray], Prepared],
                 frames: Sequence[tuple[Sequence[CameraInput | None], np.ndarray]]) -> PreparedBatch:
    """Frames preprocessed one by one by ``prepare``, joined into one batch."""
    one = [prepare(images, points) for images, points in frames]
    if len(one) == 1:
        return PreparedBatch(one[0].images, one[0].ranges, [one[0].failed])
    return PreparedBatch(torch.cat([p.images for p in one]), torch.cat([p.ranges for p in one]),
                         [p.failed for p in one])


@dataclass
class Describer:
    """Raw cameras + cloud -> a 256-d unit descriptor, with the configured precision."""

    config: ModelConfig = field(default_factory=ModelConfig)
    model: LCPR | None = None

    def __post_init__(self) -> None:
        self.config = resolve_config(self.config)  # preprocessing must follow the weights' sizes
        if self.config.threads:
            torch.set_num_threads(self.config.threads)
        if self.model is None:
            self.model = build_model(self.config)
        # the descriptor post-processing the weights file carries, read from it once
        stored = (load_checkpoint(self.config.weights, mmap=True)
                  if self.config.weights and (self.config.whitening or self.config.turn_average) else None)
        source = repr(self.config.weights)
        #: applied after the network, whatever the path
        self.whitening: Whitening | None = whitening_in(stored, source=source) if self.config.whitening else None
        if self.whitening is not None:
            log.info("LCPR: descriptors whitened as stored in %s (%d of %d directions, power %g)",
                     self.config.weights, self.whitening.dims, self.whitening.dim, self.whitening.power)
        #: six network passes per frame, their descriptors averaged (lcpr_core.lcpr.turn_average)
        self.turn_average = self.config.turn_average and turn_average_in(stored, source=source)
        if self.turn_average:
            if self.config.num_cameras != TURNS:
                raise InvalidValueError(
                    f"{self.config.weights} asks for turn averaging, defined for the {TURNS}-camera rig; "
                    f"num_cameras={self.config.num_cameras} (set model.turn_average: false)")
            log.info("LCPR: descriptors averaged over %d camera-slot turns as %s asks", TURNS, self.config.weights)
        #: camera images -> the network's input tensor, on the network's device
        if self.config.fast_decode and self.config.decode != "pil":
            log.warning("LCPR: model.fast_decode (PIL draft mode) applies to model.decode 'pil' only; decode %r "
                        "already decodes at a reduced size", self.config.decode)
        self.cameras = CameraPreprocessor(size=self.config.image_size, device=self.config.device,
                                          decoder=self.config.decode, draft=self.config.fast_decode)
        #: the backend takes the frames and makes their six turns itself, with the camera stem computed once per
        #: frame (TurnedNetwork: same arithmetic, fewer passes); on the CPU, for every path but int8, whose
        #: graph is quantised for one pass
        self.turns_in_network = (self.turn_average and torch.device(self.config.device).type == "cpu"
                                 and self.config.precision != "int8")
        network: LCPR | TurnedNetwork = TurnedNetwork(self.model).eval() if self.turns_in_network else self.model
        # a frame is one network pass, or one batch of the six turns: what a GPU path captures
        self.rows = TURNS if self.turn_average and not self.turns_in_network else 1
        self.choice: Choice = choose_backend(self.config, network, batch=self.rows)
        self.backend: Backend = self.choice.backend  # the path descriptors are computed on
        self._ranges_on_device = torch.device(self.config.device).type == "cuda"

    @functools.cached_property
    def weights_id(self) -> str:
        """What makes these descriptors (network, whitening, turn averaging), recorded in the maps they fill;
        hashed on first use (hashing every tensor takes a while at the released size), as only a detector's map
        needs it."""
        assert self.model is not None  # set in __post_init__
        tensors: dict[str, torch.Tensor | np.ndarray] = dict(self.model.state_dict())
        if self.whitening is not None:
            tensors |= {"whitening.mean": self.whitening.mean, "whitening.projection": self.whitening.projection}
        if self.turn_average:
            tensors["turn_average"] = np.array([TURNS], np.int64)
        return tensors_id(tensors)

    @property
    def path(self) -> str:
        """The precision in use: ``config.precision``, or what ``auto`` chose."""
        return self.backend.name

    @property
    def runtime(self) -> str:
        """What computes the descriptors: torch, onnxruntime or openvino."""
        return self.backend.runtime

    def inputs(
        self, images: Sequence[CameraInput | None], points: np.ndarray
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Preprocess one frame -> (1 x N x 3 x H x W, 1 x 1 x h x w) on the model's device.

        An image that cannot be decoded raises :class:`~lcpr_core.errors.InputShapeError`;
        :meth:`prepare` leaves its slot empty instead.
        """
        prepared = self.prepare(images, points, strict=True)
        return prepared.images, prepared.ranges

    def prepare(self, images: Sequence[CameraInput | None], points: np.ndarray, *,
                strict: bool = False) -> Prepared:
        """Preprocess one frame; a camera whose image is unusable is left empty (as a missing one) and named
        in ``failed`` with the reason, unless ``strict``."""
        # on the CPU the range image joins the camera images in the decode pool (after them)
        finish = self.cameras.start(images, strict=strict, beside=functools.partial(self.range_tensor, points))
        cams, failed, ranges = finish()
        assert ranges is not None
        return Prepared(cams.unsqueeze(0), ranges[None, None], failed)

    def prepare_many(self, frames: Sequence[tuple[Sequence[CameraInput | None], np.ndarray]]) -> PreparedBatch:
        """Several frames (images, points) preprocessed for one network call. On a GPU their JPEGs are decoded
        in one nvJPEG call and their clouds projected in one pass; elsewhere frame by frame (the CPU path
        already shares each frame out to its pool). Each frame's inputs equal :meth:`prepare`'s."""
        counts = {len(images) for images, _ in frames}
        if len(frames) < 2 or not self._ranges_on_device or len(counts) != 1:
            return prepare_each(self.prepare, frames)
        images, failed = self.cameras.many([images for images, _ in frames])
        return PreparedBatch(images, self.range_tensors([points for _, points in frames])[:, None], failed)

    def reserve(self, frames: int) -> None:
        """Make calls of ``frames`` frames fast: a GPU path captures a graph for that batch too (offline
        evaluation's ``--batch``); other paths need nothing."""
        reserve = getattr(self.backend, "reserve", None)
        if reserve is not None and frames > 1:
            reserve(frames * self.rows)

    def range_tensors(self, clouds: Sequence[np.ndarray]) -> torch.Tensor:
        """B clouds (N_b x >=3 points) -> B x h x w range images on the model's device: on the CPU by the numpy
        projection, on a GPU uploaded as one array and projected there in one pass."""
        preset = self.config.range_preset
        if not self._ranges_on_device:
            return torch.stack([torch.from_numpy(range_image(points, preset=preset)) for points in clouds])
        xyz = [np.asarray(points_array(points)[:, :3], dtype=np.float32) for points in clouds]
        flat = torch.from_numpy(np.concatenate(xyz)).to(self.config.device, non_blocking=True)
        return range_images_tensor(list(flat.split([len(p) for p in xyz])), preset=preset)

    def range_tensor(self, points: np.ndarray) -> torch.Tensor:
        """N x >=3 points -> h x w range image on the model's device (computed there on a GPU)."""
        return self.range_tensors([points])[0]

    def describe_tensors(self, images: torch.Tensor, ranges: torch.Tensor) -> np.ndarray:
        """Batched model inputs -> B x 256 float32 unit descriptors (whitened and averaged over the turns
        when the weights say so). A GPU out of memory raises :class:`~lcpr_core.errors.DeviceError`."""
        try:
            out = self.postprocess(self.network_outputs(images, ranges))
            return average_turns(out, images.shape[0]) if self.turn_average else out
        except torch.cuda.OutOfMemoryError as err:
            torch.cuda.empty_cache()
            raise DeviceError(f"{self.config.device} ran out of memory describing {images.shape[0]} frame(s); "
                              f"skipped ({str(err).splitlines()[0]})") from err

    def network_outputs(self, images: torch.Tensor, ranges: torch.Tensor) -> np.ndarray:
        """B frames' model inputs -> the network's raw unit descriptors: B x 256, or with turn averaging
        TURNS*B x 256, turn-major (as :func:`~lcpr_core.lcpr.turn_average.turned_batch`), before any
        post-processing."""
        if self.turn_average and not self.turns_in_network:
            return self.backend(*turned_batch(images, ranges))
        return self.backend(images, ranges)

    def postprocess(self, desc: np.ndarray) -> np.ndarray:
        """B x 256 network outputs -> what the weights file's whitening makes of them (unit descriptors)."""
        return desc if self.whitening is None else self.whitening.apply(desc)

    def describe(self, images: Sequence[CameraInput | None], points: np.ndarray) -> np.ndarray:
        """One frame (N camera images, None for a missing one; N x >=3 points) -> 256 float32."""
        return self.describe_tensors(*self.inputs(images, points))[0]
