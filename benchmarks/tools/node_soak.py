"""Soak test of the real lcpr node: N synthetic frames at 2 Hz of header time, latency and memory.

The node runs as its own process (``python -m lcpr_ros.node``), exactly as deployed;
this script publishes six camera images and one cloud per frame over DDS (header
stamps 0.5 s apart, places cycling so that every place comes back after
``--places`` / 2 seconds) and listens to ``~/candidates`` and ``/diagnostics``.

Pacing: ``--rate 1`` (default) publishes at 2 Hz of wall time, real time;
``--rate R`` at R x 2 Hz; ``--rate 0`` publishes the next frame as soon as the node
has decided on the previous one (as fast as it keeps up; the header stamps still
step 0.5 s, so the node sees a 2 Hz drive in less wall time).

Reported:
  * frame-to-candidate latency (wall time from publishing a frame to receiving its
    ``~/candidates`` message) p50/p90/p99, and the node's model time (preprocessing
    + network, its diagnostics) p50/p90/p99; target: latency p50 <= model p50 + 100 ms;
  * the node's RSS (/proc/PID/status VmRSS) when ready, after warm-up (``--warmup``
    seconds of wall time, 300 by default), at the middle and at the end; target: growth
    from warm-up to the end at most the map's own growth (descriptor, metadata and the
    compact keyframe cloud: at most ``MAP_BYTES_PER_KEYFRAME``) plus 5 % of the RSS at
    warm-up;
  * queue state and drops from its diagnostics (frames replaced while busy, sync
    backlog, pending clouds, waiting frames); target: none growing;
  * every ``--sample`` seconds: RSS, map size, latency p50/p99 of that interval, pending
    and waiting frames, written to ``--out``/soak.json and plotted in ``--out``/soak.png.

    python benchmarks/tools/node_soak.py                 # 3600 frames = 30 min of drive at 2 Hz
    python benchmarks/tools/node_soak.py --frames 300 --rate 0
    python benchmarks/tools/node_soak.py --image-size 256 704 --lidar nuscenes_lidar_top --range-size 0 0 --width 1 \
        --camera-size 256 704 --out out/soak      # the released-size network (seeded weights), 30 min
"""
from __future__ import annotations

import argparse
import json
import os
import random
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from lcpr_common.cli import tool_main

if TYPE_CHECKING:  # ROS and the package are imported after the arguments are read
    from ros_common.harness import OutputListener

REPO = Path(__file__).resolve().parents[2]

FRAME_DT = 0.5  # s of header time between frames (2 Hz)
T0 = 1_700_000_000.0
LATENCY_MARGIN_MS = 100.0
RSS_GROWTH_SHARE = 0.05  # allowed beyond the map's own growth, as a share of the RSS after warm-up
#: Upper bound of what one keyframe adds to the map: 256 float32, id/stamp/pose/source, a compact cloud.
MAP_BYTES_PER_KEYFRAME = 256 * 4 + 8 + 8 + 16 * 8 + 2 + 6 * 3072 + 16


def rss_mb(pid: int) -> float:
    from lcpr_core.timing import memory_mb

    rss = memory_mb(pid)
    if rss != rss:  # NaN
        raise RuntimeError(f"no VmRSS line in /proc/{pid}/status")
    return rss


def start_node(args: argparse.Namespace, domain: int, prefix: str, log: Path) -> subprocess.Popen[bytes]:
    ros_args = [
        "-p", f"model.image_size:=[{args.image_size[0]},{args.image_size[1]}]",
        "-p", f"model.lidar:={args.lidar}",
        "-p", f"model.range_size:=[{args.range_size[0]},{args.range_size[1]}]",
        "-p", f"model.width:={float(args.width)!r}",  # a double parameter needs a decimal point
        "-p", f"model.weights:={args.weights or 'seeded'}",  # the tiny model: random weights unless given
        "-p", f"model.precision:={args.precision}",
        *[arg for param in args.param for arg in ("-p", param)],
        "-p", f"camera_topics:=[{','.join(f'{prefix}/CAM_{k}/image/compressed' for k in range(6))}]",
        "-p", f"lidar_topic:={prefix}/LIDAR_TOP/points",
        "-p", "match.max_distance:=2.0",  # every keyframe older than 30 s is a candidate: one reply per frame
        "-p", f"diagnostics.period:={0.1 if args.rate == 0 else 1.0}",
        "-p", "diagnostics.window:=1000",
    ]
    env = {**os.environ, "ROS_DOMAIN_ID": str(domain), "PYTHONUNBUFFERED": "1"}
    out = log.open("wb")
    return subprocess.Popen([sys.executable, "-m", "lcpr_ros.node", "--ros-args", *ros_args], cwd=REPO, env=env,
                            stdout=out, stderr=subprocess.STDOUT)


