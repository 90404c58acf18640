"""``OODEvalCallback``: OmniMotionGPT's out-of-distribution protocol.

Prompts are human captions (a human shard set's, e.g. the HumanML3D test split) with the subject
replaced by an animal name (``omg.text.omgpt.to_animal``); no real animal motion matches them,
so the real set of FID-OOD is the whole real animal set: each prompt is paired with a random real
animal clip (training and validation sets of ``data``), cut to the prompt's length. The metrics are
those of ``EvalCallback`` on these prompts, logged as ``ood/<metric>`` with ``fid`` as ``fid_ood``; ``omg test`` writes
``eval_ood.json`` / ``eval_ood.md`` beside the in-distribution ``eval.json``. Where the model retrieves its human
motion, no generation may start from the prompt's own clip: every clip captioned by a prompt is left out of the
retrieval bank, and the report counts the generations whose human clip carries their prompt's caption (0).

``SideTransferCallback`` measures what no animal-trained judge can: whether a one-sided human
action ("kicks with the left leg") keeps its side when the model makes it into each animal.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import lightning as L
import numpy as np
import torch
from lightning.pytorch.utilities import rank_zero_only
from torch.nn.utils.rnn import pad_sequence

from omg.callbacks.eval import EvalCallback
from omg.callbacks.run import run_dir
from omg.data.loaders import ClipDataset, resolve_shards
from omg.data.windows import WindowSampler
from omg.errors import UsageError
from omg.evaluation import PromptSet, markdown_table, write_report
from omg.files import atomic_write, write_json
from omg.lit.human_source import OmniMotionSampler, human_source_of
from omg.lit.sampling import sampler_of
from omg.models.omgpt import primal_joints
from omg.text.omgpt import caption_key, one_sided_limb, to_animal


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
        self._sources: dict[str, set[str]] = {}  # a prompt about an animal -> the human captions it was made from
        self._source: dict[str, Any] = {}  # where the model's human motion came from, for the report

    def preflight(self, model: L.LightningModule, data: L.LightningDataModule | None) -> None:
        """``EvalCallback``'s checks, the prompts read, and the model's human source checked: a generator
        that is there, or a retrieval bank without the clips whose captions are the prompts."""
        super().preflight(model, data)
        if self._captions is None:
            urls, manifest, checks = resolve_shards(self.prompt_shards, "OODEvalCallback.prompts")
            windows = WindowSampler(self.max_frames, 1, "whole")
            human = ClipDataset.from_shards(urls, manifest["feature_dim"], windows, checks=checks).samples
            self._captions = [(t, len(s["motion"])) for s in human for t in s["texts"]]
        if not self._captions:
            raise UsageError(f"OODEvalCallback.prompts: {self.prompt_shards} holds no captions")
        sampler = sampler_of(model, "OODEvalCallback")
        if not isinstance(sampler, OmniMotionSampler):
            return
        if model.human_source == "retrieval":
            excluded, left = sampler.humans.exclude([c for c, _ in self._captions], "OODEvalCallback")
            self._source = {"human_source": "retrieval", "retrieval_bank": model.retrieval_bank or "checkpoint",
                            "retrieval_clips": left, "retrieval_excluded": excluded, "generations": 0,
                            "from_prompt_clip": 0}
        else:
            sampler.humans.check()
            self._source = {"human_source": str(model.human_source)}

    def setup(self, trainer: L.Trainer, pl_module: L.LightningModule, stage: str) -> None:
        super().setup(trainer, pl_module, stage)  # preflight: the prompts
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
            self._sources.setdefault(texts[-1], set()).add(caption_key(caption))
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

    def generate(self, module: L.LightningModule, texts: list[str], lengths: torch.Tensor, seed: int) -> torch.Tensor:
        """``EvalCallback``'s, counting (on this rank) the retrieved human clips captioned by their prompt's
        own caption: the human motion must not be the prompt's answer."""
        motion = super().generate(module, texts, lengths, seed)
        if self._source.get("human_source") == "retrieval":
            drawn = [{caption_key(t) for t in clip} for clip in human_source_of(module).retrieved]
            self._source["generations"] += len(texts)
            self._source["from_prompt_clip"] += sum(bool(self._sources.get(t, set()) & d)
                                                    for t, d in zip(texts, drawn))
        return motion

    @rank_zero_only
    def _report(self, directory: Path, summary: dict, settings: dict) -> None:
        settings = {**settings, "prompts": self.prompt_shards, "animals": self.animals, "protocol": "OOD",
                    **self._source}
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


# the limb ends among the primal joints (root, left leg, right leg, head, left arm, right arm, chest)
LIMB_ENDS = {("leg", "left"): 1, ("leg", "right"): 2, ("arm", "left"): 4, ("arm", "right"): 5}
OTHER_SIDE = {"left": "right", "right": "left"}


def limb_travel(representation, features: torch.Tensor, offsets: torch.Tensor) -> dict[tuple[str, str], float]:
    """The path length (metres) of each limb end over a motion: maa features (T, D), offsets (J, 3).
    An animal's front feet are its arms, its hind feet its legs (the primal-joint pairing)."""
    return limb_travels(representation, features[None], offsets[None])[0]


def limb_travels(representation, features: torch.Tensor, offsets: torch.Tensor) -> list[dict[tuple[str, str], float]]:
    """``limb_travel`` of each of B motions of one length at once: features (B, T, D), offsets (B, J, 3)."""
    joints = representation.decode(features.float(), offsets.float())  # (B, T, J, 3)
    ends = primal_joints(representation.skeleton)
    paths = (joints[:, 1:] - joints[:, :-1]).norm(dim=-1).sum(1)  # (B, J)
    return [{limb: float(path[ends[i]]) for limb, i in LIMB_ENDS.items()} for path in paths]


