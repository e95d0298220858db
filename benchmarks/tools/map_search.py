"""Top-k search latency, memory and HNSW recall of DescriptorMap (flat vs hnsw).

Two datasets of unit-norm descriptors per size:
  random     i.i.d. uniform on the sphere, independent queries: the worst case for HNSW;
  trajectory normalise(centre(t) + noise), centre(t) interpolating random anchors
             every 50 frames (a drive); queries revisit random frames with fresh noise.
Single queries are timed one at a time (the online use). "excl" lines exclude the
newest 10% of the map with exclude_after. Recall@k of hnsw is measured against
the flat index's top k (ids), with the same exclusion where it applies.

    python benchmarks/tools/map_search.py --sizes 10000,1000000
"""
from __future__ import annotations

import argparse
import gc
import sys
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from functools import partial
from typing import TYPE_CHECKING

import numpy as np

from lcpr_common.cli import tool_main

if TYPE_CHECKING:  # for annotations only: the functions import lcpr_core lazily
    from lcpr_core.descriptor_map import DescriptorMap, MapConfig

TARGET_EXACT_MS = 2.0  # 10k exact, per query
TARGET_APPROX_MS = 5.0  # 1M approximate, per query
TARGET_RECALL = 0.95
ANCHOR_EVERY = 50  # trajectory frames between anchors
FRAME_DT = 0.1  # seconds between map entries (10 Hz)


@dataclass
class Row:
    size: int
    data: str
    index: str
    case: str  # "plain", "excl", "ef=..."
    build_s: float | None
    mem_mb: float | None
    median_ms: float
    p90_ms: float
    batch_qps: float | None
    recall: float | None
    target: str


def rss_mb() -> float:
    from lcpr_core.timing import memory_mb

    return memory_mb()


def peak_rss_mb() -> float:
    from lcpr_core.timing import memory_mb

    return memory_mb(field="VmHWM")


def normalise(x: np.ndarray) -> np.ndarray:
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    return x


def chunks(n: int, step: int) -> Iterator[tuple[int, int]]:
    for lo in range(0, n, step):
        yield lo, min(lo + step, n)


