"""Every node's parameters come from their config fields' metadata, and no parameter a user's files name
goes away or changes its type: node_parameters.json records each node's names and types (added freely,
renamed never). A new parameter needs no change of the record; to add it there, rewrite the record with

    .venv/bin/python test/ros/test_node_parameters.py > test/ros/node_parameters.json

Defaults, ranges and descriptions are checked where they are derived (config/*.yaml, the reference pages).
"""
from __future__ import annotations

import importlib
import json
import math
import sys
from pathlib import Path
from typing import Any

import pytest

RECORD = Path(__file__).with_name("node_parameters.json")
#: node (executable) -> the module whose all_leaves() lists its parameters
NODES = {
    "lcpr_node": "lcpr_ros.params",
    "vseq2pc_node": "vseq2pc_ros.params",
    "lcpr_backend": "backend_ros.config",
    "lcpr_kiss_icp": "backend_ros.kiss_icp_node",
}


def _bound(value: float) -> float | str:
    return "inf" if math.isinf(value) else float(value)


def parameter_table(node: str) -> dict[str, dict[str, Any]]:
    """A node's parameters as its users meet them: per name the type, default, ROS range, choices and
    run-time flag."""
    rows: dict[str, dict[str, Any]] = {}
    for leaf in importlib.import_module(NODES[node]).all_leaves():
        doc = leaf.doc
        rows[leaf.name] = {
            "kind": leaf.kind.__name__, "array": leaf.array,
            "default": list(leaf.default) if leaf.array else leaf.default,
            "range": [_bound(doc.lo), _bound(doc.hi)] if doc.lo is not None and doc.hi is not None else None,
            "choices": list(doc.choices), "dynamic": doc.dynamic,
        }
    return rows


def signature(row: dict[str, Any]) -> str:
    """What a parameter file relies on: the value's type, and whether it is a list."""
    return f"{row['kind']}[]" if row["array"] else str(row["kind"])


def record_text() -> str:
    """node_parameters.json: per node, each parameter's name and type, one line each."""
    lines = ["{"]
    for i, node in enumerate(NODES):
        table = parameter_table(node)
        lines.append(f" {json.dumps(node)}: {{")
        lines += [f"  {json.dumps(name)}: {json.dumps(signature(row))}{',' if j < len(table) - 1 else ''}"
                  for j, (name, row) in enumerate(table.items())]
        lines.append(" }" + ("," if i < len(NODES) - 1 else ""))
    return "\n".join(lines + ["}"]) + "\n"


@pytest.mark.parametrize("node", list(NODES))
def test_a_node_keeps_every_recorded_parameter_with_its_type(node: str) -> None:
    recorded: dict[str, str] = json.loads(RECORD.read_text())[node]
    now = {name: signature(row) for name, row in parameter_table(node).items()}
    lost = sorted(name for name in recorded if name not in now)
    retyped = sorted(f"{name}: {recorded[name]} -> {now[name]}" for name in recorded
                     if name in now and now[name] != recorded[name])
    assert not lost and not retyped, (
        f"{node} lost parameters {lost} or changed their types {retyped}: users' parameter files name them "
        "(add freely, rename never)")


def test_a_lost_parameter_would_be_seen() -> None:
    table = parameter_table("lcpr_node")
    assert "verify.min_fitness" in table and signature(table["verify.min_fitness"]) == "float"
    assert signature({"kind": "float", "array": True}) == "float[]"


@pytest.mark.parametrize("node", list(NODES))
def test_every_parameter_is_described_by_its_config_field(node: str) -> None:
    leaves = importlib.import_module(NODES[node]).all_leaves()
    undescribed = [leaf.name for leaf in leaves if leaf.doc.description == f"{leaf.owner}.{leaf.name.split('.')[-1]}"]
    assert not undescribed, f"{node}: these fields carry no description (lcpr_common.params.param): {undescribed}"


def test_the_ros_descriptor_is_derived_from_the_field_metadata() -> None:
    pytest.importorskip("rclpy")
    from lcpr_ros.params import all_leaves
    from ros_common.ros_params import descriptor

    leaves = {leaf.name: leaf for leaf in all_leaves()}
    top_k = descriptor(leaves["match.top_k"])
    assert not top_k.read_only and (top_k.integer_range[0].from_value, top_k.integer_range[0].to_value) == (1, 1000)
    assert "candidates per query" in top_k.description
    fitness = descriptor(leaves["verify.min_fitness"]).floating_point_range[0]
    assert (fitness.from_value, fitness.to_value) == (0.0, 1.0)
    method = descriptor(leaves["match.method"])
    assert method.read_only and method.additional_constraints.startswith("one of: lcpr")
    assert not descriptor(leaves["verify.min_points"]).integer_range  # a one-sided bound is checked, not a range


if __name__ == "__main__":
    sys.stdout.write(record_text())
