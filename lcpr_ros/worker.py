"""Inference off the callback thread: one worker, one waiting slot, nothing queues up.

While the worker handles an item, the newest submitted item waits in a single slot;
an older waiting item is replaced (and reported through ``on_replaced``). So the
input side never blocks and memory never grows, whatever the input rate.
"""
from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Generic, TypeVar

T = TypeVar("T")


class LatestSlot(Generic[T]):
    """Holds at most one item; ``put`` replaces, ``take`` blocks until an item or close."""

    def __init__(self) -> None:
        self._cond = threading.Condition()
        self._item: T | None = None
        self._closed = False

    def put(self, item: T) -> T | None:
        """Store ``item``; returns the item it replaced (None if the slot was empty)."""
        with self._cond:
            if self._closed:
                return item
            replaced, self._item = self._item, item
            self._cond.notify()
            return replaced

    def take(self, timeout: float | None = None) -> T | None:
        """The waiting item; None on timeout or once closed and empty."""
        with self._cond:
            if self._item is None and not self._closed:
                self._cond.wait(timeout)
            item, self._item = self._item, None
            return item

    def close(self, *, keep: bool = True) -> T | None:
        """Refuse new items and wake the taker; ``keep=False`` also discards (and returns) the waiting one."""
        with self._cond:
            self._closed = True
            dropped = None
            if not keep:
                dropped, self._item = self._item, None
            self._cond.notify_all()
            return dropped

    @property
    def closed(self) -> bool:
        with self._cond:
            return self._closed

    @property
    def occupied(self) -> bool:
        with self._cond:
            return self._item is not None


class Worker(Generic[T]):
    """Calls ``handle(item)`` on its own thread for the newest submitted item, one at a time."""

    def __init__(
        self,
        handle: Callable[[T], None],
        *,
        on_replaced: Callable[[T], None] = lambda item: None,
        on_error: Callable[[T, Exception], None] = lambda item, err: None,
        name: str = "lcpr-worker",
    ) -> None:
        self._handle = handle
        self._on_replaced = on_replaced
        self._on_error = on_error
        self._slot: LatestSlot[T] = LatestSlot()
        self._busy = threading.Event()
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)

    def start(self) -> None:
        self._thread.start()

    def submit(self, item: T) -> None:
        replaced = self._slot.put(item)
        if replaced is not None:
            self._on_replaced(replaced)

    @property
    def busy(self) -> bool:
        return self._busy.is_set()

    @property
    def waiting(self) -> int:
        """Items waiting (0 or 1)."""
        return int(self._slot.occupied)

    def stop(self, *, drain: bool = True, timeout: float | None = None) -> bool:
        """Finish the current item (and the waiting one when ``drain``); True if the thread ended."""
        dropped = self._slot.close(keep=drain)
        if dropped is not None:
            self._on_replaced(dropped)
        if self._thread.is_alive():
            self._thread.join(timeout)
        return not self._thread.is_alive()

    def _run(self) -> None:
        while True:
            item = self._slot.take()
            if item is None:
                if self._slot.closed:
                    return
                continue
            self._busy.set()
            try:
                self._handle(item)
            except Exception as err:  # noqa: BLE001 - one bad frame must not end the worker
                self._on_error(item, err)
            finally:
                self._busy.clear()
