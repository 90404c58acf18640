"""WebDataset shards of encoded motion: the sample schema, an atomic resumable writer, the
manifest, and validation.

A shard set is a directory of ``shard-NNNNNN.tar`` files plus ``manifest.json``. Each sample
is one clip stored under a key without dots:

- ``<key>.motion.npy``: float32 (T, D) features of the set's representation;
- ``<key>.meta.json``: id, representation, skeleton, fps, source, labels, category, and
  per-clip quantities the representation needs (bone offsets);
- ``<key>.texts.json``: a list of captions, empty for unlabeled data.

Shards are written under a temporary name and renamed when complete, so a shard file that
exists is whole. The manifest records each shard's sample count, byte size and sha256;
``iter_tar`` checks a shard against them as it reads (``ShardError`` names the shard and the
failed check) and ``check_shards`` (``omg shards inspect``) checks a whole set.
``build-state.json`` records the finished shards with the source position and feature
statistics they cover; an interrupted build resumes after the last of them.

``write_shards`` reads a source once for all its splits, in one process or several
(``LazyItem``: a source item read where the build gets to it), with output independent of the
number; ``merge_shard_sets`` joins the sets built from parts of a source into one, its
statistics pooled from the parts' raw sums.
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import pickle
import re
import shlex
import signal
import sys
import tarfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterable, Iterator

import numpy as np

from omg.data.deadline import deadline
from omg.errors import UsageError
from omg.files import atomic_path, atomic_write, file_problem, npy_bytes, write_json
from omg.motion import Clip, DataSpec, Representation

SCHEMA_VERSION = 1
MANIFEST = "manifest.json"
BUILD_STATE = "build-state.json"
SHARD_PATTERN = "shard-{:06d}.tar"
# A manifest's shard names: what the writer and `omg shards merge` write (SHARD_PATTERN). Nothing
# else is accepted: a pipe: set puts each name into its command, which a shell runs.
SHARD_NAME = re.compile(r"shard-[0-9]{6,}\.tar")
PIPE_TIMEOUT_S = 600.0  # a pipe: command that prints a manifest (a few MB at most) and has not ended by then hangs
META_KEYS = ("id", "representation", "skeleton", "fps", "source", "labels", "category")


def sample_key(clip_id: str) -> str:
    """WebDataset splits keys at the first dot, so ids become dot-free keys."""
    return re.sub(r"[^A-Za-z0-9_\-]", "_", clip_id)


def encode_sample(clip: Clip, representation: Representation) -> tuple[str, dict[str, bytes], np.ndarray]:
    """One clip -> (key, {extension: bytes}, features).

    A clip's precomputed features are stored verbatim when they belong to ``representation``
    (so shards stay file-compatible with published feature files); otherwise it is encoded.
    """
    if clip.features is not None and clip.features_representation == representation.name:
        features, extra = clip.features, {}
    else:
        features, extra = representation.encode(clip)
    features = np.ascontiguousarray(features, dtype=np.float32)
    if features.ndim != 2 or features.shape[1] != representation.dim or len(features) == 0:
        raise ValueError(f"clip {clip.id!r}: encoded to shape {features.shape}, expected (T>0, {representation.dim})")
    if not np.isfinite(features).all():
        raise ValueError(f"clip {clip.id!r}: features contain NaN or inf")
    meta = {
        "id": clip.id,
        "representation": representation.name,
        "skeleton": representation.skeleton.name,
        "fps": clip.fps,
        "source": clip.source,
        "labels": clip.labels,
        "category": clip.category,
        **extra,
    }
    files = {
        "motion.npy": npy_bytes(features),
        "meta.json": json.dumps(meta).encode(),
        "texts.json": json.dumps(list(clip.texts)).encode(),
    }
    return sample_key(clip.id), files, features


def _tar_bytes(samples: list[tuple[str, dict[str, bytes]]]) -> bytes:
    """A deterministic tar (fixed mtime/owner) so rebuilding the same data gives the same bytes."""
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w", format=tarfile.USTAR_FORMAT) as tar:
        for key, files in samples:
            for ext, data in files.items():
                info = tarfile.TarInfo(f"{key}.{ext}")
                info.size, info.mtime, info.mode = len(data), 0, 0o644
                info.uname = info.gname = "omg"
                tar.addfile(info, io.BytesIO(data))
    return buf.getvalue()


@dataclass
class FeatureStats:
    """Running per-feature sums in float64, mergeable across shards."""

    count: int = 0
    total: np.ndarray | None = None
    total_sq: np.ndarray | None = None

    def add(self, features: np.ndarray) -> None:
        f = features.astype(np.float64)
        if self.total is None:
            self.total, self.total_sq = np.zeros(f.shape[1]), np.zeros(f.shape[1])
        self.count += len(f)
        self.total += f.sum(0)
        self.total_sq += (f * f).sum(0)

    def merge(self, other: FeatureStats) -> None:
        if other.total is None:
            return
        if self.total is None:
            self.total, self.total_sq = np.zeros_like(other.total), np.zeros_like(other.total)
        self.count += other.count
        self.total += other.total
        self.total_sq += other.total_sq

    def mean_std(self) -> tuple[np.ndarray, np.ndarray]:
        mean = self.total / self.count
        var = np.maximum(self.total_sq / self.count - mean * mean, 0.0)
        return mean, np.sqrt(var)

    def to_json(self) -> dict:
        return {"count": self.count, "total": self.total.tolist(), "total_sq": self.total_sq.tolist()}

    @classmethod
    def from_json(cls, d: dict) -> FeatureStats:
        return cls(d["count"], np.asarray(d["total"]), np.asarray(d["total_sq"]))


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


@dataclass
class BuildSummary:
    out_dir: Path
    clips: int = 0
    frames: int = 0
    shards: int = 0
    resumed_shards: int = 0
    skipped: dict[str, int] = field(default_factory=dict)

    def __str__(self) -> str:
        skipped = sum(self.skipped.values())
        reasons = ", ".join(f"{k}: {v}" for k, v in sorted(self.skipped.items()))
        return (
            f"{self.out_dir}: {self.clips} clips, {self.frames} frames in {self.shards} shards"
            f" ({self.resumed_shards} kept from an earlier run); skipped {skipped}"
            + (f" ({reasons})" if reasons else "")
        )


@dataclass(frozen=True)
class LazyItem:
    """A source item that is read when the build gets to it, possibly in a worker process.

    ``load(*args)`` returns a ``Clip``, ``None`` (nothing to import, e.g. a clip of another
    domain) or an exception (a bad item: counted as skipped); an exception it raises stops the
    build. With ``--workers`` the item travels to another process: ``load`` must be a
    module-level function and ``args`` picklable. Sources that list their files and yield one
    ``LazyItem`` per file are read in parallel; sources that yield clips are read in order by the
    main process and only encoded in parallel.
    """

    load: Callable[..., Clip | Exception | None]
    args: tuple = ()

    def __call__(self) -> Clip | Exception | None:
        return self.load(*self.args)


def resolved(items: Iterable) -> Iterator[Clip | Exception | None]:
    """A source's items with every ``LazyItem`` read: clips, exceptions and Nones."""
    for item in items:
        yield item() if isinstance(item, LazyItem) else item


