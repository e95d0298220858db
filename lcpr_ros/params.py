"""lcpr_node's parameters: every leaf of :class:`~lcpr_core.detector.DetectorConfig` and
:class:`~lcpr_ros.config.NodeConfig`, walked by :mod:`ros_common.params`.

Names are dotted paths (``model.weights``, ``match.top_k``, ``sync.slop``, ``map.path`` ...);
descriptions, ranges and the run-time-settable flag come from each field's metadata
(:func:`lcpr_common.params.param`), the one source of the params file, the reference page and the
ROS descriptors.
The offline tools read the same parameters from a params file (:func:`settings_from_file`), so an
offline run evaluates what the node would run.
"""
from __future__ import annotations

import os
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from lcpr_core.detector import DetectorConfig
from lcpr_core.lcpr.describer import ModelConfig
from lcpr_core.pretrained import BUNDLED, command_weights
from ros_common.errors import ConfigError
from ros_common.params import Leaf, build, describe, leaves, read_params_file, to_yaml, unique

from .config import NodeConfig, check_together

YAML_HEADER = """lcpr_node parameters (node name lcpr) with their defaults, which come from the config
dataclasses (lcpr_core.detector.DetectorConfig, lcpr_ros.config.NodeConfig).
Use: lcpr_node --ros-args --params-file config/lcpr.yaml
Regenerate after adding fields (test/ros/test_ros_params.py checks that every parameter is here):
  python -c "from lcpr_ros.params import yaml_text; print(yaml_text(), end='')" > config/lcpr.yaml
"""


@dataclass(frozen=True)
class Settings:
    """Everything the node is configured with."""

    detector: DetectorConfig
    node: NodeConfig


#: The node's defaults: the config dataclasses' own, except that the node runs the bundled trained weights
#: (the Python API's ModelConfig keeps "" = no weights).
NODE_DEFAULTS = Settings(DetectorConfig(model=ModelConfig(weights=BUNDLED)), NodeConfig())
#: deprecated parameter name -> today's; the old name is still read, with a warning
RENAMED: dict[str, str] = {"map.model": "map.descriptor_tag"}


def all_leaves() -> list[Leaf]:
    """Every parameter of the node, names unique."""
    roots = (NODE_DEFAULTS.detector, NODE_DEFAULTS.node)
    return unique([leaf for root in roots for leaf in leaves(root)])


def settings_from(values: Mapping[str, Any]) -> Settings:
    """Build and cross-check both configs from Python-typed parameter values, absent ones at the node's
    defaults (ConfigError if refused). An empty ``model.weights`` means the bundled weights, as by default."""
    values = {**{leaf.name: leaf.default for leaf in all_leaves()}, **values}
    values["model.weights"] = command_weights(values["model.weights"], imagenet=values["model.imagenet"])
    detector = build(DetectorConfig, values)
    node = build(NodeConfig, values)
    try:
        check_together(node, detector)
    except ValueError as err:
        raise ConfigError(str(err)) from err
    return Settings(detector, node)


def settings_from_file(path: str | os.PathLike[str]) -> Settings:
    """The settings a ``--params-file`` (e.g. config/lcpr.yaml) gives the node, leaves absent from it at their
    defaults; ConfigError names the file and what is wrong with it."""
    return settings_from(read_params_file(path, all_leaves(), renamed=RENAMED))


def yaml_text() -> str:
    """config/lcpr.yaml: every parameter with its default and description."""
    return to_yaml(all_leaves(), header=YAML_HEADER)


def describe_all() -> str:
    """The parameter list of ``lcpr_node --help``."""
    old = "".join(f"\n  {name} (deprecated: the old name of {new}, still read with a warning)"
                  for name, new in RENAMED.items())
    return describe(all_leaves()) + old


MARKDOWN_PAGE = "docs/reference/lcpr_node_parameters.md"
MARKDOWN_INTRO = """\
Every parameter of `lcpr_node` (node name `lcpr`) with its default, type, accepted range and
description, generated from the config dataclasses (`lcpr_core.detector.DetectorConfig`,
`lcpr_ros.config.NodeConfig`: each field's metadata), as `config/lcpr.yaml` is. "run time" marks
the parameters that can change while the node runs (`ros2 param set`); the others are read at
start. Invalid values are refused with the reason, at start (exit 1) and at run time.
`lcpr_node --help` prints the same list."""


def markdown_text() -> str:
    """docs/reference/lcpr_node_parameters.md: every parameter as Markdown tables (the docs site's page)."""
    from ros_common.params import markdown_page

    old = "".join(f"- `{name}`: the old name of `{new}`, still read (node overrides and `--params-file`) with a "
                  "deprecation warning.\n" for name, new in RENAMED.items())
    renamed = f"## Renamed parameters\n\n{old}" if old else ""
    page = markdown_page(title="lcpr_node parameters", intro=MARKDOWN_INTRO, page=MARKDOWN_PAGE,
                         module="lcpr_ros.params", leaves=all_leaves())
    return f"{page}\n{renamed}"
