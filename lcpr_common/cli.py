"""How a command ends on bad input: one line ``PROG: error: MESSAGE`` on stderr and exit status 2.

That is how argparse ends on a bad option; :func:`tool_main` ends the same way on what the command
finds later: the project's own errors (:class:`~lcpr_common.errors.ProjectError`, whose messages
name the bad value) and files that cannot be read (``OSError``). Anything else is a bug and keeps its
traceback.
"""
from __future__ import annotations

import functools
import inspect
import sys
from collections.abc import Callable
from pathlib import Path
from typing import ParamSpec, TypeVar

from .errors import ProjectError

P = ParamSpec("P")
R = TypeVar("R")

#: exit status of a command that refused its input (argparse's)
INPUT_ERROR = 2


def tool_main(main: Callable[P, R]) -> Callable[P, R | int]:
    """Wrap a command's ``main``: its result, or :data:`INPUT_ERROR` after one error line naming the
    script (``lidar_loops_compare.py: error: ...``)."""
    prog = Path(inspect.getfile(main)).name

    @functools.wraps(main)
    def wrapped(*args: P.args, **kwargs: P.kwargs) -> R | int:
        try:
            return main(*args, **kwargs)
        except (ProjectError, OSError) as err:
            print(f"{prog}: error: {err}", file=sys.stderr)
            return INPUT_ERROR

    return wrapped