@dataclass
class EncodedClip:
    """One clip, read and encoded: what ``ShardWriter.add`` stores (``error``: why it cannot be)."""

    id: str
    labels: dict
    key: str = ""
    files: dict[str, bytes] = field(default_factory=dict)
    stats: FeatureStats | None = None  # the sums over the clip's frames
    error: Exception | None = None


def encode_item(item, representation: Representation, fps: float) -> EncodedClip | Exception | None:
    """Read (a ``LazyItem``) and encode one source item; a bad clip comes back with its error."""
    if isinstance(item, LazyItem):
        item = item()
    if item is None or isinstance(item, Exception):
        return item
    try:
        if abs(item.fps - fps) > 1e-6:
            raise ValueError(f"clip {item.id!r} is at {item.fps} fps, the shard set at {fps}")
        key, files, features = encode_sample(item, representation)
    except (ValueError, OSError) as e:
        return EncodedClip(item.id, dict(item.labels), error=e)
    stats = FeatureStats()
    stats.add(features)
    return EncodedClip(item.id, dict(item.labels), key, files, stats)


def _helper(representation: Representation, fps: float, tasks, results, index: int) -> None:
    """A helper process of a build: reads and encodes the items it is sent, one at a time, and ends
    when the main process does."""
    import multiprocessing
    import signal

    import torch

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the main process's to handle
    torch.set_num_threads(1)  # N workers on N cores: one thread each
    results.put(pickle.dumps((index, 0, None, None)))  # ready for an item
    parent = multiprocessing.parent_process()
    while True:
        try:
            # a forked helper holds a copy of the pipe's sending end too, so a killed main process
            # does not end ``recv`` with EOF: look for it while waiting
            while not tasks.poll(1.0):
                if parent is not None and not parent.is_alive():
                    os._exit(0)
            position, item = tasks.recv()
        except (EOFError, OSError):  # the main process is gone (killed): so is the build
            # at once: a normal exit would wait for the results still queued, which nobody reads now
            os._exit(0)
        try:
            message = (index, position, encode_item(item, representation, fps), None)
        except Exception as e:  # noqa: BLE001 - raised by a source: it stops the build, in the main process
            message = (index, position, None, e)
        try:
            payload = pickle.dumps(message)
        except Exception as e:  # noqa: BLE001 - what cannot travel back would leave the build waiting for it
            payload = pickle.dumps((index, position, None, RuntimeError(
                f"source item {position}: its result cannot be sent between processes ({type(e).__name__}: {e})")))
        results.put(payload)


def _encoded(items: Iterable, start: int, representation: Representation, fps: float,
             workers: int) -> Iterator[tuple[int, EncodedClip | Exception | None]]:
    """(position, encoded item) for the items after position ``start``, in the items' order.

    ``workers`` > 1: this process and ``workers - 1`` helper processes (forked on Linux, spawned
    elsewhere) read and encode. A helper is sent an item only when it is
    idle; this process reads the oldest item nobody has taken whenever the oldest result is
    not ready, so the build goes on while the helpers start. At most a few items per worker
    are held, and results come back in order: the same shards as with one worker."""
    if workers <= 1:
        for position, item in enumerate(items, start=1):
            if position > start:
                yield position, encode_item(item, representation, fps)
        return
    import multiprocessing
    import queue
    from collections import deque

    # fork on Linux: a helper starts at once with this process's imports (a spawned one spends about a
    # second importing torch, as much as all the work of a small set); it runs torch on one thread
    # from its first line, as DataLoader workers do, so no OpenMP pool of this process is used in it
    context = multiprocessing.get_context("fork" if sys.platform.startswith("linux") else "spawn")
    results = context.Queue()
    helpers, pipes = [], []
    for index in range(workers - 1):
        receive, send = context.Pipe(duplex=False)
        process = context.Process(target=_helper, args=(representation, fps, receive, results, index), daemon=True)
        process.start()
        helpers.append(process)
        pipes.append(send)
    pending = ((position, item) for position, item in enumerate(items, start=1) if position > start)
    window: deque[list] = deque()  # [position, item, state]: state "todo", "busy" or (result,); oldest first
    idle: list[int] = []
    exhausted = False

    def take(payload: bytes) -> None:
        index, position, result, error = pickle.loads(payload)
        if error is not None:
            raise error
        idle.append(index)
        if position:
            entry = next(e for e in window if e[0] == position)
            entry[2] = (result,)

    try:
        while True:
            while not exhausted and len(window) < 4 * workers:
                nxt = next(pending, None)
                if nxt is None:
                    exhausted = True
                    break
                work = isinstance(nxt[1], (LazyItem, Clip))
                window.append([nxt[0], nxt[1], "todo" if work else (nxt[1],)])
            if not window:
                return
            while True:  # what the helpers have done
                try:
                    take(results.get_nowait())
                except queue.Empty:
                    break
            for entry in window:  # idle helpers take the oldest items nobody has taken
                if not idle:
                    break
                if entry[2] == "todo":
                    entry[2] = "busy"
                    pipes[idle.pop()].send((entry[0], entry[1]))
            oldest = window[0]
            if isinstance(oldest[2], tuple):
                window.popleft()
                yield oldest[0], oldest[2][0]
                continue
            entry = next((e for e in window if e[2] == "todo"), None)
            if entry is not None:  # read it here rather than wait
                entry[2] = (encode_item(entry[1], representation, fps),)
                continue
            try:
                take(results.get(timeout=5.0))
            except queue.Empty:
                if dead := [i for i, h in enumerate(helpers) if not h.is_alive()]:
                    raise RuntimeError(f"helper process {dead[0]} of the build died (out of memory?); run the "
                                       "same command again to resume, with fewer --workers") from None
    finally:  # every result is in (or the build failed): no helper holds anything worth waiting for
        for process in helpers:
            process.terminate()
        for process in helpers:
            process.join(timeout=10.0)
        results.close()


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


