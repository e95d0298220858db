"""Which LCPR to build and how to run it: :class:`ModelConfig` and the values its fields accept.

Its own module so that what reads a configuration (the describer, the inference paths in
:mod:`lcpr_core.lcpr.runtime`, the ROS parameters) needs neither the other nor torch's models.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

from lcpr_common.params import check_fields, param

from ..errors import InvalidValueError
from .preprocess import CUSTOM, PRESETS, LidarGeometry, LidarPreset, lidar_preset
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

    weights: str = param("", "LCPR weights: bundled (the trained weights shipped, synthetic cities), a checkpoint "
                             "file (the authors' released one for a real vehicle), or seeded (random, testing only)")
    imagenet: str = param("", "torchvision resnet18 state dict for the ResNet blocks, used when model.weights "
                              "is empty")
    seed: int = param(0, "seed of the random initialisation, used when both weight files are empty", lo=0,
                      hi=2**31 - 1)
    num_cameras: int = param(6, "cameras in the panorama; must equal the number of camera_topics", lo=1, hi=64)
    image_size: tuple[int, int] = param((256, 704), "[height, width] each camera image is resized to; multiples "
                                                    "of 32 (released: 256, 704)")
    lidar: str = param("nuscenes_lidar_top", "range-image preset of the LiDAR, or custom (model.lidar_geometry.*, "
                                             "rows and columns from model.range_size)",
                       choices=(*sorted(PRESETS), CUSTOM))
    lidar_geometry: LidarGeometry = field(default_factory=LidarGeometry)
    range_size: tuple[int, int] = param((0, 0), "[height, width] of the range image, multiples of 8; [0, 0] = the "
                                                "preset's")
    width: float = param(1.0, "channel multiplier of the network (1.0 = released; must match the weights)", lo=0.0,
                         hi=4.0, lo_open=True)
    precision: str = param("auto", "inference path: auto (CPU: the fastest exact one, measured at start; GPU: the "
                                   "fastest of fp32 / tf32 / bf16 within cosine 0.9999 of exact fp32), fp32 (on a "
                                   "GPU with TF32 off: the exact network), tf32 (GPU), bf16 (autocast), onnx (ONNX "
                                   "Runtime, exact), int8 (needs lcpr_quantize)", choices=PRECISIONS)
    runtime: str = param("auto", "what runs the exported graph (precision onnx / int8): auto (int8: the faster of "
                                 "the two, measured at start; onnx: onnxruntime), onnxruntime, openvino",
                         choices=RUNTIMES)
    device: str = param("cpu", "torch device, e.g. cpu or cuda:0")
    cuda_graph: bool = param(True, "on a GPU, replay the network from a CUDA graph of one frame (or its six "
                                   "turns); false = eager passes")
    threads: int = param(0, "torch intra-op threads; 0 = torch's default", lo=0, hi=1024)
    decode: str = param("auto", "camera decoding: auto (nvjpeg on a GPU where torchvision imports, else turbo), "
                                "turbo (libjpeg-turbo at a reduced size, antialiased resize; CPU), nvjpeg (GPU), pil "
                                "(the released pipeline, slowest)", choices=DECODERS)
    fast_decode: bool = param(False, "with decode pil: JPEG draft-mode decoding (faster, slightly different "
                                     "pixels)")
    whitening: bool = param(True, "apply the descriptor whitening stored in the weights file, when it has one "
                                  "(the bundled weights do; lcpr_train --whiten)")
    turn_average: bool = param(True, "average each descriptor over the six camera-slot turns (six network passes) "
                                     "when the weights file asks for it (the bundled weights do)")

    def __post_init__(self) -> None:
        if self.lidar == CUSTOM:
            if min(self.range_size) < 1:
                raise InvalidValueError(
                    f"lidar='custom' needs range_size=(rows, columns); got {tuple(self.range_size)}")
        else:
            lidar_preset(self.lidar)  # raises with the accepted names
        check_fields(self, error=InvalidValueError)
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
