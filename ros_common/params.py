"""Typed config <-> ROS parameters, generic over config dataclasses (every node uses it).

Every leaf field of a config dataclass becomes one parameter named by its dotted path
(``match.top_k``, ``sync.slop``, ``map.path`` ...), with the dataclass default as its
default and its description, range or choices and run-time flag from the field's metadata
(:func:`lcpr_common.params.param`). Going back, the dataclasses are constructed from the
parameter values, so validation is theirs: a ValueError (or the core's LcprError) raised by a
``__post_init__`` becomes a :class:`~ros_common.errors.ConfigError` with the reason, at start
and when a parameter is set at run time. No rclpy import: :mod:`ros_common.ros_params` declares them.
"""
from __future__ import annotations

import dataclasses
import os
import typing
import warnings
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from lcpr_common.params import ParamSpec, spec_of
from lcpr_core.errors import LcprError

from .errors import ConfigError

SCALARS: tuple[type, ...] = (bool, int, float, str)


@dataclass(frozen=True)
class Leaf:
    """One parameter: a scalar or tuple field of a config dataclass."""

    name: str  # dotted parameter name
    owner: str  # the dataclass that holds the field
    kind: type  # bool | int | float | str (the element type for tuples)
    array: bool  # a tuple field -> a ROS array parameter
    default: Any  # Python value (tuple for arrays)
    doc: ParamSpec  # description, range, accepted values, run-time settable (the field's metadata)

    def to_ros(self, value: Any) -> Any:
        """Python value -> what rclpy stores (lists for arrays, floats for doubles)."""
        if self.array:
            return [self.kind(v) for v in value]
        return self.kind(value)

    def to_python(self, value: Any) -> Any:
        """rclpy value (list, array.array, scalar) -> the dataclass field's type (None: an array declared by
        type alone, left empty)."""
        if self.array:
            return () if value is None else tuple(self.kind(v) for v in value)
        return self.kind(value)


def _field_kind(owner: type, name: str, hint: Any) -> tuple[type, bool]:
    """(element type, is_array) of a leaf field annotation."""
    if hint in SCALARS:
        return hint, False
    if typing.get_origin(hint) is tuple:
        args = [a for a in typing.get_args(hint) if a is not Ellipsis]
        if args and all(a == args[0] for a in args) and args[0] in SCALARS:
            return args[0], True
    raise TypeError(f"{owner.__name__}.{name}: type {hint!r} cannot be a ROS parameter "
                    "(use bool, int, float, str, a tuple of one of them, or a nested dataclass)")


def leaves(config: Any, prefix: str = "") -> list[Leaf]:
    """The parameters of a config instance (its values are the defaults), depth first, each described
    by its field's metadata (:func:`lcpr_common.params.param`); a field without any is named by its
    dataclass (test/ros/test_node_parameters.py holds the nodes to describing every one)."""
    cls = type(config)
    hints = typing.get_type_hints(cls)
    out: list[Leaf] = []
    for f in dataclasses.fields(cls):
        name = f"{prefix}{f.name}"
        value = getattr(config, f.name)
        if dataclasses.is_dataclass(value):
            out.extend(leaves(value, f"{name}."))
            continue
        kind, array = _field_kind(cls, f.name, hints[f.name])
        doc = spec_of(f) or ParamSpec(f"{cls.__name__}.{f.name}")
        out.append(Leaf(name, cls.__name__, kind, array, value, doc))
    return out


def build(cls: type, values: Mapping[str, Any], prefix: str = "") -> Any:
    """An instance of ``cls`` from dotted-name values; absent names keep their defaults.

    Raises ConfigError with the dataclass's own reason, prefixed with the group name.
    """
    hints = typing.get_type_hints(cls)
    kwargs: dict[str, Any] = {}
    for f in dataclasses.fields(cls):
        name = f"{prefix}{f.name}"
        hint = hints[f.name]
        if isinstance(hint, type) and dataclasses.is_dataclass(hint):  # a nested group (hints are classes)
            kwargs[f.name] = build(hint, values, f"{name}.")
        elif name in values:
            kind, array = _field_kind(cls, f.name, hint)
            value = values[name]
            kwargs[f.name] = tuple(kind(v) for v in value) if array else kind(value)
    try:
        return cls(**kwargs)
    except ConfigError:
        raise
    except (ValueError, TypeError, LcprError) as err:
        group = prefix.rstrip(".") or cls.__name__
        raise ConfigError(f"{group}: {err}") from err


