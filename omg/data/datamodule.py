"""``MotionDataModule``: streaming WebDataset motion shards into training batches.

Training streams shards with resampling (``omg.data.loaders.MotionStream``: each worker draws shards at
random from its rank's list, reads them through a shuffle buffer and cuts one sliding random window per
clip). The recipe that is safe under DDP:

- each rank's shard list is resolved here, in the main process, from the rank and world
  size Lightning gives us, and travels to the workers inside the dataset; no worker ever
  looks at environment variables, so no rank can read another's shards whatever the
  multiprocessing start method;
- an epoch is a fixed number of batches per rank, split exactly among the workers, so every
  rank yields the same number of batches;
- validation is a small map-style set that Lightning splits with a DistributedSampler.

The loader keeps its position in the stream, which Lightning saves in checkpoints; how a resumed
run, on the same number of ranks or another, goes on is ``omg.data.loaders``'.

``data.train`` may be a weighted mixture of shard sets (``omg.data.mixture``): each rank splits
every set's shards, and each sample is drawn from set k with probability share_k from that
set's own shuffle buffer. Its normalisation is pooled from the sets (``spec``).
"""

from __future__ import annotations

from typing import Any, Callable

import lightning as L
import numpy as np
from torch.utils.data import DataLoader

from omg.data.deadline import deadline
from omg.data.loaders import (
    DEFAULT_CACHE_MB,
    DEFAULT_TIMEOUT_S,
    ClipDataset,
    StreamLoader,
    resolve_shards,
    stalled_message,
    stream_loader,
)
from omg.data.mixture import load_mixture
from omg.data.windows import CLIP_MODES, Collate, WindowSampler
from omg.errors import UsageError
from omg.motion import DataSpec, get_representation


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
        cache_mb: a set this small is decoded once: each data worker keeps the decoded samples of the shards it
            has read while the rank's share of the motion (the manifests' frames x features, float32) fits
            in ``cache_mb`` MiB, instead of reading, checking and decoding a shard's bytes at every draw (0:
            never). The batches are the same; a larger set is read as before.
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
        timeout: float = DEFAULT_TIMEOUT_S,
        verify_shards: bool = True,
        cache_mb: float = DEFAULT_CACHE_MB,
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
        if not cache_mb >= 0:  # also NaN
            raise UsageError(f"data.cache_mb must be >= 0 MiB (0: decode every shard at each read), got {cache_mb}")
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
        return stream_loader(self.mixture, rank, world, windows, h.batches_per_epoch, h.batch_size, self.collate,
                             num_workers=h.num_workers, seed=h.seed, shuffle_buffer=h.shuffle_buffer,
                             max_bad_fraction=h.max_bad_fraction, checks=self.shard_checks, mirror=self.mirror,
                             mirror_prob=h.mirror_prob, timeout=h.timeout, epoch_fn=epoch_fn,
                             cache_mb=h.cache_mb)

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
