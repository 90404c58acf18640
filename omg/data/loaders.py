"""The datasets and loaders ``MotionDataModule`` builds, without Lightning: the resampled shard stream
(``MotionStream``) and its position-keeping loader (``StreamLoader``), the in-memory clips (``ClipDataset``),
and the shard helpers they share. A process that only reads data (a loader worker started by spawn or
forkserver, which unpickles the stream; the data benchmark's workers; ``omg shards``) imports this module,
not Lightning's.

The stream is a pure function of (seed, rank, worker, epoch): each worker draws shards at random from its
rank's list, reads them through a shuffle buffer and cuts one sliding random window per clip; an epoch is a
fixed number of batches per rank, split exactly among the workers, so every rank yields the same number of
batches. The loader is stateful: Lightning saves its (epoch, batches) position in checkpoints, and a resumed
run replays the epoch up to that point and goes on with the same batches it would have seen.

Resumed on another number of ranks (W ranks saved at epoch e after b batches, resumed on W'),
the position is kept and the shards are split anew: rank r of the new run reads urls[r::W'] and
replays its (seed, r, worker, e) stream past its first b batches, so from there on each rank sees
exactly the batches that rank of a run started on W' ranks sees at (e, b): the rest of epoch e,
then every later epoch. The trainer's epoch stays batches_per_epoch batches per rank, so the
interrupted epoch ends after the same number of steps as it would have. Shards are drawn with
replacement, so no run, resumed or not, promises a clip once per epoch; what a world-size change
loses is only the continuation of the old ranks' own streams (the draws they would have made
after batch b), and the new ranks' first b batches of epoch e are skipped, not trained on.

A weighted mixture of shard sets (``omg.data.mixture``) is drawn from in the same stream: each sample comes
from set k with probability share_k out of that set's own shuffle buffer; the set draws are part of the same
seeded stream, so the mixture's position is the loader's (epoch, batches) position, saved with the sets,
their shares and the samples drawn from each in the epoch.
"""

from __future__ import annotations

import logging
import math
import multiprocessing
import os
import signal
import time
from dataclasses import dataclass
from typing import Callable, Iterator

import numpy as np
from torch.utils.data import DataLoader, Dataset, IterableDataset, get_worker_info

from omg.data.deadline import deadline
from omg.data.mixture import Mixture, load_mixture
from omg.data.shards import Manifest, ShardError, decode_sample, iter_tar
from omg.data.shards.remote import end_with_parent
from omg.data.windows import Collate, WindowSampler, make_item, mirror_item, pick_text
from omg.errors import UsageError
from omg.motion import Representation

log = logging.getLogger(__name__)

DEFAULT_TIMEOUT_S = 600.0  # data.timeout: how long one training batch, or a validation shard's read, may take
DEFAULT_CACHE_MB = 512.0  # data.cache_mb: a rank's decoded motion up to this is decoded once per data worker


class TooManyBadSamples(RuntimeError):
    pass


def resolve_shards(spec, what: str = "data.train") -> tuple[list[str], Manifest, dict[str, dict]]:
    """Shard sets (directories, URL patterns, set URLs, or ``{path, weight}`` entries, whose weights
    are ignored here) -> (sorted shard urls, the first set's manifest, and by url what its manifest
    records about each shard: the ``iter_tar`` keyword arguments that verify it as it is read).

    A directory lists its shards in its manifest; a pattern such as
    ``/data/h3d/shard-{000000..000127}.tar`` is brace-expanded and its manifest is read from
    the directory of the first shard; see ``omg.data.mixture`` for URLs.
    """
    if not spec:
        raise UsageError(f"no shards given: set {what} to a shard directory or URL pattern")
    mixture = load_mixture(spec, what)
    return mixture.urls, mixture.manifest, mixture.checks


def read_shard(url: str, expected: dict | None) -> Iterator[dict[str, bytes]]:
    """Raw samples of one shard; given what its manifest records (``expected``), the shard is
    checked whole before any of its samples is yielded."""
    return iter_tar(url, **expected, whole=True) if expected else iter_tar(url)


def shard_problem(error: Exception) -> str:
    """Why a shard was skipped, in a few words (without its path, which the caller names)."""
    if isinstance(error, ShardError):
        return f"{error.check} check failed ({error.reason})"
    return f"unreadable ({type(error).__name__}: {error})"