class ShardWriter:
    """Writes clips into shards of at most ``max_clips`` clips or ``max_bytes`` bytes.

    Clips come from a source iterator whose order is deterministic; the build state records
    how many source items each finished shard consumed, so a resumed build skips exactly
    those. Bad clips (the encoder raises ``ValueError``) are skipped and counted by reason.
    ``stats``: a fixed (mean, std) for the manifest instead of the one measured on the clips.

    ``write(items)`` reads, encodes and writes in one go; ``write_shards`` drives one or more
    writers through ``open`` / ``add`` / ``close`` (a train/val split in one pass, workers).
    """

    def __init__(
        self,
        out_dir: str | Path,
        representation: Representation,
        fps: float,
        max_clips: int = 1000,
        max_bytes: int = 256 << 20,
        command: str = "",
        log=print,
        stats: tuple[np.ndarray, np.ndarray] | None = None,
    ):
        if max_clips < 1 or max_bytes < 1:
            raise UsageError(f"shard size must be positive, got max_clips={max_clips}, max_bytes={max_bytes}")
        if stats is not None:
            stats = tuple(np.asarray(a, dtype=np.float32).reshape(-1) for a in stats)
            if any(len(a) != representation.dim for a in stats) or not (stats[1] > 0).all():
                raise UsageError(
                    f"fixed stats for {representation.name!r} must be a mean and a positive std of "
                    f"{representation.dim} features each, got shapes {[a.shape for a in stats]}"
                )
        self.stats = stats
        self.out_dir = Path(out_dir)
        self.representation = representation
        self.fps = fps
        self.max_clips, self.max_bytes = max_clips, max_bytes
        self.command = command
        self.log = log

    def _load_state(self) -> dict:
        path = self.out_dir / BUILD_STATE
        if not path.exists():
            return {"shards": [], "skipped": {}}
        state = json.loads(path.read_text())
        expected = {"representation": self.representation.name, "fps": self.fps}
        found = {k: state.get(k) for k in expected}
        if found != expected:
            raise UsageError(
                f"{self.out_dir} holds an unfinished build with {found}, not {expected}; "
                "use the same settings to resume or choose another output directory"
            )
        # shards beyond the recorded state were never finished: remove them
        for extra in sorted(self.out_dir.glob("shard-*.tar"))[len(state["shards"]) :]:
            extra.unlink()
        return state

    def write(self, items: Iterable[Clip | LazyItem | Exception | None]) -> BuildSummary:
        """Consume the source: clips (or ``LazyItem``s), exceptions for items that failed to
        load, and None for items that belong to another split."""
        done = self.open()
        for position, item in enumerate(items, start=1):
            self.add(position, None if position <= done else encode_item(item, self.representation, self.fps))
        return self.close()

    def open(self) -> int:
        """Start or resume: returns the source position the finished shards cover."""
        self.out_dir.mkdir(parents=True, exist_ok=True)
        for stale in self.out_dir.glob(".*.tmp*"):
            stale.unlink()
        self._state = state = self._load_state()
        state.update(representation=self.representation.name, fps=self.fps)
        self._resumed = len(state["shards"])
        self._done = state["shards"][-1]["source_end"] if state["shards"] else 0
        self._seen = set(state.get("keys", []))
        self._pending: list[tuple[str, dict[str, bytes]]] = []
        self._pending_bytes, self._pending_stats = 0, FeatureStats()
        self._position = self._done
        return self._done

    def add(self, position: int, result: EncodedClip | Exception | None) -> None:
        """The source item at ``position`` (1-based, increasing): an encoded clip, the exception
        of an item that failed, or None (nothing for this writer)."""
        self._position = max(self._position, position)
        if position <= self._done or result is None:
            return
        error = result if isinstance(result, Exception) else result.error
        if error is None and result.key in self._seen:
            error = ValueError(f"duplicate clip id {result.id!r}")
        if error is not None:
            reason = type(error).__name__ if not str(error) else str(error).split(":")[0][:60]
            skipped = self._state["skipped"]
            skipped[reason] = skipped.get(reason, 0) + 1
            self.log(f"skipped source item {position}: {error}")
            return
        self._seen.add(result.key)
        self._pending.append((result.key, result.files))
        self._pending_bytes += sum(len(b) for b in result.files.values())
        self._pending_stats.merge(result.stats)
        if len(self._pending) >= self.max_clips or self._pending_bytes >= self.max_bytes:
            self._flush()

    def _flush(self) -> None:
        state = self._state
        name = SHARD_PATTERN.format(len(state["shards"]))
        data = _tar_bytes(self._pending)
        atomic_write(self.out_dir / name, data)
        state["shards"].append(
            {
                "name": name,
                "clips": len(self._pending),
                "frames": self._pending_stats.count,
                "bytes": len(data),
                "sha256": hashlib.sha256(data).hexdigest(),
                "source_end": self._position,
                "stats": self._pending_stats.to_json(),
            }
        )
        state["keys"] = sorted(self._seen)
        write_json(self.out_dir / BUILD_STATE, state)
        self.log(f"wrote {name}: {len(self._pending)} clips")
        self._pending, self._pending_bytes, self._pending_stats = [], 0, FeatureStats()

    def close(self) -> BuildSummary:
        """Write the last shard and the manifest; the build state goes."""
        if self._pending:
            self._flush()
        state = self._state
        if not state["shards"]:
            why = f"none of the {self._position} source items went to it" if self._position else "the source was empty"
            raise UsageError(f"no clip could be written to {self.out_dir} ({state['skipped'] or why})")
        self._write_manifest(state)
        (self.out_dir / BUILD_STATE).unlink()
        return BuildSummary(
            self.out_dir,
            clips=sum(s["clips"] for s in state["shards"]),
            frames=sum(s["frames"] for s in state["shards"]),
            shards=len(state["shards"]),
            resumed_shards=self._resumed,
            skipped=state["skipped"],
        )

    def _write_manifest(self, state: dict) -> None:
        stats = FeatureStats()
        for shard in state["shards"]:
            stats.merge(FeatureStats.from_json(shard["stats"]))
        shards = [{k: s[k] for k in ("name", "clips", "frames", "bytes", "sha256")} for s in state["shards"]]
        manifest = manifest_data(self.representation, self.fps, shards, stats, state["skipped"], self.command,
                                 self.stats)
        write_json(self.out_dir / MANIFEST, manifest)


def manifest_data(representation: Representation, fps: float, shards: list[dict], stats: FeatureStats,
                  skipped: dict[str, int], command: str = "",
                  fixed: tuple[np.ndarray, np.ndarray] | None = None, **extra) -> dict:
    """A set's manifest: its shards, and the mean/std finalized once from the raw sums over all
    its frames (or ``fixed``, a published normalisation)."""
    mean, std = fixed or representation.finalize_stats(*stats.mean_std())
    skeleton = representation.skeleton
    return {
        "schema_version": SCHEMA_VERSION,
        "representation": representation.name,
        "feature_dim": representation.dim,
        "skeleton": skeleton.name,
        "skeleton_def": skeleton.to_dict(),
        "fps": fps,
        "num_clips": sum(s["clips"] for s in shards),
        "num_frames": stats.count,
        "num_shards": len(shards),
        "skipped": skipped,
        "shards": shards,
        "mean": np.asarray(mean).tolist(),
        "std": np.asarray(std).tolist(),
        "stats_origin": "source" if fixed is not None else "measured",
        # the raw per-feature sums behind a measured mean/std: sets (merged parts, mixtures)
        # pool these, since a finalized std (e.g. humanml3d263's group average) cannot be pooled
        "sums": stats.to_json(),
        "command": command,
        **extra,
    }


