"""One source per setting: a config field's description, accepted values and run-time flag in its metadata.

A config dataclass declares each setting with :func:`param`::

    top_k: int = param(10, "candidates per query", lo=1, hi=1000, dynamic=True)

and its ``__post_init__`` calls :func:`check_fields`, which refuses a value outside the range or the
choices with the config's own error type, naming the field, the value and what is accepted. The
nodes' ROS parameters (descriptors, params files, the parameter reference pages: ``ros_common.params``)
read the same metadata, so a setting is described, bounded and documented in one place. Cross-field
rules (``min_range < max_range``) stay explicit code in the ``__post_init__``.
"""
from __future__ import annotations

import dataclasses
import math
import numbers
import typing
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, TypeVar

__all__ = ["ParamSpec", "check_fields", "param", "param_from", "spec_of"]

T = TypeVar("T")

#: the metadata key of a field's :class:`ParamSpec`
METADATA_KEY = "lcpr_param"


@dataclass(frozen=True)
class ParamSpec:
    """What a setting means and accepts.

    ``lo`` / ``hi`` bound a number (inclusive unless ``lo_open`` / ``hi_open``; an infinite bound
    only says the other side is open-ended); a ROS parameter gets the range ``lo .. hi`` when both are
    given. ``choices`` lists the accepted strings. ``dynamic``: the node may change it while it runs.
    """

    description: str
    lo: float | None = None
    hi: float | None = None
    choices: tuple[str, ...] = ()
    dynamic: bool = False
    lo_open: bool = False
    hi_open: bool = False

    def __post_init__(self) -> None:
        if self.choices and (self.lo is not None or self.hi is not None):
            raise TypeError(f"parameter {self.description!r}: give a range or choices, not both")
        if self.lo is not None and self.hi is not None and not self.lo <= self.hi:
            raise TypeError(f"parameter {self.description!r}: lo={self.lo} is above hi={self.hi}")

    @property
    def bounded(self) -> bool:
        """Whether a numeric range is given (at least one finite bound)."""
        return any(b is not None and math.isfinite(b) for b in (self.lo, self.hi))

    def accepts(self, value: Any, *, integer: bool = False) -> bool:
        """Whether ``value`` (one number or string; ``integer``: the field holds whole numbers) is accepted."""
        if self.choices:
            return value in self.choices
        if not self.bounded:
            return True
        if isinstance(value, bool) or not isinstance(value, numbers.Integral if integer else numbers.Real):
            return False
        number = float(value)
        if math.isnan(number):
            return False
        if self.lo is not None and (number <= self.lo if self.lo_open else number < self.lo):
            return False
        return not (self.hi is not None and (number >= self.hi if self.hi_open else number > self.hi))

    def accepted(self, name: str, *, integer: bool = False) -> str:
        """What is accepted, in words: "lcpr, fused", "an integer 1..64", "0 <= min_fitness <= 1", "voxel > 0"."""
        if self.choices:
            return ", ".join(self.choices)
        lo = self.lo if self.lo is not None and math.isfinite(self.lo) else None
        hi = self.hi if self.hi is not None and math.isfinite(self.hi) else None
        if integer:
            if lo is not None and hi is not None and not self.lo_open and not self.hi_open:
                return f"an integer {number_text(lo)}..{number_text(hi)}"
            parts = [f"{'>' if self.lo_open else '>='} {number_text(lo)}"] if lo is not None else []
            parts += [f"{'<' if self.hi_open else '<='} {number_text(hi)}"] if hi is not None else []
            return f"an integer {' and '.join(parts)}".rstrip()
        if lo is not None and hi is not None:
            return (f"{number_text(lo)} {'<' if self.lo_open else '<='} {name} "
                    f"{'<' if self.hi_open else '<='} {number_text(hi)}")
        if lo is not None:
            return f"{name} {'>' if self.lo_open else '>='} {number_text(lo)}"
        if hi is not None:
            return f"{name} {'<' if self.hi_open else '<='} {number_text(hi)}"
        return "any value"

    def range_text(self) -> str:
        """The range or the choices as the parameter pages write them ("0 .. 1", "> 0", "`a`, `b`"), or ""."""
        if self.choices:
            return ", ".join(f"`{choice}`" for choice in self.choices)
        if self.lo is not None and self.hi is not None and not self.lo_open and not self.hi_open:
            return f"{number_text(self.lo)} .. {number_text(self.hi)}"
        parts = []
        if self.lo is not None and math.isfinite(self.lo):
            parts.append(f"{'>' if self.lo_open else '>='} {number_text(self.lo)}")
        if self.hi is not None and math.isfinite(self.hi):
            parts.append(f"{'<' if self.hi_open else '<='} {number_text(self.hi)}")
        return ", ".join(parts)


