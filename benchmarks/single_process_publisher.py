"""Frames from one publishing process with Fast DDS defaults: what reaches the node, and what it says.

    python benchmarks/single_process_publisher.py [--frames 60] [--image 180 320] [--points 30000]

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

Measured with ROS 2 Jazzy's wheels (rclpy 7.1.6, Fast DDS 2.14; Intel Xeon, 2 cores; one run each):

    six 320x180 rgb8 + 30k points, 40 frames   taken  degraded  loops/20  late images counted
    node with Fast DDS defaults                   40      29         9       104
    node with FASTDDS_BUILTIN_TRANSPORTS=UDPv4    34      22         9        74   (6 "replaced while busy")
    publisher with a 16 MiB segment (FASTRTPS_DEFAULT_PROFILES_FILE=<lcpr_ros.replay.FASTDDS_PROFILE>)
                                                  40       0        20         0

So on Jazzy the fix is the publisher's segment; UDPv4 on the node does not help there.

Measured earlier (AMD EPYC, 2 cores, rclpy 9.1.2 / Fast DDS from the Kilted wheels; one run each unless noted):

    six 320x180 rgb8 + 30k points, 40 frames   taken  degraded  loops/20  late images counted
    node with Fast DDS defaults (two runs)       39-40   16-22     7-11     68 (second run)
    node with FASTDDS_BUILTIN_TRANSPORTS=UDPv4    40      2-3       19       8 (second run)
    six 1600x900 rgb8 + 34k points, 20 frames                  loops/10
    node with Fast DDS defaults                   17        9        7       37
    node with FASTDDS_BUILTIN_TRANSPORTS=UDPv4    13        6        4       23   (CPU-bound: 6 "replaced while busy")

UDPv4 is not the node's default: the demo's replay, which gives its participant a 16 MiB
segment, lost 11 images and its p90 latency rose from 212 to 396 ms with the node on UDPv4.
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

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


from ros_common.harness import (  # noqa: E402
    FramePublisher,
    OutputListener,
    driver_node,
    interrupt,
    synthetic_place,
    wait_until,
)

T0 = 1_700_000_000.0


def start_node(
    prefix: str, domain: int, log: Path, extra: list[str], node_env: dict[str, str]
) -> subprocess.Popen[bytes]:
    ros_args = [
        "-p", "model.image_size:=[32,96]", "-p", "model.lidar:=velodyne_vlp16", "-p", "model.range_size:=[8,256]",
        "-p", "model.width:=0.25", "-p", "camera_type:=raw",
        "-p", f"camera_topics:=[{','.join(f'{prefix}/CAM_{k}/image_raw' for k in range(6))}]",
        "-p", f"lidar_topic:={prefix}/points", "-p", "diagnostics.period:=0.5", *extra,
    ]
    env = {k: v for k, v in os.environ.items() if not k.startswith("FASTDDS_")}  # Fast DDS defaults
    env.update(ROS_DOMAIN_ID=str(domain), PYTHONUNBUFFERED="1",
               PYTHONPATH=os.pathsep.join([str(REPO), *filter(None, [os.environ.get("PYTHONPATH")])]), **node_env)
    return subprocess.Popen([sys.executable, "-m", "lcpr_ros.node", "--ros-args", *ros_args], cwd=REPO, env=env,
                            stdout=log.open("wb"), stderr=subprocess.STDOUT)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--frames", type=int, default=60)
    p.add_argument("--image", type=int, nargs=2, default=(180, 320), metavar=("H", "W"))
    p.add_argument("--points", type=int, default=30_000)
    p.add_argument("--node-arg", action="append", default=[], help="extra -p name:=value for the node")
    p.add_argument("--node-env", action="append", default=[], help="NAME=value in the node's environment only")
    args = p.parse_args(argv)
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