def rank_shards(urls: list[str], rank: int, world_size: int, name: str = "") -> list[str]:
    """Rank r's disjoint share of the shards (every world_size-th, starting at r)."""
    if len(urls) < world_size:
        raise UsageError(
            f"{len(urls)} shards{f' of {name}' if name else ''} cannot be split disjointly across {world_size} ranks; "
            "rebuild with a smaller shard size (--max_clips) so there are at least as many shards as ranks"
        )
    return urls[rank::world_size]


def worker_share(total: int, worker: int, num_workers: int) -> int:
    """How many of ``total`` round-robin items fall to ``worker``."""
    return total // num_workers + (worker < total % num_workers)


@dataclass(frozen=True)
class StreamSet:
    """One shard set of a mixed stream: this rank's shards of it, its share of the samples, and
    its mean clip length (for ``WindowSampler.visits``)."""

    urls: list[str]
    share: float = 1.0
    mean_frames: float | None = None
    name: str = ""


class MotionStream(IterableDataset):
    """Endless resampled shards -> shuffle buffer -> training samples cut by ``windows``.

    One epoch yields exactly ``batches`` batches of ``batch_size`` samples (the DataLoader
    batches inside each worker, so each worker yields whole batches). With sliding windows and
    ``mean_frames`` (the set's mean clip length), a clip read from a shard stays in the buffer
    for as many windows as ``WindowSampler.visits`` gives it, so long takes contribute in
    proportion to their frames and their windows are spread over many batches.

    ``sets`` (a mixture; ``urls`` and ``mean_frames`` then unused): each sample comes from set k
    with probability ``share`` k, drawn from the same seeded generator, out of the set's own
    shuffle buffer of ``ceil(share * shuffle_buffer)`` samples: a sample then waits in its buffer
    about as many draws as in a single set's, and the buffers together hold ``shuffle_buffer``.
    Mixed samples carry ``shard_set``, the index of their set.

    ``mirror`` (a representation) with ``mirror_prob`` > 0: each item is replaced by its mirror
    image (``windows.mirror_item``) with that probability, drawn from the same seeded generator
    (no draw at all when it is 0, so the stream without mirroring is unchanged).

    ``keep_decoded``: each worker keeps the decoded samples of every shard it has read whole and
    sound, and a later draw of that shard yields them again instead of reading, checking and
    decoding its bytes once more (a small set is drawn many times an epoch; ``stream_loader``
    turns it on when the rank's decoded motion fits ``data.cache_mb``). The stream is the same
    sample for sample: a kept shard was checked against its manifest when it was read.
    """

    def __init__(
        self,
        urls: list[str],
        rank: int,
        batches: int,
        batch_size: int,
        windows: WindowSampler,
        feature_dim: int,
        seed: int = 0,
        shuffle_buffer: int = 1000,
        max_bad_fraction: float = 0.01,
        mean_frames: float | None = None,
        checks: dict[str, dict] | None = None,
        sets: list[StreamSet] | None = None,
        mirror: Representation | None = None,
        mirror_prob: float = 0.0,
        keep_decoded: bool = False,
    ):
        self.mirror, self.mirror_prob = mirror, mirror_prob if mirror is not None else 0.0
        self.keep_decoded, self._decoded = keep_decoded, {}  # url -> its decoded samples, in order
        self.sets = sets or [StreamSet(urls, 1.0, mean_frames)]
        if sets:
            urls = [url for s in sets for url in s.urls]
        self.urls, self.rank, self.checks = urls, rank, checks or {}
        self.batches, self.batch_size = batches, batch_size
        self.windows, self.feature_dim = windows, feature_dim
        self.seed, self.shuffle_buffer = seed, shuffle_buffer
        self.max_bad_fraction, self.mean_frames = max_bad_fraction, mean_frames
        self.epoch, self.skip_batches = 0, 0  # set by StreamLoader before workers start

    def __len__(self) -> int:
        return self.batches * self.batch_size

    def _samples(self, rng: np.random.Generator, urls: list[str] | None = None) -> Iterator[dict]:
        """Decoded samples from shards drawn at random from ``urls`` (all the stream's by default),
        forever; bad ones are counted and skipped."""
        urls = self.urls if urls is None else urls
        seen = bad = 0
        while True:
            url = urls[int(rng.integers(len(urls)))]
            if (kept := self._decoded.get(url)) is not None:
                for sample in kept:
                    seen += 1
                    yield sample
                continue
            expected = self.checks.get(url)
            decoded: list[dict] | None = [] if self.keep_decoded else None  # None once a sample is bad
            try:
                for raw in read_shard(url, expected):
                    seen += 1
                    try:
                        sample = decode_sample(raw, self.feature_dim)
                    except (ValueError, KeyError) as e:
                        bad, decoded = bad + 1, None
                        self._bad(f"{url} key {raw.get('__key__')}", e, bad, seen)
                        continue
                    if decoded is not None:
                        decoded.append(sample)
                    yield sample
            except TooManyBadSamples:
                raise
            except Exception as e:  # noqa: BLE001 - a bad shard counts as its samples, or one when unknown
                lost = (expected or {}).get("samples", 1)
                seen, bad = seen + lost, bad + lost
                self._bad(url, shard_problem(e), bad, seen)
            else:
                if decoded is not None:  # read to its end, every sample sound
                    self._decoded[url] = decoded

    def __getstate__(self) -> dict:
        return {**self.__dict__, "_decoded": {}}  # a worker keeps what it decodes itself

    def _bad(self, where: str, reason, bad: int, seen: int) -> None:
        log.warning("skipping bad sample %s: %s (%d bad of %d read by this worker)", where, reason, bad, seen)
        if seen >= 20 and bad > self.max_bad_fraction * seen:
            raise TooManyBadSamples(
                f"{bad} of {seen} samples were bad (last: {where}: {reason}), over data.max_bad_fraction="
                f"{self.max_bad_fraction}; check the shards with `omg shards inspect`"
            )

    def __iter__(self) -> Iterator[dict]:
        info = get_worker_info()
        worker, num_workers = (info.id, info.num_workers) if info else (0, 1)
        rng = np.random.default_rng([self.seed, self.rank, worker, self.epoch])
        to_yield = worker_share(self.batches, worker, num_workers) * self.batch_size
        to_skip = worker_share(self.skip_batches, worker, num_workers) * self.batch_size
        single = len(self.sets) == 1
        sources = [self._set_items(rng, index, single) for index in range(len(self.sets))]
        bounds = np.cumsum([s.share for s in self.sets])
        bounds /= bounds[-1]
        produced = 0
        while produced < to_yield:
            k = 0 if single else min(int(np.searchsorted(bounds, rng.random(), side="right")), len(bounds) - 1)
            item = next(sources[k])
            produced += 1
            if produced > to_skip:
                yield item

    def _set_items(self, rng: np.random.Generator, index: int, single: bool) -> Iterator[dict]:
        """Training items of set ``index``, forever: its samples through its shuffle buffer, each
        kept for as many windows as it visits."""
        stream_set = self.sets[index]
        # a single set reads through self._samples(rng): the stream of omg before mixtures, draw for draw
        samples = self._samples(rng) if single else self._samples(rng, stream_set.urls)
        size = self.shuffle_buffer if single else max(1, math.ceil(stream_set.share * self.shuffle_buffer))
        buffer: list[list] = []  # [sample, samples it still yields]
        # whole clips shorter than min_len are passed over: a set read many times over without one
        # long enough would otherwise loop forever
        set_samples = sum(self.checks.get(url, {}).get("samples", 0) for url in stream_set.urls) or 1000
        too_short = 0
        while True:
            while len(buffer) < size:
                sample = next(samples)
                if not self.windows.keeps(len(sample["motion"])):
                    too_short += 1
                    if too_short > 20 * set_samples:
                        raise UsageError(f"data.min_len={self.windows.min_len}: no clip of the shards of "
                                         f"{stream_set.urls[0]} is that long, and shorter whole clips are not "
                                         "trained on; lower data.min_len")
                    continue
                too_short = 0
                if visits := self.windows.visits(len(sample["motion"]), stream_set.mean_frames, rng):
                    buffer.append([sample, visits])
            i = int(rng.integers(len(buffer)))
            entry = buffer[i]
            entry[1] -= 1
            if entry[1] == 0:
                buffer[i] = buffer[-1]
                buffer.pop()
            sample = entry[0]
            start, length = self.windows(len(sample["motion"]), rng)
            item = make_item(sample, start, length, pick_text(sample["texts"], rng))
            if self.mirror_prob and rng.random() < self.mirror_prob:
                item = mirror_item(item, self.mirror)
            if not single:
                item["shard_set"] = index
            yield item


