"""tool_main: a command ends on its own errors and unreadable files with one line and status 2; bugs keep
their traceback."""
from __future__ import annotations

from pathlib import Path

import pytest

from lcpr_common.cli import INPUT_ERROR, tool_main
from lcpr_common.errors import ProjectError
from lcpr_core.errors import InvalidValueError
from msg_tools.errors import DatasetError


@tool_main
def command(argv: list[str]) -> int:
    kind, value = argv
    if kind == "read":
        return len(Path(value).read_text())
    if kind == "dataset":
        raise DatasetError(f"folder {value!r} has no scans")
    if kind == "value":
        raise InvalidValueError(f"radius {value}; accepted: > 0")
    raise ZeroDivisionError(value)


@pytest.mark.parametrize("argv, message", [
    (["dataset", "walk"], "folder 'walk' has no scans"),
    (["value", "-1"], "radius -1; accepted: > 0"),
])
def test_the_projects_own_errors_end_a_command_with_one_line_and_status_2(argv, message, capsys) -> None:
    assert command(argv) == INPUT_ERROR == 2
    assert capsys.readouterr().err == f"test_cli.py: error: {message}\n"


def test_a_file_that_cannot_be_read_ends_a_command_the_same_way(tmp_path: Path, capsys) -> None:
    assert command(["read", str(tmp_path / "absent.txt")]) == 2
    (line,) = capsys.readouterr().err.splitlines()
    assert line.startswith("test_cli.py: error: [Errno 2] No such file or directory") and "absent.txt" in line


def test_a_command_that_succeeds_returns_its_own_status(tmp_path: Path) -> None:
    (tmp_path / "a.txt").write_text("four")
    assert command(["read", str(tmp_path / "a.txt")]) == 4


def test_a_bug_keeps_its_traceback() -> None:
    with pytest.raises(ZeroDivisionError):
        command(["bug", "x"])


def test_every_package_error_base_is_a_project_error() -> None:
    from lcpr_common.point_files import PointFileError
    from lcpr_core.errors import LcprError
    from msg_tools.errors import MsgToolsError
    from ros_common.errors import NodeError

    assert all(issubclass(base, ProjectError) for base in (LcprError, MsgToolsError, NodeError, PointFileError))