def _clip_ids(shard: Path) -> set[str]:
    """The sample keys of a local shard, as WebDataset groups its members, from the tar headers alone."""
    from webdataset.tariterators import base_plus_ext

    try:
        with tarfile.open(shard) as tar:
            return {key for key, _ in map(base_plus_ext, tar.getnames()) if key}
    except (OSError, tarfile.TarError) as e:
        raise UsageError(f"{shard}: not a readable shard ({e}); rebuild that part") from None


def _check_disjoint(manifests: list[Manifest]) -> None:
    """Each part once and no clip in two parts: a merge would otherwise train on those clips twice
    as often and pool their statistics twice."""
    owners: dict[str, Path] = {}  # clip id -> the part holding it
    seen: dict[Path, Path] = {}  # resolved folder -> the part as given
    for m in manifests:
        if (resolved := m.dir.resolve()) in seen:
            raise UsageError(f"cannot merge {m.dir}: the same part as {seen[resolved]}, given twice; "
                             "give each part once")
        seen[resolved] = m.dir
        for path in m.shard_paths:
            ids = _clip_ids(path)
            if clash := next((i for i in sorted(ids) if i in owners), None):
                raise UsageError(f"cannot merge {m.dir} and {owners[clash]}: they overlap (both hold clip {clash}); "
                                 "parts of one build hold disjoint clips")
            owners.update(dict.fromkeys(ids, m.dir))


def merge_shard_sets(parts: list[str | Path], out: str | Path, command: str = "", link: bool = False,
                     log=print) -> Manifest:
    """Join finished shard sets (the parts of an array build) into one set at ``out``: their
    shards in part order, renamed ``shard-NNNNNN.tar`` (bytes and sha256 unchanged), counts
    summed and the statistics pooled from the parts' raw sums, finalized once.

    Parts must agree on representation, feature size, skeleton and frame rate. Each shard is
    copied and checked against its part's sha256 as it is copied (``link``: hard-linked, on
    the same file system, and only its size checked)."""
    import os

    manifests = [Manifest.load(p) for p in parts]
    if not manifests:
        raise UsageError("give the part folders to merge")
    first = manifests[0]
    for m in manifests[1:]:
        for key in ("representation", "feature_dim", "skeleton", "skeleton_def", "fps"):
            if m.data.get(key) != first.data.get(key):
                what = "its skeleton definition differs" if key == "skeleton_def" else (
                    f"{key} {m.data.get(key)!r}, but {first.dir} has {first.data.get(key)!r}")
                raise UsageError(f"cannot merge {m.dir}: {what}; parts must be built with the same settings")
    if missing := [str(m.dir) for m in manifests if m.sums is None]:
        raise UsageError(f"{missing[0]}: its manifest has no raw sums to pool statistics from; rebuild that part")
    _check_disjoint(manifests)
    out = Path(out)
    if out.exists() and (any(out.glob("shard-*.tar")) or (out / MANIFEST).exists()):
        raise UsageError(f"--out {out}: already holds a shard set; choose an empty folder")
    if any(out.resolve() == m.dir.resolve() for m in manifests):
        raise UsageError(f"--out {out}: is one of the parts; choose another folder")
    out.mkdir(parents=True, exist_ok=True)
    shards, stats, skipped = [], FeatureStats(), {}
    for m in manifests:
        stats.merge(m.sums)
        for reason, n in m.data.get("skipped", {}).items():
            skipped[reason] = skipped.get(reason, 0) + n
        for entry, path in zip(m["shards"], m.shard_paths):
            name = SHARD_PATTERN.format(len(shards))
            size = entry.get("bytes")
            if link:
                if size is not None and (found := path.stat().st_size) != size:
                    raise UsageError(f"{path}: {found} bytes, its manifest says {size}; rebuild that part")
                with atomic_path(out / name) as tmp:
                    tmp.unlink(missing_ok=True)
                    os.link(path, tmp)
                digest = entry.get("sha256")
            else:
                with atomic_path(out / name) as tmp, open(path, "rb") as src, open(tmp, "wb") as dst:
                    hasher = hashlib.sha256()
                    while chunk := src.read(1 << 22):
                        hasher.update(chunk)
                        dst.write(chunk)
                digest = hasher.hexdigest()
                if entry.get("sha256") not in (None, digest):
                    (out / name).unlink()
                    raise UsageError(f"{path}: its sha256 does not match its manifest (garbled or replaced); "
                                     "rebuild that part")
                size = (out / name).stat().st_size
            shards.append({"name": name, "clips": entry.get("clips", 0), "frames": entry.get("frames", 0),
                           "bytes": size, "sha256": digest})
    from omg.motion import get_representation
    from omg.skeleton import get_skeleton

    representation = get_representation(first["representation"], get_skeleton(first["skeleton"]))
    fixed = None
    if all(m.data.get("stats_origin") == "source" for m in manifests) and all(
            m.data["mean"] == first.data["mean"] and m.data["std"] == first.data["std"] for m in manifests):
        fixed = (first.mean, first.std)  # the published normalisation every part carries
    manifest = manifest_data(representation, first["fps"], shards, stats, skipped, command, fixed,
                             parts=[str(m.dir) for m in manifests])
    manifest["skeleton_def"] = first["skeleton_def"]
    write_json(out / MANIFEST, manifest)
    log(f"merged {len(manifests)} parts into {out}: {manifest['num_clips']} clips, {stats.count} frames "
        f"in {len(shards)} shards")
    return Manifest.load(out)


