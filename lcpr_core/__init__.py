"""lcpr_core: the place-recognition core. One folder per method with the same rooms, ``lcpr/`` and
``vseq2pc/``, over a shared layer here (descriptor map, verification, metrics, ground truth, evaluation
protocol, the keyframe / exclusion / positive-pair rules, the map file format).

Pure Python and PyTorch: nothing here imports ROS. The names below load on first use, so a process that
needs only a light submodule (a verification worker: numpy and small_gicp) does not import PyTorch.
"""
from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from .errors import CheckpointError, InputShapeError, LcprError, MapError, MapSchemaError, VerificationError
    from .lcpr.checkpoint import init_from_imagenet, load_weights, save_checkpoint
    from .lcpr.describer import Describer, ModelConfig, build_model
    from .lcpr.models import LCPR, LcprOutput
    from .lcpr.preprocess import PRESETS, LidarPreset, camera_tensor, cameras_tensor, range_image
    from .torch_files import read_state_dict
    from .verification import GeometricVerifier, Verification, VerifierConfig
    from .vseq2pc.models import DescriptorModel, SequenceModel
    from .vseq2pc.preprocess import lidar_slices, structure_feature

_HOMES: dict[str, tuple[str, ...]] = {  # submodule: the names it gives the package
    ".errors": ("CheckpointError", "InputShapeError", "LcprError", "MapError", "MapSchemaError",
                "VerificationError"),
    ".lcpr.checkpoint": ("init_from_imagenet", "load_weights", "save_checkpoint"),
    ".torch_files": ("read_state_dict",),
    ".lcpr.describer": ("Describer", "ModelConfig", "build_model"),
    ".lcpr.models": ("LCPR", "LcprOutput"),
    ".lcpr.preprocess": ("PRESETS", "LidarPreset", "camera_tensor", "cameras_tensor", "range_image"),
    ".verification": ("GeometricVerifier", "Verification", "VerifierConfig"),
    ".vseq2pc.models": ("DescriptorModel", "SequenceModel"),
    ".vseq2pc.preprocess": ("lidar_slices", "structure_feature"),
}
_HOME_OF = {name: module for module, names in _HOMES.items() for name in names}

__all__ = [
    "DescriptorModel", "SequenceModel", "lidar_slices", "structure_feature",
    "LCPR", "PRESETS", "CheckpointError", "Describer", "InputShapeError", "LcprError", "LcprOutput",
    "LidarPreset", "MapError", "MapSchemaError", "ModelConfig", "build_model", "camera_tensor",
    "cameras_tensor", "init_from_imagenet", "load_weights", "range_image", "read_state_dict",
    "save_checkpoint", "GeometricVerifier", "Verification", "VerifierConfig", "VerificationError",
]


def __getattr__(name: str) -> Any:
    home = _HOME_OF.get(name)
    if home is None:  # not one of ours: Python then looks for a submodule of that name
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(home, __name__), name)
    globals()[name] = value  # later lookups skip this function
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
