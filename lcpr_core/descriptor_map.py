"""A growing map of place descriptors backed by FAISS, with per-entry metadata.

Memory: the descriptors are held once, inside the FAISS index (N * D * 4 bytes;
~1.02 GB for 1M x 256). Metadata costs 76 bytes per entry (id 8, stamp 8, position 24,
orientation 32, source code 4) in numpy arrays grown by doubling, so up to twice that while
growing. "hnsw" adds its graph (~2 * hnsw_m * 4 bytes per entry, ~0.3 GB for 1M at
m=32). ``descriptors`` returns a copy; everything else reads FAISS storage in place.

Distances are Euclidean (L2, not squared), computed by FAISS in float32.
"""
from __future__ import annotations

import dataclasses
import os
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import faiss
import numpy as np
from numpy.typing import ArrayLike

from lcpr_common.params import check_fields, param

from .errors import LcprError, MapError, MapSchemaError
from .geometry import quaternions_xyzw, rotations_from_xyzw
from .growable import GrowableArray
from .map_file import check_header_fields, read_map_file, write_map_file
from .map_rows import MapRows, RowAccess
from .scan_context import ScanContextConfig, ScanContextRows
from .verification.clouds import CloudStore

__all__ = ["MapConfig", "Match", "DescriptorMap", "INDEX_TYPES", "SCHEMA_VERSION"]

INDEX_TYPES: tuple[str, ...] = ("flat", "hnsw")
# 2: keyframe clouds (cloud_ids, cloud_counts, cloud_points); 3: orientations (the full odometry pose, for
# submaps); optional in 3: scan_contexts (with the header record of what made them). Version 1 and 2 files
# still load (their orientations unknown: NaN).
SCHEMA_VERSION = 3
_READABLE_VERSIONS = (1, 2, 3)
_FORMAT = "lcpr_core.descriptor_map"
_NPZ_KEYS = ("descriptors", "ids", "stamps", "poses", "source_codes")
_CLOUD_KEYS = ("cloud_ids", "cloud_counts", "cloud_points")
_SCAN_CONTEXTS = "scan_contexts"  # (N, rings, sectors) float32, optional: saved when match.method made them
_SC_HEADER = "scan_context"  # the header's record of what made them (ScanContextConfig.describing)
_ORIENTATIONS = "orientations"  # (N, 4) unit quaternions x, y, z, w of world_T_base; schema version >= 3
_ROTATION_TOLERANCE = 1e-4  # how far from orthonormal (det +1) a pose's rotation block may be
# A filtered search over at most this many allowed rows is done exactly (brute force).
_EXACT_FALLBACK_ROWS = 16384

@dataclass(frozen=True)
class MapConfig:
    """Descriptor size, descriptor tag and search structure of a map.

    descriptor_tag: names what made the descriptors (a map file must carry the tag the
    detector expects; written as ``model`` in the file header). index: "flat" (exact L2)
    or "hnsw" (approximate, faiss.IndexHNSWFlat). The hnsw_* fields only matter for "hnsw".
    """

    dim: int = param(256, "descriptor size stored in the map", lo=1, hi=65536)
    descriptor_tag: str = param("lcpr", "names what made the map's descriptors (the file header's 'model' field); "
                                        "a map file must carry the same tag (formerly map.model, still accepted "
                                        "with a warning)")
    index: str = param("flat", "search structure", choices=INDEX_TYPES)
    hnsw_m: int = param(32, "HNSW graph degree (map.index = hnsw)", lo=1, hi=1024)
    hnsw_ef_search: int = param(128, "HNSW search breadth (map.index = hnsw)", lo=1, hi=1 << 20)
    hnsw_ef_construction: int = param(200, "HNSW build breadth (map.index = hnsw)", lo=1, hi=1 << 20)

    def __post_init__(self) -> None:
        check_fields(self, error=MapError)
        if not isinstance(self.descriptor_tag, str) or not self.descriptor_tag:
            raise MapError(f"descriptor_tag={self.descriptor_tag!r} is not accepted; it must be a non-empty string")

    def index_params(self) -> dict[str, Any]:
        """The index type and its parameters, as stored in a map file."""
        params: dict[str, Any] = {"index": self.index}
        if self.index == "hnsw":
            params.update(m=self.hnsw_m, ef_search=self.hnsw_ef_search, ef_construction=self.hnsw_ef_construction)
        return params


