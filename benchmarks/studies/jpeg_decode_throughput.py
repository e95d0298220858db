"""How fast can a batch of camera JPEGs become pixels: nvJPEG in one call, frame by frame, from several threads,
against libjpeg-turbo's reduced-size decode in a CPU thread pool. Images per second, naming the CPU and GPU.

    python benchmarks/studies/jpeg_decode_throughput.py [--frames 16] [--repeats 5]

The images are the twelve real nuScenes JPEGs in ../shared/data (1600 x 900), repeated to ``--frames``
frames of six: what ``lcpr_eval`` decodes per network call on a GPU. The CPU decode is the one the
``turbo`` decoder runs (scaled by 1/2 inside libjpeg-turbo for the released 256 x 704 input).
"""
from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor


def median_ms(run: Callable[[], object], repeats: int) -> float:
    run()  # warm up (allocations, handles, thread start-up)
    times = []
    for _ in range(repeats):
        tic = time.perf_counter()
        run()
        times.append(time.perf_counter() - tic)
    return statistics.median(times) * 1e3


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--frames", type=int, default=16)
    p.add_argument("--repeats", type=int, default=5)
    args = p.parse_args(argv)

    import torch

    from lcpr_common.shared_data import shared_dir
    from lcpr_core.lcpr.preprocess.dataset_files import find_nuscenes_keyframe
    from lcpr_core.lcpr.preprocess.decode import rgb_array
    from lcpr_core.timing import cpu_model

    shared = shared_dir()
    if shared is None:
        p.error("../shared (the real nuScenes keyframes) not found; set LCPR_SHARED_DIR")
    jpegs = [image for name in ("nuscenes_sample", "nuscenes_sample2")
             for image in find_nuscenes_keyframe(shared / "data" / name).read()[0]]
    images = (jpegs * (6 * args.frames // len(jpegs) + 1))[:6 * args.frames]
    count = len(images)

    def report(name: str, ms: float) -> None:
        print(f"{name}: {ms:.1f} ms for {count} images = {count / ms * 1e3:.0f} images/s", flush=True)

    cpus = os.cpu_count() or 1

    def cpu_decode(image: bytes) -> object:
        return rgb_array(image, (256, 704))

    for threads in sorted({1, 2, min(8, cpus), max(cpus - 2, 1)}):
        with ThreadPoolExecutor(threads) as cpu_pool:
            report(f"CPU turbo 1/2-scale decode, {threads} threads",
                   median_ms(lambda: list(cpu_pool.map(cpu_decode, images)), args.repeats))
    if torch.cuda.is_available():
        from torchvision.io import ImageReadMode, decode_jpeg  # type: ignore[import-not-found, unused-ignore]

        data = [torch.frombuffer(bytearray(b), dtype=torch.uint8) for b in images]

        def nvjpeg(chunk: list[torch.Tensor]) -> object:
            return decode_jpeg(chunk, mode=ImageReadMode.RGB, device="cuda")

        def synced(run: Callable[[], object]) -> Callable[[], None]:
            def go() -> None:
                run()
                torch.cuda.synchronize()
            return go

        report("nvJPEG, one call", median_ms(synced(lambda: nvjpeg(data)), args.repeats))
        report("nvJPEG, one call per frame of six",
               median_ms(synced(lambda: [nvjpeg(data[i:i + 6]) for i in range(0, count, 6)]), args.repeats))
        for threads in (2, 4):
            parts = [data[i::threads] for i in range(threads)]
            with ThreadPoolExecutor(threads) as gpu_pool:
                def in_threads(pool: ThreadPoolExecutor = gpu_pool, chunks: list[list[torch.Tensor]] = parts) -> object:
                    return list(pool.map(nvjpeg, chunks))

                report(f"nvJPEG, {threads} threads, one call each", median_ms(synced(in_threads), args.repeats))
        print(f"GPU {torch.cuda.get_device_name()}")
    print(f"CPU {cpu_model()} ({cpus} cores); {count} JPEGs of 1600 x 900")
    return 0


if __name__ == "__main__":
    sys.exit(main())
