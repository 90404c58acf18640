"""``OODEvalCallback``: OmniMotionGPT's out-of-distribution protocol.

Prompts are human captions (a human shard set's, e.g. the HumanML3D test split) with the subject
replaced by an animal name (``omg.text.subjects.to_animal``); no real animal motion matches them,
so the real set of FID-OOD is the whole real animal set: each prompt is paired with a random real
animal clip (training and validation sets of ``data``), cut to the prompt's length. The metrics are
those of ``EvalCallback`` on these prompts, logged as ``ood/<metric>`` with ``fid`` as ``fid_ood``; ``omg test`` writes
``eval_ood.json`` / ``eval_ood.md`` beside the in-distribution ``eval.json``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import lightning as L
import numpy as np
import torch
from lightning.pytorch.utilities import rank_zero_only

from omg.callbacks.eval import EvalCallback
from omg.data.datamodule import ClipDataset, resolve_shards
from omg.errors import UsageError
from omg.evaluation import PromptSet, markdown_table, write_report
from omg.text.subjects import to_animal


class OODEvalCallback(EvalCallback):
    """``EvalCallback`` on human captions made about animals.

    Args:
        prompts: the human shard set whose captions are the prompts (a directory or URL pattern).
        animals: the animal names put in the captions (default: the model's ``animal_names``, or the
            categories of the real animal clips).
        max_frames: the longest prompt (AnimalML3D / HumanML3D: 196 frames).
        **kwargs: ``EvalCallback``'s arguments (evaluator, metrics, num_prompts, replications, ...).
    """

    report_name = "eval_ood"

    def __init__(self, prompts: str, animals: list[str] | None = None, max_frames: int = 196, **kwargs: Any):
        super().__init__(**kwargs)
        if not prompts:
            raise UsageError("OODEvalCallback.prompts: a human shard directory whose captions become the prompts")
        self.prompt_shards, self.animals, self.max_frames = prompts, animals, max_frames
        self._captions: list[tuple[str, int]] | None = None  # (caption, clip length)
        self._real: list[dict] | None = None

    def setup(self, trainer: L.Trainer, pl_module: L.LightningModule, stage: str) -> None:
        super().setup(trainer, pl_module, stage)
        urls, manifest, checks = resolve_shards(self.prompt_shards)
        human = ClipDataset.from_shards(urls, manifest["feature_dim"], self._windows, checks=checks).samples
        self._captions = [(t, len(s["motion"])) for s in human for t in s["texts"]]
        if not self._captions:
            raise UsageError(f"OODEvalCallback.prompts: {self.prompt_shards} holds no captions")
        data = trainer.datamodule
        real = list(self._samples)
        if getattr(data, "train_urls", None):
            real += ClipDataset.from_shards(data.train_urls, data.feature_dim, self._windows,
                                            checks=data.shard_checks).samples
        self._real = real
        if self.animals is None:
            self.animals = list(getattr(pl_module, "animal_names", None) or
                                sorted({s["meta"].get("category") or "animal" for s in real}))

    def prompts(self, replication: int) -> PromptSet:
        """Seeded human captions about random animals, each with a random real animal clip."""
        rng = np.random.default_rng([self.seed, replication, 1])
        texts, windows, categories, offsets = [], [], [], []
        for _ in range(self.num_prompts):
            caption, frames = self._captions[int(rng.integers(len(self._captions)))]
            animal = self.animals[int(rng.integers(len(self.animals)))]
            real = self._real[int(rng.integers(len(self._real)))]
            length = max(2, min(frames, len(real["motion"]), self.max_frames))
            start = int(rng.integers(len(real["motion"]) - length + 1))
            texts.append(to_animal(caption, animal))
            windows.append(real["motion"][start:start + length])
            categories.append(animal)
            offsets.append(real["meta"].get("offsets"))
        lengths = torch.tensor([len(w) for w in windows])
        motions = torch.zeros(len(windows), int(lengths.max()), windows[0].shape[1])
        for b, w in enumerate(windows):
            motions[b, : len(w)] = torch.from_numpy(np.ascontiguousarray(w))
        has_offsets = all(o is not None for o in offsets)
        return PromptSet(texts, lengths, motions, categories,
                         torch.tensor(np.array(offsets), dtype=torch.float32) if has_offsets else None,
                         [{} for _ in texts])

    def run_once(self, trainer: L.Trainer, module: L.LightningModule, replication: int) -> dict[str, float]:
        values = super().run_once(trainer, module, replication)
        return {rename(k): v for k, v in values.items()}

    @rank_zero_only
    def _report(self, directory: Path, summary: dict, settings: dict) -> None:
        settings = {**settings, "prompts": self.prompt_shards, "animals": self.animals, "protocol": "OOD"}
        # logged as ood/<metric>, reported as <metric>
        summary = {key.removeprefix("ood/"): value for key, value in summary.items()}
        json_path, md_path = write_report(directory, summary, settings, name=self.report_name)
        print(f"\nOOD prompts (human captions about animals)\n{markdown_table(summary, self.replications)}\n\n"
              f"written to {json_path} and {md_path}")


def rename(key: str) -> str:
    """``ood/<key>``, with ``fid`` as ``fid_ood`` (its real set is the whole animal set): the OOD
    values are logged beside the in-distribution ones."""
    head, _, name = key.rpartition("/")
    name = "fid_ood" if name == "fid" else name
    return f"ood/{head}/{name}" if head else f"ood/{name}"
