"""The progress bars every long job shows (tqdm); disabled, they print nothing and cost nothing."""
from __future__ import annotations

from collections.abc import Iterable, Iterator
from typing import TYPE_CHECKING, NoReturn, TypeVar

if TYPE_CHECKING:
    from tqdm import tqdm

T = TypeVar("T")


def progress_bar(total: int | None, *, desc: str, unit: str, enabled: bool = True,
                 leave: bool = True) -> tqdm[NoReturn]:
    """A bar to ``update()`` by hand (``enabled=False``: a silent one, so callers need no checks)."""
    from tqdm import tqdm  # imported when a job starts: tqdm is not needed to import the package

    return tqdm(total=total, desc=desc, unit=unit, disable=not enabled, leave=leave, dynamic_ncols=True)


def progress_iter(items: Iterable[T], *, total: int | None, unit: str, desc: str | None = None,
                  enabled: bool = True) -> Iterator[T]:
    """``items``, counted on a bar when enabled (passed through untouched otherwise)."""
    if not enabled:
        yield from items
        return
    from tqdm import tqdm

    yield from tqdm(items, total=total, desc=desc, unit=unit)
