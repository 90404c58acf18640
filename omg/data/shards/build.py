"""A build: a source read once for all its splits, in one process or a pool of them with the same
output for any number, with progress lines."""

from __future__ import annotations

import os
import signal
import sys
import time
from concurrent.futures import Future
from dataclasses import dataclass, field
from typing import Callable, Iterable, Iterator

import numpy as np

from omg.data.shards.items import EncodedClip, LazyItem, encode_item
from omg.data.shards.writer import BuildSummary, ShardWriter
from omg.motion import Clip, Representation


@dataclass
class SourceItems:
    """What a source may return instead of a bare iterator, to pass set-level facts along.

    ``stats`` maps a representation name to a published (mean, std) pair, each (D,); a shard
    set of that representation stores them in its manifest instead of the measured ones, so
    models normalise exactly as the published ones do (HumanML3D's ``Mean.npy``/``Std.npy``).
    """

    items: Iterable[Clip | Exception]
    stats: dict[str, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)

    def __iter__(self) -> Iterator[Clip | Exception]:
        return iter(self.items)


def _start_worker() -> None:
    """A pool worker of a build: Ctrl-C is the main process's to handle, torch runs on one thread (N
    workers on N cores), and the worker ends when the main process does. A forked worker holds a copy
    of the pool's pipes too, so a killed main process does not end its wait for work with EOF: a
    thread watches for it."""
    import multiprocessing
    import threading

    import torch

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    torch.set_num_threads(1)
    parent = multiprocessing.parent_process()

    def watch() -> None:
        while parent is None or parent.is_alive():
            time.sleep(1.0)
        os._exit(0)  # at once: a normal exit would wait for results nobody reads now

    threading.Thread(target=watch, daemon=True).start()


def _encoded(items: Iterable, start: int, representation: Representation, fps: float,
             workers: int) -> Iterator[tuple[int, EncodedClip | Exception | None]]:
    """(position, encoded item) for the items after position ``start``, in the items' order.

    ``workers`` > 1: a pool of that many processes (the standard library's, forked on Linux: a
    worker starts at once with this process's imports, where a spawned one spends about a second
    importing torch) reads and encodes; at most ``4 * workers`` items are in flight and results are
    taken in order, so the shards are the same as with one worker. An exception a source raises
    in a worker stops the build, raised here."""
    if workers <= 1:
        for position, item in enumerate(items, start=1):
            if position > start:
                yield position, encode_item(item, representation, fps)
        return
    import gc
    import multiprocessing
    from collections import deque
    from concurrent.futures import ProcessPoolExecutor
    from concurrent.futures.process import BrokenProcessPool

    context = multiprocessing.get_context("fork" if sys.platform.startswith("linux") else "spawn")
    # A forked worker inherits this process's uncollected garbage, and its collector would finalize it there,
    # where an object whose finalizer waits on one of this process's threads (a DDP wrapper's gloo group, left
    # by a training in the same process) waits for ever: collected here, where those threads are
    gc.collect()
    window: deque[tuple[int, Future | EncodedClip | Exception | None]] = deque()
    pool = ProcessPoolExecutor(workers, mp_context=context, initializer=_start_worker)
    try:
        pending = ((p, item) for p, item in enumerate(items, start=1) if p > start)
        for position, item in pending:
            work = isinstance(item, (LazyItem, Clip))  # None and exceptions pass through as they are
            window.append((position, pool.submit(encode_item, item, representation, fps) if work else item))
            while len(window) >= 4 * workers:
                yield _taken(window.popleft())
        while window:
            yield _taken(window.popleft())
    except BrokenProcessPool:
        raise RuntimeError("a worker process of the build died (out of memory?); run the same command again to "
                           "resume, with fewer --workers") from None
    finally:  # every result is in (or the build failed): nothing queued is worth doing
        pool.shutdown(wait=False, cancel_futures=True)


def _taken(entry: tuple[int, Future | EncodedClip | Exception | None]) -> tuple[int, EncodedClip | Exception | None]:
    position, result = entry
    return position, result.result() if hasattr(result, "result") else result


class BuildProgress:
    """A line on stderr every ``interval`` seconds while a build runs: items read (of how many,
    where the source knows), clips written, items skipped, the rate and the time left."""

    def __init__(self, total: int | None = None, interval: float = 5.0, stream=None, label: str = "build"):
        self.total, self.interval, self.label = total, interval, label
        self.stream = stream if stream is not None else sys.stderr
        self.read = self.clips = self.skipped = 0
        self.started = self.last = time.monotonic()
        self.reported = False

    def update(self, result) -> None:
        self.read += 1
        if isinstance(result, Exception) or (isinstance(result, EncodedClip) and result.error is not None):
            self.skipped += 1
        elif result is not None:
            self.clips += 1
        if time.monotonic() - self.last >= self.interval:
            self.report()

    def line(self) -> str:
        elapsed = max(time.monotonic() - self.started, 1e-9)
        rate = self.read / elapsed
        of = f" of {self.total} ({100.0 * self.read / self.total:.0f}%)" if self.total else ""
        left = ""
        if self.total and rate > 0:
            left = f", {_duration(max(self.total - self.read, 0) / rate)} left"
        return (f"{self.label}: {self.read}{of} items read, {self.clips} clips, {self.skipped} skipped, "
                f"{rate:.1f} items/s, {_duration(elapsed)} elapsed{left}")

    def report(self) -> None:
        self.last, self.reported = time.monotonic(), True
        print(self.line(), file=self.stream, flush=True)

    def finish(self) -> None:
        """The final line, for a build that has shown progress (a short one has its summary alone)."""
        if self.reported:
            self.report()


def _duration(seconds: float) -> str:
    seconds = int(round(seconds))
    return f"{seconds // 3600}:{seconds // 60 % 60:02d}:{seconds % 60:02d}"


def write_shards(items: Iterable, writers: dict[str, ShardWriter], route: Callable[[EncodedClip], str] | None = None,
                 workers: int = 1, progress: BuildProgress | None = None) -> list[BuildSummary]:
    """Read and encode the items once and write each clip to the writer ``route`` names (the
    first writer without a route; a failed item is counted by the first writer).

    Each writer resumes after its own finished shards; the items before the earliest of them
    are not read again. ``workers``: processes that read and encode (see ``_encoded``); the
    shards are the same for any number."""
    names = list(writers)
    first = writers[names[0]]
    if any(w.representation.name != first.representation.name or w.fps != first.fps for w in writers.values()):
        raise ValueError("the writers of one build must share the representation and the frame rate")
    import torch

    start = min(writer.open() for writer in writers.values())
    if progress is not None:
        progress.read = start  # the items before were written by an earlier run
        progress.started = time.monotonic()
    # a clip's tensors are small: one intra-op thread per process, as in the workers (reading the
    # real clips of ../shared/data/motion took 3-4x longer with two threads on a busy 2-core CPU)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        for position, result in _encoded(items, start, first.representation, first.fps, workers):
            target = None
            if result is not None:
                routed = isinstance(result, EncodedClip) and route is not None
                target = route(result) if routed else names[0]
            for name, writer in writers.items():
                writer.add(position, result if name == target else None)
            if progress is not None:
                progress.update(result)
    finally:
        torch.set_num_threads(threads)
    if progress is not None:
        progress.finish()
    return [writer.close() for writer in writers.values()]
