"""lcpr_core: the LCPR place-recognition core (models, preprocessing, descriptor map, metrics).

Pure Python and PyTorch: nothing here imports ROS.
"""
from .checkpoint import init_from_imagenet, load_weights, read_state_dict, save_checkpoint
from .describer import Describer, ModelConfig, build_model
from .errors import CheckpointError, InputShapeError, LcprError, MapError, MapSchemaError
from .models import LCPR, LcprOutput
from .preprocess import PRESETS, LidarPreset, camera_tensor, cameras_tensor, range_image

__all__ = [
    "LCPR", "PRESETS", "CheckpointError", "Describer", "InputShapeError", "LcprError", "LcprOutput",
    "LidarPreset", "MapError", "MapSchemaError", "ModelConfig", "build_model", "camera_tensor",
    "cameras_tensor", "init_from_imagenet", "load_weights", "range_image", "read_state_dict",
    "save_checkpoint",
]
