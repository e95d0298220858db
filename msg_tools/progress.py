"""The progress bar every long job shows (tqdm); disabled, it prints nothing and its calls do nothing."""
from __future__ import annotations

from typing import TYPE_CHECKING, NoReturn

if TYPE_CHECKING:
    from tqdm import tqdm


def progress_bar(total: int | None, *, desc: str, unit: str, enabled: bool = True,
                 leave: bool = True) -> tqdm[NoReturn]:
    """A bar to ``update()`` by hand (``enabled=False``: a silent one, so callers need no checks)."""
    from tqdm import tqdm  # imported when a job starts: tqdm is not needed to import the package

    return tqdm(total=total, desc=desc, unit=unit, disable=not enabled, leave=leave, dynamic_ncols=True)
