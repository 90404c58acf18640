"""``MotionDataModule``: streaming WebDataset motion shards into training batches.

Training streams shards with resampling (each worker draws shards at random from its rank's
list, reads them through a shuffle buffer and cuts one sliding random window per clip).
The recipe that is safe under DDP:

- each rank's shard list is resolved here, in the main process, from the rank and world
  size Lightning gives us, and travels to the workers inside the dataset; no worker ever
  looks at environment variables, so no rank can read another's shards whatever the
  multiprocessing start method;
- an epoch is a fixed number of batches per rank, split exactly among the workers, so every
  rank yields the same number of batches;
- validation is a small map-style set that Lightning splits with a DistributedSampler.

The stream is a pure function of (seed, rank, worker, epoch), and the loader is stateful:
Lightning saves its (epoch, batches) position in checkpoints, and a resumed run replays the
epoch up to that point and goes on with the same batches it would have seen.

Resumed on another number of ranks (W ranks saved at epoch e after b batches, resumed on W'),
the position is kept and the shards are split anew: rank r of the new run reads urls[r::W'] and
replays its (seed, r, worker, e) stream past its first b batches, so from there on each rank sees
exactly the batches that rank of a run started on W' ranks sees at (e, b): the rest of epoch e,
then every later epoch. The trainer's epoch stays batches_per_epoch batches per rank, so the
interrupted epoch ends after the same number of steps as it would have. Shards are drawn with
replacement, so no run, resumed or not, promises a clip once per epoch; what a world-size change
loses is only the continuation of the old ranks' own streams (the draws they would have made
after batch b), and the new ranks' first b batches of epoch e are skipped, not trained on.

``data.train`` may be a weighted mixture of shard sets (``omg.data.mixture``): each rank splits
every set's shards, and each sample is drawn from set k with probability share_k from that
set's own shuffle buffer; the set draws are part of the same seeded stream, so the mixture's
position is the loader's (epoch, batches) position, saved with the sets, their shares and the
samples drawn from each in the epoch. Its normalisation is pooled from the sets (``spec``).
"""

from __future__ import annotations

import logging
import math
import multiprocessing
import os
import signal
import time
from dataclasses import dataclass
from typing import Any, Callable, Iterator

import lightning as L
import numpy as np
from torch.utils.data import DataLoader, Dataset, IterableDataset, get_worker_info

from omg.data.deadline import deadline
from omg.data.mixture import load_mixture
from omg.data.shards import Manifest, ShardError, decode_sample, iter_tar
from omg.data.shards.remote import end_with_parent
from omg.data.windows import CLIP_MODES, Collate, WindowSampler, make_item, mirror_item, pick_text
from omg.errors import UsageError
from omg.motion import DataSpec, Representation, get_representation

log = logging.getLogger(__name__)


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
    ):
        self.mirror, self.mirror_prob = mirror, mirror_prob if mirror is not None else 0.0
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
            expected = self.checks.get(url)
            try:
                for raw in read_shard(url, expected):
                    seen += 1
                    try:
                        yield decode_sample(raw, self.feature_dim)
                        continue
                    except (ValueError, KeyError) as e:
                        where, reason = f"{url} key {raw.get('__key__')}", e
                    bad += 1
                    self._bad(where, reason, bad, seen)
            except TooManyBadSamples:
                raise
            except Exception as e:  # noqa: BLE001 - a bad shard counts as its samples, or one when unknown
                lost = (expected or {}).get("samples", 1)
                seen, bad = seen + lost, bad + lost
                self._bad(url, shard_problem(e), bad, seen)

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


