"""Where the bundled trained weights live (small, trained on the synthetic city; see README)."""
from __future__ import annotations

import sys
from pathlib import Path

from .errors import InvalidValueError

BUNDLED_NAME = "lcpr_synth_narrow.pth"
#: match.max_distance for the bundled weights: their max-F1 threshold (0.701, online protocol, whitened
#: and turn-averaged descriptors) on the validation city grid seed 3 (neither a training city nor a
#: test city nor the demo's), from benchmarks/lcpr_finetune.py (step 7, the float16 file shipped) on the
#: corpus of benchmarks/lcpr_corpus.sh.
BUNDLED_MAX_DISTANCE = 0.70
#: VSeq2PC (sequence model, descriptor model) trained on synthetic KITTI-like drives whose depth is a
#: monocular depth network's (none beyond 25 m, a smooth 10 % error), from
#: benchmarks/vseq2pc_train_synth.sh (README, "VSeq2PC").
VSEQ2PC_BUNDLED_NAMES = ("vseq2pc_synth_sequence.pth", "vseq2pc_synth_descriptor.pth")
#: The same recipe (12 stage-2 epochs) on drives with exact depth to any range: for depth that is close to
#: exact (projected LiDAR, stereo, RGB-D). Each set trails the other on the other's depth (README, "VSeq2PC").
VSEQ2PC_EXACT_DEPTH_NAMES = ("vseq2pc_synth_exact_sequence.pth", "vseq2pc_synth_exact_descriptor.pth")
#: ``default_vseq2pc_weights(depth=...)``: which bundled VSeq2PC set suits which depth images.
VSEQ2PC_DEPTH_KINDS = {"network": VSEQ2PC_BUNDLED_NAMES, "exact": VSEQ2PC_EXACT_DEPTH_NAMES}
_FOLDERS = (
    Path(__file__).resolve().parents[1] / "weights",  # a source checkout
    Path(sys.prefix) / "share" / "lcpr_loop_closure" / "weights",  # pip / colcon data_files
)


def _bundled(name: str) -> str | None:
    for folder in _FOLDERS:
        if (folder / name).is_file():
            return str(folder / name)
    return None


def default_weights() -> str | None:
    """Path of the bundled trained LCPR checkpoint, or None when this install has none."""
    return _bundled(BUNDLED_NAME)


def default_vseq2pc_weights(*, depth: str = "network") -> tuple[str, str] | None:
    """Paths of the bundled trained VSeq2PC (sequence, descriptor) weights for ``depth`` images ("network":
    a monocular depth network's, the default; "exact"), or None when this install has none."""
    try:
        names = VSEQ2PC_DEPTH_KINDS[depth]
    except KeyError as err:
        raise InvalidValueError(f"depth {depth!r}: expected one of {', '.join(sorted(VSEQ2PC_DEPTH_KINDS))}") from err
    sequence, descriptor = (_bundled(name) for name in names)
    return (sequence, descriptor) if sequence and descriptor else None