def _is_int(value) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _is_number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _manifest_problem(data) -> str | None:
    """What is wrong with a parsed manifest, in a few words, or None."""
    if not isinstance(data, dict):
        return f"not a JSON object but a JSON {type(data).__name__}"
    if "schema_version" not in data:
        return "missing key 'schema_version'"
    if data["schema_version"] != SCHEMA_VERSION:
        return f"schema version {data['schema_version']!r}, this omg reads {SCHEMA_VERSION}; rebuild the shards"
    required = ("representation", "skeleton", "feature_dim", "fps", "shards", "mean", "std")
    if missing := [k for k in required if k not in data]:
        return f"missing key{'s' if len(missing) > 1 else ''} {', '.join(map(repr, missing))}"
    for key in ("representation", "skeleton"):
        if not isinstance(data[key], str) or not data[key]:
            return f"{key!r} must be a non-empty string, got {data[key]!r}"
    if not _is_int(data["feature_dim"]) or data["feature_dim"] < 1:
        return f"'feature_dim' must be a positive integer, got {data['feature_dim']!r}"
    if not _is_number(data["fps"]) or not data["fps"] > 0:
        return f"'fps' must be a positive number, got {data['fps']!r}"
    for key in ("mean", "std"):
        values = data[key]
        if not isinstance(values, list) or not all(_is_number(v) for v in values):
            return f"{key!r} must be a list of numbers"
        if len(values) != data["feature_dim"]:
            return f"{key!r} has {len(values)} values, 'feature_dim' is {data['feature_dim']}"
        if not np.isfinite(values).all() or (key == "std" and min(values) <= 0):
            return f"{key!r} must be {'positive and ' if key == 'std' else ''}finite"
    if "sums" in data:
        sums = data["sums"]
        if not (isinstance(sums, dict) and _is_int(sums.get("count")) and sums["count"] >= 0
                and all(isinstance(sums.get(k), list) and len(sums[k]) == data["feature_dim"]
                        and all(_is_number(v) for v in sums[k]) for k in ("total", "total_sq"))):
            return "'sums' must be {count, total, total_sq} with 'feature_dim' values each"
    for key in ("num_clips", "num_frames", "num_shards"):
        if key in data and (not _is_int(data[key]) or data[key] < 0):
            return f"{key!r} must be a non-negative integer, got {data[key]!r}"
    shards = data["shards"]
    if not isinstance(shards, list) or not shards:
        return "'shards' must be a non-empty list of shard entries"
    names = set()
    for i, entry in enumerate(shards):
        if not isinstance(entry, dict):
            return f"shards[{i}] must be an object, got {entry!r}"
        name = entry.get("name")
        if not isinstance(name, str) or not SHARD_NAME.fullmatch(name):
            return (f"shards[{i}] needs a 'name' of the form shard-NNNNNN.tar (a file in the manifest's directory, as "
                    f"`omg shards build` names them), got {name!r}")
        if name in names:
            return f"shard {name} is listed twice"
        names.add(name)
        for key in ("clips", "frames", "bytes"):
            if key in entry and (not _is_int(entry[key]) or entry[key] < 0):
                return f"shard {name}: {key!r} must be a non-negative integer, got {entry[key]!r}"
        sha = entry.get("sha256")
        if sha is not None and not (isinstance(sha, str) and re.fullmatch(r"[0-9a-f]{64}", sha)):
            return f"shard {name}: 'sha256' must be 64 lowercase hex digits, got {sha!r}"
    if "num_shards" in data and data["num_shards"] != len(shards):
        return f"'num_shards' is {data['num_shards']} but {len(shards)} shards are listed"
    if ("num_clips" in data and all("clips" in s for s in shards)
            and data["num_clips"] != sum(s["clips"] for s in shards)):
        return f"'num_clips' is {data['num_clips']} but the shards hold {sum(s['clips'] for s in shards)} clips"
    return None


@dataclass
class Manifest:
    """The parsed ``manifest.json`` of a shard set.

    ``load`` checks the schema: a manifest that is not JSON, lacks a key, has a value of the
    wrong type or another schema version is a ``UsageError`` naming the file and the problem.
    Per shard it records ``name`` and, in manifests written by ``ShardWriter``, ``clips``
    (samples), ``frames``, ``bytes`` (file size) and ``sha256`` (of the file); the last three
    are optional for readers: a check whose value is not recorded is not made.

    ``url``: where a set on object storage or behind a ``pipe:`` command was fetched from (the
    manifest's own URL); its shards are the same URL with the shard's name in place of
    ``manifest.json`` (``shard_urls``). None for a set on a local disk.
    """

    path: Path
    data: dict
    url: str | None = None
    _by_name: dict | None = field(default=None, init=False, repr=False, compare=False)  # shard entries by name

    @classmethod
    def load(cls, location: str | Path) -> Manifest:
        """A set's manifest from a local directory (or its manifest.json) or a URL: a directory URL
        (``s3://bucket/sets/amass``), a manifest URL (``gs://…/amass/manifest.json``) or a command
        that prints the manifest (``pipe:cat /data/amass/manifest.json``)."""
        local = _local_path(str(location))
        if local is None:
            return cls._fetch(manifest_url(str(location)))
        path = local if local.name == MANIFEST and not local.is_dir() else local / MANIFEST
        if not path.exists():
            hint = (" (an unfinished build: run the same build command again)"
                    if (path.parent / BUILD_STATE).exists() else "")
            raise UsageError(f"no {MANIFEST} in {path.parent}{hint}; "
                             "build shards with `omg shards build` or `omg shards synth`")
        try:
            data = path.read_bytes()
        except OSError as e:
            raise UsageError(f"{path}: cannot be read ({e.strerror or e})") from None
        return cls(path, cls._parse(data, str(path)))

    @classmethod
    def _fetch(cls, url: str) -> Manifest:
        try:
            data = read_url(url)
        except (OSError, ValueError) as e:
            raise UsageError(f"{url}: the manifest cannot be fetched ({e})") from None
        return cls(Path(MANIFEST), cls._parse(data, url), url)

    @staticmethod
    def _parse(raw: bytes, where: str) -> dict:
        try:
            data = json.loads(raw)
        except UnicodeDecodeError:
            raise UsageError(f"{where}: not a text file (invalid UTF-8); rebuild the shards") from None
        except json.JSONDecodeError as e:
            raise UsageError(f"{where}: not valid JSON ({e.msg} at line {e.lineno} column {e.colno}); "
                             "rebuild the shards") from None
        if problem := _manifest_problem(data):
            hint = "" if "schema version" in problem else "; rebuild the shards"
            raise UsageError(f"{where}: invalid manifest: {problem}{hint}")
        return data

    @property
    def dir(self) -> Path:
        return self.path.parent

    @property
    def location(self) -> str:
        """The set as messages name it: its directory, or the URL its manifest came from."""
        return self.url or str(self.dir)

    @property
    def shard_urls(self) -> list[str]:
        """Every shard's path, or URL for a fetched set (what ``iter_tar`` opens)."""
        if self.url is None:
            return [str(p) for p in self.shard_paths]
        quote = shlex.quote if self.url.startswith("pipe:") else str  # a shell reads a pipe: command
        return [sibling_url(self.url, MANIFEST, quote(s["name"])) for s in self.data["shards"]]

    @property
    def shard_paths(self) -> list[Path]:
        return [self.dir / s["name"] for s in self.data["shards"]]

    def entry(self, url: str | Path) -> dict | None:
        """The manifest's entry for a shard path or URL (matched by file name; in a ``pipe:``
        command, by the last word that names a file), or None."""
        if self._by_name is None:  # one dict, not a scan per shard: a set may have 10^4 shards
            self._by_name = {s["name"]: s for s in self.data["shards"]}
        return self._by_name.get(url_file_name(str(url)))

    def expected(self, url: str | Path) -> dict:
        """What the manifest records about one shard, as keyword arguments of ``iter_tar``:
        ``{"sha256": hex, "samples": clips, "size": bytes}`` (only those recorded; ``{}`` for a
        shard the manifest does not list)."""
        entry = self.entry(url) or {}
        found = {"sha256": entry.get("sha256"), "samples": entry.get("clips"), "size": entry.get("bytes")}
        return {k: v for k, v in found.items() if v is not None}

    @property
    def mean(self) -> np.ndarray:
        return np.asarray(self.data["mean"], dtype=np.float32)

    @property
    def std(self) -> np.ndarray:
        return np.asarray(self.data["std"], dtype=np.float32)

    @property
    def sums(self) -> FeatureStats | None:
        """The raw per-feature sums of the set's frames (None in manifests written before omg
        recorded them): what pooled statistics of several sets are computed from."""
        return FeatureStats.from_json(self.data["sums"]) if "sums" in self.data else None

    def __getitem__(self, key: str):
        return self.data[key]

    def spec(self) -> DataSpec:
        """What a model needs to know about its data, stored in its checkpoint."""
        return DataSpec.coerce(self.data, self.url or f"{self.dir / MANIFEST}")

    def summary(self) -> str:
        d = self.data
        shards = d["shards"]
        clips = d.get("num_clips", sum(s.get("clips", 0) for s in shards))
        frames = d.get("num_frames", sum(s.get("frames", 0) for s in shards))
        hours = frames / d["fps"] / 3600
        return (
            f"{self.location}: {clips} clips, {frames} frames ({hours:.2f} h at {d['fps']} fps) "
            f"in {len(shards)} shards; representation {d['representation']} ({d['feature_dim']}-d) "
            f"on {d['skeleton']}; built by: {d.get('command') or 'unknown'}"
        )


