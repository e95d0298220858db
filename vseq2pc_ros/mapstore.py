"""The scan map file named by ``map.path``: opened at start (refusing bad files, untouched)."""
from __future__ import annotations

from lcpr_core.vseq2pc import SearchConfig, Vseq2pcMap, Vseq2pcNet
from ros_common.mapstore import load_map_file


def open_map(path: str, net: Vseq2pcNet, search: SearchConfig) -> Vseq2pcMap:
    """The map saved at ``path`` for ``net``, or an empty one when ``path`` is "" or absent.

    A file that cannot be used (damaged, other format, made with other descriptor weights)
    raises MapLoadError and is left as it is (:func:`ros_common.mapstore.load_map_file`).
    """
    loaded = load_map_file(path, lambda file: Vseq2pcMap.load(file, net, config=search))
    return loaded if loaded is not None else Vseq2pcMap(net, config=search)
