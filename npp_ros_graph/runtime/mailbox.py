"""The Mailbox: how an executor callback hands work to a node's worker thread without blocking."""

from __future__ import annotations

import threading
from collections import deque
from typing import Generic, TypeVar

T = TypeVar("T")


class Mailbox(Generic[T]):
    """Hands items from executor callbacks to a worker thread: put() never blocks, take() waits on a
    Condition (no polling) and close() releases every waiter.

    ``keep=1`` holds only the newest item: put() returns the one it overtook, so the node can count
    what it dropped. ``keep=None`` holds every item, in order (a node bounds that backlog itself).
    """

    def __init__(self, keep: int | None = None) -> None:
        self._items: deque[T] = deque(maxlen=keep)
        self._ready = threading.Condition()
        self.closed = False

    def put(self, item: T) -> T | None:
        with self._ready:
            overtaken = self._items[0] if len(self._items) == self._items.maxlen else None
            self._items.append(item)
            self._ready.notify()
        return overtaken

    def take(self, timeout: float | None = None) -> T | None:
        """The oldest item held; None when the timeout passes first or the mailbox is closed."""
        with self._ready:
            if not self._ready.wait_for(lambda: self._items or self.closed, timeout) or self.closed:
                return None
            return self._items.popleft()

    def close(self) -> None:
        with self._ready:
            self.closed = True
            self._ready.notify_all()

    def __len__(self) -> int:
        return len(self._items)
