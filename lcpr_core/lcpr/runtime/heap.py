"""Keep a long-running process's heap from growing when ONNX Runtime runs beside verification.

glibc raises its mmap threshold whenever a large mmapped block is freed, so after the first
frames every per-frame buffer up to 32 MiB comes from the heap instead. In the node, ONNX
Runtime's buffers and geometric verification's clouds and trees (long-lived prepared clouds
among them) then interleave on that heap, and its free holes are never returned: at the
released size the node's RSS grew by 580 MB in 3 minutes with ``model.precision: onnx``
(``benchmarks/tools/node_soak.py``; docs/studies/inference_paths.md). Fixing the threshold (which also stops
its adjustment) sends those buffers to mmap, where freeing returns them to the system.

:func:`fix_mmap_threshold` does that once per process, only with glibc, and never where the
user set ``MALLOC_MMAP_THRESHOLD_`` (glibc's own variable) themselves.
"""
from __future__ import annotations

import ctypes
import ctypes.util
import logging
import os
import threading
from collections.abc import Mapping

from ...errors import RuntimeSetupError

log = logging.getLogger(__name__)

#: Blocks at least this large are mmapped (bytes). Chosen with node_soak at the released size
#: (docs/studies/inference_paths.md): 4 MiB let RSS keep growing, 128 KiB cost 20 % of the model time, 1 MiB neither.
MMAP_THRESHOLD = 1024 * 1024
USER_VARIABLE = "MALLOC_MMAP_THRESHOLD_"
_M_MMAP_THRESHOLD = -3  # glibc <malloc.h>
_lock = threading.Lock()
_done: str | None = None  # what the first call decided, for later calls and the log


def fix_mmap_threshold(threshold: int = MMAP_THRESHOLD, *, environ: Mapping[str, str] | None = None) -> str:
    """Fix glibc's mmap threshold at ``threshold`` bytes, once per process; returns what was done.

    One of ``"fixed at N bytes"``, ``"left to MALLOC_MMAP_THRESHOLD_=V"`` (the user's choice) or
    ``"not glibc"`` (musl, macOS, Windows: nothing to do). Later calls return the first answer.
    """
    global _done
    if threshold <= 0:
        raise RuntimeSetupError(f"mmap threshold {threshold}; it must be > 0 bytes")
    environ = os.environ if environ is None else environ
    with _lock:
        if _done is not None:
            return _done
        if environ.get(USER_VARIABLE):
            _done = f"left to {USER_VARIABLE}={environ[USER_VARIABLE]}"
        else:
            _done = _mallopt(threshold)
        log.info("glibc mmap threshold %s (keeps the heap flat beside ONNX Runtime; %s overrides)", _done,
                 USER_VARIABLE)
        return _done


def _mallopt(threshold: int) -> str:
    name = ctypes.util.find_library("c")
    try:
        libc = ctypes.CDLL(name)
        mallopt = libc.mallopt
        libc.gnu_get_libc_version  # noqa: B018 (raises AttributeError outside glibc)
    except (OSError, AttributeError, TypeError):
        return "not glibc"
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    if mallopt(_M_MMAP_THRESHOLD, int(threshold)) != 1:
        return f"refused by mallopt ({threshold} bytes)"
    return f"fixed at {threshold} bytes"
