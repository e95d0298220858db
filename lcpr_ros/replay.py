"""``lcpr_replay``: publish a rosbag2 over DDS, keeping every message's original header stamp.

Messages are published as their recorded CDR bytes (rclpy's ``publish`` of serialised
data), so nothing is re-encoded and header stamps are exactly those in the bag; the
rclpy message class of each topic is only needed to create its publisher
(``pkg/msg/Name`` -> ``pkg.msg.Name``). Topics whose type is not installed (e.g.
tf2_msgs/TFMessage on /tf_static in an environment without tf2_msgs) are skipped
with a warning.

Pacing follows the bag's log (receive) times: ``--rate 1`` is real time, ``--rate 2``
twice as fast, ``--rate 0`` as fast as possible. Sensor-data subscribers keep only
the last few messages per topic, so a fast replay into a slow consumer drops
messages there, as a live sensor would.

With Fast DDS (the default RMW), every message to a subscriber on this host is sent
through the publishing participant's shared-memory segment, 512 KiB by default: less
than one camera+LiDAR frame (a synthetic cloud alone is about 640 KB). Sending the
cloud then recycles the buffers of the images published just before it, before the
subscriber has read them; reliable QoS repairs them only at the writer's next
heartbeat (every 3 s), so whole runs of images arrive seconds after their cloud.
``lcpr_replay`` therefore gives its participant a larger segment (see
:func:`shared_memory_profile`) unless Fast DDS is configured through its own
environment variables.

    lcpr_replay /data/nuscenes_scene_0061 --rate 1 --topics /LIDAR_TOP/points /CAM_FRONT/image/compressed
"""
from __future__ import annotations

import argparse
import importlib
import os
import signal
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterator, MutableMapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import rclpy
from rclpy.duration import Duration
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from rclpy.signals import SignalHandlerOptions
from rclpy.utilities import remove_ros_args

from lcpr_common.progress import progress_bar
from msg_tools.bags.open import open_bag
from msg_tools.errors import BagError
from ros_common.stamps import NS_PER_S

QOS = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
LATCHED = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)

#: Shared-memory segment of the replaying participant: several frames of a nuScenes-like bag (six
#: 1600 x 900 JPEGs and a 700 KB cloud, ~3 MB) while the subscriber reads them; Fast DDS's default is 512 KiB.
SHM_SEGMENT_BYTES = 16 * 1024 * 1024
#: Set by a user who configures Fast DDS; the replay then leaves its transports alone.
FASTDDS_VARIABLES = ("FASTDDS_DEFAULT_PROFILES_FILE", "FASTRTPS_DEFAULT_PROFILES_FILE", "FASTDDS_BUILTIN_TRANSPORTS")
#: Where Fast DDS looks for a profiles file: 3.x (Kilted) reads the first, 2.x (Jazzy, Humble) the second.
PROFILE_VARIABLES = ("FASTDDS_DEFAULT_PROFILES_FILE", "FASTRTPS_DEFAULT_PROFILES_FILE")
FASTDDS_PROFILE = """<?xml version="1.0" encoding="UTF-8"?>
<!-- lcpr_replay: Fast DDS's default transports (shared memory + UDPv4), with a larger shared-memory segment -->
<profiles xmlns="http://www.eprosima.com">
  <transport_descriptors>
    <transport_descriptor>
      <transport_id>lcpr_replay_shm</transport_id>
      <type>SHM</type>
      <segment_size>{segment_bytes}</segment_size>
    </transport_descriptor>
    <transport_descriptor>
      <transport_id>lcpr_replay_udp</transport_id>
      <type>UDPv4</type>
    </transport_descriptor>
  </transport_descriptors>
  <participant profile_name="lcpr_replay" is_default_profile="true">
    <rtps>
      <useBuiltinTransports>false</useBuiltinTransports>
      <userTransports>
        <transport_id>lcpr_replay_shm</transport_id>
        <transport_id>lcpr_replay_udp</transport_id>
      </userTransports>
    </rtps>
  </participant>
</profiles>
"""


@dataclass
class ReplayStats:
    published: dict[str, int] = field(default_factory=dict)  # topic -> messages
    skipped: dict[str, str] = field(default_factory=dict)  # topic -> why
    seconds: float = 0.0
    interrupted: bool = False

    @property
    def total(self) -> int:
        return sum(self.published.values())


def message_class(msgtype: str) -> type | None:
    """The rclpy class of ``pkg/msg/Name``, or None when that package is not installed."""
    package, _, name = msgtype.partition("/msg/")
    try:
        return getattr(importlib.import_module(f"{package}.msg"), name)
    except (ImportError, AttributeError):
        return None


def uses_own_fastdds_settings(environ: MutableMapping[str, str]) -> bool:
    """True when another RMW is chosen or the user configures Fast DDS through its environment variables."""
    rmw = environ.get("RMW_IMPLEMENTATION", "")
    return bool(rmw and not rmw.startswith("rmw_fastrtps")) or any(environ.get(name) for name in FASTDDS_VARIABLES)