def decode_sample(raw: dict[str, bytes], feature_dim: int | None = None) -> dict:
    """Raw tar members of one sample -> {"motion", "meta", "texts", "key"}; raises ValueError."""
    missing = [ext for ext in ("motion.npy", "meta.json", "texts.json") if ext not in raw]
    if missing:
        raise ValueError(f"missing {', '.join(missing)}")
    motion = np.load(io.BytesIO(raw["motion.npy"]), allow_pickle=False)
    if motion.dtype != np.float32 or motion.ndim != 2 or len(motion) == 0:
        raise ValueError(f"motion.npy is {motion.dtype} {motion.shape}, expected float32 (T>0, D)")
    if feature_dim is not None and motion.shape[1] != feature_dim:
        raise ValueError(f"motion.npy has {motion.shape[1]} features, the manifest says {feature_dim}")
    if not np.isfinite(motion).all():
        raise ValueError("motion.npy contains NaN or inf")
    meta = json.loads(raw["meta.json"])
    if missing := [k for k in META_KEYS if k not in meta]:
        raise ValueError(f"meta.json lacks {', '.join(missing)}")
    texts = json.loads(raw["texts.json"])
    if not isinstance(texts, list) or not all(isinstance(t, str) for t in texts):
        raise ValueError("texts.json is not a list of strings")
    return {"key": raw.get("__key__", meta["id"]), "motion": motion, "meta": meta, "texts": texts}




# ---------------------------------------------------------------------------------------------
# Reading shards, checked against the manifest

SHARD_CHECKS = ("file", "size", "readable", "samples", "end-of-archive", "sha256")
_END_OF_ARCHIVE = b"\0" * 1024  # two zero blocks end every tar
_COMPRESSED_MAGIC = (b"\x1f\x8b", b"BZh", b"\xfd7zXZ", b"\x28\xb5\x2f\xfd")


class ShardError(ValueError):
    """A shard that is missing, unreadable, or does not match what its manifest records.

    ``shard``: the path or URL; ``check``: which check failed, one of ``SHARD_CHECKS``
    (``file`` missing, ``size`` bytes differ, ``readable`` the tar is broken, ``samples`` the
    sample count differs, ``end-of-archive`` the tar lacks its closing zero blocks, ``sha256``
    the bytes are garbled or replaced); ``reason``: what was found, e.g. "truncated: 3 of 5
    samples". ``str(e)`` is ``"<shard>: <reason>"``.
    """

    def __init__(self, shard: str, check: str = "readable", reason: str = ""):
        super().__init__(f"{shard}: {reason}" if reason else str(shard))
        self.shard, self.check, self.reason = str(shard), check, reason or str(shard)

    def __reduce__(self):  # keep the fields through pickling (DataLoader workers)
        return type(self), (self.shard, self.check, self.reason)


class _CheckedReader:
    """A read-only stream wrapper that hashes and counts the bytes as they pass and keeps the
    first and the last bytes, so a shard is verified in the same single pass that parses it."""

    def __init__(self, raw, sha256: bool):
        self.raw = raw
        self.hash = hashlib.sha256() if sha256 else None
        self.count = 0
        self.head = self.tail = b""
        self.trailing_garbage = False  # non-zero bytes drained after tarfile stopped reading

    def read(self, size: int = -1) -> bytes:
        data = self.raw.read(size)
        if data:
            if self.hash is not None:
                self.hash.update(data)
            self.count += len(data)
            if len(self.head) < 8:
                self.head = (self.head + data)[:8]
            self.tail = data[-1024:] if len(data) >= 1024 else (self.tail + data)[-1024:]
        return data

    def drain(self) -> None:
        """Read the rest: what follows the point where tarfile stopped (its read-ahead aside)
        must be end-of-archive zeros, else a damaged header ended the archive early."""
        while data := self.read(1 << 20):
            if data.count(0) != len(data):
                self.trailing_garbage = True

    @property
    def compressed(self) -> bool:
        return self.head.startswith(_COMPRESSED_MAGIC)


def _local_path(url: str) -> Path | None:
    """The local file a shard or set location names, or None for a URL or a ``pipe:`` command."""
    if url.startswith("file://"):
        return Path(url[len("file://"):])
    if "://" in url or url.startswith("pipe:") or url == "-":
        return None
    return Path(url)


def url_file_name(url: str) -> str:
    """The file a path, URL or ``pipe:`` command reads: the last path component of its last word
    that has one (``pipe:aws s3 cp s3://b/set/shard-000001.tar -`` -> ``shard-000001.tar``)."""
    words = [w for w in url.rstrip("/").split() if "." in w.rsplit("/", 1)[-1]] or [url.rstrip("/")]
    return words[-1].rsplit("/", 1)[-1]


def sibling_url(url: str, name: str, new_name: str) -> str:
    """``url`` with its last ``name`` replaced by ``new_name``: a set's manifest URL gives its shards'
    URLs (``pipe:cat /d/manifest.json`` -> ``pipe:cat /d/shard-000000.tar``) and a shard's the manifest's."""
    head, found, tail = url.rpartition(name)
    if not found:
        raise UsageError(f"{url}: cannot tell where {name} is in it; name the set by its directory URL "
                         f"or by its {MANIFEST} URL")
    return head + new_name + tail


