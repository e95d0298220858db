"""Atomic file writes: a reader sees the old file or the new one, never half of either."""
from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike[str]) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; on success it replaces ``path`` atomically.

    The temporary file keeps ``path``'s suffix, so libraries that choose a format by
    suffix (numpy, matplotlib) write the right one. If the body raises, the
    temporary file is removed and ``path`` is left as it was.
    """
    target = Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp_name = tempfile.mkstemp(prefix=f".{target.name}.", suffix=f".tmp{target.suffix}", dir=target.parent)
    os.close(fd)
    tmp = Path(tmp_name)
    try:
        yield tmp
        with open(tmp, "rb+") as fh:
            os.fsync(fh.fileno())
        os.replace(tmp, target)
    finally:
        tmp.unlink(missing_ok=True)


def write_atomic(path: str | os.PathLike[str], write: Callable[[Path], object]) -> None:
    """Call ``write(tmp_path)`` and move the result onto ``path`` atomically."""
    with atomic_path(path) as tmp:
        write(tmp)


def write_bytes_atomic(path: str | os.PathLike[str], data: bytes) -> None:
    write_atomic(path, lambda tmp: tmp.write_bytes(data))


def save_torch(obj: object, path: str | os.PathLike[str], *, shared: bool = False) -> int:
    """``torch.save(obj)`` onto ``path`` atomically; returns the file's size in bytes.

    Saved through an open file, so the archive's records are named ``archive/...`` and not after
    the temporary file. ``shared``: readable by all (a file to ship; temporary files start private).
    """
    import torch  # here: the other writers of this module need no torch

    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            torch.save(obj, fh)
        if shared:
            tmp.chmod(0o644)
    return Path(path).stat().st_size


def save_figure(fig: Any, path: str | os.PathLike[str], *, dpi: float | None = None) -> None:
    """Lay out a matplotlib figure and write it as a PNG, atomically (every plot of the package)."""
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=dpi)
