"""PointField layouts <-> numpy structured dtypes (the layout half of the PointCloud2 conversion)."""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np

from .errors import PointFieldDatatypeError, PointFieldLayoutError

#: sensor_msgs/PointField datatype constants and their numpy types.
POINTFIELD_DTYPES: dict[int, np.dtype] = {
    1: np.dtype(np.int8), 2: np.dtype(np.uint8), 3: np.dtype(np.int16), 4: np.dtype(np.uint16),
    5: np.dtype(np.int32), 6: np.dtype(np.uint32), 7: np.dtype(np.float32), 8: np.dtype(np.float64),
}
POINTFIELD_NAMES: dict[int, str] = {
    1: "INT8", 2: "UINT8", 3: "INT16", 4: "UINT16", 5: "INT32", 6: "UINT32", 7: "FLOAT32", 8: "FLOAT64",
}
_DATATYPE_OF = {dtype: code for code, dtype in POINTFIELD_DTYPES.items()}
_ACCEPTED = ", ".join(f"{code} ({name})" for code, name in POINTFIELD_NAMES.items())
_ACCEPTED_DTYPES = ", ".join(str(d) for d in POINTFIELD_DTYPES.values())
_MAX_POINT_STEP = 2**31 - 1  # numpy's largest itemsize (a C int)


@dataclass(frozen=True)
class FieldSpec:
    """One PointField, independent of the message library it came from."""

    name: str
    offset: int
    datatype: int
    count: int

    def values(self) -> dict[str, Any]:
        return {"name": self.name, "offset": self.offset, "datatype": self.datatype, "count": self.count}


def read_field_specs(fields: Sequence[Any]) -> list[FieldSpec]:
    """PointField messages (rosbags or rclpy) -> :class:`FieldSpec` list, in message order."""
    return [FieldSpec(str(f.name), int(f.offset), int(f.datatype), int(f.count)) for f in fields]


def fields_to_dtype(specs: Sequence[FieldSpec], *, point_step: int, is_bigendian: bool) -> np.dtype:
    """The structured dtype of one point as stored in the message (byte order included).

    Raises :class:`PointFieldDatatypeError` for an unknown datatype and
    :class:`PointFieldLayoutError` for a repeated or empty name, a count below 1, a
    field reaching past ``point_step`` or two fields sharing bytes.
    """
    if not 0 <= point_step <= _MAX_POINT_STEP:
        raise PointFieldLayoutError(f"point_step {point_step} is outside the accepted range 0..{_MAX_POINT_STEP} "
                                    "(the largest item numpy holds)")
    order: Literal[">", "<"] = ">" if is_bigendian else "<"
    names: list[str] = []
    formats: list[Any] = []
    offsets: list[int] = []
    spans: list[tuple[int, int, str]] = []
    for spec in specs:
        if spec.datatype not in POINTFIELD_DTYPES:
            raise PointFieldDatatypeError(
                f"field {spec.name!r} has datatype {spec.datatype}; accepted datatypes: {_ACCEPTED}"
            )
        if not spec.name:
            raise PointFieldLayoutError(f"a field at offset {spec.offset} has an empty name; every field needs a name")
        if spec.name in names:
            raise PointFieldLayoutError(f"field name {spec.name!r} appears twice; names must be unique")
        if spec.count < 1:
            raise PointFieldLayoutError(f"field {spec.name!r} has count {spec.count}; accepted: count >= 1")
        base = POINTFIELD_DTYPES[spec.datatype].newbyteorder(order)
        end = spec.offset + base.itemsize * spec.count
        if spec.offset < 0 or end > point_step:
            raise PointFieldLayoutError(
                f"field {spec.name!r} occupies bytes [{spec.offset}, {end}) but point_step is {point_step}"
            )
        names.append(spec.name)
        formats.append(base if spec.count == 1 else (base, (spec.count,)))
        offsets.append(spec.offset)
        spans.append((spec.offset, end, spec.name))
    spans.sort()
    for (_s0, e0, n0), (s1, _e1, n1) in zip(spans, spans[1:], strict=False):
        if s1 < e0:
            raise PointFieldLayoutError(f"fields {n0!r} and {n1!r} overlap: {n1!r} starts at byte {s1}, "
                                        f"{n0!r} ends at {e0}")
    return np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": point_step})


def native_dtype(dtype: np.dtype) -> np.dtype:
    """The same layout (names, offsets, itemsize) with every field in native byte order."""
    formats: list[Any] = []
    # dtype.fields is None only for an unstructured dtype, whose names are None too
    fields: Mapping[str, tuple[Any, ...]] = dtype.fields or {}
    for name in dtype.names or ():
        fdt = fields[name][0]
        if fdt.shape:
            formats.append((fdt.base.newbyteorder("="), fdt.shape))
        else:
            formats.append(fdt.newbyteorder("="))
    return np.dtype({
        "names": list(dtype.names or ()),
        "formats": formats,
        "offsets": [fields[n][1] for n in dtype.names or ()],
        "itemsize": dtype.itemsize,
    })


def dtype_to_field_specs(dtype: np.dtype) -> list[FieldSpec]:
    """A structured dtype -> PointField specs, checking every field has a ROS datatype."""
    if dtype.names is None or not dtype.names:
        raise PointFieldLayoutError(f"a point cloud array needs a structured dtype with named fields, got {dtype}")
    fields = dtype.fields
    assert fields is not None  # a dtype with names has fields
    specs = []
    for name in dtype.names:
        fdt, offset = fields[name][:2]
        base, shape = (fdt.base, fdt.shape) if fdt.shape else (fdt, ())
        if len(shape) > 1:
            raise PointFieldLayoutError(
                f"field {name!r} has shape {shape}; PointFields hold scalars or 1-D runs (count), not {len(shape)}-D"
            )
        if base.names is not None:
            raise PointFieldDatatypeError(f"field {name!r} is itself structured ({base}); accepted: {_ACCEPTED_DTYPES}")
        code = _DATATYPE_OF.get(base.newbyteorder("="))
        if code is None:
            raise PointFieldDatatypeError(f"field {name!r} has dtype {base}, which no PointField datatype holds; "
                                          f"accepted: {_ACCEPTED_DTYPES}")
        count = shape[0] if shape else 1
        if count < 1:
            raise PointFieldLayoutError(f"field {name!r} has count {count}; accepted: count >= 1")
        specs.append(FieldSpec(str(name), int(offset), code, int(count)))
    return specs
