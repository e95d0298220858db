"""LCPR: six camera images and one LiDAR range image -> a 256-d, yaw-invariant place descriptor.

    from lcpr_core.lcpr import Describer, ModelConfig
    from lcpr_core.detector import LoopDetector, DetectorConfig, Frame   # also lcpr_core.detector
    describer = Describer(ModelConfig(weights="lcpr.pth"))        # the authors' files load too
    descriptor = describer.describe(images, points)               # six H x W x 3 uint8, N x 3 cloud
    detector = LoopDetector(DetectorConfig())                     # what lcpr_node runs
    result = detector.process(Frame(stamp=t, images=images, points=points, pose=T))

Rooms (the same as VSeq2PC's, ``lcpr_core.vseq2pc``): models/ (the network), preprocess/ (range
image, camera tensors, the camera-slot turn, dataset files), checkpoint (released files in, ours
out), describer (config -> model, raw frame -> descriptor), whitening and turn_average (the
descriptor post-processing a checkpoint may carry), runtime/ (torch, exported-graph and
int8 inference paths), detector (LoopDetector: what lcpr_node and lcpr_eval drive), training/.
Commands (lcpr_train, lcpr_eval, lcpr_keyframe_demo) live in lcpr_offline. The shared layer (descriptor
map, verification, metrics, ground truth, evaluation protocol, keyframe/exclusion/positive rules, map
file) is one level up, in lcpr_core.
"""
from ..torch_files import read_state_dict
from .checkpoint import init_from_imagenet, load_weights, save_checkpoint
from .describer import Describer, ModelConfig, build_model
from .models import LCPR, LcprOutput

__all__ = [
    "LCPR", "Describer", "LcprOutput", "ModelConfig", "build_model",
    "init_from_imagenet", "load_weights", "read_state_dict", "save_checkpoint",
]