def unique(found: Sequence[Leaf]) -> list[Leaf]:
    """``found`` unchanged; TypeError when two config fields map to one parameter name."""
    names = [leaf.name for leaf in found]
    clash = {n for n in names if names.count(n) > 1}
    if clash:
        raise TypeError(f"config fields map to the same parameter names: {sorted(clash)}")
    return list(found)


def renamed_value(old: str, new: str, *, old_value: Any, new_value: Any, default: Any,
                  where: str) -> tuple[Any, str | None]:
    """The value of parameter ``new`` when the deprecated name ``old`` may have been given too, and the
    deprecation message to show (None when the old name was not used).

    ``None`` for an absent name; a name at ``default`` counts as absent. ConfigError when both were given
    different values.
    """
    old_given = old_value is not None and old_value != default
    new_given = new_value is not None and new_value != default
    if not old_given:
        return (default if new_value is None else new_value), None
    if new_given and new_value != old_value:
        raise ConfigError(f"{where}: {old}={old_value!r} and {new}={new_value!r} disagree; {old} is the old name of "
                          f"{new}: give only {new}")
    return old_value, f"{where}: parameter {old} is deprecated, use {new} (took {new}={old_value!r})"


def read_params_file(path: str | os.PathLike[str], leaves_: Sequence[Leaf], *,
                     renamed: Mapping[str, str] | None = None) -> dict[str, Any]:
    """Every leaf's value from a ROS 2 ``--params-file`` (one node section with ``ros__parameters``),
    leaves absent from it at their defaults; ConfigError names the file and what is wrong with it.

    ``renamed`` maps deprecated parameter names to today's: an old name is still read (with a warning)."""
    import yaml  # local: only the offline tools read parameter files themselves

    where = os.fspath(path)
    try:
        data = yaml.safe_load(Path(where).read_text())
    except (OSError, yaml.YAMLError) as err:
        raise ConfigError(f"parameter file {where}: {err}") from err
    sections = [v for v in data.values() if isinstance(v, dict) and "ros__parameters" in v] \
        if isinstance(data, dict) else []
    if len(sections) != 1:
        raise ConfigError(f"parameter file {where} holds {len(sections)} node sections with ros__parameters; "
                          "expected one (e.g. '/**: ros__parameters: ...')")
    values: dict[str, Any] = {leaf.name: leaf.default for leaf in leaves_}
    given = _flatten(sections[0]["ros__parameters"])
    for old, new in (renamed or {}).items():
        if old in given:
            given[new], message = renamed_value(old, new, old_value=given.pop(old), new_value=given.get(new),
                                                default=values[new], where=f"parameter file {where}")
            if message:
                warnings.warn(message, FutureWarning, stacklevel=2)  # FutureWarning: shown by default
    unknown = sorted(set(given) - set(values))
    if unknown:
        raise ConfigError(f"parameter file {where} names unknown parameters {unknown}")
    values.update({name: tuple(v) if isinstance(v, list) else v for name, v in given.items()})
    return values


