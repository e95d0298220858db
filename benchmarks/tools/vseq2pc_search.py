"""Query latency of the VSeq2PC scan database: the exact batched head pass vs the FAISS prefilter.

Per size, a ScanDatabase of random slice descriptors (N x 8 x 288, uniform [0, 1), added in
chunks so memory stays at one copy) is searched by revisit-like queries: a random scan's
random slice plus Gaussian noise. Every query is timed alone (the online use), top 10.

  full          the descriptor model's head on |D_seq - D_slice| for all N x 8 slices (chunks of
                --chunk scans), max over slices, top 10;
  prefilter M   FAISS (flat L2) picks the M scans with the smallest min-slice distance, the head
                scores only those.

recall@1: share of queries whose prefilter top-1 is the full pass's top-1; recall@10: mean
overlap of the two top-10 sets. With an untrained head these recalls say little (its scores
do not follow L2); pass --descriptor-weights for a trained one.

    python benchmarks/tools/vseq2pc_search.py --sizes 5000,100000 --queries 15
"""
from __future__ import annotations

import argparse
import sys
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from lcpr_common.cli import tool_main

if TYPE_CHECKING:  # torch and the package are imported after the arguments are read
    from lcpr_core.vseq2pc.models import DescriptorModel
    from lcpr_core.vseq2pc.retrieval import ScanDatabase, SearchConfig


@dataclass
class Row:
    size: int
    mode: str
    median_ms: float
    p90_ms: float
    recall1: float | None
    recall10: float | None


def rss_mb() -> float:
    from lcpr_core.timing import memory_mb

    return memory_mb()


def build(size: int, rng: np.random.Generator, *, chunk: int = 10000) -> ScanDatabase:
    from lcpr_core.vseq2pc.retrieval import ScanDatabase

    db = ScanDatabase(weights_id="bench")
    for lo in range(0, size, chunk):
        n = min(chunk, size - lo)
        db.add(rng.random((n, 8, 288), dtype=np.float32), stamps=np.arange(lo, lo + n, dtype=float))
    return db


def queries(db: ScanDatabase, count: int, rng: np.random.Generator, noise: float) -> np.ndarray:
    rows = rng.integers(0, len(db), count)
    slices = rng.integers(0, 8, count)
    base = db._view()[rows, slices]  # noqa: SLF001 - a benchmark may peek
    return (base + rng.normal(0.0, noise, base.shape)).astype(np.float32)


def timed(db: ScanDatabase, head: DescriptorModel, qs: np.ndarray, config: SearchConfig
          ) -> tuple[list[float], list[list[int]]]:
    times, tops = [], []
    db.search(qs[0], head, config=config)  # warm-up
    for q in qs:
        t0 = time.perf_counter()
        found = db.search(q, head, config=config)[0]
        times.append((time.perf_counter() - t0) * 1e3)
        tops.append([m.row for m in found])
    return times, tops


@tool_main
def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--sizes", default="5000,100000", help="database sizes in scans (comma-separated)")
    p.add_argument("--queries", type=int, default=15, help="timed queries per size and mode")
    p.add_argument("--prefilter", default="100,1000", help="prefilter sizes M (comma-separated)")
    p.add_argument("--chunk", type=int, default=4096, help="scans per batched head pass")
    p.add_argument("--noise", type=float, default=0.05, help="query noise (sigma) around the revisited slice")
    p.add_argument("--descriptor-weights", default=None, help="trained descriptor model (default: seeded init)")
    p.add_argument("--threads", type=int, default=None)
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args()

    import torch

    from lcpr_core.vseq2pc.checkpoint import load_descriptor_state_dict
    from lcpr_core.vseq2pc.models import DescriptorModel
    from lcpr_core.vseq2pc.retrieval import SearchConfig

    if args.threads:
        torch.set_num_threads(args.threads)
    torch.manual_seed(args.seed)
    head = DescriptorModel().eval()
    if args.descriptor_weights:
        head.load_state_dict(load_descriptor_state_dict(args.descriptor_weights))
    rng = np.random.default_rng(args.seed)
    rows: list[Row] = []
    print(f"torch threads {torch.get_num_threads()}; head: {args.descriptor_weights or 'seeded initialisation'}")
    for size in (int(s) for s in args.sizes.split(",")):
        t0 = time.perf_counter()
        db = build(size, rng)
        print(f"{size} scans: built in {time.perf_counter() - t0:.1f} s, RSS {rss_mb():.0f} MiB "
              f"(descriptors {size * 8 * 288 * 4 / 2**20:.0f} MiB)", flush=True)
        qs = queries(db, args.queries, rng, args.noise)
        exact = SearchConfig(k=10, exclude_recent_s=None, chunk_scans=args.chunk)
        full_ms, full_top = timed(db, head, qs, exact)
        rows.append(Row(size, "full", float(np.median(full_ms)), float(np.percentile(full_ms, 90)), None, None))
        print(f"  full pass: median {rows[-1].median_ms:.1f} ms", flush=True)
        for m in (int(v) for v in args.prefilter.split(",")):
            if m >= size:
                continue
            config = SearchConfig(k=10, exclude_recent_s=None, chunk_scans=args.chunk, prefilter=m)
            ms, top = timed(db, head, qs, config)
            r1 = float(np.mean([a[0] == b[0] for a, b in zip(top, full_top, strict=True)]))
            r10 = float(np.mean([len(set(a) & set(b)) / 10 for a, b in zip(top, full_top, strict=True)]))
            rows.append(Row(size, f"prefilter {m}", float(np.median(ms)), float(np.percentile(ms, 90)), r1, r10))
            print(f"  prefilter {m}: median {rows[-1].median_ms:.1f} ms", flush=True)
        del db
    print(f"\n{'scans':>8}  {'mode':<15} {'median ms':>10} {'p90 ms':>8} {'recall@1':>9} {'recall@10':>10}")
    for r in rows:
        rec1 = "-" if r.recall1 is None else f"{r.recall1:.2f}"
        rec10 = "-" if r.recall10 is None else f"{r.recall10:.2f}"
        print(f"{r.size:>8}  {r.mode:<15} {r.median_ms:>10.1f} {r.p90_ms:>8.1f} {rec1:>9} {rec10:>10}")


if __name__ == "__main__":
    sys.exit(main())
