"""Bounded heavy reads: at most N map exports at once; one more is refused at once (503 + ``Retry-After``).

An export holds its slot from the request until its last byte is sent (or the client goes away): a
streamed export reads the database and formats rows for as long as the client reads, a PNG export draws
a figure in a worker thread. Refusing beyond the limit, instead of queueing, keeps worker threads and
memory free for every other request (``/healthz``, ``/v1/maps``, paths).

The streamed exports' chunks are formatted in at most ``FORMAT_THREADS`` threads at a time
(:attr:`ReadSlots.threads`), however many exports stream: formatting holds the GIL, and every thread that
wants it delays the event loop that answers the other requests.
"""

from __future__ import annotations

import threading
from collections.abc import Callable

import anyio

from mapserver.api.errors import BusyError

FORMAT_THREADS = 2


class ReadSlots:
    """A counter of running heavy reads with a limit (thread-safe)."""

    def __init__(self, limit: int, *, retry_after_s: int = 2, what: str = "exports") -> None:
        self.limit = limit
        self.retry_after_s = retry_after_s
        self.what = what
        self._lock = threading.Lock()
        self._running = 0
        self.threads = anyio.CapacityLimiter(FORMAT_THREADS)

    @property
    def running(self) -> int:
        """Return the heavy reads holding a slot now."""
        with self._lock:
            return self._running

    def acquire(self) -> Callable[[], None]:
        """Take a slot; return its release (idempotent).

        Raises:
            BusyError: every slot is taken (HTTP 503 with ``Retry-After``).
        """
        with self._lock:
            if self._running >= self.limit:
                msg = f"{self._running} {self.what} are running, the server's limit; try again in a moment"
                raise BusyError(msg, retry_after_s=self.retry_after_s)
            self._running += 1
        released = threading.Event()

        def release() -> None:
            if released.is_set():
                return
            released.set()
            with self._lock:
                self._running -= 1

        return release