def _flatten(tree: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    for key, value in tree.items():
        name = f"{prefix}{key}"
        if isinstance(value, Mapping):
            out.update(_flatten(value, name + "."))
        else:
            out[name] = value
    return out


def describe(leaves_: Iterable[Leaf]) -> str:
    """Human-readable parameter list (``lcpr_node --help``)."""
    lines = []
    for leaf in leaves_:
        doc = leaf.doc
        extra = []
        if doc.bounded:
            extra.append(f"range {doc.range_text().replace(' .. ', '..')}")
        if doc.choices:
            extra.append(f"one of {', '.join(doc.choices)}")
        if doc.dynamic:
            extra.append("settable at run time")
        default = list(leaf.default) if leaf.array else leaf.default
        lines.append(f"  {leaf.name} (default {default!r}{'; ' if extra else ''}{'; '.join(extra)})\n"
                     f"      {doc.description}")
    return "\n".join(lines)


def to_yaml(leaves_: Iterable[Leaf], node_name: str = "/**", header: str = "") -> str:
    """A ROS 2 params file (``ros__parameters``) holding every leaf's default, one comment each.

    Leaves sharing a group (``map.dim`` and ``map.path``) go under one key, in order of first use.
    """
    import json

    tree: dict[str, Any] = {}
    for leaf in leaves_:
        *groups, key = leaf.name.split(".")
        branch = tree
        for group in groups:
            branch = branch.setdefault(group, {})
        branch[key] = leaf

    lines = [f"# {line}".rstrip() for line in header.splitlines()]
    lines += [f"{node_name}:", "  ros__parameters:"]

    def emit(branch: dict[str, Any], depth: int) -> None:
        indent = "  " * depth
        for key, item in branch.items():
            if isinstance(item, dict):
                lines.append(f"{indent}{key}:")
                emit(item, depth + 1)
                continue
            default = list(item.default) if item.array else item.default
            lines.append(f"{indent}# {item.doc.description}")
            if item.array and not default:  # rcl's params-file parser refuses an empty list: left out, as a hint
                lines.append(f"{indent}# {key}: []  (the default; a list given here must not be empty)")
                continue
            lines.append(f"{indent}{key}: {json.dumps(default)}")  # JSON values are valid YAML flow values

    emit(tree, 2)
    return "\n".join(lines) + "\n"


def _markdown_cell(text: str) -> str:
    """``text`` safe inside a Markdown table cell (GitHub's and Python-Markdown's tables alike)."""
    for char in "\\`*_[]|":
        text = text.replace(char, "\\" + char)
    return text.replace("<", "&lt;").replace(">", "&gt;").replace("\n", " ")


def markdown_page(*, title: str, intro: str, page: str, module: str, leaves: list[Leaf]) -> str:
    """A node's parameter reference page: ``title``, ``intro`` (what the parameters come from), the note
    that the page is generated (regenerated with ``module``'s ``markdown_text`` into ``page``), the tables."""
    return f"""# {title}

{intro}

Do not edit this page: `test/project/test_docs_site.py` fails when it differs from the dataclasses.
Regenerate it with

```bash
.venv/bin/python -c "from {module} import markdown_text; print(markdown_text(), end='')" > {page}
```

{to_markdown(leaves)}"""


def to_markdown(leaves_: Iterable[Leaf]) -> str:
    """Markdown tables of the leaves (the docs site's parameter pages): one section per group (the name's
    first part; names without a dot under "Top-level parameters"), in order of first use; each row gives
    the parameter, its default (written as :func:`to_yaml` writes it), its type, the accepted range or
    values, whether it can change while the node runs, and its description.
    """
    import json

    groups: dict[str, list[Leaf]] = {}
    for leaf in leaves_:
        group, dot, _ = leaf.name.partition(".")
        groups.setdefault(group if dot else "", []).append(leaf)

    lines: list[str] = []
    for group, members in groups.items():
        lines += [f"## `{group}.*`" if group else "## Top-level parameters", "",
                  "| parameter | default | type | range or values | run time | description |",
                  "|---|---|---|---|---|---|"]
        for leaf in members:
            doc = leaf.doc
            default = json.dumps(list(leaf.default) if leaf.array else leaf.default)
            default = f"`{default}`" if "`" not in default and "|" not in default else _markdown_cell(default)
            kind = f"{leaf.kind.__name__}[]" if leaf.array else leaf.kind.__name__
            accepted = doc.range_text()
            lines.append(f"| `{leaf.name}` | {default} | {kind} | {accepted} | {'yes' if doc.dynamic else ''} "
                         f"| {_markdown_cell(doc.description)} |")
        lines.append("")
    return "\n".join(lines)