def processed(listener: OutputListener) -> int:
    values = listener.latest_values("detector")
    return sum(int(v) for k, v in values.items() if k.startswith("frames "))


def ms(values: list[float]) -> str:
    if not values:
        return "n/a"
    p50, p90, p99 = np.percentile(np.asarray(values) * 1000, (50, 90, 99))
    return f"p50 {p50:7.1f}  p90 {p90:7.1f}  p99 {p99:7.1f} ms"


@tool_main
def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter,
                                     epilog=__doc__.split("\n\n", 1)[1])
    parser.add_argument("--frames", type=int, default=3600, help="frames to publish (default 3600 = 30 min at 2 Hz)")
    parser.add_argument("--rate", type=float, default=1.0, help="wall pacing: 1 = real time (2 Hz), 0 = as fast as "
                                                                "the node keeps up")
    parser.add_argument("--places", type=int, default=100, help="distinct places, visited in turn (default 100)")
    parser.add_argument("--image-size", type=int, nargs=2, default=(32, 96), metavar=("H", "W"),
                        help="model.image_size (default 32 96, a tiny model; released: 256 704)")
    parser.add_argument("--lidar", default="velodyne_vlp16", help="model.lidar preset (released: nuscenes_lidar_top)")
    parser.add_argument("--range-size", type=int, nargs=2, default=(8, 256), metavar=("H", "W"),
                        help="model.range_size (default 8 256; 0 0 = the preset's, released: 32 x 1056)")
    parser.add_argument("--width", type=float, default=0.25, help="model.width (default 0.25; released: 1.0)")
    parser.add_argument("--weights", default="", help="model.weights (default: seeded random weights)")
    parser.add_argument("--param", action="append", default=[], metavar="NAME:=VALUE",
                        help="another node parameter, e.g. verify.enabled:=false (repeatable)")
    parser.add_argument("--precision", default="auto",
                        help="model.precision: auto (default, as the node), fp32, bf16, onnx, int8")
    parser.add_argument("--camera-size", type=int, nargs=2, default=(48, 128), metavar=("H", "W"),
                        help="size of the published JPEG camera images (nuScenes: 900 1600)")
    parser.add_argument("--json", type=Path, help="also write the results here")
    parser.add_argument("--out", type=Path, default=Path("out/soak"), help="soak.json and soak.png go here")
    parser.add_argument("--warmup", type=float, default=300.0, help="s of wall time before memory is judged")
    parser.add_argument("--sample", type=float, default=10.0, help="s of wall time between samples")
    args = parser.parse_args()
    if args.frames < 2 or args.rate < 0:
        parser.error("--frames must be >= 2 and --rate >= 0")

    import rclpy
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor

    from ros_common.harness import FramePublisher, OutputListener, interrupt, synthetic_place, wait_until

    domain = random.randint(1, 100)
    prefix = f"/soak{random.randint(0, 10**6)}"
    workdir = Path(tempfile.mkdtemp(prefix="lcpr_soak_"))
    log = workdir / "node.log"
    node_proc = start_node(args, domain, prefix, log)
    context = Context()
    rclpy.init(context=context, domain_id=domain)
    driver = rclpy.create_node("soak_driver", context=context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(driver)
    spinner = threading.Thread(target=executor.spin, daemon=True)
    spinner.start()
    results: dict[str, object] = {}
    try:
        if not wait_until(lambda: "[lcpr]: ready" in log.read_text(errors="replace") or node_proc.poll() is not None,
                        120) or node_proc.poll() is not None:
            print(log.read_text(errors="replace"), file=sys.stderr)
            return 1
        rss = {"ready": rss_mb(node_proc.pid)}
        pub = FramePublisher(driver, [f"{prefix}/CAM_{k}/image/compressed" for k in range(6)],
                             f"{prefix}/LIDAR_TOP/points")
        listener = OutputListener(driver)
        pub.wait_for_subscribers(30)
        listener.wait_for_publishers(30)
        wait_until(lambda: bool(listener.latest_values("detector")), 10)
        places = [synthetic_place(i, size=tuple(args.camera_size)) for i in range(args.places)]
        sent: dict[int, float] = {}
        start = time.monotonic()
        snapshots: dict[str, dict[str, str]] = {}
        series: list[dict[str, float]] = []
        next_sample, seen_replies = start, 0
        warm_rss: float | None = None
        warm_map = 0.0
        for i in range(args.frames):
            stamp_ms = round((T0 + i * FRAME_DT) * 1000)
            if args.rate > 0:
                delay = start + i * FRAME_DT / args.rate - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
            sent[stamp_ms] = time.monotonic()
            pub.publish(places[i % args.places], stamp_ms / 1000)
            if args.rate == 0:
                wait_until(lambda: processed(listener) >= i + 1, 30)  # noqa: B023 (called at once)
            now = time.monotonic()
            if now >= next_sample:
                next_sample += args.sample
                detector = listener.latest_values("detector")
                replies = list(zip(listener.out.candidates, listener.out.received, strict=True))[seen_replies:]
                seen_replies += len(replies)
                recent = [received - sent[round(rows[0]["query_stamp"] * 1000)] for rows, received in replies
                          if round(rows[0]["query_stamp"] * 1000) in sent]
                p50, p99 = (np.percentile(np.asarray(recent) * 1000, (50, 99)).tolist() if recent
                            else (float("nan"), float("nan")))
                series.append({"t_s": now - start, "frames": i + 1, "rss_mb": rss_mb(node_proc.pid),
                               "map_size": int(detector.get("map size", "0")), "latency_p50_ms": p50,
                               "latency_p99_ms": p99, "sync_pending": float(detector.get("sync pending", "nan")),
                               "worker_waiting": float(detector.get("worker waiting", "nan"))})
                warm_after = min(args.warmup, args.frames * FRAME_DT / max(args.rate, 1e-9) / 4)
                if warm_rss is None and now - start >= warm_after:
                    warm_rss, warm_map = series[-1]["rss_mb"], series[-1]["map_size"]
                    rss["warm"] = warm_rss
                    snapshots["warm"] = listener.latest_values("inputs")
            if i + 1 == args.frames // 2:
                rss["middle"] = rss_mb(node_proc.pid)
                snapshots["middle"] = listener.latest_values("inputs")
            if (i + 1) % 100 == 0:
                print(f"  {i + 1}/{args.frames} frames, {len(listener.out.candidates)} replies, "
                      f"RSS {rss_mb(node_proc.pid):.0f} MB", file=sys.stderr)
        last = round((T0 + (args.frames - 1) * FRAME_DT) * 1000)
        wait_until(lambda: any(round(rows[0]["query_stamp"] * 1000) == last for rows in listener.out.candidates), 30)
        time.sleep(2.5)  # one more diagnostics message with the final counts
        wall = time.monotonic() - start
        rss["end"] = rss_mb(node_proc.pid)

        latencies = [received - sent[round(rows[0]["query_stamp"] * 1000)]
                     for rows, received in zip(listener.out.candidates, listener.out.received, strict=True)
                     if round(rows[0]["query_stamp"] * 1000) in sent]
        detector = listener.latest_values("detector")
        inputs = listener.latest_values("inputs")
        model = [float(detector.get(f"model {p} (ms)", "nan")) for p in ("p50", "p90", "p99")]
        lat = np.percentile(np.asarray(latencies) * 1000, (50, 90, 99)).tolist() if latencies else [float("nan")] * 3
        drops = {k.removeprefix("dropped "): int(v) for k, v in inputs.items() if k.startswith("dropped ")}
        map_size = int(detector.get("map size", "0"))
        map_mb = map_size * MAP_BYTES_PER_KEYFRAME / 2**20
        base_rss = rss.get("warm", rss["ready"])
        growth = rss["end"] - base_rss
        allowed = (map_size - warm_map) * MAP_BYTES_PER_KEYFRAME / 2**20 + RSS_GROWTH_SHARE * base_rss
        results = {
            "frames": args.frames, "rate": args.rate, "wall_s": wall, "header_s": args.frames * FRAME_DT,
            "replies": len(listener.out.candidates), "latency_ms": lat, "model_ms": model, "rss_mb": rss,
            "map_size": int(detector.get("map size", "0")), "drops": drops,
            "sync_pending": detector.get("sync pending"), "worker_waiting": detector.get("worker waiting"),
            "image_size": list(args.image_size), "lidar": args.lidar, "range_size": list(args.range_size),
            "width": args.width, "precision": args.precision, "inference_path": detector.get("inference path"),
            "series": series, "rss_growth_mb": growth, "rss_growth_allowed_mb": allowed,
        }
        print(f"\nlcpr node soak: {args.frames} frames ({args.frames * FRAME_DT:.0f} s of 2 Hz header time) "
              f"in {wall:.0f} s wall (rate {args.rate}); model {args.image_size[0]}x{args.image_size[1]} "
              f"images, {args.lidar} range {args.range_size[0]}x{args.range_size[1]}, width {args.width}")
        print(f"  replies (~/candidates)     {len(listener.out.candidates)} for {args.frames} frames "
              f"(frames in the first 30 s have no eligible match)")
        print(f"  frame-to-candidate latency {ms(latencies)}")
        print(f"  model time (node)          p50 {model[0]:7.1f}  p90 {model[1]:7.1f}  p99 {model[2]:7.1f} ms "
              f"(model.precision {args.precision}: {detector.get('inference path', '?')})")
        print("  node RSS                   " + "  ".join(f"{k} {v:.0f} MB" for k, v in rss.items())
              + f"  (map itself: at most {map_mb:.1f} MB)")
        print(f"  drops                      {drops or 'none'}; sync pending {detector.get('sync pending')}, "
              f"worker waiting {detector.get('worker waiting')}")
        ok_latency = lat[0] <= model[0] + LATENCY_MARGIN_MS
        ok_memory = growth <= allowed
        print(f"  latency p50 <= model p50 + {LATENCY_MARGIN_MS:.0f} ms: {'yes' if ok_latency else 'NO'}; "
              f"RSS growth after warm-up {growth:+.1f} MB <= map's growth + {RSS_GROWTH_SHARE:.0%} = "
              f"{allowed:.1f} MB: {'yes' if ok_memory else 'NO'}")
        results.update(latency_ok=ok_latency, memory_ok=ok_memory)
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / "soak.json").write_text(json.dumps(results, indent=2))
        plot_series(series, args.out / "soak.png", warm_rss=warm_rss, allowed=allowed,
                    title=f"lcpr node soak: {args.frames} frames at {2 * args.rate:g} Hz, model "
                          f"{args.image_size[0]}x{args.image_size[1]} width {args.width}")
        print(f"  written: {args.out / 'soak.json'}, {args.out / 'soak.png'}")
        if args.json:
            args.json.write_text(json.dumps(results, indent=2))
        return 0 if ok_latency and ok_memory else 2
    finally:
        interrupt(node_proc)
        executor.shutdown(timeout_sec=5)
        spinner.join(5)
        driver.destroy_node()
        rclpy.try_shutdown(context=context)


