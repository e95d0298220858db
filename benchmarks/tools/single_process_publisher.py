"""Frames from one publishing process with Fast DDS defaults: what reaches the node, and what it says.

    python benchmarks/tools/single_process_publisher.py [--frames 60] [--image 180 320] [--points 30000]

A driver container or ``ros2 bag play`` publishes six camera images and a cloud from one
process. With Fast DDS's defaults on one host the publisher's shared-memory segment
(512 KiB) is smaller than a frame, so samples are recycled before the subscriber reads
them and only reliable repairs (at the next heartbeat, up to seconds later) bring them.
This script does exactly that: six ``rgb8`` images of ``--image`` pixels and a
``--points`` cloud per frame, 2 Hz of header and wall time, reliable publishers of depth
10, no Fast DDS profile, and ``lcpr_node`` as its own process with default settings
(a tiny seeded model: delivery is measured, not descriptors). Places repeat after
``--frames`` / 2 frames, so the second half revisits the first exactly.

Prints: frames published; frames the node decided on; frames it took with all six
cameras, degraded (a camera missing) or lost; the node's drops, warnings and loops.
``--node-env FASTDDS_BUILTIN_TRANSPORTS=UDPv4`` runs the node on UDP loopback only, so the
publisher sends it its own copy of each sample instead of sharing its segment.

What it measured with Fast DDS 2.14 (Jazzy) and 3.x (Kilted), and why the fix is the publisher's
shared-memory segment rather than UDPv4 on the node: docs/limitations.md.
"""
from __future__ import annotations

import argparse
import os
import random
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from lcpr_common.cli import tool_main

REPO = Path(__file__).resolve().parents[2]
T0 = 1_700_000_000.0


def start_node(
    prefix: str, domain: int, log: Path, extra: list[str], node_env: dict[str, str]
) -> subprocess.Popen[bytes]:
    ros_args = [
        "-p", "model.weights:=seeded", "-p", "model.image_size:=[32,96]", "-p", "model.lidar:=velodyne_vlp16",
        "-p", "model.range_size:=[8,256]",
        "-p", "model.width:=0.25", "-p", "camera_type:=raw",
        "-p", f"camera_topics:=[{','.join(f'{prefix}/CAM_{k}/image_raw' for k in range(6))}]",
        "-p", f"lidar_topic:={prefix}/points", "-p", "diagnostics.period:=0.5", *extra,
    ]
    env = {k: v for k, v in os.environ.items() if not k.startswith("FASTDDS_")}  # Fast DDS defaults
    env.update(ROS_DOMAIN_ID=str(domain), PYTHONUNBUFFERED="1", **node_env)
    return subprocess.Popen([sys.executable, "-m", "lcpr_ros.node", "--ros-args", *ros_args], cwd=REPO, env=env,
                            stdout=log.open("wb"), stderr=subprocess.STDOUT)


@tool_main
def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--frames", type=int, default=60)
    p.add_argument("--image", type=int, nargs=2, default=(180, 320), metavar=("H", "W"))
    p.add_argument("--points", type=int, default=30_000)
    p.add_argument("--node-arg", action="append", default=[], help="extra -p name:=value for the node")
    p.add_argument("--node-env", action="append", default=[], help="NAME=value in the node's environment only")
    args = p.parse_args(argv)

    from ros_common.harness import FramePublisher, OutputListener, driver_node, interrupt, synthetic_place, wait_until

    for key in [k for k in os.environ if k.startswith("FASTDDS_")]:
        del os.environ[key]  # this process too: Fast DDS defaults
    domain, prefix = random.randint(1, 100), f"/spp{random.randint(0, 10**6)}"
    workdir = Path(tempfile.mkdtemp(prefix="lcpr_spp_"))
    log = workdir / "node.log"
    extra = [a for pair in (("-p", x) for x in args.node_arg) for a in pair]
    node = start_node(prefix, domain, log, extra, dict(e.split("=", 1) for e in args.node_env))
    with driver_node("one_process_driver", domain) as driver:
        try:
            if not wait_until(lambda: "[lcpr]: ready" in log.read_text(errors="replace") or node.poll() is not None,
                              120):
                print(log.read_text(errors="replace"), file=sys.stderr)
                return 1
            pub = FramePublisher(driver, [f"{prefix}/CAM_{k}/image_raw" for k in range(6)], f"{prefix}/points",
                                 compressed=False)
            listener = OutputListener(driver)
            pub.wait_for_subscribers(30)
            listener.wait_for_publishers(30)
            half = max(args.frames // 2, 1)
            places = [synthetic_place(i, size=tuple(args.image), points=args.points) for i in range(half)]
            start = time.monotonic()
            for i in range(args.frames):
                delay = start + 0.5 * i - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
                pub.publish(places[i % half], T0 + 0.5 * i + (40.0 if i >= half else 0.0))
            time.sleep(8.0)  # late repairs, the last frames, two more diagnostics messages
            detector, inputs = listener.latest_values("detector"), listener.latest_values("inputs")
        finally:
            interrupt(node)
    decided = sum(int(v) for k, v in detector.items() if k.startswith("frames "))
    missing = {k.removeprefix("frames without "): int(v) for k, v in inputs.items()
               if k.startswith("frames without ") and int(v)}
    degraded_max = max(missing.values(), default=0)
    print(f"one process, Fast DDS defaults: {args.frames} frames of six {args.image[1]}x{args.image[0]} rgb8 "
          f"images and {args.points} points at 2 Hz")
    print(f"  node decided on {decided} frames ({args.frames - decided} lost before the detector)")
    print(f"  camera images missing from decided frames: {missing or 'none'} (at least {degraded_max} frames "
          "degraded)")
    print(f"  drops: { {k: v for k, v in inputs.items() if k.startswith('dropped ')} or 'none'}")
    print(f"  warnings: {inputs.get('warnings', '')}")
    print(f"  loops published: {detector.get('loops', '?')} (exact revisits: {args.frames - half})")
    print(f"  node log: {log}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
