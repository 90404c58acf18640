"""A second shard stream read beside the trainer's own data: OmniMotionGPT trains on human and
animal motion at once, each set with its own skeleton, offsets and captions.

``omg fit`` gives the model one ``MotionDataModule`` (``data:``, the animal set, which the
evaluation also reads); ``CompanionStream`` reads the other set (the model's ``human_data:``)
with the same stream classes and the same DDP recipe: each rank's disjoint share of the shards,
a stream that is a pure function of (seed, rank, worker, epoch), and a position that a
checkpoint saves and a resumed run restores.
"""

from __future__ import annotations

import inspect
import json
from collections.abc import Iterator, Sequence
from types import SimpleNamespace
from typing import Any

import numpy as np

from omg.data.datamodule import ClipDataset, MotionDataModule, StreamLoader
from omg.data.windows import WindowSampler
from omg.errors import UsageError
from omg.settings import arguments

# model.init_args.human_data of OmniMotionModule: MotionDataModule's arguments, each None (unset) its default
CompanionData = arguments(MotionDataModule, "CompanionData", __name__,
                          doc="The second shard set's MotionDataModule arguments (unset: data's default).")


class CompanionStream:
    """Endless training batches of a second shard set; ``args`` are ``MotionDataModule``'s
    (``train``, ``val``, ``batch_size``, ``max_len``, ``min_len``, ``clips``, ``num_workers`` ...)."""

    def __init__(self, args: dict[str, Any], clips: str = "whole"):
        try:
            bound = inspect.signature(MotionDataModule).bind(**args)
        except TypeError as e:
            raise UsageError(f"human_data: {e}; it takes the arguments of data (train, val, batch_size, ...)") from None
        bound.apply_defaults()
        self.args = SimpleNamespace(**bound.arguments)
        self.data = MotionDataModule(**args)
        mode = self.args.clips
        self.windows = WindowSampler(self.args.max_len, self.args.min_len, clips if mode == "auto" else mode)
        self.loader: StreamLoader | None = None
        self._batches: Iterator[dict] | None = None
        self._resume: dict | None = None

    @property
    def spec(self):
        return self.data.spec

    def start(self, rank: int = 0, world_size: int = 1) -> None:
        """Build this rank's loader (call once the trainer knows the rank)."""
        if not self.data.train_urls:
            raise UsageError("human_data.train: a shard directory or URL pattern is needed to train")
        # epochs of its own: each pass over the loader is the next epoch of this stream
        self.loader = self.data.stream_loader(rank, world_size, self.windows)
        if self._resume is not None:
            self.loader.load_state_dict(self._resume)
            self._resume = None
        self._batches = None

    def next(self) -> dict:
        """The next training batch (normalised as the data module normalises)."""
        if self.loader is None:
            self.start()
        while True:
            if self._batches is None:
                self._batches = iter(self.loader)
            try:
                return next(self._batches)
            except StopIteration:
                self._batches = None

    def state_dict(self) -> dict:
        return self.loader.state_dict() if self.loader is not None else dict(self._resume or {})

    def load_state_dict(self, state: dict) -> None:
        if self.loader is not None:
            self.loader.load_state_dict(state)
            self._batches = None
        else:
            self._resume = dict(state)

    def val_samples(self) -> list[dict]:
        """The decoded validation clips (``{"motion", "meta", "texts"}``), un-normalised."""
        if not self.data.val_urls:
            return []
        return ClipDataset.from_shards(self.data.val_urls, self.data.feature_dim, self.windows,
                                       self.args.max_bad_fraction, self.data.shard_checks, self.args.timeout).samples


def category_offsets(samples: Sequence[dict]) -> dict[str, list[list[float]]]:
    """Mean bone offsets (J, 3) per category of decoded samples' meta."""
    sums: dict[str, tuple[np.ndarray, int]] = {}
    for meta in samples:
        if meta.get("offsets") is None:
            continue
        name = meta.get("category") or "animal"
        total, count = sums.get(name, (0.0, 0))
        sums[name] = (total + np.asarray(meta["offsets"], dtype=np.float64), count + 1)
    return {name: (total / count).round(6).tolist() for name, (total, count) in sorted(sums.items())}


def scan_metas(urls: Sequence[str]) -> list[dict]:
    """Every sample's meta.json of the shards (motion is not decoded)."""
    from omg.data.shards import iter_tar

    return [json.loads(raw["meta.json"]) for url in urls for raw in iter_tar(url) if "meta.json" in raw]
