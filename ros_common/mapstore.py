"""The map file named by ``map.path`` (both nodes): load at start, refuse bad files, save between
items under the node's lock, answer ``~/save_map``."""
from __future__ import annotations

import os
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

from lcpr_core.errors import MapError

from .errors import MapLoadError

M = TypeVar("M")


def load_map_file(path: str, load: Callable[[Path], M]) -> M | None:
    """The map saved at ``path``, read by ``load`` (None when ``path`` is "" or absent). A file that
    cannot be used (``load`` raises MapError) raises MapLoadError and is not touched."""
    if not path:
        return None
    file = Path(path)
    if not file.exists():
        _check_writable(file)
        return None
    if not file.is_file():
        raise MapLoadError(f"map.path {file} exists but is not a file; give a .npz file path")
    try:
        return load(file)
    except MapError as err:
        raise MapLoadError(
            f"refusing to start: {err}. The file was left as it is; move it away, or point map.path elsewhere"
        ) from err


def _check_writable(file: Path) -> None:
    folder = file.parent
    while not folder.exists() and folder != folder.parent:
        folder = folder.parent
    if not os.access(folder, os.W_OK | os.X_OK):
        raise MapLoadError(f"map.path {file}: {folder} is not writable, so the map could never be saved")


def save_under_lock(lock: threading.Lock, path: str, save: Callable[[str], int], *, timeout: float, holder: str,
                    example: str) -> int:
    """``save(path)`` while holding ``lock`` (the node's worker holds it per item), waiting at most
    ``timeout`` s (-1: for ever); returns what ``save`` returns (the map's size)."""
    if not path:
        raise MapError(f"map.path is empty; set it (e.g. -p map.path:={example}) to save the map")
    if not lock.acquire(timeout=timeout):
        raise MapError(f"the {holder} stayed busy for {timeout} s; the map was not saved")
    try:
        return save(path)
    finally:
        lock.release()


def answer_save_request(response: Any, save: Callable[[], int], *, what: str, path: str,
                        log: Callable[[str], object]) -> Any:
    """Fill a std_srvs/Trigger response from ``save()``: success and "saved N <what> to <path>", or the error."""
    try:
        count = save()
    except MapError as err:
        response.success, response.message = False, str(err)
        return response
    response.success, response.message = True, f"saved {count} {what} to {path}"
    log(response.message)
    return response
