"""One bound on how long a blocking data read may take, wherever it blocks.

A read can stall in many places: opening a FIFO or a ``pipe:`` command's output, a read from a
hung mount or HTTP server, a DataLoader queue, or the socket through which the main process
fetches a batch's shared-memory file descriptor from a worker (``multiprocessing.resource_sharer``:
a stopped worker blocks it forever, and ``DataLoader(timeout=...)`` does not bound it). Rather than a
timeout for each, ``deadline`` arms one alarm (SIGALRM) around the whole fetch in the main thread:
the blocked system call is interrupted and the block ends with one ``UsageError``.
"""

from __future__ import annotations

import signal
import threading
import time
from contextlib import contextmanager
from typing import Iterator

from omg.errors import UsageError


class _Expired(BaseException):
    """Raised by the alarm inside whatever call was blocked. A BaseException, as KeyboardInterrupt is: the
    readers' ``except Exception`` (a bad shard is skipped and counted) must not take a stall for a bad shard."""


@contextmanager
def deadline(seconds: float, message: str) -> Iterator[None]:
    """Raise ``UsageError(message)`` when the block takes longer than ``seconds`` (0: no limit).

    Bounds the block only in a process's main thread (where Lightning runs and a DataLoader worker
    reads); elsewhere the block runs unbounded. An enclosing deadline's alarm is restored afterwards.
    """
    if not seconds or threading.current_thread() is not threading.main_thread() or not hasattr(signal, "setitimer"):
        yield
        return
    token = _Expired()
    armed = True

    def expire(signum, frame):
        if armed:
            raise token

    previous = signal.signal(signal.SIGALRM, expire)
    outer, _ = signal.setitimer(signal.ITIMER_REAL, seconds)
    start = time.monotonic()
    try:
        try:
            yield
        finally:
            # disarm first: an alarm that fires up to here is still caught below, one after is a no-op
            signal.setitimer(signal.ITIMER_REAL, 0)
            armed = False
    except _Expired as e:
        if e is not token:
            raise
        raise UsageError(message) from None
    finally:
        signal.signal(signal.SIGALRM, previous)
        if outer:
            signal.setitimer(signal.ITIMER_REAL, max(outer - (time.monotonic() - start), 1e-3))
