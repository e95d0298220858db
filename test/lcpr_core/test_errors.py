"""lcpr_core's errors: one module holds them, and the package raises nothing else."""
from __future__ import annotations

import ast
import builtins
import inspect
from pathlib import Path

import pytest

import lcpr_core
from lcpr_core import errors
from lcpr_core.errors import InvalidValueError, LcprError
from lcpr_core.lcpr.describer import ModelConfig

PACKAGE = Path(lcpr_core.__file__).parent
#: Built-in exceptions lcpr_core may raise directly: none but the ones Python's protocols require.
ALLOWED_BUILTINS = {"NotImplementedError", "StopIteration", "KeyboardInterrupt", "AttributeError", "TypeError"}


def raised_names(tree: ast.AST) -> list[tuple[int, str]]:
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Raise) and node.exc is not None:
            call = node.exc.func if isinstance(node.exc, ast.Call) else node.exc
            if isinstance(call, ast.Name):
                found.append((node.lineno, call.id))
    return found


def test_lcpr_core_raises_only_its_own_errors_or_a_protocols_builtin() -> None:
    own = {name for name, cls in inspect.getmembers(errors, inspect.isclass) if issubclass(cls, LcprError)}
    builtin = {name for name in dir(builtins) if name.endswith(("Error", "Exception"))} - ALLOWED_BUILTINS
    bad = [f"{path.relative_to(PACKAGE.parent)}:{line}: raise {name}"
           for path in sorted(PACKAGE.rglob("*.py"))
           for line, name in raised_names(ast.parse(path.read_text()))
           if name in builtin and name not in own]
    assert not bad, "raise an lcpr_core.errors class instead:\n" + "\n".join(bad)


def test_every_error_class_of_lcpr_core_lives_in_its_errors_module() -> None:
    elsewhere = [f"{path.relative_to(PACKAGE.parent)}: class {node.name}"
                 for path in sorted(PACKAGE.rglob("*.py")) if path.name != "errors.py"
                 for node in ast.walk(ast.parse(path.read_text()))
                 if isinstance(node, ast.ClassDef) and node.name.endswith("Error")]
    assert not elsewhere, "\n".join(elsewhere)


def test_a_bad_setting_is_an_lcpr_error_that_callers_catching_value_error_still_catch() -> None:
    with pytest.raises(InvalidValueError, match="threads=-1") as caught:
        ModelConfig(threads=-1)
    assert isinstance(caught.value, LcprError) and isinstance(caught.value, ValueError)