class StreamLoader(DataLoader):
    """A DataLoader over a ``MotionStream`` that knows its position in the stream.

    The position is (epoch, batches yielded in it), and for a mixture the sets, their shares and
    the samples drawn from each in the epoch (``mixture``). The epoch is the trainer's (``epoch_fn``):
    Lightning ends epochs by batch count and never runs the iterator dry, so a count of
    exhausted iterators would replay epoch 0 forever. Without a trainer each ``iter()`` is the
    next epoch. Lightning saves ``state_dict()`` in checkpoints and calls ``load_state_dict()``
    on resume: the saved epoch's remaining batches are then yielded, and nothing is skipped when
    the trainer resumes into a later epoch (a checkpoint written at an epoch's last batch).
    A mixture that differs from the saved one (sets or shares changed) cannot continue exactly:
    a warning says so and the new mixture's stream goes on from the saved position.
    """

    def __init__(self, dataset: MotionStream, epoch_fn: Callable[[], int] | None = None, fetch_timeout: float = 0.0,
                 **kwargs):
        super().__init__(dataset, batch_size=dataset.batch_size, **kwargs)
        self.epoch_fn = epoch_fn
        self.fetch_timeout = fetch_timeout  # seconds one batch may take (0: no limit), workers or not
        self.epoch, self.batches_done = -1, 0  # nothing yielded yet
        self.mixed = len(dataset.sets) > 1
        self.drawn = [0] * len(dataset.sets)  # samples from each set in this epoch
        self._resume: dict | None = None

    def __len__(self) -> int:
        return self.dataset.batches

    def __iter__(self):
        epoch = self.epoch_fn() if self.epoch_fn is not None else self.epoch + 1
        resume, self._resume = self._resume, None
        resumed = resume is not None and resume["epoch"] == epoch
        skip = resume["batches_done"] if resumed else 0
        self.epoch, self.batches_done = epoch, skip
        self.drawn = list(resume["drawn"]) if resumed and resume.get("drawn") else [0] * len(self.dataset.sets)
        self.dataset.epoch, self.dataset.skip_batches = epoch, skip
        batches = super().__iter__()
        while True:
            try:
                # the whole fetch, not DataLoader(timeout=): that bounds only the wait on the workers' queue,
                # not a read in the main process (num_workers 0) nor the fd fetch from a stopped worker
                with deadline(self.fetch_timeout, stalled_message(self.fetch_timeout, "no training batch arrived")):
                    batch = next(batches, None)
            except BaseException:  # a stall, or a stop signal during one (omg.data.deadline): no worker is left
                stop_workers(batches)
                raise
            if batch is None:
                return
            self.batches_done += 1
            if self.mixed:
                for k in batch["shard_set"].tolist():
                    self.drawn[k] += 1
            yield batch

    def mixture_state(self) -> dict:
        sets = self.dataset.sets
        return {"sets": [s.name for s in sets], "shares": [s.share for s in sets], "drawn": list(self.drawn)}

    def state_dict(self) -> dict:
        state = {"epoch": self.epoch, "batches_done": self.batches_done}
        if self.mixed:
            state["mixture"] = self.mixture_state()
        return state

    def load_state_dict(self, state: dict) -> None:
        epoch, done = int(state["epoch"]), int(state["batches_done"])
        drawn = None
        saved, mine = state.get("mixture"), self.mixture_state() if self.mixed else None
        if saved is not None or mine is not None:
            same = (saved is not None and mine is not None and saved["sets"] == mine["sets"]
                    and np.allclose(saved["shares"], mine["shares"], rtol=0, atol=1e-12))
            if same:
                drawn = [int(n) for n in saved["drawn"]]
            else:
                log.warning("data.train is not the mixture the checkpoint was trained on (%s, now %s): the stream "
                            "cannot continue exactly; the new one goes on from epoch %d, batch %d",
                            _mixture_text(saved), _mixture_text(mine), epoch, done)
        if done >= self.dataset.batches:  # that epoch is complete: resume at the next one's start
            epoch, done, drawn = epoch + 1, 0, None
        self._resume = {"epoch": epoch, "batches_done": done, "drawn": drawn}
        if self.epoch_fn is None:
            self.epoch = epoch - 1


