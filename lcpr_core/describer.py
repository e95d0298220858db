"""Building an LCPR from a config and turning raw sensor data into descriptors."""
from __future__ import annotations

import contextlib
import logging
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field

import numpy as np
import torch

from .checkpoint import init_from_imagenet, load_weights
from .models import LCPR
from .preprocess import LidarPreset, cameras_tensor, lidar_preset, range_image
from .preprocess.camera import CameraInput

log = logging.getLogger(__name__)

PRECISIONS = ("fp32", "bf16")


@dataclass(frozen=True)
class ModelConfig:
    """Which LCPR to build and how to run it."""

    weights: str = ""  # released checkpoint or state dict; "" = none
    imagenet: str = ""  # torchvision resnet18 state dict, used when weights is ""
    seed: int = 0  # random initialisation seed, used when both files are ""
    num_cameras: int = 6
    image_size: tuple[int, int] = (256, 704)
    lidar: str = "nuscenes_lidar_top"  # range-image preset (lcpr_core.preprocess.PRESETS)
    precision: str = "fp32"  # fp32 | bf16 (autocast)
    device: str = "cpu"
    threads: int = 0  # torch intra-op threads; 0 = leave torch's default
    fast_decode: bool = False  # JPEG draft-mode decoding of compressed images

    def __post_init__(self) -> None:
        if self.precision not in PRECISIONS:
            raise ValueError(f"precision={self.precision!r}; accepted: {', '.join(PRECISIONS)}")
        lidar_preset(self.lidar)  # raises with the accepted names
        if self.threads < 0:
            raise ValueError(f"threads={self.threads}; it must be >= 0 (0 = torch's default)")

    @property
    def range_preset(self) -> LidarPreset:
        return lidar_preset(self.lidar)


def build_model(config: ModelConfig = ModelConfig()) -> LCPR:
    """An LCPR in eval mode with weights from the config, saying in the log where they came from."""
    preset = config.range_preset
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(config.seed)
        model = LCPR(
            num_cameras=config.num_cameras,
            image_size=config.image_size,
            range_size=(preset.height, preset.width),
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
class Describer:
    """Raw cameras + cloud -> a 256-d unit descriptor, with the configured precision."""

    config: ModelConfig = field(default_factory=ModelConfig)
    model: LCPR | None = None

    def __post_init__(self) -> None:
        if self.config.threads:
            torch.set_num_threads(self.config.threads)
        if self.model is None:
            self.model = build_model(self.config)

    @contextlib.contextmanager
    def _precision(self) -> Iterator[None]:
        device_type = torch.device(self.config.device).type
        with torch.inference_mode(), torch.autocast(
            device_type, dtype=torch.bfloat16, enabled=self.config.precision == "bf16"
        ):
            yield

    def inputs(
        self, images: Sequence[CameraInput | None], points: np.ndarray
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Preprocess one frame -> (1 x N x 3 x H x W, 1 x 1 x h x w)."""
        cams = cameras_tensor(images, size=self.config.image_size, fast_decode=self.config.fast_decode)
        rng = torch.from_numpy(range_image(points, preset=self.config.range_preset))
        return cams.unsqueeze(0), rng.view(1, 1, *rng.shape)

    def describe_tensors(self, images: torch.Tensor, ranges: torch.Tensor) -> np.ndarray:
        """Batched model inputs -> B x 256 float32 descriptors."""
        assert self.model is not None
        device = self.config.device
        with self._precision():
            desc = self.model(images.to(device), ranges.to(device))
        return desc.float().cpu().numpy()

    def describe(self, images: Sequence[CameraInput | None], points: np.ndarray) -> np.ndarray:
        """One frame (N camera images, None for a missing one; N x >=3 points) -> 256 float32."""
        return self.describe_tensors(*self.inputs(images, points))[0]