def manifest_url(location: str) -> str:
    """The manifest URL of a set given by URL: a URL or command naming ``manifest.json`` is it; a
    directory URL (``s3://bucket/sets/amass``) gets ``/manifest.json`` appended."""
    if MANIFEST in location:
        return location
    if location.startswith("pipe:"):
        raise UsageError(f"{location}: a pipe: set must print its {MANIFEST}, e.g. pipe:cat /data/set/{MANIFEST} "
                         "(its shards are read by the same command with the shard's name in its place)")
    return location.rstrip("/") + "/" + MANIFEST


def _fsspec_opener(url: str):
    """(fsspec's opener for ``url`` or None, what to install when that is None)."""
    protocol = url.split("://", 1)[0]
    try:
        import fsspec
        from fsspec.registry import known_implementations
    except ImportError:
        return None, f"pip install fsspec and its {protocol} backend"
    if protocol not in known_implementations:
        return None, f"fsspec knows no {protocol}:// protocol"
    try:
        fsspec.get_filesystem_class(protocol)
    except ImportError:  # e.g. s3:// without s3fs
        return None, known_implementations[protocol].get("err") or f"install fsspec's {protocol} backend"
    return (lambda: fsspec.open(url, "rb").open()), ""


def open_url(url: str):
    """A binary stream of a local file, a ``pipe:`` command's output, or an object-store URL:
    ``s3://``, ``gs://``, ``hf://``… through fsspec when it and the protocol's backend are installed,
    else whatever ``webdataset.gopen`` knows (``http(s)://`` by curl, ``gs://`` by gsutil)."""
    local = _local_path(url)
    if local is not None:
        return open(local, "rb")
    if url.startswith("pipe:"):
        from webdataset import utils
        from webdataset.gopen import Pipe

        if utils.enforce_security:
            raise ValueError("pipe: URLs are disabled (WDS_SECURE is set)")
        # as webdataset.gopen, but the command in a process group of its own, which a read given up
        # (a stall, a failed check, a reader that stops early) kills whole: see _abandon
        return Pipe(url[len("pipe:"):], mode="rb", shell=True, bufsize=8192, ignore_status=[141],
                    start_new_session=True)
    opener, missing = _fsspec_opener(url)
    if opener is not None:
        return opener()
    from webdataset.gopen import gopen, gopen_schemes

    scheme = url.split("://", 1)[0]
    if scheme not in gopen_schemes:
        raise OSError(f"no reader for {scheme}:// URLs ({missing})")
    return gopen(url)


def read_url(url: str, timeout: float = PIPE_TIMEOUT_S) -> bytes:
    """All the bytes ``open_url`` gives; a ``pipe:`` command that fails, or runs longer than
    ``timeout`` seconds, raises ``OSError`` (with the last line it printed to stderr)."""
    if url.startswith("pipe:"):
        import subprocess

        # its own process group: on a timeout the shell and everything it started are stopped
        with subprocess.Popen(url[len("pipe:"):], shell=True, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                              start_new_session=True) as process:
            try:
                out, err = process.communicate(timeout=timeout)
            except subprocess.TimeoutExpired:
                _kill_group(process)
                raise OSError(f"the command did not end within {timeout:g} s and was stopped") from None
        if process.returncode != 0:
            said = err.decode(errors="replace").strip().splitlines()
            raise OSError(f"the command exited with {process.returncode}" + (f": {said[-1]}" if said else ""))
        return out
    with open_url(url) as stream:
        return stream.read()


def _first_arg(e: Exception) -> str:
    """An exception's own message, without the " @ <stream>" webdataset appends."""
    return str(e.args[0]).split(" @ <")[0] if e.args else type(e).__name__


def _size_error(url: str, found: int, size: int) -> ShardError:
    if found < size:
        return ShardError(url, "size", f"truncated: {found} of {size} bytes")
    return ShardError(url, "size", f"{found} bytes, the manifest says {size}")


def _byte_errors(url: str, reader: _CheckedReader, sha256: str | None, size: int | None,
                 early_end: bool = False) -> list[ShardError]:
    """Checks on the bytes of a fully read shard, most telling first; ``early_end``: non-zero
    bytes followed the point where tarfile saw the end of the archive."""
    errors = []
    if size is not None and reader.count != size:
        errors.append(_size_error(url, reader.count, size))
    if not reader.compressed and (reader.count < len(_END_OF_ARCHIVE) or reader.tail != _END_OF_ARCHIVE):
        errors.append(ShardError(url, "end-of-archive",
                                 f"no end-of-archive blocks: the tar is cut after {reader.count} bytes"))
    elif early_end:
        errors.append(ShardError(url, "end-of-archive",
                                 "data after an early end of the archive (a damaged member header?)"))
    if sha256 is not None and reader.hash is not None and (digest := reader.hash.hexdigest()) != sha256:
        errors.append(ShardError(url, "sha256", f"sha256 {digest[:12]}… of its {reader.count} bytes does not match "
                                                f"the manifest's {sha256[:12]}… (garbled or replaced)"))
    return errors


def _count_error(url: str, count: int, samples: int | None) -> ShardError | None:
    if samples is None or count == samples:
        return None
    if count < samples:
        return ShardError(url, "samples", f"truncated: {count} of {samples} samples")
    return ShardError(url, "samples", f"{count} samples, the manifest says {samples}")


def _kill_group(process) -> None:
    """Kill a command started in a process group of its own, with everything it started, and reap it."""
    try:
        os.killpg(process.pid, signal.SIGKILL)
    except ProcessLookupError:  # it ended meanwhile
        pass
    process.wait()


def _abandon(stream) -> None:
    """Close a stream that will not be read to its end. A ``pipe:`` command is killed with its process
    group, not waited for: webdataset's close waits up to two hours for a command that is stalled, and
    killing only the shell would leave its commands running."""
    process = getattr(stream, "proc", None)
    if process is not None and process.poll() is None:
        _kill_group(process)
    try:
        stream.close()
    except OSError:  # the killed command's exit status: not news
        pass


def _tar_samples(stream, url: str) -> Iterator[dict[str, bytes]]:
    import webdataset as wds

    files = wds.tariterators.tar_file_expander([{"url": url, "stream": stream}])
    for sample in wds.tariterators.group_by_keys(files):
        sample.pop("__url__", None)
        yield sample


