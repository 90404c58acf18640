"""One bound on how long a blocking data read may take, wherever it blocks, and a stop signal that ends it.

A read can stall in many places: opening a FIFO or a ``pipe:`` command's output, a read from a
hung mount or HTTP server, a DataLoader queue, or the socket through which the main process
fetches a batch's shared-memory file descriptor from a worker (``multiprocessing.resource_sharer``:
a stopped worker blocks it forever, and ``DataLoader(timeout=...)`` does not bound it). Rather than a
timeout for each, ``deadline`` arms one alarm (SIGALRM) around the whole fetch in the main thread:
the blocked system call is interrupted and the block ends with one ``UsageError``.

A stop signal inside the block is the other end of a stall. Lightning's SIGTERM handler, and omg's
Ctrl-C one (``omg.callbacks.run.InterruptCheckpoint``), only set a flag that the training loop reads at
the end of a step, and a read that never returns never gets there: SIGTERM and Ctrl-C did nothing
until ``data.timeout`` (10 minutes by default). So while a block runs, a SIGTERM or SIGINT whose
handler is such a flag-setter (a Python function; the default actions end the process, or raise
KeyboardInterrupt, at once) still runs that handler, and if the block has not ended
``STOP_GRACE_S`` seconds later it raises Lightning's ``SIGTERMException``: the run stops as it
stops at a step's end, with ``omg fit``'s usual line (``omg.cli``).
"""

from __future__ import annotations

import os
import signal
import threading
import time
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Iterator

from omg.errors import UsageError

# what a read that is merely slow still gets after a stop signal, so that its step ends and saves
# interrupted.ckpt as usual; a stalled one is given up then
STOP_GRACE_S = 3.0
STOP_SIGNALS = (signal.SIGTERM, signal.SIGINT)


class _Expired(BaseException):
    """Raised by the alarm inside whatever call was blocked. A BaseException, as KeyboardInterrupt is: the
    readers' ``except Exception`` (a bad shard is skipped and counted) must not take a stall for a bad shard."""


@dataclass(eq=False)  # blocks are told apart by identity
class _Block:
    end: float | None  # time.monotonic() at which it expires; None: no limit of its own
    token: _Expired = field(default_factory=_Expired)


@dataclass
class _State:
    """The main thread's open blocks (outermost first) and what the outermost one replaced."""
    blocks: list[_Block] = field(default_factory=list)
    pid: int = 0  # the process that opened them (a forked worker inherits the handlers, not the blocks)
    alarm_handler: object = None
    alarm_left: float = 0.0  # an enclosing alarm's seconds left when the outermost block began
    began: float = 0.0
    stop_handlers: dict = field(default_factory=dict)  # signal -> the handler our wrapper calls
    stop_at: float | None = None  # when a stop signal's grace ends


_state = _State()


@contextmanager
def deadline(seconds: float, message: str) -> Iterator[None]:
    """Raise ``UsageError(message)`` when the block takes longer than ``seconds`` (0: no limit), and
    ``SIGTERMException`` when it is still running ``STOP_GRACE_S`` after a SIGTERM or Ctrl-C.

    Works only in a process's main thread (where Lightning runs and a DataLoader worker reads);
    elsewhere the block runs unbounded. Blocks nest; whatever alarm and stop-signal handlers the
    outermost one replaced are restored afterwards, an enclosing alarm with its time left.
    """
    if threading.current_thread() is not threading.main_thread() or not hasattr(signal, "setitimer"):
        yield
        return
    block = _Block(time.monotonic() + seconds if seconds else None)
    if not _state.blocks:
        _open()
    _state.blocks.append(block)
    _arm()
    try:
        try:
            yield
        finally:
            _leave(block)  # an alarm that fires up to here is still caught below, one after finds no block
    except _Expired as e:
        if e is not block.token:
            raise
        raise UsageError(message) from None
    finally:
        _leave(block)  # again, when the alarm came before the first one began (one alarm: it is not re-armed)


def _open() -> None:
    _state.pid, _state.began, _state.stop_at = os.getpid(), time.monotonic(), None
    _state.alarm_handler = signal.signal(signal.SIGALRM, _on_alarm)
    _state.alarm_left = signal.setitimer(signal.ITIMER_REAL, 0)[0]
    _state.stop_handlers = {}
    for signum in STOP_SIGNALS:
        handler = signal.getsignal(signum)
        if callable(handler) and handler is not signal.default_int_handler:  # a flag-setter (see the module doc)
            _state.stop_handlers[signum] = handler
            signal.signal(signum, _on_stop)


def _leave(block: _Block) -> None:
    if block in _state.blocks:
        _state.blocks.remove(block)  # first: a late alarm finds no block of its own
        if _state.blocks:
            _arm()
        else:
            _close()


def _close() -> None:
    signal.setitimer(signal.ITIMER_REAL, 0)
    signal.signal(signal.SIGALRM, _state.alarm_handler)
    for signum, handler in _state.stop_handlers.items():
        if signal.getsignal(signum) is _on_stop:  # else the handler set another one (a second Ctrl-C aborts)
            signal.signal(signum, handler)
    _state.stop_handlers, _state.stop_at = {}, None
    if _state.alarm_left:
        signal.setitimer(signal.ITIMER_REAL, max(_state.alarm_left - (time.monotonic() - _state.began), 1e-3))


def _arm() -> None:
    """The alarm at the earliest of the open blocks' ends and a stop signal's grace."""
    ends = [b.end for b in _state.blocks if b.end is not None] + ([_state.stop_at] if _state.stop_at else [])
    signal.setitimer(signal.ITIMER_REAL, max(min(ends) - time.monotonic(), 1e-3) if ends else 0)


def _on_alarm(signum, frame) -> None:
    if os.getpid() != _state.pid or not _state.blocks:
        return
    now = time.monotonic()
    if _state.stop_at is not None and now >= _state.stop_at:
        from lightning.pytorch.utilities.exceptions import SIGTERMException

        _state.stop_at = None
        raise SIGTERMException  # what Lightning's loops raise at a step's end after the same signal
    for block in _state.blocks:  # the outermost that has expired
        if block.end is not None and now >= block.end:
            raise block.token
    _arm()  # woken early


def _on_stop(signum, frame) -> None:
    handler = _state.stop_handlers.get(signum)
    if handler is not None:
        handler(signum, frame)
    if os.getpid() == _state.pid and _state.blocks and _state.stop_at is None:
        _state.stop_at = time.monotonic() + STOP_GRACE_S
        _arm()
