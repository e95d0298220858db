"""A config field's metadata (lcpr_common.params): one source for its description, range and checks."""
from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from lcpr_common.params import ParamSpec, check_fields, param, spec_of


class Refused(ValueError):
    """Stands for a package's own error type."""


@dataclasses.dataclass(frozen=True)
class Example:
    count: int = param(3, "items", lo=1, hi=10, dynamic=True)
    share: float = param(0.5, "a share", lo=0.0, hi=1.0)
    size: float = param(2.0, "m", lo=0.0, lo_open=True)
    mode: str = param("a", "how", choices=("a", "b"))
    offsets: tuple[float, ...] = param((1.0, 2.0), "m", lo=0.0, hi=5.0)
    loose: float = param(-1.0, "the caller checks it", lo=-1.0, hi=2.0)
    free: str = param("", "anything")

    def __post_init__(self) -> None:
        check_fields(self, error=Refused, prefix="group.", skip=("loose",))


def test_a_field_keeps_its_default_and_carries_its_spec() -> None:
    fields = {f.name: f for f in dataclasses.fields(Example)}
    assert Example().count == 3 and Example().offsets == (1.0, 2.0)
    assert spec_of(fields["count"]) == ParamSpec("items", lo=1, hi=10, dynamic=True)
    mode = spec_of(fields["mode"])
    assert mode is not None and mode.choices == ("a", "b")


@pytest.mark.parametrize(("changes", "says"), [
    ({"count": 11}, "group.count=11; accepted: an integer 1..10"),
    ({"count": 2.0}, "group.count=2.0; accepted: an integer 1..10"),
    ({"count": True}, "group.count=True; accepted: an integer 1..10"),
    ({"share": 1.5}, "group.share=1.5; accepted: 0 <= share <= 1"),
    ({"share": math.nan}, "group.share=nan; accepted: 0 <= share <= 1"),
    ({"size": 0.0}, "group.size=0.0; accepted: size > 0"),
    ({"mode": "c"}, "group.mode='c'; accepted: a, b"),
    ({"offsets": (1.0, 6.0)}, "group.offsets=[1.0, 6.0]; accepted: 0 <= offsets <= 5"),
], ids=["above", "float for an integer", "bool for an integer", "share", "nan", "open bound", "choice", "element"])
def test_a_value_outside_its_field_spec_is_refused_naming_the_field_the_value_and_what_is_accepted(
        changes: dict, says: str) -> None:
    with pytest.raises(Refused) as caught:
        Example(**changes)
    assert str(caught.value) == says


def test_values_inside_the_spec_are_accepted_numpy_numbers_included() -> None:
    config = Example(count=np.int64(10), share=np.float32(1.0),  # type: ignore[arg-type]
                     size=math.inf, mode="b", offsets=(0.0, 5.0))
    assert config.count == 10 and config.mode == "b"


def test_a_skipped_field_is_left_to_its_config() -> None:
    assert Example(loose=7.0).loose == 7.0


def test_the_page_and_message_texts_of_a_range() -> None:
    assert ParamSpec("x", lo=0, hi=4).range_text() == "0 .. 4"
    assert ParamSpec("x", lo=0, hi=4, lo_open=True).range_text() == "> 0, <= 4"
    assert ParamSpec("x", lo=1).range_text() == ">= 1"
    assert ParamSpec("x", lo=0.0, hi=math.inf).range_text() == "0 .. inf"
    assert ParamSpec("x", choices=("a", "b")).range_text() == "`a`, `b`"
    assert ParamSpec("x").range_text() == ""
    assert ParamSpec("x", lo=0.0, hi=math.inf).accepted("x") == "x >= 0"
    assert ParamSpec("x", lo=0, hi=90, lo_open=True, hi_open=True).accepted("tilt") == "0 < tilt < 90"
    assert ParamSpec("x", lo=0).accepted("n", integer=True) == "an integer >= 0"


def test_a_spec_with_both_a_range_and_choices_or_an_empty_range_is_a_programming_error() -> None:
    with pytest.raises(TypeError, match="range or choices"):
        ParamSpec("x", lo=0, choices=("a",))
    with pytest.raises(TypeError, match="above hi"):
        ParamSpec("x", lo=2, hi=1)