def _read_shard(url: str, sha256: str | None = None, samples: int | None = None, size: int | None = None,
                whole: bool = False, precheck: bool = True) -> Iterator[dict[str, bytes]]:
    local = _local_path(url)
    if local is not None:
        if problem := file_problem(local):  # a FIFO would block the read
            raise ShardError(url, "file", problem)
        if precheck and size is not None and (found := local.stat().st_size) != size:
            raise _size_error(url, found, size)
    try:
        raw = open_url(url)
    except OSError as e:
        raise ShardError(url, "file", f"cannot be opened ({e.strerror or e})") from None
    source = _CheckedReader(raw, sha256 is not None)  # hashes, counts and keeps the tail of the file's bytes
    try:
        if whole:  # parsed from memory: every check runs before the first sample is yielded
            data = b"".join(iter(lambda: source.read(1 << 22), b""))
            reader = _CheckedReader(io.BytesIO(data), False)
            del data
        else:
            reader = source
        count, buffered, parsed = 0, [], _tar_samples(reader, url)
        while True:
            try:
                sample = next(parsed)
            except StopIteration:
                break
            except Exception as e:  # noqa: BLE001 - any failure to parse the tar names the shard
                reason = (f"unreadable after {count} sample{'' if count == 1 else 's'} "
                          f"({type(e).__name__}: {_first_arg(e)})")
                source.drain()
                if notes := [err.reason for err in _byte_errors(url, source, sha256, size)
                             if err.check != "end-of-archive"]:
                    reason += "; " + "; ".join(notes)
                raise ShardError(url, "readable", reason) from None
            count += 1
            if whole:
                buffered.append(sample)
            else:
                yield sample
        reader.drain()
        errors = _byte_errors(url, source, sha256, size, early_end=reader.trailing_garbage)
        if error := _count_error(url, count, samples):
            errors.insert(0, error)
        if errors:
            raise errors[0]
        yield from buffered
    except BaseException:  # a failed check, a stall (omg.data.deadline), or a reader that stopped early
        _abandon(raw)
        raise
    else:
        raw.close()


def iter_tar(path: str | Path, sha256: str | None = None, *, samples: int | None = None, size: int | None = None,
             whole: bool = False) -> Iterator[dict[str, bytes]]:
    """Raw samples (``{"__key__", ext: bytes}``) of one tar, grouped by key like WebDataset.

    ``path`` is a file or any URL ``open_url`` opens (``pipe:`` commands, object-store URLs
    through fsspec, what ``webdataset.gopen`` opens). The expected values come from
    the manifest (``Manifest.expected(url)`` gives them as keyword arguments):

    - ``sha256``: the bytes are hashed as they are read;
    - ``samples``: the number of samples the shard must yield ("truncated: N of M samples");
    - ``size``: the file size in bytes; a local file is measured before anything is read.

    A tar without its end-of-archive zero blocks (cut at a member boundary) fails whether
    or not anything is expected. Any failure raises ``ShardError`` naming the shard and the
    check. Streaming (``whole=False``) yields samples as they are read, so the count, hash and
    end checks raise only after the shard's last sample: the samples before cannot be taken
    back. ``whole=True`` reads the shard into memory and runs every check before yielding
    the first sample: nothing from a bad shard is ever yielded.
    """
    return _read_shard(str(path), sha256, samples, size, whole, precheck=True)


def verify_shard(path: str | Path, sha256: str | None = None, *, size: int | None = None) -> str:
    """Hash a whole shard file (in chunks, without parsing it); raises ``ShardError`` when it is
    missing or its size or sha256 differ from the expected ones; returns its sha256."""
    url = str(path)
    local = _local_path(url)
    if local is None or (problem := file_problem(local)):
        raise ShardError(url, "file", problem if local is not None else "no such file")
    if size is not None and (found := local.stat().st_size) != size:
        raise _size_error(url, found, size)
    digest = hashlib.sha256()
    with open(local, "rb") as f:
        while chunk := f.read(1 << 22):
            digest.update(chunk)
    if sha256 is not None and digest.hexdigest() != sha256:
        raise ShardError(url, "sha256", f"sha256 {digest.hexdigest()[:12]}… does not match the manifest's "
                                        f"{sha256[:12]}… (garbled or replaced)")
    return digest.hexdigest()


@dataclass
class ShardCheck:
    """The result of checking one shard: samples read and decoded, sample-level problems,
    the shard-level ``error`` if any, and which manifest checks could be made."""

    name: str
    samples: int = 0
    good: int = 0
    problems: list[str] = field(default_factory=list)
    error: ShardError | None = None
    checks: tuple[str, ...] = ()

    @property
    def ok(self) -> bool:
        return self.error is None and not self.problems

    @property
    def verified(self) -> bool:
        """Its bytes matched the manifest's sha256 (and every other recorded check passed)."""
        return self.error is None and "sha256" in self.checks


@dataclass
class ShardSetCheck:
    """The result of ``check_shards``: one ``ShardCheck`` per shard of the manifest."""

    manifest: Manifest
    shards: list[ShardCheck]

    @property
    def good(self) -> int:
        """Samples that decoded, in shards that passed every shard-level check."""
        return sum(s.good for s in self.shards if s.error is None)

    @property
    def failed(self) -> list[ShardCheck]:
        return [s for s in self.shards if s.error is not None]

    @property
    def verified(self) -> int:
        return sum(s.verified for s in self.shards)

    @property
    def problems(self) -> list[str]:
        """Shard-level failures as '<shard>: <check> check failed: <reason>' and bad samples as
        '<shard> <key>: <reason>'."""
        out = []
        for s in self.shards:
            if s.error is not None:
                out.append(f"{s.name}: {s.error.check} check failed: {s.error.reason}")
            out += s.problems
        return out


def check_shards(shard_dir: str | Path, timeout: float = 0.0, timeout_name: str = "timeout") -> ShardSetCheck:
    """Read every shard of a set once: decode every sample and check each shard's file, size,
    sample count, end-of-archive blocks and sha256 against the manifest. Raises
    ``UsageError`` only for a missing or invalid manifest, or a shard whose read takes over ``timeout``
    seconds (0: no limit; ``timeout_name`` is the option that sets it); every other fault is reported."""
    manifest = Manifest.load(shard_dir)
    results = []
    for entry, url in zip(manifest["shards"], manifest.shard_urls):
        expected = manifest.expected(entry["name"])
        result = ShardCheck(entry["name"], checks=("file", "readable", "end-of-archive", *expected))
        stalled = (f"{url} was not read in {timeout_name}={timeout:g} s: a stalled read; check the storage, "
                   f"or raise {timeout_name} (0 waits forever)")
        with deadline(timeout, stalled):
            try:
                # streamed without the size pre-check: a bad shard's samples are still decoded and named
                for raw in _read_shard(url, whole=False, precheck=False, **expected):
                    result.samples += 1
                    try:
                        decode_sample(raw, manifest["feature_dim"])
                        result.good += 1
                    except (ValueError, KeyError) as e:
                        result.problems.append(f"{entry['name']} {raw.get('__key__')}: {e}")
            except ShardError as e:
                result.error = e
        results.append(result)
    return ShardSetCheck(manifest, results)


def validate(shard_dir: str | Path) -> tuple[Manifest, int, list[str]]:
    """Decode every sample and check every shard against the manifest (see ``check_shards``);
    returns (manifest, good sample count, problems as 'shard key: reason' or 'shard: ...')."""
    result = check_shards(shard_dir)
    return result.manifest, result.good, result.problems
