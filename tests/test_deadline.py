"""``omg.data.deadline``: one bound on a blocking read, which puts back whatever alarm it replaced."""

from __future__ import annotations

import os
import signal
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