class SideTransferCallback(L.Callback):
    """At ``omg test``: each human clip whose caption names one side and one limb ("kicks with the
    left leg", "waves with the right hand") is made into every animal (``translate``, the clip's own
    caption about the animal); the clip counts where the human's named limb end travels farther
    than the other side's, and *kept* where the animal's does too (arms are an animal's front feet,
    legs its hind feet). Written to ``eval_sides.json`` / ``eval_sides.md`` and printed.

    Args:
        prompts: the human shard set (a directory or URL pattern) whose captioned clips are used.
        animals: the animals (default: every animal the model knows).
        max_frames: clips are cut to this many frames (the model's longest: 196).
        batch_size: the most motions one ``translate`` call makes (clips x animals; lengths padded).
    """

    report_name = "eval_sides"

    def __init__(self, prompts: str, animals: list[str] | None = None, max_frames: int = 196, batch_size: int = 64):
        if not prompts:
            raise UsageError("SideTransferCallback.prompts: a human shard directory with captioned clips")
        if not isinstance(batch_size, int) or batch_size < 1:  # EvalCallback's check and wording
            raise UsageError(f"SideTransferCallback.batch_size must be an integer >= 1, got {batch_size!r}")
        self.prompt_shards, self.animals, self.max_frames = prompts, animals, max_frames
        self.batch_size = batch_size

    def clips(self) -> list[tuple[str, tuple[str, str], dict]]:
        """(caption, (limb, side), sample) of every one-sided caption of the human set."""
        urls, manifest, checks = resolve_shards(self.prompt_shards)
        windows = WindowSampler(self.max_frames, 1, "whole")
        samples = ClipDataset.from_shards(urls, manifest["feature_dim"], windows, checks=checks).samples
        return [(t, limb, s) for s in samples for t in s["texts"] if (limb := one_sided_limb(t))]

    @torch.no_grad()
    def measure(self, module: L.LightningModule) -> dict[str, dict[str, Any]]:
        animals = self.animals or module.animal_names
        counts = {(a, kind): [0, 0] for a in animals for kind in ("leg", "arm")}  # (clips, kept)
        kept = []  # (caption, (limb, side), human maa (T, D), offsets (J, 3)) of the clips whose named side moves
        for caption, (kind, side), sample in self.clips():
            human = torch.from_numpy(np.ascontiguousarray(sample["motion"][: self.max_frames])).float()
            human_offsets = torch.tensor(sample["meta"]["offsets"], dtype=torch.float32)
            if len(human) < 2:
                continue
            travel = limb_travel(module.human_rep, human, human_offsets)
            if travel[kind, side] > travel[kind, OTHER_SIDE[side]]:  # else nothing to keep
                kept.append((caption, (kind, side), human, human_offsets))
        animal_offsets = torch.stack([module.animal_offsets(a).cpu() for a in animals])  # (A, J_a, 3)
        rows = len(animals)  # each clip made into every animal, several clips a call
        per_call = max(1, self.batch_size // rows)
        kept.sort(key=lambda clip: len(clip[2]))  # clips of like lengths together: little padding to compute
        for start in range(0, len(kept), per_call):
            captions, limbs, humans, offsets = zip(*kept[start:start + per_call])
            lengths = [len(human) for human in humans]
            out = module.translate([c for c in captions for _ in animals],
                                   pad_sequence(humans, batch_first=True).repeat_interleave(rows, 0),  # zero-padded
                                   torch.stack(offsets).repeat_interleave(rows, 0),
                                   [n for n in lengths for _ in animals], animals * len(captions)).cpu()
            for b, (kind, side) in enumerate(limbs):
                moved = limb_travels(module.representation, out[b * rows:(b + 1) * rows, : lengths[b]], animal_offsets)
                for animal, travel in zip(animals, moved):
                    counts[animal, kind][0] += 1
                    counts[animal, kind][1] += int(travel[kind, side] > travel[kind, OTHER_SIDE[side]])
        return {f"{animal}/{kind}": {"clips": n, "kept": k, "fraction": k / n if n else float("nan")}
                for (animal, kind), (n, k) in counts.items()}

    def on_test_epoch_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        if not hasattr(pl_module, "translate"):
            raise UsageError("SideTransferCallback needs an OmniMotionGPT checkpoint (a model with translate)")
        self._report(trainer, self.measure(pl_module))

    @rank_zero_only
    def _report(self, trainer: L.Trainer, sides: dict[str, dict[str, Any]]) -> None:
        directory = Path(run_dir(trainer))
        directory.mkdir(parents=True, exist_ok=True)
        lines = ["| animal / limb | one-sided human captions | side kept | fraction |", "|---|---:|---:|---:|"]
        lines += [f"| {key} | {v['clips']} | {v['kept']} | {v['fraction']:.3f} |" for key, v in sides.items()]
        table = "\n".join(lines)
        write_json(directory / f"{self.report_name}.json", {"settings": {"prompts": self.prompt_shards},
                                                             "sides": sides})
        atomic_write(directory / f"{self.report_name}.md", f"# One-sided human actions made into animals\n\n{table}\n"
                     .encode())
        print(f"\nOne-sided human actions made into animals (side kept: the animal's matching limb moves "
              f"more)\n{table}\n\nwritten to {directory / (self.report_name + '.json')}")
