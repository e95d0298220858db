"""Inference off the callback thread: one worker, a short FIFO (lcpr_ros.worker keeps one slot).

Clouds for the map and camera frames for sequences share the worker; losing every
cloud but the newest would leave holes in the map, so up to ``max_waiting`` items
wait, in order; when full the oldest is dropped (reported through ``on_dropped``).
"""
from __future__ import annotations

import threading
from collections import deque
from collections.abc import Callable
from typing import Generic, TypeVar

T = TypeVar("T")


class FifoWorker(Generic[T]):
    def __init__(self, handle: Callable[[T], None], *, max_waiting: int,
                 on_dropped: Callable[[T], None] = lambda item: None,
                 on_error: Callable[[T, Exception], None] = lambda item, err: None,
                 name: str = "vseq2pc-worker") -> None:
        self._handle = handle
        self._on_dropped = on_dropped
        self._on_error = on_error
        self.max_waiting = max_waiting
        self._cond = threading.Condition()
        self._items: deque[T] = deque()
        self._closed = False
        self._busy = False
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)

    def start(self) -> None:
        self._thread.start()

    def submit(self, item: T) -> None:
        dropped: list[T] = []
        with self._cond:
            if self._closed:
                dropped.append(item)
            else:
                self._items.append(item)
                while len(self._items) > self.max_waiting:
                    dropped.append(self._items.popleft())
                self._cond.notify()
        for old in dropped:
            self._on_dropped(old)

    @property
    def waiting(self) -> int:
        with self._cond:
            return len(self._items)

    @property
    def busy(self) -> bool:
        with self._cond:
            return self._busy

    def idle(self) -> bool:
        with self._cond:
            return not self._items and not self._busy

    def stop(self, *, drain: bool = True, timeout: float | None = None) -> bool:
        """Finish the current item (and the waiting ones when ``drain``); True if the thread ended."""
        with self._cond:
            self._closed = True
            dropped = [] if drain else list(self._items)
            if not drain:
                self._items.clear()
            self._cond.notify_all()
        for item in dropped:
            self._on_dropped(item)
        if self._thread.is_alive():
            self._thread.join(timeout)
        return not self._thread.is_alive()

    def _run(self) -> None:
        while True:
            with self._cond:
                while not self._items and not self._closed:
                    self._cond.wait()
                if not self._items:
                    return
                item = self._items.popleft()
                self._busy = True
            try:
                self._handle(item)
            except Exception as err:  # noqa: BLE001 - one bad item must not end the worker
                self._on_error(item, err)
            finally:
                with self._cond:
                    self._busy = False
