"""Running a node as a process: stop on SIGINT/SIGTERM, spin until then, then an orderly close."""
from __future__ import annotations

import signal
import threading
from types import FrameType, TracebackType
from typing import Any

import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node


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
