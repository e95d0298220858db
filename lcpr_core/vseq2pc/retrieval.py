"""The LiDAR scan database of VSeq2PC and its search.

Each scan is stored as its 8 slice descriptors (8 x 288, slice s = the 90-degree
window starting at sector 135 + 45 s). A query (a sequence descriptor, 288) is scored
against every allowed scan in one batched pass: the descriptor model's head on
|D_seq - D_slice| for all N x 8 slices, the scan's logit being the maximum over its
slices. Optionally a FAISS prefilter first keeps the M scans with the smallest
min-slice L2 distance and the head scores only those (approximate: the head is not a
function of the L2 distance).

Memory: descriptors live once, inside a FAISS IndexFlatL2 of N x 8 rows
(N * 9216 bytes: 0.92 GB for 100k scans); per scan 8 + 8 + 128 bytes of id, stamp and
pose. A search allocates at most ``chunk_scans`` x 8 x (288 + 128) floats at a time.
Clouds (for geometric verification, :mod:`lcpr_core.vseq2pc.verify`): each scan's compact cloud,
int16 centimetres, 6 bytes a point, at most 4096 points (24 KiB) + 16 bytes a scan at the default
``verify.SCAN_CLOUD``; a map file of schema 1 (before clouds) loads with none.

Files: one .npz (no pickle), written atomically, with a JSON header naming the
format, schema version and the descriptor weights that made the descriptors.
"""
from __future__ import annotations

import math
import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import faiss
import numpy as np
import torch
from numpy.typing import ArrayLike

from ..errors import InputShapeError, InvalidValueError, LcprError, MapError, MapSchemaError
from ..exclusion import matchable, matchable_prefix
from ..map_file import check_header_fields, read_map_file, write_map_file
from ..map_rows import MapRows, RowAccess
from ..verification.clouds import CloudStore, compact_cloud
from ..verification.config import CloudConfig
from .models import DescriptorModel
from .net import DESCRIPTOR_DIM, SLICES, Vseq2pcNet
from .preprocess import structure_feature
from .sequence import SequenceBatch

__all__ = ["DATABASE_SCHEMA_VERSION", "SCAN_CLOUD", "ScanDatabase", "ScanMatch", "SearchConfig", "Vseq2pcMap",
           "head_logits"]

DATABASE_SCHEMA_VERSION = 2  # 2: scan clouds (cloud_ids, cloud_counts, cloud_points); 1 still loads
_READABLE_VERSIONS = (1, 2)
_FORMAT = "lcpr_core.vseq2pc_map"
_NPZ_KEYS = ("descriptors", "ids", "stamps", "poses")
_CLOUD_KEYS = ("cloud_ids", "cloud_counts", "cloud_points")

#: What a scan keeps for verification: 0.4 m voxels up to 50 m (a camera's pseudo-cloud reaches 25 m ahead of
#: frames at most 15 m on), at most 4096 points: <= 24 KiB per scan (6 bytes a point) + 16 bytes.
SCAN_CLOUD = CloudConfig(voxel=0.4, max_points=4096, min_range=1.0, max_range=50.0)


@dataclass(frozen=True)
class SearchConfig:
    """k: candidates per query. exclude_recent_s: scans stamped later than query stamp minus this are
    skipped (None = no time rule). exclude_recent_rows: with a query row, the scans at that row, after
    it, and the this-many before it are skipped (a frame gap; 0 = only the row itself and later ones).
    prefilter: None = exact head on every scan; M = FAISS top-M scans by min-slice L2 distance first.
    chunk_scans: scans per batched pass (bounds memory)."""

    k: int = 10
    exclude_recent_s: float | None = 30.0
    exclude_recent_rows: int = 0
    prefilter: int | None = None
    chunk_scans: int = 4096

    def __post_init__(self) -> None:
        if isinstance(self.k, bool) or not isinstance(self.k, int) or self.k < 1:
            raise InvalidValueError(f"k={self.k!r}; expected a positive integer")
        if self.exclude_recent_s is not None and not self.exclude_recent_s >= 0:
            raise InvalidValueError(f"exclude_recent_s={self.exclude_recent_s!r}; expected seconds >= 0 or None")
        if self.exclude_recent_rows < 0:
            raise InvalidValueError(f"exclude_recent_rows={self.exclude_recent_rows!r}; expected >= 0")
        if self.prefilter is not None and self.prefilter < 1:
            raise InvalidValueError(f"prefilter={self.prefilter!r}; expected None (exact) or a positive scan count")
        if self.chunk_scans < 1:
            raise InvalidValueError(f"chunk_scans={self.chunk_scans!r}; expected a positive scan count")


