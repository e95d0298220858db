"""Frame-to-loop latency of the node's pipeline on a drive replayed in real time, without DDS.

    python benchmarks/tools/replay_latency.py BAG [--device cuda] [--weights FILE] [--rate 1.0] [--limit N]

The bag's frames are read first; then each is handed to the node's worker
(:class:`ros_common.worker.Worker` with one waiting slot, as ``lcpr_node``) at its header-stamp
spacing divided by ``--rate``, and the worker runs ``LoopDetector.process`` (decoding, range
image, network, search, verification) as the node does. Prints, naming the CPU and GPU: p50 / p90
of the latency from handing a frame over to its result, for keyframes and for published loops,
and the frames dropped because the worker was busy. Without ``--weights`` the released size with
seeded weights (speed does not depend on their values; loops need trained weights, so their count
is not the point). DDS transport and message conversion are not included: ``lcpr_demo`` measures
those through a real node.
"""
from __future__ import annotations

import argparse
import sys
import threading
import time
from pathlib import Path

import numpy as np

from lcpr_common.cli import tool_main


def percentiles(values: list[float]) -> str:
    if not values:
        return "-"
    p50, p90 = np.percentile(np.asarray(values) * 1e3, [50, 90])
    return f"p50 {p50:.1f} ms, p90 {p90:.1f} ms ({len(values)})"


@tool_main
def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("bag", type=Path, help="a nuScenes-rig rosbag2 (e.g. msg_tools_synth --rig nuscenes)")
    p.add_argument("--device", default="cpu")
    p.add_argument("--weights", default="", help="LCPR weights (default: the released size, seeded)")
    p.add_argument("--rate", type=float, default=1.0, help="replay speed (1.0 = the bag's own timing)")
    p.add_argument("--limit", type=int, default=0, help="frames to replay (default all)")
    args = p.parse_args(argv)
    if args.rate <= 0:
        p.error(f"--rate {args.rate}; it must be > 0")

    import torch

    from lcpr_core import ModelConfig
    from lcpr_core.detector import DetectorConfig, Frame, LoopDetector, Result
    from lcpr_core.lcpr.runtime.cuda import gpu_name
    from lcpr_core.timing import cpu_model
    from lcpr_offline.lcpr_evaluate import to_detector_frame
    from msg_tools.bags import read_frames
    from msg_tools.frames import NUSCENES_TOPICS
    from ros_common.worker import Worker

    stream = read_frames(args.bag, topics=NUSCENES_TOPICS, decode_compressed=False)
    frames: list[Frame] = []
    for sensor_frame in stream:
        frames.append(to_detector_frame(sensor_frame))
        if args.limit and len(frames) >= args.limit:
            break
    stream.close()
    detector = LoopDetector(DetectorConfig(model=ModelConfig(weights=args.weights, device=args.device)))
    describer = detector.describer
    detector.process(frames[0])  # warm the path up (allocator, kernels) before the clock runs
    detector = LoopDetector(detector.config, describer=describer)

    handed: dict[int, float] = {}
    keyframe_latency: list[float] = []
    loop_latency: list[float] = []
    dropped: list[int] = []
    failed: list[str] = []
    lock = threading.Lock()

    def handle(index: int) -> None:
        result: Result = detector.process(frames[index])
        done = time.perf_counter() - handed[index]
        with lock:
            if result.keyframe_id is not None:
                keyframe_latency.append(done)
            if result.loop is not None:
                loop_latency.append(done)

    worker: Worker[int] = Worker(handle, max_waiting=1, on_dropped=dropped.append,
                                 on_error=lambda i, err: failed.append(f"frame {i}: {err}"), name="replay-worker")
    worker.start()
    start, first = time.perf_counter(), frames[0].stamp
    for i, frame in enumerate(frames):
        due = start + (frame.stamp - first) / args.rate
        time.sleep(max(0.0, due - time.perf_counter()))
        handed[i] = time.perf_counter()
        worker.submit(i)
    worker.stop(drain=True)
    wall = time.perf_counter() - start

    gpu = f", GPU {gpu_name(args.device)}" if torch.device(args.device).type == "cuda" else ""
    print(f"CPU {cpu_model()} ({torch.get_num_threads()} torch threads){gpu}; precision {describer.path}, decoder "
          f"{describer.cameras.decoder}, network {describer.config.image_size[0]}x{describer.config.image_size[1]} "
          f"width {describer.config.width:g}{' six turns' if describer.turn_average else ''}")
    print(f"{len(frames)} frames replayed at {args.rate:g}x in {wall:.1f} s; dropped while busy: {len(dropped)}; "
          f"failed: {len(failed)}")
    print(f"frame -> result, keyframes: {percentiles(keyframe_latency)}")
    print(f"frame -> result, published loops: {percentiles(loop_latency)}")
    for line in failed[:5]:
        print("  " + line)
    return 0


if __name__ == "__main__":
    sys.exit(main())
