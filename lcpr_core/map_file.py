"""The map file format both methods use (LCPR's descriptor map, VSeq2PC's scan database).

One ``.npz`` archive, written atomically and read with ``allow_pickle=False``: a ``header`` member
holding a JSON object (``format``, ``schema_version`` and the fields each map adds) beside its
arrays. Reading checks, before numpy allocates anything, that no member claims more bytes than
it holds (a damaged or forged file is refused with its name, not a MemoryError), then that the
header names the expected format and a readable version. Every error is a :class:`MapError`
(:class:`MapSchemaError` for a version this code does not read) naming the file.
"""
from __future__ import annotations

import json
import os
import zipfile
from collections.abc import Iterable, Mapping, Sequence
from typing import Any

import numpy as np

from .atomic import atomic_path
from .errors import MapError, MapSchemaError

#: A member's data may claim at most this many times the archive's own size (deflate peaks near 1032:1).
_MAX_EXPANSION = 1100


def write_map_file(path: str | os.PathLike[str], header: Mapping[str, Any], arrays: Mapping[str, np.ndarray], *,
                   kind: str) -> None:
    """``header`` (JSON) and ``arrays`` into one .npz at ``path``, atomically: on failure the old file stays."""
    members: dict[str, Any] = {"header": np.array(json.dumps(dict(header))), **arrays}  # Any: savez's own flags
    try:
        with atomic_path(path) as tmp, open(tmp, "wb") as fh:
            np.savez(fh, **members)  # a file handle: numpy must not append ".npz"
    except OSError as err:
        raise MapError(f"cannot save the {kind} to {os.fspath(path)}: {err}") from err


def read_map_file(path: str | os.PathLike[str], *, kind: str, file_format: str, versions: Sequence[int],
                  required: Sequence[str], optional_group: Sequence[str] = (), optional: Sequence[str] = ()
                  ) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """(header, arrays) of a file :func:`write_map_file` wrote; ``optional_group``: all of them or none;
    ``optional``: each read when present (a member older versions lack; the caller checks the version)."""
    where = os.fspath(path)
    if not os.path.exists(where):
        raise MapError(f"{kind} {where} does not exist")
    try:
        _check_member_sizes(where, kind)
        npz = np.load(where, allow_pickle=False, mmap_mode=None)
    except MapError:
        raise
    except Exception as err:  # noqa: BLE001 - BadZipFile, OSError, ValueError (pickle, damaged .npy header), ...
        raise MapError(f"{kind} {where} cannot be read (.npz): {type(err).__name__}: {err}") from err
    if not isinstance(npz, np.lib.npyio.NpzFile):
        raise MapError(f"{kind} {where} is not an .npz archive (found a single .npy array)")
    try:
        with npz:
            missing = [key for key in ("header", *required) if key not in npz.files]
            if missing:
                raise MapError(f"{kind} {where} lacks {', '.join(missing)}; expected arrays header, "
                               f"{', '.join(required)}")
            present = [key for key in optional_group if key in npz.files]
            if present and len(present) != len(optional_group):
                raise MapError(f"{kind} {where} holds {', '.join(present)} but not all of {', '.join(optional_group)}")
            present += [key for key in optional if key in npz.files]
            arrays = {key: npz[key] for key in (*required, *present)}
            raw_header = npz["header"]
    except MapError:
        raise
    except Exception as err:  # noqa: BLE001 - zipfile/numpy raise many kinds on damaged archives
        raise MapError(f"{kind} {where} cannot be read (.npz): {type(err).__name__}: {err}") from err
    return _parse_header(raw_header, where, kind=kind, file_format=file_format, versions=versions), arrays


def check_header_fields(header: Mapping[str, Any], fields: Iterable[tuple[str, type]], *, kind: str,
                        where: str) -> None:
    """Each named header field must hold a value of its type."""
    for key, expected in fields:
        if not isinstance(header.get(key), expected):
            raise MapError(f"{kind} {where} header field {key!r} is {header.get(key)!r}; "
                           f"expected a {expected.__name__}")


def _parse_header(raw: np.ndarray, where: str, *, kind: str, file_format: str,
                  versions: Sequence[int]) -> dict[str, Any]:
    try:
        header = json.loads(str(raw.item()))
    except (ValueError, TypeError) as err:
        raise MapError(f"{kind} {where} has an unreadable header: {err}") from err
    if not isinstance(header, dict) or header.get("format") != file_format:
        raise MapError(f"{kind} {where} is not a {file_format} file")
    version = header.get("schema_version")
    if version not in versions:
        raise MapSchemaError(f"{kind} {where} has schema version {version!r}; this code reads version(s) "
                             f"{', '.join(map(str, versions))}")
    return header


def _check_member_sizes(where: str, kind: str) -> None:
    """Refuse an array whose .npy header claims more bytes than its member holds, or a member claiming
    more than the archive could hold, before numpy allocates it."""
    archive = os.path.getsize(where)
    with zipfile.ZipFile(where) as zf:
        for info in zf.infolist():
            if info.file_size > _MAX_EXPANSION * max(archive, 1):
                raise MapError(f"{kind} {where}: member {info.filename} claims {info.file_size} bytes, "
                               f"impossible in a {archive}-byte archive")
            with zf.open(info) as fh:
                version = np.lib.format.read_magic(fh)
                reader = (np.lib.format.read_array_header_1_0 if version == (1, 0)
                          else np.lib.format.read_array_header_2_0)
                shape, _, dtype = reader(fh)
                if dtype.hasobject:
                    raise MapError(f"{kind} {where}: member {info.filename} holds Python objects (pickle); refused")
                claimed = int(np.prod(shape, dtype=object)) * dtype.itemsize
                held = info.file_size - fh.tell()
                if claimed > held:
                    raise MapError(f"{kind} {where}: member {info.filename} claims shape {tuple(shape)} "
                                   f"{dtype} ({claimed} bytes) but holds {held}")
