"""The root of every exception the project's packages raise.

Each package keeps its own base (``lcpr_core.errors.LcprError``, ``msg_tools.errors.MsgToolsError``,
``ros_common.errors.NodeError``, ...) and derives it from :class:`ProjectError`, so a command can end
on any of them with one line (:func:`lcpr_common.cli.tool_main`) and a test can tell them from a bug.
"""
from __future__ import annotations


class ProjectError(Exception):
    """Base class of the project's own errors: a refused input or setting, named in the message."""
