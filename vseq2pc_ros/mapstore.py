"""The scan map file named by ``map.path``: load at start (refusing bad files, untouched), save atomically."""
from __future__ import annotations

from pathlib import Path

from lcpr_core.errors import MapError
from lcpr_core.vseq2pc import SearchConfig, Vseq2pcMap, Vseq2pcNet
from lcpr_ros.errors import MapLoadError
from lcpr_ros.mapstore import _check_writable


def open_map(path: str, net: Vseq2pcNet, search: SearchConfig) -> Vseq2pcMap:
    """The map saved at ``path`` for ``net``, or an empty one when ``path`` is "" or absent.

    A file that cannot be used (damaged, other format, made with other descriptor weights)
    raises MapLoadError and is left as it is.
    """
    if path:
        file = Path(path)
        if file.exists():
            if not file.is_file():
                raise MapLoadError(f"map.path {file} exists but is not a file; give a .npz file path")
            try:
                return Vseq2pcMap.load(file, net, config=search)
            except MapError as err:
                raise MapLoadError(f"refusing to start: {err}. The file was left as it is; move it away, "
                                   "or point map.path elsewhere") from err
        _check_writable(file)
    return Vseq2pcMap(net, config=search)
