"""lcpr_node's parameters: every leaf of :class:`~lcpr_core.lcpr.detector.DetectorConfig` and
:class:`~lcpr_ros.config.NodeConfig`, walked by :mod:`ros_common.params`.

Names are dotted paths (``model.weights``, ``match.top_k``, ``sync.slop``, ``map.path`` ...);
descriptions, ranges and the run-time-settable flag come from :data:`lcpr_ros.param_docs.DOCS`.
The offline tools read the same parameters from a params file (:func:`settings_from_file`), so an
offline run evaluates what the node would run.
"""
from __future__ import annotations

import os
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from lcpr_core.lcpr.detector import DetectorConfig
from ros_common.errors import ConfigError
from ros_common.params import Leaf, build, describe, leaves, read_params_file, to_yaml, unique

from .config import NodeConfig, check_together
from .param_docs import DOCS

YAML_HEADER = """lcpr_node parameters (node name lcpr) with their defaults, which come from the config
dataclasses (lcpr_core.lcpr.detector.DetectorConfig, lcpr_ros.config.NodeConfig).
Use: lcpr_node --ros-args --params-file config/lcpr.yaml
Regenerate after adding fields (test/test_ros_params.py checks that every parameter is here):
  python -c "from lcpr_ros.params import yaml_text; print(yaml_text(), end='')" > config/lcpr.yaml
"""


@dataclass(frozen=True)
class Settings:
    """Everything the node is configured with."""

    detector: DetectorConfig
    node: NodeConfig


ROOTS: tuple[type, ...] = (DetectorConfig, NodeConfig)
#: deprecated parameter name -> today's; the old name is still read, with a warning
RENAMED: dict[str, str] = {"map.model": "map.descriptor_tag"}


def all_leaves() -> list[Leaf]:
    """Every parameter of the node, names unique."""
    return unique([leaf for root in ROOTS for leaf in leaves(root(), docs=DOCS)])


def settings_from(values: Mapping[str, Any]) -> Settings:
    """Build and cross-check both configs from Python-typed parameter values (ConfigError if refused)."""
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