@dataclass(frozen=True)
class ScanMatch:
    """One candidate scan. probability: sigmoid(logit), the network's belief that the sequence and the
    scan show the same place; slice: the best slice (the camera looked along the scan's yaw + 45 * slice
    degrees); pose: 4 x 4 or None; rank counts from 0 (the retrieval rank).

    Verification (:mod:`lcpr_core.vseq2pc.verify`) fills the rest: ``verified`` (the registration
    accepted it), ``fitness`` (overlap 0..1), ``match_T_query`` (4 x 4: the query camera's pose in the
    scan's LiDAR frame; None when not registered), ``covariance`` (6 x 6 over x, y, z, roll, pitch, yaw
    of match_T_query) and ``verification``: "accepted", why not, or "off"."""

    row: int
    id: int
    stamp: float
    pose: np.ndarray | None
    logit: float
    probability: float
    slice: int
    rank: int
    verified: bool = False
    fitness: float = 0.0
    match_T_query: np.ndarray | None = None
    covariance: np.ndarray | None = None
    verification: str = "off"

    @property
    def relative_yaw_deg(self) -> float:
        """The best slice's centre direction in the scan's frame, degrees in (-180, 180]."""
        yaw = 45.0 * self.slice
        return yaw - 360.0 if yaw > 180.0 else yaw