def plot_series(series: list[dict[str, float]], path: Path, *, warm_rss: float | None, allowed: float,
                title: str) -> None:
    """RSS, latency and map size over wall time (PNG)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from lcpr_core.atomic import atomic_path

    t = np.array([s["t_s"] for s in series]) / 60.0
    fig, axes = plt.subplots(3, 1, figsize=(8, 8), sharex=True)
    axes[0].plot(t, [s["rss_mb"] for s in series], label="node RSS")
    if warm_rss is not None:
        axes[0].axhline(warm_rss + allowed, color="r", ls="--", label="allowed at the end")
    axes[0].set_ylabel("MB")
    axes[0].legend()
    axes[1].plot(t, [s["latency_p50_ms"] for s in series], label="latency p50")
    axes[1].plot(t, [s["latency_p99_ms"] for s in series], label="latency p99")
    axes[1].set_ylabel("ms")
    axes[1].legend()
    axes[2].plot(t, [s["map_size"] for s in series], label="map size (keyframes)")
    axes[2].plot(t, [s["worker_waiting"] + s["sync_pending"] for s in series], label="frames queued")
    axes[2].set_xlabel("minutes (wall)")
    axes[2].legend()
    fig.suptitle(title)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=90, format="png")
    plt.close(fig)


if __name__ == "__main__":
    sys.exit(main())
