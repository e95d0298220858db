"""PCD files (Point Cloud Library, v0.7) -> numpy: ``ascii`` and ``binary`` data, any fields.

    arr = read_pcd("000123.pcd")          # structured array, one field per PCD field
    xyz = pcd_xyz(arr)                    # N x 3 float64

``binary_compressed`` (LZF) is refused with a message that says how to convert it.
"""
from __future__ import annotations

import os

import numpy as np

from .errors import DatasetError

_TYPES = {("F", 4): "<f4", ("F", 8): "<f8", ("I", 1): "i1", ("I", 2): "<i2", ("I", 4): "<i4", ("I", 8): "<i8",
          ("U", 1): "u1", ("U", 2): "<u2", ("U", 4): "<u4", ("U", 8): "<u8"}
_MAX_HEADER = 64 * 1024


def read_pcd(path: str | os.PathLike[str]) -> np.ndarray:
    """A PCD file -> (N,) structured array (fields named as in the file; COUNT > 1 -> subarray)."""
    where = os.fspath(path)
    try:
        with open(where, "rb") as fh:
            raw = fh.read()
    except OSError as err:
        raise DatasetError(f"cannot read PCD file {where}: {err}") from err
    header: dict[str, list[str]] = {}
    pos = 0
    while True:
        end = raw.find(b"\n", pos)
        if end < 0 or end > _MAX_HEADER:
            raise DatasetError(f"{where}: no DATA line in the first {_MAX_HEADER} bytes; not a PCD file")
        line = raw[pos:end].decode("ascii", errors="replace").strip()
        pos = end + 1
        if not line or line.startswith("#"):
            continue
        key, *values = line.split()
        header[key.upper()] = values
        if key.upper() == "DATA":
            break
    try:
        fields = header["FIELDS"]
        sizes = [int(v) for v in header["SIZE"]]
        types = [t.upper() for t in header["TYPE"]]
        counts = [int(v) for v in header.get("COUNT", ["1"] * len(fields))]
        points = int(header["POINTS"][0]) if "POINTS" in header else int(header["WIDTH"][0]) * int(header["HEIGHT"][0])
        data = header["DATA"][0].lower()
    except (KeyError, IndexError, ValueError) as err:
        raise DatasetError(f"{where}: PCD header lacks or garbles {err}; "
                           "expected FIELDS, SIZE, TYPE, POINTS, DATA") from err
    if not len(fields) == len(sizes) == len(types) == len(counts):
        raise DatasetError(f"{where}: FIELDS/SIZE/TYPE/COUNT have {len(fields)}/{len(sizes)}/{len(types)}/"
                           f"{len(counts)} entries; they must agree")
    if not fields or len(set(fields)) != len(fields):
        raise DatasetError(f"{where}: FIELDS {fields}; accepted: one or more distinct names")
    if points < 0 or min(counts) < 1:
        raise DatasetError(f"{where}: POINTS {points}, COUNT {counts}; accepted: POINTS >= 0 and every COUNT >= 1")
    formats = []
    for name, t, s, c in zip(fields, types, sizes, counts, strict=True):
        code = _TYPES.get((t, s))
        if code is None:
            raise DatasetError(f"{where}: field {name!r} has TYPE {t} SIZE {s}; accepted: F 4/8, I or U 1/2/4/8")
        formats.append((name, code) if c == 1 else (name, code, (c,)))
    dtype = np.dtype(formats)
    if data == "binary":
        need = points * dtype.itemsize
        if len(raw) - pos < need:
            raise DatasetError(f"{where}: {points} points of {dtype.itemsize} bytes need {need} bytes after the "
                               f"header; the file has {len(raw) - pos} (truncated?)")
        return np.frombuffer(raw, dtype=dtype, count=points, offset=pos).copy()
    if data == "ascii":
        try:
            numbers = np.array(raw[pos:].split(), dtype=np.float64)
        except ValueError as err:
            raise DatasetError(f"{where}: ascii DATA holds a value that is not a number: {err}") from err
        width = sum(counts)
        if numbers.size < points * width:
            raise DatasetError(f"{where}: {numbers.size} values for {points} points of {width}; truncated?")
        table = numbers[: points * width].reshape(points, width)
        out = np.empty(points, dtype)
        col = 0
        for name, c in zip(fields, counts, strict=True):
            out[name] = table[:, col] if c == 1 else table[:, col:col + c]
            col += c
        return out
    raise DatasetError(f"{where}: DATA {data!r} is not supported; accepted: ascii, binary "
                       "(convert binary_compressed files with pcl_convert_pcd_ascii_binary)")


def pcd_xyz(arr: np.ndarray) -> np.ndarray:
    """x, y, z columns of a :func:`read_pcd` array as N x 3 float64."""
    missing = [n for n in "xyz" if n not in (arr.dtype.names or ())]
    if missing:
        raise DatasetError(f"PCD fields {arr.dtype.names} lack {', '.join(missing)}; x, y and z are needed")
    return np.stack([arr[n].astype(np.float64) for n in "xyz"], axis=1)
