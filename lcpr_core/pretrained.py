"""Where the bundled trained weights live (small, trained on the synthetic city; see README)."""
from __future__ import annotations

import sys
from pathlib import Path

BUNDLED_NAME = "lcpr_synth_narrow.pth"
#: match.max_distance for the bundled weights: their max-F1 threshold (0.780, online protocol, whitened
#: and turn-averaged descriptors) on the validation city grid seed 3 (neither a training city nor a
#: test city nor the demo's), from benchmarks/lcpr_turn_average.py on the corpus of
#: benchmarks/lcpr_corpus.sh (0.777 with whitening alone, benchmarks/lcpr_whitening.py).
BUNDLED_MAX_DISTANCE = 0.78
#: VSeq2PC (sequence model, descriptor model) trained on synthetic KITTI-like drives, from
#: benchmarks/vseq2pc_train_synth.sh (README, "VSeq2PC").
VSEQ2PC_BUNDLED_NAMES = ("vseq2pc_synth_sequence.pth", "vseq2pc_synth_descriptor.pth")
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


def default_vseq2pc_weights() -> tuple[str, str] | None:
    """Paths of the bundled trained VSeq2PC (sequence, descriptor) weights, or None when this install has none."""
    sequence, descriptor = (_bundled(name) for name in VSEQ2PC_BUNDLED_NAMES)
    return (sequence, descriptor) if sequence and descriptor else None
