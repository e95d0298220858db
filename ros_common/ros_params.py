"""Declaring the config's parameters on an rclpy node and validating changes at run time."""
from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from typing import Any

from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor, SetParametersResult
from rclpy.exceptions import InvalidParameterTypeException, InvalidParameterValueException
from rclpy.node import Node
from rclpy.parameter import Parameter

from .errors import ConfigError
from .params import Leaf, renamed_value

#: an array parameter whose default is empty is declared by its type (rclpy reads ``[]`` as a byte array)
_ARRAY_TYPES: dict[type, Parameter.Type] = {bool: Parameter.Type.BOOL_ARRAY, int: Parameter.Type.INTEGER_ARRAY,
                                            float: Parameter.Type.DOUBLE_ARRAY, str: Parameter.Type.STRING_ARRAY}


def descriptor(leaf: Leaf) -> ParameterDescriptor:
    """The leaf's ROS descriptor, from its field's metadata: description, read-only unless dynamic, the
    accepted strings, and the range ``lo .. hi`` of a scalar number when both bounds are given (an open
    bound is refused when the config is built, which a ROS range cannot say)."""
    doc = leaf.doc
    desc = ParameterDescriptor(
        description=doc.description,
        read_only=not doc.dynamic,
        additional_constraints=f"one of: {', '.join(doc.choices)}" if doc.choices else "",
    )
    if doc.lo is not None and doc.hi is not None and not leaf.array:
        if leaf.kind is float:
            desc.floating_point_range = [FloatingPointRange(from_value=float(doc.lo), to_value=float(doc.hi))]
        elif leaf.kind is int:
            desc.integer_range = [IntegerRange(from_value=int(doc.lo), to_value=int(doc.hi), step=1)]
    return desc


def declare(node: Node, leaves: Sequence[Leaf], *, renamed: Mapping[str, str] | None = None) -> dict[str, Any]:
    """Declare every leaf (overrides from --ros-args / params files apply) -> Python-typed values.

    A value outside its range or of the wrong type raises ConfigError naming the parameter.
    ``renamed`` maps deprecated names to today's: an old name is declared too (read-only), and a value
    given under it becomes the new parameter's value, with a warning in the log.
    """
    defaults = {leaf.name: leaf.to_ros(leaf.default) for leaf in leaves}
    old_values: dict[str, tuple[str, Any]] = {}  # new name -> (old name, the value given under it)
    for old, new in (renamed or {}).items():
        try:
            value = node.declare_parameter(old, defaults[new], ParameterDescriptor(
                description=f"deprecated: the old name of {new}", read_only=True)).value
        except (InvalidParameterTypeException, InvalidParameterValueException) as err:
            raise ConfigError(f"parameter {old} (the old name of {new}): {err}") from err
        if value != defaults[new]:
            old_values[new] = (old, value)
            defaults[new] = value  # an override of the new name still wins; checked below
    values: dict[str, Any] = {}
    for leaf in leaves:
        initial = defaults[leaf.name]
        if leaf.array and initial == []:  # rclpy would type an empty list as a byte array: declare the type
            initial = _ARRAY_TYPES[leaf.kind]
        try:
            param = node.declare_parameter(leaf.name, initial, descriptor(leaf))
        except InvalidParameterTypeException as err:
            hint = " (write a decimal point for a double, e.g. 1.0)" if leaf.kind is float else ""
            raise ConfigError(f"parameter {leaf.name}: {err}{hint}") from err
        except InvalidParameterValueException as err:
            raise ConfigError(f"parameter {leaf.name}: {err}") from err
        if leaf.name in old_values:
            old, old_value = old_values[leaf.name]
            _, message = renamed_value(old, leaf.name, old_value=old_value, new_value=param.value,
                                       default=leaf.to_ros(leaf.default), where=f"node {node.get_name()}")
            if message:
                node.get_logger().warning(message)
        values[leaf.name] = leaf.to_python(param.value)
    return values


def current_values(node: Node, leaves: Sequence[Leaf]) -> dict[str, Any]:
    # an array declared by its type alone (an empty default) stays uninitialised until given: its value is ()
    return {leaf.name: leaf.to_python(node.get_parameter_or(leaf.name, Parameter(leaf.name, value=None)).value)
            for leaf in leaves}


class RuntimeParameters:
    """Validates parameter changes by building the configs; applies accepted ones.

    Register after :func:`declare` (declaration would otherwise run the check with
    half of the parameters missing).
    """

    def __init__(self, node: Node, leaves: Sequence[Leaf], apply: Callable[[Any], None], *,
                 build: Callable[[dict[str, Any]], Any]) -> None:
        self._node = node
        self._leaves = {leaf.name: leaf for leaf in leaves}
        self._apply = apply
        self._build = build  # parameter values -> the node's configs (raises ValueError to refuse)
        node.add_on_set_parameters_callback(self._check)
        node.add_post_set_parameters_callback(self._changed)

    def _candidate(self, changes: Sequence[Parameter]) -> Any:
        values = current_values(self._node, list(self._leaves.values()))
        for param in changes:
            leaf = self._leaves.get(param.name)
            if leaf is None:
                continue
            try:
                values[param.name] = leaf.to_python(param.value)
            except (TypeError, ValueError) as err:
                raise ConfigError(f"parameter {param.name}: {param.value!r} is not a {leaf.kind.__name__}") from err
        return self._build(values)

    def _check(self, changes: list[Parameter]) -> SetParametersResult:
        try:
            self._candidate(changes)
        except ConfigError as err:
            return SetParametersResult(successful=False, reason=str(err))
        return SetParametersResult(successful=True)

    def _changed(self, changes: list[Parameter]) -> None:
        settings = self._candidate([])
        self._apply(settings)
        names = ", ".join(f"{p.name}={p.value!r}" for p in changes)
        self._node.get_logger().info(f"parameters changed: {names}")