def head_logits(head: DescriptorModel, query: torch.Tensor, slices: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The max-slice rule (every use of it): a query (288,), or (..., 1, 288) beside its scans, against
    (..., 8, 288) slice descriptors -> the best slice's logit and its index, each (...)."""
    logits = head.logit(query, slices)  # ... x 8, broadcast over the scans and slices
    best = logits.max(dim=-1)
    return best.values, best.indices


class ScanDatabase(RowAccess):
    """Slice descriptors (N x 8 x 288) with id, stamp and pose per scan; rows count from 0 in insertion order.

    Not thread-safe: share one database between threads behind a lock.
    """

    def __init__(self, *, weights_id: str = "") -> None:
        self.weights_id = weights_id
        self._index = faiss.IndexFlatL2(DESCRIPTOR_DIM)  # N * 8 slice rows: the only copy of the descriptors
        self._rows = MapRows((4, 4), unit="scans")  # ids, stamps, poses (lcpr_core.map_rows)
        self.clouds = CloudStore()  # compact scan clouds by id, for geometric verification

    def __repr__(self) -> str:
        return f"ScanDatabase({len(self)} scans x {SLICES} x {DESCRIPTOR_DIM}, weights {self.weights_id or '?'})"

    @property
    def descriptors(self) -> np.ndarray:
        """(N, 8, 288) float32 copy."""
        return self._view().copy()

    def _view(self) -> np.ndarray:
        """(N, 8, 288) view of FAISS storage; invalid after the next add(), internal use."""
        n = len(self)
        if n == 0:
            return np.zeros((0, SLICES, DESCRIPTOR_DIM), np.float32)
        flat = faiss.rev_swig_ptr(self._index.get_xb(), n * SLICES * DESCRIPTOR_DIM)
        return flat.reshape(n, SLICES, DESCRIPTOR_DIM)

    # ------------------------------------------------------------------ adding
    def add(self, descriptors: np.ndarray, *, stamps: ArrayLike, poses: np.ndarray | None = None,
            ids: int | np.ndarray | None = None) -> np.ndarray:
        """Append (8, 288) or (n, 8, 288) slice descriptors; returns their (n,) ids.

        stamps: seconds, one per scan. poses: (4, 4) or (n, 4, 4) world_T_lidar, None = unknown.
        ids: unique, not yet used; default: one more than the largest so far.
        """
        x = np.asarray(descriptors)
        if x.shape == (SLICES, DESCRIPTOR_DIM):
            x = x[None]
        if x.ndim != 3 or x.shape[1:] != (SLICES, DESCRIPTOR_DIM) or x.dtype.kind != "f":
            raise MapError(f"descriptors of shape {x.shape} dtype {x.dtype}; expected float (n, {SLICES}, "
                           f"{DESCRIPTOR_DIM}) or ({SLICES}, {DESCRIPTOR_DIM})")
        x = np.ascontiguousarray(x, np.float32)
        if not np.isfinite(x).all():
            raise MapError("descriptors contain NaN or inf")
        n = len(x)
        new_ids, t, p = self._rows.check(n, stamps=stamps, poses=poses, ids=ids)
        if n == 0:
            return new_ids
        self._index.add(x.reshape(n * SLICES, DESCRIPTOR_DIM))
        self._rows.append(new_ids, t, p)
        return new_ids.copy()

    # ------------------------------------------------------------------ search
    def allowed(self, *, stamp: float | None, row: int | None, config: SearchConfig) -> np.ndarray | slice:
        """The rows a query may match: a prefix ``slice(0, end)`` when that is what the rules leave
        (stamps in order), else a sorted row array."""
        n = len(self)
        end = n
        if row is not None:
            end = min(end, max(0, int(row) - config.exclude_recent_rows))
        if stamp is None or config.exclude_recent_s is None:
            return slice(0, end)
        stamps = self._rows.stamps[:end]
        if self._rows.stamps_sorted:
            return slice(0, matchable_prefix(stamps, stamp, config.exclude_recent_s))
        return np.flatnonzero(matchable(stamps, stamp, config.exclude_recent_s))

    def search(self, query: np.ndarray, head: DescriptorModel, *, config: SearchConfig = SearchConfig(),
               stamps: float | Sequence[float] | np.ndarray | None = None,
               rows: int | Sequence[int] | np.ndarray | None = None) -> list[list[ScanMatch]]:
        """Best scans for each (Q, 288) query (or one (288,)), best first, at most ``config.k``.

        stamps: the query stamps for the time rule (None: no time rule); rows: the query's own
        row for the frame-gap rule (None: no gap rule). Ties keep the lower row first.
        """
        q = np.asarray(query, np.float32)
        if q.shape == (DESCRIPTOR_DIM,):
            q = q[None]
        if q.ndim != 2 or q.shape[1] != DESCRIPTOR_DIM:
            raise InputShapeError(f"query of shape {q.shape}; expected (Q, {DESCRIPTOR_DIM}) or ({DESCRIPTOR_DIM},)")
        qs = _per_query(stamps, len(q), "stamps")
        qr = _per_query(rows, len(q), "rows")
        out = []
        for i in range(len(q)):
            allowed = self.allowed(stamp=None if qs is None else qs[i], row=None if qr is None else int(qr[i]),
                                   config=config)
            logits, best, cand = self._score(q[i], head, allowed, config)
            out.append(self._matches(logits, best, cand, config.k))
        return out

    def _score(self, q: np.ndarray, head: DescriptorModel, allowed: np.ndarray | slice, config: SearchConfig
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Logits, best slices and rows of the scored scans."""
        rows = np.arange(len(self))[allowed] if isinstance(allowed, slice) else allowed
        target: np.ndarray | slice = allowed
        if config.prefilter is not None and config.prefilter < len(rows):
            rows = target = self._prefilter(q, allowed, rows, config.prefilter)
        return (*self.exact_logits(q, head, target, chunk_scans=config.chunk_scans), rows)

    def exact_logits(self, query: np.ndarray, head: DescriptorModel, rows: np.ndarray | slice | None = None, *,
                     chunk_scans: int = 4096) -> tuple[np.ndarray, np.ndarray]:
        """Max-slice logits (n,) and best slices (n,) of one (288,) query against ``rows`` (default all)."""
        view = self._view()
        rows = slice(0, len(self)) if rows is None else rows
        contiguous = isinstance(rows, slice)
        n = len(range(*rows.indices(len(self)))) if isinstance(rows, slice) else len(rows)
        start = rows.indices(len(self))[0] if isinstance(rows, slice) else 0
        logits, best = np.empty(n, np.float32), np.empty(n, np.int64)
        param = next(head.parameters())
        qt = torch.from_numpy(np.asarray(query, np.float32)).to(param.device, param.dtype)
        with torch.inference_mode():
            for lo in range(0, n, chunk_scans):
                hi = min(lo + chunk_scans, n)
                block = view[start + lo : start + hi] if contiguous else view[rows[lo:hi]]  # type: ignore[index]
                values, slices = head_logits(head, qt, torch.from_numpy(np.ascontiguousarray(block)).to(
                    param.device, param.dtype))
                logits[lo:hi] = values.float().cpu().numpy()
                best[lo:hi] = slices.cpu().numpy()
        return logits, best

    def _prefilter(self, q: np.ndarray, allowed: np.ndarray | slice, rows: np.ndarray, m: int) -> np.ndarray:
        """The m allowed scans with the smallest min-slice L2 distance to q (sorted by row)."""
        if isinstance(allowed, slice):
            end = allowed.indices(len(self))[1]
            sel: faiss.IDSelector | None = None if end == len(self) else faiss.IDSelectorRange(0, end * SLICES)
            bitmap = None
        else:
            mask = np.zeros(len(self) * SLICES, bool)
            mask[(rows[:, None] * SLICES + np.arange(SLICES)).reshape(-1)] = True
            bitmap = np.packbits(mask, bitorder="little")  # kept alive while the selector is used
            sel = faiss.IDSelectorBitmap(len(mask), faiss.swig_ptr(bitmap))
        kk = min(m * SLICES, len(rows) * SLICES)  # m * 8 slices always cover at least m scans
        # faiss wraps every SearchParameters* __init__ to take fields as keywords; its stubs do not say so
        params = None if sel is None else faiss.SearchParameters(sel=sel)  # type: ignore[call-arg]
        _, hits = self._index.search(q[None], kk, params=params)
        del bitmap
        scans = hits[0][hits[0] >= 0] // SLICES
        _, first = np.unique(scans, return_index=True)
        return np.sort(scans[np.sort(first)][:m])

    def _matches(self, logits: np.ndarray, best: np.ndarray, rows: np.ndarray, k: int) -> list[ScanMatch]:
        if len(rows) == 0:
            return []
        kk = min(k, len(rows))
        top = np.argpartition(-logits, kk - 1)[:kk] if kk < len(rows) else np.arange(len(rows))
        top = top[np.lexsort((rows[top], -logits[top]))]
        ids, stamps, poses = self._rows.ids, self._rows.stamps, self._rows.poses
        out = []
        for rank, j in enumerate(top.tolist()):
            r = int(rows[j])
            pose = None if np.isnan(poses[r]).all() else poses[r].copy()
            logit = float(logits[j])
            out.append(ScanMatch(row=r, id=int(ids[r]), stamp=float(stamps[r]), pose=pose, logit=logit,
                                 probability=_sigmoid(logit), slice=int(best[j]), rank=rank))
        return out

    # ------------------------------------------------------------------ files
    def save(self, path: str | os.PathLike[str]) -> None:
        """Write the database to one .npz (no pickle), atomically: on failure the old file stays."""
        header = {"format": _FORMAT, "schema_version": DATABASE_SCHEMA_VERSION, "slices": SLICES,
                  "dim": DESCRIPTOR_DIM, "count": len(self), "weights_id": self.weights_id,
                  "clouds": len(self.clouds)}
        arrays = {"descriptors": self._view(), "ids": self._rows.ids, "stamps": self._rows.stamps,
                  "poses": self._rows.poses, **self.clouds.to_arrays()}
        write_map_file(path, header, arrays, kind="scan database")

    @classmethod
    def load(cls, path: str | os.PathLike[str], *, expect_weights_id: str | None = None) -> ScanDatabase:
        """Read a file written by :meth:`save`. With ``expect_weights_id``, the file's descriptors must
        come from those weights (else MapSchemaError)."""
        where = os.fspath(path)
        header, data = read_map_file(where, kind="scan database", file_format=_FORMAT,
                                     versions=_READABLE_VERSIONS, required=_NPZ_KEYS, optional_group=_CLOUD_KEYS)
        if header.get("slices") != SLICES or header.get("dim") != DESCRIPTOR_DIM:
            raise MapSchemaError(f"scan database {where} holds {header.get('slices')} x {header.get('dim')} "
                                 f"descriptors per scan; expected {SLICES} x {DESCRIPTOR_DIM}")
        check_header_fields(header, (("count", int), ("weights_id", str)), kind="scan database", where=where)
        if expect_weights_id is not None and header["weights_id"] != expect_weights_id:
            raise MapSchemaError(f"scan database {where} was made with descriptor weights "
                                 f"{header['weights_id']!r}; these weights are {expect_weights_id!r}")
        n = header["count"]
        shapes = {"descriptors": ((n, SLICES, DESCRIPTOR_DIM), "f"), "ids": ((n,), "iu"),
                  "stamps": ((n,), "f"), "poses": ((n, 4, 4), "f")}
        for key, (shape, kinds) in shapes.items():
            if data[key].shape != shape or data[key].dtype.kind not in kinds:
                raise MapError(f"scan database {where}: {key} has shape {data[key].shape} dtype {data[key].dtype}; "
                               f"expected {shape}")
        out = cls(weights_id=header["weights_id"])
        try:
            out.add(data["descriptors"], stamps=data["stamps"], poses=data["poses"], ids=data["ids"])
        except MapError as err:
            raise MapError(f"scan database {where} is damaged: {err}") from err
        if all(key in data for key in _CLOUD_KEYS):
            try:
                out.clouds = CloudStore.from_arrays(data, where=f"scan database {where}")
            except LcprError as err:
                raise MapError(str(err)) from err
        return out


def _sigmoid(x: float) -> float:
    return 1.0 / (1.0 + math.exp(-x)) if x >= 0 else math.exp(x) / (1.0 + math.exp(x))


def _per_query(values: Any, q: int, what: str) -> np.ndarray | None:
    if values is None:
        return None
    arr = np.asarray(values, np.float64)
    if arr.ndim == 0:
        arr = np.full(q, float(arr))
    if arr.shape != (q,) or np.isnan(arr).any():
        raise InputShapeError(f"{what} of shape {arr.shape}; expected one number or ({q},), not NaN")
    return arr


@dataclass
class Vseq2pcMap:
    """The networks, a scan database and search settings: what a VSeq2PC node needs.

    >>> vmap = Vseq2pcMap(Vseq2pcNet.from_files(sequence=..., descriptor=...))
    >>> vmap.add_scan(points, labels, stamp=t, pose=world_T_lidar)
    >>> matches = vmap.query(batch)            # one list of ScanMatch per query of the batch
    """

    net: Vseq2pcNet
    database: ScanDatabase | None = None
    config: SearchConfig = field(default_factory=SearchConfig)

    def __post_init__(self) -> None:
        if self.database is None:
            self.database = ScanDatabase(weights_id=self.net.weights_id)
        elif self.database.weights_id and self.database.weights_id != self.net.weights_id:
            raise MapSchemaError(f"the scan database was made with descriptor weights {self.database.weights_id!r}; "
                                 f"the network's are {self.net.weights_id!r}")

    @property
    def db(self) -> ScanDatabase:
        assert self.database is not None
        return self.database

    def __len__(self) -> int:
        return len(self.db)

    def add_scan(self, points: np.ndarray, labels: np.ndarray, *, stamp: float, pose: np.ndarray | None = None,
                 id: int | None = None, keep_cloud: bool = True) -> int:
        """Describe one labelled cloud (N x >=3 LiDAR-frame points, N SemanticKITTI labels) and add it, with its
        compact cloud (:data:`SCAN_CLOUD`) unless ``keep_cloud`` is False."""
        cloud = compact_cloud(points, SCAN_CLOUD) if keep_cloud else None
        return self.add_feature(structure_feature(points, labels), stamp=stamp, pose=pose, id=id, cloud=cloud)

    def add_feature(self, feature: np.ndarray, *, stamp: float, pose: np.ndarray | None = None,
                    id: int | None = None, cloud: np.ndarray | None = None) -> int:
        """Add a scan from its 12 x 360 structure feature; returns its id. ``cloud``: its compact cloud
        (M x 3, :func:`lcpr_core.vseq2pc.verify.scan_cloud`), kept for verification."""
        desc = self.net.slice_descriptors(np.asarray(feature, np.float32)[None])
        new_id = int(self.db.add(desc, stamps=stamp, poses=pose, ids=id)[0])
        if cloud is not None:
            self.db.clouds.add(new_id, cloud)
        return new_id

    def cloud(self, scan_id: int) -> np.ndarray | None:
        """The scan's compact cloud (M x 3 float32, its LiDAR frame), or None when the map has none for it."""
        return self.db.clouds.get(scan_id)

    def query(self, batch: SequenceBatch | np.ndarray, *, stamps: np.ndarray | None = None,
              rows: np.ndarray | None = None, config: SearchConfig | None = None) -> list[list[ScanMatch]]:
        """Best scans for each query of a SequenceBatch (its query stamps feed the time rule) or of a
        B x 4 x 12 x 90 array (give ``stamps`` for the time rule)."""
        if isinstance(batch, SequenceBatch):
            frames, stamps = batch.frames, batch.query_stamps if stamps is None else stamps
        else:
            frames = batch
        d_seq = self.net.query_descriptors(frames)
        return self.db.search(d_seq, self.net.descriptor, config=config or self.config, stamps=stamps, rows=rows)

    def save(self, path: str | os.PathLike[str]) -> None:
        self.db.save(path)

    @classmethod
    def load(cls, path: str | os.PathLike[str], net: Vseq2pcNet, *, config: SearchConfig | None = None) -> Vseq2pcMap:
        """A saved database for ``net`` (refused when made with other descriptor weights)."""
        return cls(net, ScanDatabase.load(path, expect_weights_id=net.weights_id), config or SearchConfig())