def stream_loader(mixture: Mixture, rank: int, world: int, windows: WindowSampler, batches: int, batch_size: int,
                  collate: Collate, num_workers: int = 0, seed: int = 0, shuffle_buffer: int = 1000,
                  max_bad_fraction: float = 0.01, checks: dict[str, dict] | None = None,
                  mirror: Representation | None = None, mirror_prob: float = 0.0, timeout: float = 0.0,
                  epoch_fn: Callable[[], int] | None = None, cache_mb: float = 0.0) -> StreamLoader:
    """Rank ``rank`` of ``world``'s training stream of a shard mixture (each set's shards split across the
    ranks), cut by ``windows``: ``batches`` batches of ``batch_size`` an epoch, read by ``num_workers``
    workers, each batch fetched within ``timeout`` seconds (0: no limit); ``epoch_fn`` gives the epoch
    (each ``iter()`` is the next without it). Each worker keeps its decoded samples (``keep_decoded``) when
    the rank's share of the sets' motion, as its manifests count it, fits ``cache_mb`` MiB. The other
    arguments are ``MotionStream``'s."""
    sets = None
    if len(mixture.sets) > 1:
        sets = [StreamSet(rank_shards(s.urls, rank, world, s.location), share, s.mean_frames, s.location)
                for s, share in zip(mixture.sets, mixture.shares)]
    manifest = mixture.manifest
    frames = [s.frames for s in mixture.sets]  # 0 where a manifest does not count them
    decoded_mib = sum(frames) * manifest["feature_dim"] * 4 / world / 2**20  # float32 features
    stream = MotionStream(
        rank_shards(mixture.urls, rank, world),
        rank=rank,
        batches=batches,
        batch_size=batch_size,
        windows=windows,
        feature_dim=manifest["feature_dim"],
        seed=seed,
        shuffle_buffer=shuffle_buffer,
        max_bad_fraction=max_bad_fraction,
        checks=checks,
        mean_frames=manifest["num_frames"] / max(1, manifest["num_clips"]),
        sets=sets,
        mirror=mirror,
        mirror_prob=mirror_prob,
        keep_decoded=all(frames) and decoded_mib <= cache_mb,
    )
    return StreamLoader(stream, epoch_fn=epoch_fn, num_workers=num_workers, collate_fn=collate,
                        persistent_workers=False, fetch_timeout=timeout, worker_init_fn=exit_on_sigterm)


