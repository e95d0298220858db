"""Where the reference material and real data live: ``../shared`` beside the checkout, or ``$LCPR_SHARED_DIR``.

One rule for every tool that reads ``shared/`` in place (the simulator's KITTI-00 route, the keyframe demo,
benchmarks, the test fixtures), so a checkout cloned anywhere finds it the same way.
"""
from __future__ import annotations

import os
from pathlib import Path

ENV_VAR = "LCPR_SHARED_DIR"


def shared_candidates() -> list[Path]:
    """Folders tried in order: $LCPR_SHARED_DIR, beside the checkout, beside and under the working directory."""
    found: list[Path] = []
    env = os.environ.get(ENV_VAR)
    if env:
        found.append(Path(env))
    checkout = Path(__file__).resolve().parents[1]
    found += [checkout.parent / "shared", Path.cwd().parent / "shared", Path.cwd() / "shared"]
    return found


def shared_dir(*, marker: str = "data") -> Path | None:
    """The first candidate that holds ``marker`` (a sub-folder such as ``data`` or ``reference``), else None."""
    for candidate in shared_candidates():
        if (candidate / marker).is_dir():
            return candidate
    return None


def shared_path(*parts: str) -> Path:
    """``shared/<parts>`` in the first candidate where it exists; else the path under the first candidate.

    The fallback keeps the caller's own error message (which names the path) meaningful when nothing is found.
    """
    candidates = shared_candidates()
    for candidate in candidates:
        path = candidate.joinpath(*parts)
        if path.exists():
            return path
    return candidates[0].joinpath(*parts)
