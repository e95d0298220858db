"""Where the bundled trained weights live (small, trained on the synthetic city; see README)."""
from __future__ import annotations

import sys
from pathlib import Path

BUNDLED_NAME = "lcpr_synth_narrow.pth"
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