@contextmanager
def shared_memory_profile(
    segment_bytes: int = SHM_SEGMENT_BYTES, *, environ: MutableMapping[str, str] | None = None
) -> Iterator[Path | None]:
    """Within: participants created in this process (enter before ``rclpy.init``) get a Fast DDS
    shared-memory segment of ``segment_bytes``; yields the profile file, or None where the user's own
    settings (:func:`uses_own_fastdds_settings`) are kept. See the module docstring for why."""
    if segment_bytes <= 0:
        raise ValueError(f"segment_bytes={segment_bytes}; it must be > 0")
    environ = os.environ if environ is None else environ
    if uses_own_fastdds_settings(environ):
        yield None
        return
    with tempfile.TemporaryDirectory(prefix="lcpr_replay_") as folder:
        path = Path(folder) / "fastdds_profile.xml"
        path.write_text(FASTDDS_PROFILE.format(segment_bytes=int(segment_bytes)))
        for name in PROFILE_VARIABLES:
            environ[name] = str(path)
        try:
            yield path
        finally:
            for name in PROFILE_VARIABLES:
                environ.pop(name, None)


def replay(
    node: Node,
    bag: str | Path,
    *,
    rate: float = 1.0,
    topics: Sequence[str] = (),
    wait_subscribers: float = 0.0,
    stop: threading.Event | None = None,
    progress: bool = False,
    log: Callable[[str], None] = print,
) -> ReplayStats:
    """Publish the bag's messages (only ``topics`` when given) from ``node``; see the module docstring."""
    if rate < 0:
        raise ValueError(f"rate={rate}; it must be >= 0 (0 = as fast as possible)")
    stop = stop or threading.Event()
    stats = ReplayStats()
    with open_bag(bag) as reader:
        wanted = set(topics)
        missing = wanted - {c.topic for c in reader.connections}
        if missing:
            present = sorted(c.topic for c in reader.connections)
            raise BagError(f"topics {sorted(missing)} are not in {bag}; it has {present}")
        publishers: dict[str, Any] = {}
        connections = []
        for c in reader.connections:
            if wanted and c.topic not in wanted:
                continue
            cls = message_class(c.msgtype)
            if cls is None:
                stats.skipped[c.topic] = f"{c.msgtype} is not installed"
                log(f"skipping {c.topic}: message type {c.msgtype} is not installed here")
                continue
            if c.topic not in publishers:
                qos = LATCHED if c.topic.endswith("tf_static") else QOS
                publishers[c.topic] = node.create_publisher(cls, c.topic, qos)
                stats.published[c.topic] = 0
            connections.append(c)
        _wait_for_subscribers(list(publishers.values()), wait_subscribers, stop)
        total = sum(c.msgcount for c in connections)
        bar = progress_bar(total, desc="replay", unit="msg", enabled=progress)
        start_wall = time.monotonic()
        first_ns: int | None = None
        try:
            for connection, log_ns, raw in reader.messages(connections=connections):
                if stop.is_set():
                    stats.interrupted = True
                    break
                if first_ns is None:
                    first_ns = log_ns
                if rate > 0:
                    due = start_wall + (log_ns - first_ns) / NS_PER_S / rate
                    if not _sleep_until(due, stop):
                        stats.interrupted = True
                        break
                publishers[connection.topic].publish(bytes(raw))
                stats.published[connection.topic] += 1
                bar.update(1)
        finally:
            bar.close()
        for publisher in publishers.values():  # let reliable subscribers take the last messages
            publisher.wait_for_all_acked(Duration(seconds=2))
    stats.seconds = time.monotonic() - start_wall if connections else 0.0
    return stats


def _sleep_until(due: float, stop: threading.Event) -> bool:
    """Wait until the monotonic time ``due``; False if stopped first."""
    delay = due - time.monotonic()
    return not stop.wait(delay) if delay > 0 else not stop.is_set()


def _wait_for_subscribers(publishers: list[Any], timeout: float, stop: threading.Event) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline and not stop.is_set():
        if publishers and all(p.get_subscription_count() > 0 for p in publishers):
            return
        stop.wait(0.05)


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="lcpr_replay", description=__doc__.split("\n\n")[0],
        formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__.split("\n\n", 1)[1],
    )
    parser.add_argument("bag", type=Path, help="rosbag2 folder (sqlite3 or mcap)")
    parser.add_argument("--rate", type=float, default=1.0,
                        help="playback speed: 1 = real time (default), 2 = twice as fast, 0 = as fast as possible")
    parser.add_argument("--topics", nargs="+", default=[], metavar="TOPIC", help="publish only these topics")
    parser.add_argument("--wait-subscribers", type=float, default=5.0, metavar="SECONDS",
                        help="wait up to this long for a subscriber on every topic before starting (default 5)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    return parser


def main(args: Sequence[str] | None = None) -> int:
    argv = list(sys.argv if args is None else args)
    options = _parser().parse_args(remove_ros_args(argv)[1:])
    if options.rate < 0:
        _parser().error(f"--rate {options.rate}: it must be >= 0 (0 = as fast as possible)")
    stop = threading.Event()
    previous = {}
    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGINT, signal.SIGTERM):
            previous[sig] = signal.signal(sig, lambda signum, frame: stop.set())
    try:
        with shared_memory_profile():
            rclpy.init(args=argv, signal_handler_options=SignalHandlerOptions.NO)
            node = rclpy.create_node("lcpr_replay")
            try:
                stats = replay(node, options.bag, rate=options.rate, topics=options.topics,
                               wait_subscribers=options.wait_subscribers, stop=stop,
                               progress=not options.no_progress, log=lambda text: node.get_logger().warning(text))
            except (BagError, ValueError) as err:
                node.get_logger().error(str(err))
                return 1
            finally:
                node.destroy_node()
                rclpy.try_shutdown()
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    state = "interrupted after" if stats.interrupted else "published"
    print(f"{state} {stats.total} messages on {len(stats.published)} topics in {stats.seconds:.2f} s", file=sys.stderr)
    return 130 if stats.interrupted else 0


if __name__ == "__main__":
    sys.exit(main())
