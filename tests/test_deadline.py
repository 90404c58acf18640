"""``omg.data.deadline``: one bound on a blocking read, which puts back whatever alarm it replaced, and
a stop signal (SIGTERM, Ctrl-C) that ends a blocked read instead of waiting for the bound."""

from __future__ import annotations

import os
import signal
import threading
import time

import pytest

from omg.data.deadline import deadline
from omg.errors import UsageError


def test_a_blocked_read_ends_with_the_message_and_the_alarm_is_put_back():
    read_end, write_end = os.pipe()  # nothing is ever written: os.read blocks
    handler = signal.getsignal(signal.SIGALRM)
    try:
        start = time.monotonic()
        with pytest.raises(UsageError, match="^stalled$"):
            with deadline(0.5, "stalled"):
                os.read(read_end, 1)
        assert time.monotonic() - start < 5
        assert signal.getsignal(signal.SIGALRM) is handler
        assert signal.getitimer(signal.ITIMER_REAL) == (0.0, 0.0)
    finally:
        os.close(read_end)
        os.close(write_end)


def test_an_inner_deadline_keeps_the_outer_one_and_zero_means_no_limit():
    with pytest.raises(UsageError, match="outer"):
        with deadline(1.0, "outer"):
            with deadline(30.0, "inner"):
                pass
            remaining = signal.getitimer(signal.ITIMER_REAL)[0]
            assert 0 < remaining <= 1.0
            with deadline(0, "never"):
                time.sleep(2)  # the outer alarm, not this block's (which has none), ends it


@pytest.fixture
def flag_on_sigterm():
    """A SIGTERM handler that only sets a flag, as Lightning's does during a run; put back afterwards."""
    seen = []
    previous = signal.signal(signal.SIGTERM, lambda signum, frame: seen.append(signum))
    yield seen
    signal.signal(signal.SIGTERM, previous)


def test_a_stop_signal_ends_a_blocked_read_after_the_grace(flag_on_sigterm, monkeypatch):
    """SIGTERM while a read is blocked: the run's own handler still runs (Lightning sets its flag), and
    the block, which would never end (no limit of its own), raises Lightning's SIGTERMException."""
    from lightning.pytorch.utilities.exceptions import SIGTERMException

    from omg.data import deadline as module

    monkeypatch.setattr(module, "STOP_GRACE_S", 0.5)
    handler = signal.getsignal(signal.SIGTERM)
    read_end, write_end = os.pipe()
    # the signal, and a rescue that ends the read after 10 s should nothing else end it (a failure, not a hang)
    timers = [threading.Timer(0.2, os.kill, (os.getpid(), signal.SIGTERM)),
              threading.Timer(10, os.write, (write_end, b"x"))]
    try:
        start = time.monotonic()
        for timer in timers:
            timer.start()
        with pytest.raises(SIGTERMException):
            with deadline(0, "never"):
                os.read(read_end, 1)
        assert 0.6 < time.monotonic() - start < 5
        assert flag_on_sigterm == [signal.SIGTERM]
        assert signal.getsignal(signal.SIGTERM) is handler and signal.getitimer(signal.ITIMER_REAL) == (0.0, 0.0)
    finally:
        for timer in timers:
            timer.cancel()
        os.close(read_end)
        os.close(write_end)


def test_a_read_that_ends_within_the_grace_is_not_cut(flag_on_sigterm, monkeypatch):
    """A slow read, not a stalled one: it ends before the grace and its step goes on (to save a checkpoint)."""
    from omg.data import deadline as module

    monkeypatch.setattr(module, "STOP_GRACE_S", 2.0)
    read_end, write_end = os.pipe()
    timers = [threading.Timer(0.1, os.kill, (os.getpid(), signal.SIGTERM)),
              threading.Timer(0.4, os.write, (write_end, b"x"))]
    try:
        for timer in timers:
            timer.start()
        with deadline(0, "never"):
            assert os.read(read_end, 1) == b"x"
        assert flag_on_sigterm == [signal.SIGTERM]
        assert signal.getitimer(signal.ITIMER_REAL) == (0.0, 0.0)  # the grace's alarm is gone with the block
    finally:
        for timer in timers:
            timer.cancel()
        os.close(read_end)
        os.close(write_end)
