"""vseq2pc_node's parameters: every leaf of NodeConfig, walked by :mod:`ros_common.params`.

Every leaf of :class:`~vseq2pc_ros.config.NodeConfig` is one parameter named by its
dotted path (``match.top_k``, ``extrinsics.rpy``, ``map.path`` ...), its default the
dataclass default. Descriptions, ranges and the run-time-settable flag come from each
field's metadata (:func:`lcpr_common.params.param`; not lcpr_node's fields: the names
overlap but mean other things).
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

from rclpy.node import Node

from ros_common.params import Leaf, build, describe, leaves, to_yaml, unique
from ros_common.ros_params import RuntimeParameters

from .config import NodeConfig

YAML_HEADER = """vseq2pc_node parameters (node name vseq2pc) with their defaults, from vseq2pc_ros.config.NodeConfig.
Use: vseq2pc_node --ros-args --params-file config/vseq2pc.yaml
Regenerate after adding fields:
  python -c "from vseq2pc_ros.params import yaml_text; print(yaml_text(), end='')" > config/vseq2pc.yaml
"""


def all_leaves() -> list[Leaf]:
    """Every parameter of the node, names unique."""
    return unique(leaves(NodeConfig()))


def settings_from(values: Mapping[str, Any]) -> NodeConfig:
    """NodeConfig from Python-typed parameter values; ConfigError with the reason if refused."""
    return build(NodeConfig, values)


def yaml_text() -> str:
    """config/vseq2pc.yaml: every parameter with its default and description."""
    return to_yaml(all_leaves(), header=YAML_HEADER)


def make_runtime(node: Node, leaves_: Sequence[Leaf], apply: Any) -> RuntimeParameters:
    """ros_common's run-time validation, building this node's config."""
    return RuntimeParameters(node, leaves_, apply, build=settings_from)


def describe_all() -> str:
    """The parameter list of ``vseq2pc_node --help``."""
    return describe(all_leaves())


MARKDOWN_PAGE = "docs/reference/vseq2pc_node_parameters.md"
MARKDOWN_INTRO = """\
Every parameter of `vseq2pc_node` (node name `vseq2pc`) with its default, type, accepted range and
description, generated from `vseq2pc_ros.config.NodeConfig` (each field's metadata), as
`config/vseq2pc.yaml` is. "run time" marks the parameters that can change while the node runs
(`ros2 param set`); the others are read at start. Invalid values are refused with the reason, at
start (exit 1) and at run time. `vseq2pc_node --help` prints the same list."""


def markdown_text() -> str:
    """docs/reference/vseq2pc_node_parameters.md: every parameter as Markdown tables (the docs site's page)."""
    from ros_common.params import markdown_page

    return markdown_page(title="vseq2pc_node parameters", intro=MARKDOWN_INTRO, page=MARKDOWN_PAGE,
                         module="vseq2pc_ros.params", leaves=all_leaves())