def number_text(value: float) -> str:
    """A bound as written: 1000000 rather than 1e+06, 0 rather than 0.0, 0.5 as 0.5."""
    number = float(value)
    if math.isinf(number):
        return "inf" if number > 0 else "-inf"
    return str(int(number)) if number.is_integer() and abs(number) < 1e15 else repr(number)


def param(default: T, description: str, *, lo: float | None = None, hi: float | None = None,
          lo_open: bool = False, hi_open: bool = False, choices: Sequence[str] = (),
          dynamic: bool = False) -> T:
    """A dataclass field with ``default`` and its :class:`ParamSpec` (the default must be immutable)."""
    spec = ParamSpec(description, lo=lo, hi=hi, choices=tuple(choices), dynamic=dynamic, lo_open=lo_open,
                     hi_open=hi_open)
    return dataclasses.field(default=default, metadata={METADATA_KEY: spec})


def param_from(cls: type, name: str) -> Any:
    """A field with the default and the :class:`ParamSpec` of ``cls``'s field ``name``: a node setting that
    passes a core option through unchanged is described, bounded and defaulted by the core's field."""
    found = next((f for f in dataclasses.fields(cls) if f.name == name), None)
    if found is None or spec_of(found) is None or found.default is dataclasses.MISSING:
        raise TypeError(f"{cls.__name__}.{name} is no field declared with param()")
    return dataclasses.field(default=found.default, metadata=found.metadata)


def spec_of(field: dataclasses.Field[Any]) -> ParamSpec | None:
    """The :class:`ParamSpec` a field was declared with (:func:`param`), or None."""
    spec = field.metadata.get(METADATA_KEY)
    return spec if isinstance(spec, ParamSpec) else None


_CHECKED: dict[type, tuple[tuple[str, ParamSpec, bool, bool], ...]] = {}


def _checked_fields(cls: type) -> tuple[tuple[str, ParamSpec, bool, bool], ...]:
    """(name, spec, holds integers, is a tuple) of each field of ``cls`` with a range or choices (read once per
    class: configs are made often)."""
    if cls in _CHECKED:
        return _CHECKED[cls]
    hints = typing.get_type_hints(cls)
    out = []
    for field in dataclasses.fields(cls):
        spec = spec_of(field)
        if spec is None or not (spec.choices or spec.bounded):
            continue
        hint = hints[field.name]
        array = typing.get_origin(hint) is tuple
        element = next((a for a in typing.get_args(hint) if a is not Ellipsis), None) if array else hint
        out.append((field.name, spec, element is int, array))
    _CHECKED[cls] = tuple(out)
    return _CHECKED[cls]


def check_fields(config: Any, *, error: Callable[[str], Exception] = ValueError, prefix: str = "",
                 skip: Sequence[str] = ()) -> None:
    """Refuse the first field of the dataclass instance ``config`` whose value lies outside its
    :class:`ParamSpec`'s range or choices (every element, for a tuple), raising ``error(message)``: the
    package's own error type. The message names the field (``prefix`` + its name), the value and what is
    accepted. ``skip``: fields whose accepted values are no single range (the caller checks them itself;
    their spec still bounds the ROS parameter)."""
    for name, spec, integer, array in _checked_fields(type(config)):
        if name in skip:
            continue
        value = getattr(config, name)
        values = value if array and isinstance(value, (tuple, list)) else (value,)
        if not all(spec.accepts(v, integer=integer) for v in values):
            shown = list(value) if array and isinstance(value, (tuple, list)) else value
            raise error(f"{prefix}{name}={shown!r}; accepted: {spec.accepted(name, integer=integer)}")
