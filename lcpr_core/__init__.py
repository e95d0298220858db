"""lcpr_core: the place-recognition core. One folder per method with the same rooms, ``lcpr/`` and
``vseq2pc/``, over a shared layer here (descriptor map, verification, metrics, ground truth, evaluation
protocol, the keyframe / exclusion / positive-pair rules, the map file format).

Pure Python and PyTorch: nothing here imports ROS.
"""
from .errors import CheckpointError, InputShapeError, LcprError, MapError, MapSchemaError, VerificationError
from .lcpr.checkpoint import init_from_imagenet, load_weights, read_state_dict, save_checkpoint
from .lcpr.describer import Describer, ModelConfig, build_model
from .lcpr.models import LCPR, LcprOutput
from .lcpr.preprocess import PRESETS, LidarPreset, camera_tensor, cameras_tensor, range_image
from .verification import GeometricVerifier, Verification, VerifierConfig
from .vseq2pc.models import DescriptorModel, SequenceModel
from .vseq2pc.preprocess import lidar_slices, structure_feature

__all__ = [
    "DescriptorModel", "SequenceModel", "lidar_slices", "structure_feature",
    "LCPR", "PRESETS", "CheckpointError", "Describer", "InputShapeError", "LcprError", "LcprOutput",
    "LidarPreset", "MapError", "MapSchemaError", "ModelConfig", "build_model", "camera_tensor",
    "cameras_tensor", "init_from_imagenet", "load_weights", "range_image", "read_state_dict",
    "save_checkpoint", "GeometricVerifier", "Verification", "VerifierConfig", "VerificationError",
]