def stalled_message(timeout: float, what: str) -> str:
    return (f"{what} in data.timeout={timeout:g} s: a stalled shard read or data worker; check the shard storage "
            "(omg shards inspect), or raise data.timeout (0 waits forever)")


def stop_workers(batches, grace: float = 2.0) -> None:
    """End a DataLoader iterator's worker processes now. SIGTERM, which each turns into an exit that kills
    the ``pipe:`` command it reads from (``exit_on_sigterm``); SIGCONT, as a stopped (SIGSTOP) worker acts
    on no other signal; SIGKILL for any still there after ``grace`` seconds. (torch's own shutdown sends
    SIGTERM only: a stopped worker never exits, and Python's exit then waits for it forever.)"""
    from torch.utils.data._utils import signal_handling

    if getattr(batches, "_worker_pids_set", False):  # as torch's shutdown does first: else its SIGCHLD
        signal_handling._remove_worker_pids(id(batches))  # handler takes these exits for a worker's crash
        batches._worker_pids_set = False
    workers = [worker for worker in getattr(batches, "_workers", []) if worker.is_alive()]
    for worker in workers:
        worker.terminate()
        try:
            os.kill(worker.pid, signal.SIGCONT)
        except ProcessLookupError:
            pass
    end = time.monotonic() + grace
    for worker in workers:
        worker.join(max(0.0, end - time.monotonic()))
        if worker.is_alive():
            worker.kill()
            worker.join()


