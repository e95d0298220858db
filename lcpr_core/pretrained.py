"""Where the bundled trained weights live (small, trained on the synthetic city; see README)."""
from __future__ import annotations

import sys
from pathlib import Path

BUNDLED_NAME = "lcpr_synth_narrow.pth"
#: match.max_distance for the bundled weights: their max-F1 threshold (0.386) on a validation
#: city of its own (seed 3; neither a training city nor the demo's), from step 5 of
#: benchmarks/lcpr_train_synth.sh.
BUNDLED_MAX_DISTANCE = 0.39
_CANDIDATES = (
    Path(__file__).resolve().parents[1] / "weights" / BUNDLED_NAME,  # a source checkout
    Path(sys.prefix) / "share" / "lcpr_loop_closure" / "weights" / BUNDLED_NAME,  # pip / colcon data_files
)


def default_weights() -> str | None:
    """Path of the bundled trained LCPR checkpoint, or None when this install has none."""
    for path in _CANDIDATES:
        if path.is_file():
            return str(path)
    return None
