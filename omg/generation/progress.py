"""How far a generation call is, as its generator reports it, and the time it has left.

A generator reports a ``Progress`` through ``GenerationRequest.progress`` when a batch of motions starts, after
each of its sampler's steps (a diffusion family's, through the solver's ``StepProgress``) and when the batch is
done; a family without diffusion steps reports its batches (one motion each) only. Watching draws no random
number and calls no model: the motions are those of an unwatched call. ``ProgressClock`` turns the reports into
the elapsed time and the time left, from the seconds per step measured in the call (``omg generate``'s line and
``omg serve``'s ``/v1/status`` read the same clock).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass

from omg.diffusion import StepProgress


@dataclass(frozen=True)
class Progress:
    """The batch in flight: its ``rows`` motions from motion ``start`` (0-based) of the call's ``total``, its sampler
    at ``step`` of ``steps`` (0 steps: a family without them), ``finished`` once its motions are made."""

    start: int
    rows: int
    total: int
    step: int = 0
    steps: int = 0
    finished: bool = False

    @property
    def done(self) -> int:
        """The call's motions made."""
        return self.start + self.rows if self.finished else self.start

    @property
    def motions(self) -> str:
        """The batch's motions in words: ``motion 3 of 8``, ``motions 1-4 of 8``."""
        if self.rows == 1:
            return f"motion {self.start + 1} of {self.total}"
        return f"motions {self.start + 1}-{self.start + self.rows} of {self.total}"


ProgressReport = Callable[[Progress], None]


class Batch:
    """What a generator reports of one batch to ``report`` (nothing when it is None): its start when made, each
    step of its sampler (``solver``, the ``StepProgress`` a diffusion sampler takes), and ``finish``."""

    def __init__(self, report: ProgressReport | None, start: int, rows: int, total: int, steps: int = 0):
        self.report, self.start, self.rows, self.total, self.steps = report, start, rows, total, steps
        self.step(0, steps)

    def step(self, step: int, steps: int) -> None:
        if self.report is not None:
            self.steps = steps
            self.report(Progress(self.start, self.rows, self.total, step, steps))

    @property
    def solver(self) -> StepProgress | None:
        """The sampler's step hook; None when nobody watches (the sampler is then called as it always is)."""
        return None if self.report is None else self.step

    def finish(self) -> None:
        if self.report is not None:
            self.report(Progress(self.start, self.rows, self.total, self.steps, self.steps, finished=True))


class ProgressClock:
    """A ``ProgressReport`` that times the call: ``elapsed()`` since the clock was made (the call's start), and
    ``time_left()`` at the seconds per step measured in the call (per motion for a family without steps): from
    the batch in flight's start to its latest step, or over the previous batch before the first step of the
    next; before any is measured, ``seconds_per_step`` given (an earlier call's), else unknown (None)."""

    def __init__(self, seconds_per_step: float | None = None, clock: Callable[[], float] = time.perf_counter):
        self.clock = clock
        self.started = clock()
        self.seconds_per_step = seconds_per_step
        self.latest: Progress | None = None
        self._batch_started = self.started
        self._reported = self.started  # when ``latest`` came

    def __call__(self, progress: Progress) -> None:
        now = self.clock()
        previous = self.latest
        if previous is None or previous.finished or previous.start != progress.start:
            self._batch_started = now  # a batch starts
        elif not progress.finished and progress.step:
            self.seconds_per_step = (now - self._batch_started) / progress.step
        elif progress.finished and not progress.steps:
            self.seconds_per_step = now - self._batch_started  # a batch of a family without steps is one "step"
        self.latest, self._reported = progress, now

    def elapsed(self) -> float:
        return self.clock() - self.started

    def steps_left(self) -> int | None:
        """The sampler steps (batches, for a family without them) the call has still to make; None before any
        report. Every batch but the last has as many motions as the one in flight."""
        p = self.latest
        if p is None:
            return None
        per_batch = p.steps or 1
        in_flight = 0 if p.finished else per_batch - p.step
        return in_flight + per_batch * math.ceil((p.total - p.start - p.rows) / max(p.rows, 1))

    def time_left(self) -> float | None:
        """Seconds until the call is done, at the measured rate less the time since the latest report; None while
        unknown."""
        left = self.steps_left()
        if left is None or self.seconds_per_step is None:
            return None
        return max(left * self.seconds_per_step - (self.clock() - self._reported), 0.0)