def exit_on_sigterm(worker_id: int) -> None:
    """A data worker's ``worker_init_fn``: SIGTERM raises SystemExit, so the worker unwinds and a shard
    read it abandons kills its ``pipe:`` command (``omg.data.shards``) instead of leaving it running
    (torch's handler ends the process at once). And the worker is killed when the main process ends,
    SIGKILL included: torch's own check of that waits for the worker's next index, which a stalled read
    never asks for (its ``pipe:`` command then goes with it: ``omg.data.shards.remote.dies_with_parent``)."""
    signal.signal(signal.SIGTERM, _exit_on_signal)
    end_with_parent(signal.SIGKILL, multiprocessing.parent_process().pid)


def _exit_on_signal(signum, frame):
    raise SystemExit(128 + signum)


def _mixture_text(state: dict | None) -> str:
    if state is None:
        return "a single set"
    return ", ".join(f"{name} {100 * share:.1f}%" for name, share in zip(state["sets"], state["shares"]))


class ClipDataset(Dataset):
    """All clips in RAM (map-style): center windows for validation, or samples cut by the
    window sampler, as the MDM / HumanML3D loaders do for training."""

    def __init__(self, samples: list[dict], windows: WindowSampler, random_windows: bool = False):
        self.samples, self.windows = samples, windows
        self.random_windows = random_windows

    @classmethod
    def from_shards(cls, urls: list[str], feature_dim: int, windows: WindowSampler,
                    max_bad_fraction: float = 0.01, checks: dict[str, dict] | None = None, timeout: float = 0.0,
                    **kwargs) -> ClipDataset:
        """Decode every sample of ``urls``; bad samples and unreadable shards are skipped with a
        warning and counted, and more than ``max_bad_fraction`` of them stops with one line, as does
        a shard whose read takes over ``timeout`` seconds (data.timeout; 0: no limit)."""
        samples, bad, last, checks = [], 0, "", checks or {}
        for url in urls:
            expected = checks.get(url)
            with deadline(timeout, stalled_message(timeout, f"{url} was not read")):
                try:
                    for raw in read_shard(url, expected):
                        try:
                            samples.append(decode_sample(raw, feature_dim))
                        except (ValueError, KeyError) as e:
                            bad, last = bad + 1, f"{url} key {raw.get('__key__')}: {e}"
                            log.warning("skipping bad sample %s", last)
                except Exception as e:  # noqa: BLE001 - a bad shard is counted, not raised
                    bad += (expected or {}).get("samples", 1)
                    last = f"{url}: {shard_problem(e)}"
                    log.warning("skipping %s", last)
        seen = len(samples) + bad
        if bad and (not samples or bad > max_bad_fraction * seen):
            raise TooManyBadSamples(f"{bad} of {seen} samples of {len(urls)} shards were bad (last: {last}), over "
                                    f"data.max_bad_fraction={max_bad_fraction}; check them with `omg shards inspect`")
        return cls(samples, windows, **kwargs)

    def __len__(self) -> int:
        return len(self.samples)

    def __getitem__(self, index: int) -> dict:
        sample = self.samples[index]
        if self.random_windows:
            rng = np.random.default_rng()
            start, length = self.windows(len(sample["motion"]), rng)
            return make_item(sample, start, length, pick_text(sample["texts"], rng))
        start, length = self.windows.center(len(sample["motion"]))
        return make_item(sample, start, length, sample["texts"][0] if sample["texts"] else "")


def in_memory_loader(urls: list[str], feature_dim: int, windows: WindowSampler, batch_size: int, num_workers: int,
                     collate: Collate) -> DataLoader:
    """The MDM-style baseline: every clip in RAM, random windows, shuffled each epoch."""
    dataset = ClipDataset.from_shards(urls, feature_dim, windows, random_windows=True)
    dataset.samples = [s for s in dataset.samples if windows.keeps(len(s["motion"]))]  # min_len of whole clips
    return DataLoader(dataset, batch_size=batch_size, shuffle=True, num_workers=num_workers, collate_fn=collate,
                      drop_last=True)
