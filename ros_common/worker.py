"""Inference off the callback thread: one worker thread, a short queue that never blocks the input side.

While the worker handles an item, at most ``max_waiting`` newer items wait, in order; when one more
arrives the oldest waiting item is dropped (and reported through ``on_dropped``), so memory never
grows whatever the input rate. lcpr_node keeps one waiting frame (``max_waiting=1``: a late frame is
worth less than the newest); vseq2pc_node keeps several, since a lost cloud leaves a hole in the map.
"""
from __future__ import annotations

import threading
from collections import deque
from collections.abc import Callable
from typing import Generic, TypeVar

T = TypeVar("T")


class DropOldestQueue(Generic[T]):
    """At most ``capacity`` items; ``put`` drops the oldest beyond it, ``take`` blocks until an item or close."""

    def __init__(self, capacity: int = 1) -> None:
        if capacity < 1:
            raise ValueError(f"capacity={capacity}; it must be >= 1")
        self.capacity = capacity
        self._cond = threading.Condition()
        self._items: deque[T] = deque()
        self._closed = False

    def put(self, item: T) -> list[T]:
        """Store ``item``; returns the items it pushed out (oldest first; ``[item]`` once closed)."""
        with self._cond:
            if self._closed:
                return [item]
            self._items.append(item)
            dropped = [self._items.popleft() for _ in range(len(self._items) - self.capacity)]
            self._cond.notify()
            return dropped

    def take(self, timeout: float | None = None) -> T | None:
        """The oldest waiting item; None on timeout or once closed and empty."""
        with self._cond:
            if not self._items and not self._closed:
                self._cond.wait(timeout)
            return self._items.popleft() if self._items else None

    def close(self, *, keep: bool = True) -> list[T]:
        """Refuse new items and wake the taker; ``keep=False`` also discards (and returns) the waiting ones."""
        with self._cond:
            self._closed = True
            dropped = [] if keep else list(self._items)
            if not keep:
                self._items.clear()
            self._cond.notify_all()
            return dropped

    @property
    def closed(self) -> bool:
        with self._cond:
            return self._closed

    def __len__(self) -> int:
        with self._cond:
            return len(self._items)


class Worker(Generic[T]):
    """Calls ``handle(item)`` on its own thread, one item at a time, oldest waiting item first."""

    def __init__(
        self,
        handle: Callable[[T], None],
        *,
        max_waiting: int = 1,
        on_dropped: Callable[[T], None] = lambda item: None,
        on_error: Callable[[T, Exception], None] = lambda item, err: None,
        name: str = "node-worker",
    ) -> None:
        self._handle = handle
        self._on_dropped = on_dropped
        self._on_error = on_error
        self._queue: DropOldestQueue[T] = DropOldestQueue(max_waiting)
        self._busy = threading.Event()
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)

    @property
    def max_waiting(self) -> int:
        return self._queue.capacity

    def start(self) -> None:
        self._thread.start()

    def submit(self, item: T) -> None:
        for dropped in self._queue.put(item):
            self._on_dropped(dropped)

    @property
    def busy(self) -> bool:
        return self._busy.is_set()

    @property
    def waiting(self) -> int:
        """Items waiting (at most ``max_waiting``)."""
        return len(self._queue)

    def stop(self, *, drain: bool = True, timeout: float | None = None) -> bool:
        """Finish the current item (and the waiting ones when ``drain``); True if the thread ended."""
        for dropped in self._queue.close(keep=drain):
            self._on_dropped(dropped)
        if self._thread.is_alive():
            self._thread.join(timeout)
        return not self._thread.is_alive()

    def _run(self) -> None:
        while True:
            item = self._queue.take()
            if item is None:
                if self._queue.closed:
                    return
                continue
            self._busy.set()
            try:
                self._handle(item)
            except Exception as err:  # noqa: BLE001 - one bad item must not end the worker
                self._on_error(item, err)
            finally:
                self._busy.clear()
