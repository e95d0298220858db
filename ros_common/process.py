"""Running a node as a process: stop on SIGINT/SIGTERM, spin until then, then an orderly close."""
from __future__ import annotations

import argparse
import signal
import sys
import threading
from collections.abc import Callable, Sequence
from types import FrameType, TracebackType
from typing import Any, Protocol

import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.signals import SignalHandlerOptions
from rclpy.utilities import remove_ros_args

from lcpr_core.errors import MapError

from .config import MapFileConfig
from .errors import ConfigError, MapLoadError


class Drains(Protocol):
    def stop(self, *, drain: bool, timeout: float | None) -> bool: ...


class StopOnSignal:
    """While active, SIGINT and SIGTERM only set ``event`` (rclpy's handlers are off: the
    node decides how to stop). The previous handlers come back on exit."""

    SIGNALS = (signal.SIGINT, signal.SIGTERM)

    def __init__(self) -> None:
        self.event = threading.Event()
        self._previous: dict[int, Any] = {}

    def _handle(self, signum: int, frame: FrameType | None) -> None:
        self.event.set()

    def __enter__(self) -> StopOnSignal:
        if threading.current_thread() is threading.main_thread():  # signal handlers live in the main thread
            for sig in self.SIGNALS:
                self._previous[sig] = signal.signal(sig, self._handle)
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)


def spin_until(node: Node, stop: threading.Event, *, period: float = 0.1) -> None:
    """Run the node's callbacks on this thread until ``stop`` is set or the context shuts down."""
    executor = SingleThreadedExecutor(context=node.context)
    executor.add_node(node)
    try:
        while not stop.is_set() and rclpy.ok(context=node.context):
            executor.spin_once(timeout_sec=period)
    finally:
        executor.shutdown()


def node_parser(*, prog: str, node_name: str, summary: str, params_file: str,
                parameters: str) -> argparse.ArgumentParser:
    """The ``--help`` of a node executable: what it does, how to set parameters, and every parameter."""
    return argparse.ArgumentParser(
        prog=prog,
        description=f"{summary} (node name {node_name!r}). Set parameters with --ros-args -p name:=value or "
                    f"--ros-args --params-file {params_file}.",
        epilog="parameters:\n" + parameters,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )


def run_node(
    make_node: Callable[[], Any],
    *,
    parser: argparse.ArgumentParser,
    argv: Sequence[str] | None,
    closing: str,
) -> int:
    """The life of a node process: 0 after a clean stop (Ctrl-C, SIGTERM), 1 when the node
    refuses to start (bad parameters, a bad map file), 2 for a malformed command line.

    ``make_node`` builds the node (raising ConfigError or MapLoadError to refuse);
    ``closing`` is logged before the node's ``close()`` (which finishes work and saves).
    """
    args = list(sys.argv if argv is None else argv)
    try:
        user_args = remove_ros_args(args)[1:]
    except RuntimeError as err:  # rcl refuses a malformed --ros-args section (RCLInvalidROSArgsError)
        print(f"{parser.prog}: {err}", file=sys.stderr)
        return 2
    parser.parse_args(user_args)
    with StopOnSignal() as stop:
        rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
        try:
            try:
                node = make_node()
            except (ConfigError, MapLoadError) as err:
                rclpy.logging.get_logger(parser.prog).error(f"cannot start: {err}")
                return 1
            try:
                spin_until(node, stop.event)
            finally:
                node.get_logger().info(f"shutting down: {closing}")
                node.close()
                node.destroy_node()
        finally:
            rclpy.try_shutdown()
    return 0


def finish_and_save(node: Node, worker: Drains, map_file: MapFileConfig, save_map: Callable[..., int], *,
                    timeout: float, what: str) -> None:
    """A node's close(): let ``worker`` finish what it holds (at most ``timeout`` s), then save the map
    when ``map_file`` (the node's map.* settings) asks for it; failures are logged, nothing is raised (the
    process is ending)."""
    log = node.get_logger()
    if not worker.stop(drain=True, timeout=timeout):
        log.error(f"the worker is still busy after {timeout} s")
    if map_file.path and map_file.save_on_shutdown:
        try:
            count = save_map(timeout=5.0)
        except MapError as err:
            log.error(f"map not saved at shutdown: {err}")
        else:
            log.info(f"saved {count} {what} to {map_file.path}")
