"""lcpr_node's map file: the descriptor map at ``map.path`` (opened and saved with :mod:`ros_common.mapstore`)."""
from __future__ import annotations

from lcpr_core.descriptor_map import DescriptorMap, MapConfig
from ros_common.mapstore import load_map_file


def load_prior_map(path: str, expect: MapConfig) -> DescriptorMap | None:
    """The descriptor map saved at ``path`` (see :func:`load_map_file`)."""
    return load_map_file(path, lambda file: DescriptorMap.load(file, expect=expect))


def save_map(descriptor_map: DescriptorMap, path: str) -> int:
    """Write the map atomically (the old file stays if writing fails); returns its size."""
    descriptor_map.save(path)
    return len(descriptor_map)