def random_data(n: int, dim: int, queries: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    db = np.empty((n, dim), np.float32)
    for lo, hi in chunks(n, 65536):
        db[lo:hi] = normalise(rng.standard_normal((hi - lo, dim), dtype=np.float32))
    return db, normalise(rng.standard_normal((queries, dim), dtype=np.float32))


def trajectory_data(n: int, dim: int, queries: int, seed: int, *, noise: float = 0.15) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    anchors = normalise(rng.standard_normal((n // ANCHOR_EVERY + 2, dim), dtype=np.float32))

    def centre(t: np.ndarray) -> np.ndarray:  # (len(t), dim)
        a, w = np.divmod(t, ANCHOR_EVERY)
        w = (w / ANCHOR_EVERY).astype(np.float32)[:, None]
        return normalise((1 - w) * anchors[a] + w * anchors[a + 1])

    def sample(t: np.ndarray) -> np.ndarray:
        jitter = rng.standard_normal((len(t), dim), dtype=np.float32) * np.float32(noise / np.sqrt(dim))
        return normalise(centre(t) + jitter)

    db = np.empty((n, dim), np.float32)
    for lo, hi in chunks(n, 65536):
        db[lo:hi] = sample(np.arange(lo, hi))
    return db, sample(rng.integers(0, n, size=queries))


def build(
    map_cls: type[DescriptorMap], config: MapConfig, db: np.ndarray, label: str
) -> tuple[DescriptorMap, float, float]:
    from tqdm import tqdm

    before = rss_mb()
    start = time.perf_counter()
    m = map_cls(config)
    stamps = np.arange(len(db)) * FRAME_DT
    with tqdm(total=len(db), desc=f"build {label}", unit="vec", unit_scale=True, leave=False) as bar:
        for lo, hi in chunks(len(db), 20000):
            m.add(db[lo:hi], stamps=stamps[lo:hi])
            bar.update(hi - lo)
    return m, time.perf_counter() - start, rss_mb() - before


def time_single(search: Callable[[np.ndarray], list], queries: np.ndarray) -> tuple[float, float, list[list[int]]]:
    search(queries[0])  # warm-up
    times, hits = [], []
    for q in queries:
        t0 = time.perf_counter()
        res = search(q)
        times.append(time.perf_counter() - t0)
        hits.append([h.id for h in res])
    ms = np.array(times) * 1e3
    return float(np.median(ms)), float(np.percentile(ms, 90)), hits


def time_batch(m: DescriptorMap, queries: np.ndarray, k: int) -> float:
    t0 = time.perf_counter()
    m.search(queries, k=k)
    return len(queries) / (time.perf_counter() - t0)


def recall(approx: list[list[int]], exact: list[list[int]]) -> float:
    return float(np.mean([len(set(a) & set(e)) / max(len(e), 1) for a, e in zip(approx, exact, strict=True)]))


def verdict(size: int, index: str, median_ms: float, rec: float | None) -> str:
    if index == "flat" and size <= 10000:
        return f"<{TARGET_EXACT_MS:g}ms: {'ok' if median_ms < TARGET_EXACT_MS else 'MISS'}"
    if index == "hnsw" and size >= 1_000_000:
        ok = median_ms < TARGET_APPROX_MS and (rec or 0.0) >= TARGET_RECALL
        return f"<{TARGET_APPROX_MS:g}ms@>={TARGET_RECALL}: {'ok' if ok else 'MISS'}"
    return ""


def run_one(size: int, data: str, args: argparse.Namespace) -> list[Row]:
    from lcpr_core.descriptor_map import DescriptorMap, MapConfig

    make = random_data if data == "random" else trajectory_data
    db, queries = make(size, args.dim, args.queries, args.seed)
    k = args.k
    cut = float(int(0.9 * size) * FRAME_DT)  # exclude the newest 10%
    rows: list[Row] = []

    flat, build_s, mem = build(DescriptorMap, MapConfig(dim=args.dim, index="flat"), db, f"{data} {size} flat")
    med, p90, exact = time_single(partial(flat.search, k=k), queries)
    qps = time_batch(flat, queries, k)
    rows.append(Row(size, data, "flat", "plain", build_s, mem, med, p90, qps, 1.0, verdict(size, "flat", med, None)))
    med, p90, exact_excl = time_single(partial(flat.search, k=k, exclude_after=cut), queries)
    rows.append(Row(size, data, "flat", "excl", None, None, med, p90, None, 1.0, ""))
    del flat
    gc.collect()

    config = MapConfig(dim=args.dim, index="hnsw", hnsw_m=args.hnsw_m, hnsw_ef_construction=args.ef_construction)
    hnsw, build_s, mem = build(DescriptorMap, config, db, f"{data} {size} hnsw")
    del db
    gc.collect()
    for ef in args.ef_sweep:
        hnsw.set_ef_search(ef)
        med, p90, hits = time_single(partial(hnsw.search, k=k), queries)
        qps = time_batch(hnsw, queries, k)
        rec = recall(hits, exact)
        first = ef == args.ef_sweep[0]
        rows.append(Row(size, data, "hnsw", f"ef={ef}", build_s if first else None, mem if first else None,
                        med, p90, qps, rec, verdict(size, "hnsw", med, rec)))
    hnsw.set_ef_search(config.hnsw_ef_search)
    med, p90, hits = time_single(partial(hnsw.search, k=k, exclude_after=cut), queries)
    rows.append(Row(size, data, "hnsw", f"excl ef={config.hnsw_ef_search}", None, None, med, p90, None,
                    recall(hits, exact_excl), ""))
    del hnsw
    gc.collect()
    return rows


def fmt(value: float | None, spec: str) -> str:
    return "-" if value is None else format(value, spec)


def print_table(rows: list[Row]) -> None:
    head = f"{'size':>8} {'data':>10} {'index':>5} {'case':>12} {'build s':>8} {'mem MB':>7} " \
           f"{'med ms':>7} {'p90 ms':>7} {'batch q/s':>9} {'R@k':>6}  target"
    print(head)
    print("-" * len(head))
    for r in rows:
        print(f"{r.size:>8} {r.data:>10} {r.index:>5} {r.case:>12} {fmt(r.build_s, '.1f'):>8} "
              f"{fmt(r.mem_mb, '.0f'):>7} {r.median_ms:>7.3f} {r.p90_ms:>7.3f} {fmt(r.batch_qps, '.0f'):>9} "
              f"{fmt(r.recall, '.3f'):>6}  {r.target}")


@tool_main
def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sizes", default="10000,1000000", help="comma-separated map sizes")
    parser.add_argument("--data", default="random,trajectory", help="datasets: random, trajectory")
    parser.add_argument("--dim", type=int, default=None, help="descriptor size (default: MapConfig's)")
    parser.add_argument("--queries", type=int, default=200)
    parser.add_argument("--k", type=int, default=20)
    parser.add_argument("--hnsw-m", type=int, default=None, help="default: MapConfig's")
    parser.add_argument("--ef-construction", type=int, default=None, help="default: MapConfig's")
    parser.add_argument("--ef-sweep", default="32,64,128,256,512,1024,2048", help="hnsw ef_search values to time")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()

    from lcpr_core.descriptor_map import MapConfig

    defaults = MapConfig()
    args.dim = defaults.dim if args.dim is None else args.dim
    args.hnsw_m = defaults.hnsw_m if args.hnsw_m is None else args.hnsw_m
    args.ef_construction = defaults.hnsw_ef_construction if args.ef_construction is None else args.ef_construction
    args.ef_sweep = [int(v) for v in args.ef_sweep.split(",")]

    import faiss

    faiss.omp_set_num_threads(args.threads)
    print(f"faiss {faiss.__version__}, {args.threads} threads, dim {args.dim}, k {args.k}, "
          f"{args.queries} queries, hnsw M={args.hnsw_m} efConstruction={args.ef_construction}")
    rows: list[Row] = []
    for size in (int(s) for s in args.sizes.split(",")):
        for data in args.data.split(","):
            new = run_one(size, data, args)
            print_table(new)
            print(flush=True)
            rows += new
    print("=== summary (latency: single queries one at a time; mem: RSS delta of the build) ===")
    print_table(rows)
    print(f"peak RSS of the whole run: {peak_rss_mb():.0f} MiB")


if __name__ == "__main__":
    sys.exit(main())