class MotionDataModule(L.LightningDataModule):
    """Motion shards -> batches of ``motion`` (B, T, D) normalised, ``mask`` (B, T), ``text``.

    Args:
        train: a shard set: a directory, a URL pattern (``/data/shard-{000000..000099}.tar``), a
            directory URL (``s3://bucket/sets/amass``) or a manifest URL
            (``pipe:cat /data/amass/manifest.json``); or a list of sets, mixed in proportion to
            their frames; or a weighted mixture, a list of ``{path: SET, weight: W}``
            (``omg.data.mixture``). Not needed by ``omg validate`` and ``omg test``, which read ``val``.
        val: the same for validation (a small set: it is loaded into memory), or None.
        batch_size: samples per batch on each rank.
        max_len / min_len: sample length bounds in frames (OMG pretraining: windows l ~ U[1, L], L = 300
            frames at 30 fps; HumanML3D fine-tuning: whole clips of up to 196 frames at 20 fps). Whole clips
            shorter than ``min_len`` are not trained on (the papers' filters: HumanML3D 20, AnimalML3D
            10 frames); windows use a shorter clip whole. ``min_len`` unset: 1 for windows (OMG Sec. 3.1,
            a window may be a single keyframe), 40 for whole clips (HumanML3D's loader).
        clips: how samples are cut from clips: ``windows`` (sliding random windows, long takes
            sampled in proportion to their length: unlabeled pretraining), ``whole`` (the whole
            clip, a random ``max_len`` crop when longer: captioned data), or ``auto``: ``clip_sampling``.
        clip_sampling: what ``clips: auto`` cuts: the model's ``clip_sampling`` attribute, which ``omg fit``
            links here when it parses the config (``windows`` for a model that names none).
        batches_per_epoch: batches each rank yields per training epoch.
        shuffle_buffer: samples held by each worker to shuffle within.
        normalize: standardise features with the data's mean/std (``spec``: the manifest's, or a
            mixture's pooled statistics).
        max_bad_fraction: stop when more than this fraction of the samples a worker read were bad.
        timeout: seconds one training batch, or the read of one validation shard, may take before the
            run stops with one line (0: wait forever); a stalled read or data worker never hangs a run,
            with data workers or without (``omg.data.deadline``).
        verify_shards: check each shard against its manifest (size, sample count, sha256) before
            any of its samples is used; a shard that fails is skipped whole and counted as bad.
        mirror_prob: mirror augmentation: the probability that a training sample is replaced by
            its mirror image, left and right swapped in the motion (exactly, by the representation's
            ``mirror``: humanml3d263, maa) and in its caption (``omg.text.sides``). Default 0 (off)
            until its effect on a recipe is measured; validation and test sets are never mirrored.
    """

    def __init__(
        self,
        train: str | list[str | dict[str, Any]] | None = None,
        val: str | list[str | dict[str, Any]] | None = None,
        batch_size: int = 32,
        max_len: int = 300,
        min_len: int | None = None,
        clips: str = "auto",
        clip_sampling: str = "windows",
        batches_per_epoch: int = 1000,
        num_workers: int = 2,
        shuffle_buffer: int = 1000,
        seed: int = 0,
        normalize: bool = True,
        max_bad_fraction: float = 0.01,
        timeout: float = 600.0,
        verify_shards: bool = True,
        mirror_prob: float = 0.0,
    ):
        # this call's arguments, explicitly: Lightning's frame inspection would also collect those of
        # an enclosing __init__ (a LightningModule that builds a second data module, as OmniMotionGPT does)
        # (clip_sampling is the model's, linked, not a setting of the data: the data's record is as it was)
        arguments = {name: value for name, value in locals().items()
                     if name not in ("self", "__class__", "clip_sampling")}
        super().__init__()
        if batch_size < 1 or batches_per_epoch < 1 or num_workers < 0 or shuffle_buffer < 1:
            raise UsageError(
                "data.batch_size, data.batches_per_epoch and data.shuffle_buffer must be positive and "
                f"data.num_workers >= 0, got {batch_size}, {batches_per_epoch}, {shuffle_buffer}, {num_workers}"
            )
        if not timeout >= 0:  # also NaN
            raise UsageError(f"data.timeout must be >= 0 seconds (0: no limit), got {timeout}")
        if not 0 <= max_bad_fraction <= 1:  # also NaN
            raise UsageError(f"data.max_bad_fraction must be in [0, 1], got {max_bad_fraction}")
        # else the first batch would fail, after the run folder was written (None: the mode's default)
        if not 1 <= (1 if min_len is None else min_len) <= max_len:
            raise UsageError(f"data.min_len and data.max_len must satisfy 1 <= min_len <= max_len, "
                             f"got min_len={min_len}, max_len={max_len}")
        if clips not in ("auto", *CLIP_MODES):
            raise UsageError(f"data.clips must be auto, {' or '.join(CLIP_MODES)}, got {clips!r}")
        if clip_sampling not in CLIP_MODES:
            raise UsageError(f"data.clip_sampling must be {' or '.join(CLIP_MODES)}, got {clip_sampling!r}")
        if not 0.0 <= mirror_prob <= 1.0:  # also NaN
            raise UsageError(f"data.mirror_prob is a probability in [0, 1], got {mirror_prob}")
        self.save_hyperparameters(arguments)
        self.clip_sampling = clip_sampling
        if not train and not val:
            raise UsageError("no shards given: set data.train to a shard directory or URL pattern (data.val alone "
                             "is enough for `omg validate` and `omg test`)")
        self.train_urls, self.val_urls, self.shard_checks, manifest = [], [], {}, None
        self.mixture = None
        if train:
            # the manifests too: a pipe: command or URL that never answers is a stall like a shard's
            with deadline(timeout, stalled_message(timeout, "the manifests of data.train were not read")):
                self.mixture = load_mixture(train, "data.train")
            self.train_urls, manifest, self.shard_checks = self.mixture.urls, self.mixture.manifest, self.mixture.checks
        if val:
            with deadline(timeout, stalled_message(timeout, "the manifests of data.val were not read")):
                self.val_urls, val_manifest, val_checks = resolve_shards(val, "data.val")
            if manifest is not None:  # else every validation sample would fail to decode, one by one
                manifest.spec().check_compatible(val_manifest.spec(), f"data.train ({manifest.location})",
                                                 f"data.val ({val_manifest.location})")
            self.shard_checks = {**self.shard_checks, **val_checks}
            manifest = manifest or val_manifest
        self.manifest = manifest  # the (first) training set's; the validation set's when there is none
        # a mixture's pooled statistics; models store this spec, and generation denormalises with it
        self._spec = self.mixture.spec() if self.mixture is not None else manifest.spec()
        if not verify_shards:
            self.shard_checks = {}
        mean, std = (np.asarray(self._spec.mean, np.float32), np.asarray(self._spec.std, np.float32)) \
            if normalize else (None, None)
        self.collate = Collate(mean, std)
        self.mirror = None
        if mirror_prob > 0:  # a representation that cannot mirror fails here, not in a data worker
            self.mirror = get_representation(self.representation, self.skeleton)
            self.mirror.mirror_map()

    # what models need to know about the data
    @property
    def feature_dim(self) -> int:
        return self.manifest["feature_dim"]

    @property
    def representation(self) -> str:
        return self.manifest["representation"]

    @property
    def skeleton(self) -> str:
        return self.manifest["skeleton"]

    @property
    def fps(self) -> float:
        return self.manifest["fps"]

    @property
    def spec(self) -> DataSpec:
        return self._spec

    @property
    def windows(self) -> WindowSampler:
        """How samples are cut: ``data.clips``, or under ``auto`` ``data.clip_sampling`` (the model's)."""
        mode = self.hparams.clips
        return WindowSampler(self.hparams.max_len, self.hparams.min_len,
                             self.clip_sampling if mode == "auto" else mode)

    def _rank_world(self) -> tuple[int, int]:
        trainer = self.trainer
        return (trainer.global_rank, trainer.world_size) if trainer is not None else (0, 1)

    def train_dataloader(self) -> StreamLoader:
        if not self.train_urls:
            raise UsageError("training needs data.train: a shard directory or URL pattern")
        trainer = self.trainer
        return self.stream_loader(*self._rank_world(), self.windows,
                                  epoch_fn=(lambda: trainer.current_epoch) if trainer is not None else None)

    def stream_loader(self, rank: int, world: int, windows: WindowSampler,
                      epoch_fn: Callable[[], int] | None = None) -> StreamLoader:
        """Rank ``rank``'s training stream of ``data.train`` (a mixture's sets each split across the
        ranks), cut by ``windows``; ``epoch_fn`` gives the epoch (each ``iter()`` is the next without it)."""
        h = self.hparams
        manifest = self.manifest
        mixture = self.mixture
        sets = None
        if len(mixture.sets) > 1:
            sets = [StreamSet(rank_shards(s.urls, rank, world, s.location), share, s.mean_frames, s.location)
                    for s, share in zip(mixture.sets, mixture.shares)]
        stream = MotionStream(
            rank_shards(self.train_urls, rank, world),
            rank=rank,
            batches=h.batches_per_epoch,
            batch_size=h.batch_size,
            windows=windows,
            feature_dim=self.feature_dim,
            seed=h.seed,
            shuffle_buffer=h.shuffle_buffer,
            max_bad_fraction=h.max_bad_fraction,
            checks=self.shard_checks,
            mean_frames=manifest["num_frames"] / max(1, manifest["num_clips"]),
            sets=sets,
            mirror=self.mirror,
            mirror_prob=h.mirror_prob,
        )
        return StreamLoader(stream, epoch_fn=epoch_fn, num_workers=h.num_workers, collate_fn=self.collate,
                            persistent_workers=False, fetch_timeout=h.timeout, worker_init_fn=exit_on_sigterm)

    def val_clips(self) -> ClipDataset:
        """The validation set, decoded and verified (bad samples skipped and counted)."""
        return ClipDataset.from_shards(self.val_urls, self.feature_dim, self.windows, self.hparams.max_bad_fraction,
                                       self.shard_checks, timeout=self.hparams.timeout)

    def val_dataloader(self) -> DataLoader | list:
        if not self.val_urls:
            return []
        return DataLoader(self.val_clips(), batch_size=self.hparams.batch_size, collate_fn=self.collate,
                          num_workers=0)

    def test_dataloader(self) -> DataLoader | list:
        return self.val_dataloader()


def in_memory_loader(urls: list[str], feature_dim: int, windows: WindowSampler, batch_size: int, num_workers: int,
                     collate: Collate) -> DataLoader:
    """The MDM-style baseline: every clip in RAM, random windows, shuffled each epoch."""
    dataset = ClipDataset.from_shards(urls, feature_dim, windows, random_windows=True)
    dataset.samples = [s for s in dataset.samples if windows.keeps(len(s["motion"]))]  # min_len of whole clips
    return DataLoader(dataset, batch_size=batch_size, shuffle=True, num_workers=num_workers, collate_fn=collate,
                      drop_last=True)
