"""``PairedDataModule``: the run's data (``data:``) and, where a model trains on two shard sets at
once, a second one (``data.human``: OmniMotionGPT's human motion beside the animal set).

Without ``human`` it is ``MotionDataModule``. With it, the training loader is Lightning's
``CombinedLoader({"animal": ..., "human": ...}, mode="min_size")``: the animal loader's batches per
epoch set the epoch, and the human stream is endless (``EndlessLoader``), each pass over its
loader that stream's next epoch, so its epochs turn over at their own steps and it goes on across
the trainer's epochs where it was. Each set keeps its own skeleton, offsets, captions, shards split
across the ranks and seeded stream (``MotionStream``); both positions are stateful loaders, which
Lightning saves in checkpoints (``loops.fit_loop.state_dict.combined_loader``, animal then human)
and restores on resume. Validation and testing read the animal set only (the human set's manifests
are not even opened).
"""

from __future__ import annotations

import inspect
from collections.abc import Iterator

from lightning.pytorch.utilities.combined_loader import CombinedLoader

from omg.data.datamodule import MotionDataModule
from omg.data.loaders import ClipDataset, StreamLoader
from omg.data.omgpt import category_offsets, scan_metas
from omg.errors import UsageError
from omg.settings import arguments, set_fields

# data.human: MotionDataModule's arguments, each None (unset) its default
CompanionData = arguments(MotionDataModule, "CompanionData", __name__,
                          doc="The second shard set's MotionDataModule arguments (unset: data's default).")


class EndlessLoader:
    """A ``StreamLoader`` read without end: each time it runs dry the next pass (its stream's next
    epoch) starts, and a new ``iter()`` goes on from the batch the last one stopped at. No length, so
    that a ``CombinedLoader`` in ``min_size`` mode ends its epochs by the other loader's."""

    def __init__(self, loader: StreamLoader):
        self.loader = loader
        self._batches: Iterator[dict] | None = None

    def __iter__(self) -> Iterator[dict]:
        while True:
            if self._batches is None:
                self._batches = iter(self.loader)
            try:
                yield next(self._batches)
            except StopIteration:
                self._batches = None

    def state_dict(self) -> dict:
        return self.loader.state_dict()

    def load_state_dict(self, state: dict) -> None:
        self.loader.load_state_dict(state)
        self._batches = None


class PairedDataModule(MotionDataModule):
    """``MotionDataModule`` (its arguments: the animal set, ``data:``) and a second set.

    Args:
        human: the second shard set's ``MotionDataModule`` arguments (``CompanionData``: ``train``,
            ``val``, ``batch_size``, ``max_len``, ``min_len``, ...), each unset its default but
            ``clip_sampling``, the first set's (the model's). OmniMotionGPT's human motion (smpl22 maa
            shards, captioned); the older key ``model.init_args.human_data`` is read as this one (``omg fit``).
    """

    def __init__(self, *args, human: CompanionData | None = None, **kwargs):
        super().__init__(*args, **kwargs)
        fields = set_fields(CompanionData, human, "data.human")
        self.human_args = fields or None  # recorded among the data's hyper-parameters only when set
        if fields:
            self.hparams["human"] = fields
            try:
                inspect.signature(MotionDataModule).bind(**fields)
            except TypeError as e:
                raise UsageError(f"data.human: {e}; it takes the arguments of data (train, val, batch_size, ...)") \
                    from None
        self._human: MotionDataModule | None = None

    @property
    def human(self) -> MotionDataModule | None:
        """The second set's data module, opened when first asked for (a run that only validates or tests
        never reads its manifests), or None."""
        if self._human is None and self.human_args:
            try:
                self._human = MotionDataModule(**{"clip_sampling": self.clip_sampling, **self.human_args})
            except UsageError as e:  # its checks name data's keys: say which set
                raise UsageError(f"data.human: {e}") from None
        return self._human

    def train_dataloader(self) -> StreamLoader | CombinedLoader:
        animal = super().train_dataloader()
        if not self.human_args:
            return animal
        if not self.human.train_urls:
            raise UsageError("data.human.train: a shard directory or URL pattern is needed to train")
        # the human stream's epochs are its own: each pass over its loader is the next one
        human = self.human.stream_loader(*self._rank_world(), self.human.windows)
        return CombinedLoader({"animal": animal, "human": EndlessLoader(human)}, mode="min_size")

    def human_val_samples(self) -> list[dict]:
        """The human validation clips, decoded (``{"motion", "meta", "texts"}``), un-normalised."""
        if self.human is None or not self.human.val_urls:
            return []
        h = self.human
        return ClipDataset.from_shards(h.val_urls, h.feature_dim, h.windows, h.hparams.max_bad_fraction,
                                       h.shard_checks, h.hparams.timeout).samples

    def category_offsets(self) -> dict[str, list[list[float]]]:
        """Each category's mean bone offsets (J, 3) over the clips of the training shards (the validation
        shards without them), from their meta alone."""
        return category_offsets(scan_metas(self.train_urls or self.val_urls))


__all__ = ["CompanionData", "EndlessLoader", "PairedDataModule"]

