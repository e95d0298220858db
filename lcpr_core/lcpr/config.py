"""Which LCPR to build and how to run it: :class:`ModelConfig` and the values its fields accept.

Its own module so that what reads a configuration (the describer, the inference paths in
:mod:`lcpr_core.lcpr.runtime`, the ROS parameters) needs neither the other nor torch's models.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

from ..errors import InvalidValueError
from .preprocess import CUSTOM, LidarGeometry, LidarPreset, lidar_preset
from .preprocess.cameras import DECODERS

__all__ = ["CHECKPOINT_FIELDS", "PRECISIONS", "RUNTIMES", "ModelConfig"]

#: fp32 / bf16: torch (bf16 = autocast; fp32 on a GPU with TF32 off: the exact network); tf32: torch on a GPU
#: with TF32 convolutions and matrix products; onnx: the exported graph in ONNX Runtime (exact); int8: its
#: statically quantised graph (made by lcpr_quantize); auto: the fastest exact one here (lcpr_core.lcpr.runtime).
PRECISIONS = ("fp32", "tf32", "bf16", "onnx", "int8", "auto")
#: What runs an exported graph (onnx, int8): auto = for int8 the faster of the two here, for onnx ONNX Runtime.
RUNTIMES = ("auto", "onnxruntime", "openvino")
#: ModelConfig fields a checkpoint's 'config' entry fixes (the architecture and its input sizes).
CHECKPOINT_FIELDS = ("width", "num_cameras", "image_size", "range_size", "lidar")


@dataclass(frozen=True)
class ModelConfig:
    """Which LCPR to build and how to run it."""

    weights: str = ""  # checkpoint or state dict path, "bundled" (the trained weights shipped), "seeded" or "" = none
    imagenet: str = ""  # torchvision resnet18 state dict, used when weights is ""
    seed: int = 0  # random initialisation seed, used when both files are ""
    num_cameras: int = 6
    image_size: tuple[int, int] = (256, 704)
    lidar: str = "nuscenes_lidar_top"  # range-image preset (preprocess.PRESETS), or "custom": lidar_geometry
    lidar_geometry: LidarGeometry = field(default_factory=LidarGeometry)
    range_size: tuple[int, int] = (0, 0)  # range image (height, width) replacing the preset's; (0, 0) = the preset's
    width: float = 1.0  # channel multiplier (1.0 = released network; trained narrow models: 0.25-0.5)
    precision: str = "auto"  # auto | fp32 | bf16 (autocast) | onnx | int8 (see PRECISIONS)
    runtime: str = "auto"  # auto | onnxruntime | openvino: what runs the exported graph (see RUNTIMES)
    device: str = "cpu"
    cuda_graph: bool = True  # on a GPU, replay each precision's forward pass from a CUDA graph (runtime.cuda)
    threads: int = 0  # torch intra-op threads; 0 = leave torch's default
    decode: str = "auto"  # camera decoding: auto | turbo | nvjpeg | pil (see preprocess.cameras.DECODERS)
    fast_decode: bool = False  # with decode "pil": JPEG draft-mode decoding of compressed images
    whitening: bool = True  # apply the weights file's descriptor whitening, when it has one (.whitening)
    turn_average: bool = True  # average over the six camera-slot turns when the weights file asks (.turn_average)

    def __post_init__(self) -> None:
        if self.precision not in PRECISIONS:
            raise InvalidValueError(f"precision={self.precision!r}; accepted: {', '.join(PRECISIONS)}")
        if self.decode not in DECODERS:
            raise InvalidValueError(f"decode={self.decode!r}; accepted: {', '.join(DECODERS)}")
        if self.runtime not in RUNTIMES:
            raise InvalidValueError(f"runtime={self.runtime!r}; accepted: {', '.join(RUNTIMES)}")
        if self.lidar == CUSTOM:
            if min(self.range_size) < 1:
                raise InvalidValueError(
                    f"lidar='custom' needs range_size=(rows, columns); got {tuple(self.range_size)}")
        else:
            lidar_preset(self.lidar)  # raises with the accepted names
        if self.threads < 0:
            raise InvalidValueError(f"threads={self.threads}; it must be >= 0 (0 = torch's default)")
        if not 0 < self.width <= 4:
            raise InvalidValueError(f"width={self.width}; accepted: a channel multiplier in (0, 4], e.g. 1.0 or 0.25")
        if len(self.range_size) != 2 or (tuple(self.range_size) != (0, 0) and min(self.range_size) < 1):
            raise InvalidValueError(f"range_size={self.range_size}; accepted: (0, 0) (the preset's) or (height, width)")

    @property
    def range_preset(self) -> LidarPreset:
        if self.lidar == CUSTOM:
            return self.lidar_geometry.preset(*self.range_size)
        preset = lidar_preset(self.lidar)
        if tuple(self.range_size) == (0, 0):
            return preset
        return dataclasses.replace(preset, height=int(self.range_size[0]), width=int(self.range_size[1]))