@dataclass(frozen=True)
class Match:
    """One search hit. ``distance`` is the Euclidean (not squared) L2 distance;
    ``pose`` is None when the entry has no pose; ``rank`` counts from 0."""

    id: int
    distance: float
    stamp: float
    pose: tuple[float, float, float] | None
    source: str
    rank: int


class DescriptorMap(RowAccess):
    """Place descriptors (N x D float32) with id, stamp, pose and source per entry.

    A pose is a position (``poses``, N x 3) and, when the full odometry pose was given, an orientation
    (``orientations``, N x 4 quaternions): :meth:`pose_matrices` rebuilds world_T_base for the local
    submaps of :mod:`lcpr_core.verification.submap`.

    Ids are int64, assigned consecutively from max id + 1 (0 for an empty map)
    unless given; they survive save/load. Entries are never removed.
    Not thread-safe: share one map between threads behind a lock.
    """

    def __init__(self, config: MapConfig | None = None, *, weights_id: str = "") -> None:
        self._config = config if config is not None else MapConfig()
        #: what made the descriptors (lcpr_core.fingerprint, e.g. Describer.weights_id); "" = unknown
        self.weights_id = weights_id
        self._index, self._storage = _make_index(self._config)
        self._ef_search = self._config.hnsw_ef_search
        self._rows = MapRows((3,))  # ids, stamps, poses (lcpr_core.map_rows)
        self._orientations = GrowableArray(np.float64, (4,))  # x, y, z, w of world_T_base; NaN = unknown
        self._source_codes = GrowableArray(np.int32)
        self._source_names: list[str] = []
        self._source_lookup: dict[str, int] = {}
        self.clouds = CloudStore()  # compact keyframe clouds for geometric verification, by id
        #: row-aligned Scan Contexts of the keyframes' raw clouds (match.method scan_context / fused), or None
        self.scan_contexts: ScanContextRows | None = None

    # ------------------------------------------------------------------ accessors
    @property
    def config(self) -> MapConfig:
        return dataclasses.replace(self._config, hnsw_ef_search=self._ef_search)

    @property
    def dim(self) -> int:
        return self._config.dim

    def __repr__(self) -> str:
        tag, index = self._config.descriptor_tag, self._config.index
        return f"DescriptorMap({len(self)} x {self.dim}-d {tag!r}, index={index!r})"

    @property
    def sources(self) -> list[str]:
        """Source name per entry (builds a Python list; O(N))."""
        names = self._source_names
        return [names[c] for c in self._source_codes.view().tolist()]

    @property
    def stamps(self) -> np.ndarray:
        """(N,) float64 stamp of each entry, in insertion order; read-only."""
        return self._rows.stamps

    @property
    def source_codes(self) -> np.ndarray:
        """(N,) int32 index into the source names per entry; read-only, O(1) (``sources`` builds a list)."""
        return self._source_codes.view()

    def source_at(self, row: int) -> str:
        """The source name of the entry at ``row`` (insertion position, not id)."""
        return self._source_names[int(self._source_codes.view()[row])]

    def source_code_of(self, name: str) -> int | None:
        """The code ``source_codes`` holds for source ``name``; None when no entry has that source."""
        return self._source_lookup.get(name)

    @property
    def orientations(self) -> np.ndarray:
        """(N, 4) float64 unit quaternions (x, y, z, w) of each entry's world_T_base; NaN where only the
        position (or nothing) was given. Read-only."""
        return self._orientations.view()

    def pose_matrices(self, rows: slice | Sequence[int] | np.ndarray) -> np.ndarray:
        """(K, 4, 4) world_T_base of the entries at ``rows`` (positions in insertion order, not ids); all NaN
        where the position or the orientation is unknown."""
        at = rows if isinstance(rows, slice) else np.asarray(rows, np.int64)
        p, q = self._rows.poses[at], self.orientations[at]
        out = np.zeros((len(p), 4, 4))
        out[:, :3, :3] = rotations_from_xyzw(q)
        out[:, :3, 3] = p
        out[:, 3, 3] = 1.0
        out[~(np.isfinite(p).all(axis=1) & np.isfinite(q).all(axis=1))] = np.nan
        return out

    def row_of(self, keyframe_id: int) -> int | None:
        """The row (insertion position) of an id, or None when the map lacks it."""
        ids = self._rows.ids
        if self._rows.ids_increasing:
            row = int(np.searchsorted(ids, keyframe_id))
            return row if row < len(ids) and ids[row] == keyframe_id else None
        found = np.flatnonzero(ids == keyframe_id)
        return int(found[0]) if len(found) else None

    def descriptor_at(self, row: int) -> np.ndarray:
        """(D,) float32 copy of the descriptor at ``row`` (insertion position, not id)."""
        if not 0 <= row < len(self):
            raise MapError(f"row {row} of a map of {len(self)} entries; expected 0..{len(self) - 1}")
        return self._xb()[row].copy()

    @property
    def descriptors(self) -> np.ndarray:
        """(N, D) float32 copy of the stored descriptors."""
        return self._xb().copy()

    def set_ef_search(self, ef_search: int) -> None:
        """Change the HNSW search breadth (speed/recall trade-off) of this map."""
        if isinstance(ef_search, bool) or not isinstance(ef_search, (int, np.integer)) or ef_search < 1:
            raise MapError(f"ef_search={ef_search!r} is not accepted; it must be a positive integer")
        self._ef_search = int(ef_search)

    # ------------------------------------------------------------------ adding
    def add(
        self,
        descriptors: ArrayLike,
        *,
        stamps: float | ArrayLike,
        poses: ArrayLike | None = None,
        sources: str | Sequence[str] | None = None,
        ids: int | ArrayLike | None = None,
    ) -> np.ndarray:
        """Append one (D,) or many (N, D) descriptors; returns their (N,) int64 ids.

        stamps: (N,) seconds (a float for one descriptor). poses: positions (N, 3) or (3,), or full
        world_T_base poses (N, 4, 4) or (4, 4) (position and orientation kept); NaN for unknown.
        sources: one name for all, or one per entry. ids: (N,) non-negative, unique and not yet in
        the map; default max id + 1 onwards.
        """
        x = self._check_vectors(descriptors, "descriptors")  # (N, D)
        n = len(x)
        positions, q = _split_poses(poses, n)
        new_ids, t, p = self._rows.check(n, stamps=stamps, poses=positions, ids=ids)  # (N,), (N,), (N, 3)
        src = _check_sources(sources, n)
        if n == 0:
            return new_ids
        codes = np.fromiter((self._source_code(s) for s in src), dtype=np.int32, count=n)
        self._index.add(x)
        self._rows.append(new_ids, t, p)
        self._orientations.extend(q)
        self._source_codes.extend(codes)
        return new_ids.copy()

    def _source_code(self, name: str) -> int:
        code = self._source_lookup.get(name)
        if code is None:
            code = len(self._source_names)
            self._source_names.append(name)
            self._source_lookup[name] = code
        return code

    def _check_vectors(self, values: ArrayLike, what: str) -> np.ndarray:
        try:
            arr = np.asarray(values)
        except (TypeError, ValueError) as err:
            raise MapError(f"{what} cannot be read as an array of floats: {err}") from err
        d = self.dim
        if arr.ndim not in (1, 2) or arr.shape[-1] != d:
            raise MapError(f"{what} of shape {tuple(arr.shape)} do not fit this map; expected ({d},) or (N, {d})")
        if arr.dtype.kind != "f":
            raise MapError(f"{what} have dtype {arr.dtype}; expected a floating dtype (float16/32/64)")
        arr = np.ascontiguousarray(arr.reshape(-1, d), dtype=np.float32)
        if not np.isfinite(arr).all():
            bad = np.flatnonzero(~np.isfinite(arr).all(axis=1))
            raise MapError(f"{what} rows {bad[:5].tolist()} contain NaN or inf (after casting to float32)")
        return arr

    # ------------------------------------------------------------------ search
    def search(
        self,
        query: ArrayLike,
        *,
        k: int = 20,
        exclude_after: float | ArrayLike | None = None,
        max_distance: float | None = None,
        allowed: np.ndarray | None = None,
    ) -> list[Match] | list[list[Match]]:
        """Nearest entries to one (D,) query -> list[Match], or to (Q, D) -> list[list[Match]].

        exclude_after: entries with stamp > exclude_after are skipped (pass
        query_stamp - window); a float for all queries or one per query (Q,).
        max_distance: drop hits farther than this (L2). allowed: a bool mask over the first rows (rows
        beyond it are not allowed); only those rows are searched (not with exclude_after). Hits are sorted
        by distance, at most k per query, fewer if the map (or window) is smaller.
        """
        single = np.ndim(query) == 1
        q = self._check_vectors(query, "query")  # (Q, D)
        if isinstance(k, bool) or not isinstance(k, (int, np.integer)) or k < 1:
            raise MapError(f"k={k!r} is not accepted; it must be a positive integer")
        if max_distance is not None and not (max_distance >= 0):
            raise MapError(f"max_distance={max_distance!r} is not accepted; it must be >= 0 or None")
        if allowed is not None:
            mask = np.asarray(allowed)
            if exclude_after is not None or mask.dtype != np.bool_ or mask.ndim != 1 or len(mask) > len(self):
                raise MapError(f"allowed of dtype {mask.dtype} shape {mask.shape} (exclude_after "
                               f"{exclude_after!r}); expected a bool mask over at most the map's {len(self)} rows, "
                               "without exclude_after")
            full = np.zeros(len(self), np.bool_)
            full[: len(mask)] = mask
            dist, pos = self._search_mask(q, int(k), full)
            return self._hits(dist, pos, max_distance, single)
        windows = _check_windows(exclude_after, len(q))
        if windows is None or windows.ndim == 0:
            after = None if windows is None else float(windows)
            dist, pos = self._search_block(q, int(k), after)
        else:
            blocks = [self._search_block(q[i : i + 1], int(k), float(w)) for i, w in enumerate(windows)]
            dist = np.concatenate([b[0] for b in blocks]) if blocks else np.empty((0, k), np.float32)
            pos = np.concatenate([b[1] for b in blocks]) if blocks else np.empty((0, k), np.int64)
        return self._hits(dist, pos, max_distance, single)

    def _hits(self, dist: np.ndarray, pos: np.ndarray, max_distance: float | None, single: bool
              ) -> list[Match] | list[list[Match]]:
        results = [self._matches(dist[i], pos[i], max_distance) for i in range(len(dist))]
        return results[0] if single else results

    def _search_block(self, q: np.ndarray, k: int, after: float | None) -> tuple[np.ndarray, np.ndarray]:
        """Squared distances and row positions (Q, k), position -1 where empty."""
        n = len(self)
        empty = (np.full((len(q), k), np.inf, np.float32), np.full((len(q), k), -1, np.int64))
        if n == 0:
            return empty
        if after is None:
            return self._index_search(q, k, None)
        stamps = self._rows.stamps
        if self._rows.stamps_sorted:
            end = int(np.searchsorted(stamps, after, side="right"))  # rows [0, end) allowed
            if end == 0:
                return empty
            if end == n:
                return self._index_search(q, k, None)
            if self._config.index == "flat" or end <= _EXACT_FALLBACK_ROWS:
                return _exact(q, self._xb()[:end], k, None)
            return self._index_search(q, k, faiss.IDSelectorRange(0, end))
        # Stamps out of order: select allowed rows with a bitmap (O(N) per search).
        return self._search_mask(q, k, stamps <= after)

    def _search_mask(self, q: np.ndarray, k: int, allowed: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`_search_block` over the rows where the (N,) bool mask ``allowed`` holds."""
        n = len(self)
        empty = (np.full((len(q), k), np.inf, np.float32), np.full((len(q), k), -1, np.int64))
        count = int(allowed.sum())
        if count == 0:
            return empty
        if count == n:
            return self._index_search(q, k, None)
        if self._config.index == "hnsw" and count <= _EXACT_FALLBACK_ROWS:
            rows = np.flatnonzero(allowed)
            return _exact(q, self._xb()[rows], k, rows)
        bitmap = np.packbits(allowed, bitorder="little")  # kept alive for the selector
        return self._index_search(q, k, faiss.IDSelectorBitmap(n, faiss.swig_ptr(bitmap)))

    def _index_search(self, q: np.ndarray, k: int, sel: Any) -> tuple[np.ndarray, np.ndarray]:
        if self._config.index == "hnsw":
            # faiss 1.15's stubs omit SearchParametersHNSW (it exists at run time)
            params = faiss.SearchParametersHNSW(efSearch=max(self._ef_search, k))  # type: ignore[attr-defined]
            if sel is not None:
                params.sel = sel
            return self._index.search(q, k, params=params)
        if sel is None:
            return self._index.search(q, k)
        # faiss wraps every SearchParameters* __init__ to take fields as keywords; its stubs do not say so
        return self._index.search(q, k, params=faiss.SearchParameters(sel=sel))  # type: ignore[call-arg]

    def _matches(self, dist2: np.ndarray, pos: np.ndarray, max_distance: float | None) -> list[Match]:
        keep = pos >= 0
        dist = np.sqrt(np.maximum(dist2[keep], 0.0)).astype(np.float64)
        pos = pos[keep]
        order = np.argsort(dist, kind="stable")  # faiss already sorts; make sure
        dist, pos = dist[order], pos[order]
        if max_distance is not None:
            inside = dist <= max_distance
            dist, pos = dist[inside], pos[inside]
        ids = self._rows.ids[pos].tolist()
        stamps = self._rows.stamps[pos].tolist()
        poses = self._rows.poses[pos]
        known = (~np.isnan(poses).all(axis=1)).tolist()
        codes = self._source_codes.view()[pos].tolist()
        out = []
        for rank, (i, d, s, p, c, k) in enumerate(zip(ids, dist.tolist(), stamps, poses.tolist(), codes, known,
                                                      strict=True)):
            pose = (p[0], p[1], p[2]) if k else None
            out.append(Match(id=i, distance=d, stamp=s, pose=pose, source=self._source_names[c], rank=rank))
        return out

    def _xb(self) -> np.ndarray:
        """(N, D) view of FAISS storage; invalid after the next add(), internal use only."""
        n = len(self)
        if n == 0:
            return np.empty((0, self.dim), np.float32)
        return faiss.rev_swig_ptr(self._storage.get_xb(), n * self.dim).reshape(n, self.dim)

    # ------------------------------------------------------------------ files
    def save(self, path: str | os.PathLike[str]) -> None:
        """Write the map to one .npz (no pickle), atomically: on failure the old file stays."""
        header = {
            "format": _FORMAT,
            "schema_version": SCHEMA_VERSION,
            "dim": self.dim,
            "model": self._config.descriptor_tag,  # the file keeps its field name
            "weights_id": self.weights_id,
            **self.config.index_params(),
            "count": len(self),
            "sources": self._source_names,
            "clouds": len(self.clouds),
        }
        arrays = {
            "descriptors": self._xb(),
            "ids": self._rows.ids,
            "stamps": self._rows.stamps,
            "poses": self._rows.poses,
            _ORIENTATIONS: self.orientations,
            "source_codes": self._source_codes.view(),
            **self.clouds.to_arrays(),
        }
        scs = self.scan_contexts
        if scs is not None and len(scs) == len(self):  # kept only when every row has its row
            header[_SC_HEADER] = scs.config.describing()
            arrays[_SCAN_CONTEXTS] = np.ascontiguousarray(scs.matrices())
        write_map_file(path, header, arrays, kind="descriptor map")

    @classmethod
    def keyframe_sessions(cls, path: str | os.PathLike[str]) -> tuple[list[str], np.ndarray]:
        """(session name, stamp) of every keyframe of the map file at ``path``, read without building its index
        (what a back end checks a prior graph against: ``PoseGraphBackend.check_map``)."""
        where = os.fspath(path)
        header, data = read_map_file(where, kind="map file", file_format=_FORMAT, versions=_READABLE_VERSIONS,
                                     required=("stamps", "source_codes"))  # not the descriptors, nor the clouds
        check_header_fields(header, (("sources", list),), kind="map file", where=where)
        names, codes = header["sources"], np.asarray(data["source_codes"])
        bad_codes = len(codes) != len(data["stamps"]) or (len(codes) and (codes.min() < 0 or codes.max() >= len(names)))
        if not all(isinstance(n, str) for n in names) or bad_codes:
            raise MapError(f"map file {where}: its sources {names!r} do not name every entry's source code (one "
                           "per stamp)")
        return [names[int(c)] for c in codes], np.asarray(data["stamps"], np.float64)

    @classmethod
    def load(cls, path: str | os.PathLike[str], *, expect: MapConfig | None = None) -> DescriptorMap:
        """Read a map written by save() and rebuild its index (the file is only read).

        With ``expect``, the file's dim and descriptor tag must equal expect's (else
        MapSchemaError) and the index is built as ``expect`` says; without it, as
        the file says.
        """
        where = os.fspath(path)
        header, data = read_map_file(where, kind="map file", file_format=_FORMAT, versions=_READABLE_VERSIONS,
                                     required=_NPZ_KEYS, optional_group=_CLOUD_KEYS,
                                     optional=(_ORIENTATIONS, _SCAN_CONTEXTS))
        check_header_fields(header, (("dim", int), ("model", str), ("index", str), ("count", int),
                                     ("sources", list)), kind="map file", where=where)
        if not all(isinstance(name, str) for name in header["sources"]):
            raise MapError(f"map file {where} header field 'sources' holds non-strings; expected a list of str")
        file_dim, file_model = header["dim"], header["model"]
        if expect is not None and (expect.dim != file_dim or expect.descriptor_tag != file_model):
            raise MapSchemaError(
                f"map file {where} holds {file_dim}-d {file_model!r} descriptors; "
                f"this detector makes {expect.dim}-d {expect.descriptor_tag!r} descriptors"
            )
        config = expect if expect is not None else _config_from_header(header, where)
        x, ids, stamps, poses, codes = _check_arrays(data, header, where)
        orientations = _check_orientations(data, header, where)

        weights = header.get("weights_id", "")  # maps saved before it was recorded have none
        if not isinstance(weights, str):
            raise MapError(f"map file {where} header field 'weights_id' is {weights!r}; expected a string")
        out = cls(config, weights_id=weights)
        if len(x):
            out._index.add(x)
        out._rows.append(ids, stamps, poses)
        out._orientations.extend(orientations)
        out._source_codes.extend(codes)
        out._source_names = list(header["sources"])
        out._source_lookup = {name: i for i, name in enumerate(out._source_names)}
        if all(key in data for key in _CLOUD_KEYS):
            try:
                out.clouds = CloudStore.from_arrays(data, where=f"map file {where}")
            except LcprError as err:
                raise MapError(str(err)) from err
        out.scan_contexts = _check_scan_contexts(data, header, where)
        return out


# ---------------------------------------------------------------------- helpers
def _make_index(config: MapConfig) -> tuple[Any, Any]:
    """The FAISS index and the IndexFlat that stores its vectors."""
    if config.index == "hnsw":
        hnsw = faiss.IndexHNSWFlat(config.dim, config.hnsw_m)
        hnsw.hnsw.efConstruction = config.hnsw_ef_construction
        hnsw.hnsw.efSearch = config.hnsw_ef_search
        return hnsw, faiss.downcast_index(hnsw.storage)
    flat = faiss.IndexFlatL2(config.dim)
    return flat, flat


def _exact(q: np.ndarray, xb: np.ndarray, k: int, rows: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """Brute-force k-NN over xb; ``rows`` maps xb rows back to map rows."""
    kk = min(k, len(xb))
    dist, pos = faiss.knn(q, xb, kk)
    if rows is not None:
        pos = np.where(pos >= 0, rows[np.maximum(pos, 0)], -1)
    if kk < k:
        dist = np.pad(dist, ((0, 0), (0, k - kk)), constant_values=np.inf)
        pos = np.pad(pos, ((0, 0), (0, k - kk)), constant_values=-1)
    return dist, pos


def _check_sources(sources: str | Sequence[str] | None, n: int) -> list[str]:
    if sources is None:
        return [""] * n
    if isinstance(sources, str):
        return [sources] * n
    out = list(sources)
    if len(out) != n:
        raise MapError(f"{len(out)} sources given for {n} descriptors; expected one string or {n}")
    bad = [s for s in out if not isinstance(s, str)]
    if bad:
        raise MapError(f"source {bad[0]!r} is not a string; sources must be str")
    return out


def _check_windows(exclude_after: float | ArrayLike | None, q: int) -> np.ndarray | None:
    if exclude_after is None:
        return None
    try:
        arr = np.asarray(exclude_after, dtype=np.float64)
    except (TypeError, ValueError) as err:
        raise MapError(f"exclude_after={exclude_after!r} is not accepted; expected a stamp or one per query") from err
    if arr.ndim != 0 and arr.shape != (q,):
        raise MapError(f"exclude_after of shape {arr.shape} does not fit {q} queries; expected a float or ({q},)")
    if np.isnan(arr).any():
        raise MapError("exclude_after is NaN; expected a stamp in seconds (inf allowed)")
    return arr



def _split_poses(poses: ArrayLike | None, n: int) -> tuple[ArrayLike | None, np.ndarray]:
    """(positions for MapRows.check, (n, 4) orientations) of what ``add`` was given: positions (n, 3) / (3,)
    pass through with unknown orientations; full poses (n, 4, 4) / (4, 4) are split, their rotation
    blocks checked (rows of NaN: unknown)."""
    unknown = np.full((n, 4), np.nan)
    if poses is None:
        return None, unknown
    try:
        arr = np.asarray(poses, dtype=np.float64)
    except (TypeError, ValueError) as err:
        raise MapError(f"poses cannot be read as floats: {err}") from err
    if arr.shape[-2:] != (4, 4):
        return arr, unknown
    if arr.shape == (4, 4) and n == 1:
        arr = arr[None]
    if arr.shape != (n, 4, 4):
        raise MapError(f"poses of shape {arr.shape} do not fit {n} descriptors; expected ({n}, 3) positions or "
                       f"({n}, 4, 4) world_T_base")
    known = np.isfinite(arr).all(axis=(1, 2))
    partly = ~known & ~np.isnan(arr).all(axis=(1, 2))
    if partly.any():
        raise MapError(f"poses {np.flatnonzero(partly)[:5].tolist()} are partly unknown (NaN or inf); give a "
                       "finite 4 x 4 world_T_base or all NaN")
    r = arr[known, :3, :3]
    off = np.abs(np.swapaxes(r, 1, 2) @ r - np.eye(3)).max(axis=(1, 2), initial=0.0) > _ROTATION_TOLERANCE
    off |= np.linalg.det(r) <= 0
    if off.any():
        bad = np.flatnonzero(known)[off]
        raise MapError(f"poses {bad[:5].tolist()} are not rigid: their rotation block is not orthonormal with "
                       "determinant +1")
    q = unknown.copy()
    q[known] = quaternions_xyzw(r)
    return arr[:, :3, 3], q


def _check_orientations(data: dict[str, np.ndarray], header: dict[str, Any], where: str) -> np.ndarray:
    """(N, 4) orientations of a map file; all unknown (NaN) for a version that did not store them."""
    n = header["count"]
    if _ORIENTATIONS not in data:
        if header["schema_version"] >= 3:
            raise MapError(f"map file {where} (schema version {header['schema_version']}) lacks {_ORIENTATIONS}; "
                           "expected (N, 4) quaternions")
        return np.full((n, 4), np.nan)
    q = data[_ORIENTATIONS]
    if q.shape != (n, 4) or q.dtype.kind != "f":
        raise MapError(f"map file {where}: {_ORIENTATIONS} has shape {q.shape} dtype {q.dtype}; expected ({n}, 4) "
                       "floats")
    q = q.astype(np.float64)
    known = np.isfinite(q).all(axis=1)
    if (~known & ~np.isnan(q).all(axis=1)).any() or (np.abs(np.linalg.norm(q[known], axis=1) - 1.0) > 1e-6).any():
        raise MapError(f"map file {where}: {_ORIENTATIONS} holds rows that are neither unit quaternions nor all NaN")
    return q


def _check_scan_contexts(data: dict[str, np.ndarray], header: dict[str, Any], where: str) -> ScanContextRows | None:
    """The file's Scan Context rows, or None when it has none (they are rebuilt from the clouds when needed)."""
    if _SCAN_CONTEXTS not in data:
        return None
    made = header.get(_SC_HEADER)
    try:
        config = ScanContextConfig(**made) if isinstance(made, dict) else None
    except (TypeError, LcprError) as err:
        raise MapError(f"map file {where}: header field {_SC_HEADER!r} is {made!r} ({err})") from err
    if config is None:
        raise MapError(f"map file {where} holds {_SCAN_CONTEXTS} but its header has no {_SC_HEADER!r} record "
                       "of what made them")
    m = data[_SCAN_CONTEXTS]
    shape = (header["count"], config.num_rings, config.num_sectors)
    if m.shape != shape or m.dtype != np.float32 or not np.isfinite(m).all() or (m < 0).any():
        raise MapError(f"map file {where}: {_SCAN_CONTEXTS} has shape {m.shape} dtype {m.dtype}; expected {shape} "
                       "finite float32 heights >= 0")
    rows = ScanContextRows(config)
    for sc in m:
        rows.add(sc if sc.any() else None)
    return rows


def _config_from_header(header: dict[str, Any], where: str) -> MapConfig:
    extra: dict[str, Any] = {}
    if header["index"] == "hnsw":
        extra = dict(hnsw_m=header.get("m"), hnsw_ef_search=header.get("ef_search"),
                     hnsw_ef_construction=header.get("ef_construction"))
    try:
        return MapConfig(dim=header["dim"], descriptor_tag=header["model"], index=header["index"], **extra)
    except MapError as err:
        raise MapError(f"map file {where} has a bad configuration: {err}") from err


def _check_arrays(data: dict[str, np.ndarray], header: dict[str, Any], where: str) -> tuple[np.ndarray, ...]:
    n, d = header["count"], header["dim"]
    expected = {
        "descriptors": ((n, d), "f"),
        "ids": ((n,), "iu"),
        "stamps": ((n,), "f"),
        "poses": ((n, 3), "f"),
        "source_codes": ((n,), "iu"),
    }
    for key, (shape, kinds) in expected.items():
        arr = data[key]
        if arr.shape != shape or arr.dtype.kind not in kinds:
            raise MapError(f"map file {where}: {key} has shape {arr.shape} dtype {arr.dtype}; expected {shape}")
    x = np.ascontiguousarray(data["descriptors"], dtype=np.float32)
    ids = data["ids"].astype(np.int64)
    codes = data["source_codes"].astype(np.int32)
    if not np.isfinite(x).all():
        raise MapError(f"map file {where}: descriptors contain NaN or inf")
    if n and (ids.min() < 0 or len(np.unique(ids)) != n):
        raise MapError(f"map file {where}: ids are negative or repeat; expected unique ids >= 0")
    if n and (codes.min() < 0 or codes.max() >= len(header["sources"])):
        raise MapError(f"map file {where}: source codes out of range 0..{len(header['sources']) - 1}")
    return x, ids, data["stamps"].astype(np.float64), data["poses"].astype(np.float64), codes
