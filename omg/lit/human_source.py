"""OmniMotionGPT's human source and its sampler.

OmniMotionGPT makes an animal motion from a prompt by translating a human motion; when none is given, the
human motion comes from the module's ``human_source``: a captioned human clip retrieved by its caption (the
clips the checkpoint keeps, or the shards of ``retrieval_bank``) or an OMG ControlNet's text-to-motion (the
checkpoint ``human_source`` names). ``OmniMotionSampler`` composes that source with the module's
``translate`` into the ``Sampler`` (``omg.lit.sampling``) that the evaluation callbacks and ``omg generate``
call; ``sampler_of`` finds it for the module by its class (``MODULE_SAMPLERS``).

The module keeps what training makes and a checkpoint holds (the retrieval clips, the settings that name the
source); a ``HumanSource`` keeps what sampling makes (the loaded generator, the clips' caption features, the
captions excluded, the clips last drawn). There is one per module (``human_source_of``), so that callbacks
sampling one module share its exclusions and its loaded generator.
"""

from __future__ import annotations

import weakref
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from omg.diffusion import StepProgress
from omg.errors import UsageError
from omg.lit.omgpt import HUMAN_SKELETON, OmniMotionModule
from omg.lit.sampling import Sampler, SamplingSettings
from omg.motion import DataSpec
from omg.motion.maa import maa_from_positions
from omg.registry import MODULE_SAMPLERS, class_key
from omg.skeleton import get_skeleton
from omg.text.omgpt import caption_key, choose_animal, to_person


class HumanSource:
    """Where an OmniMotionGPT module's human motion comes from when none is given (``human_source``).

    Reads the module's settings each time (``human_source``, ``retrieval_bank``, ``retrieval_top_k``,
    ``retrieval_draw``, ``retrieval_temperature``), so that a setting changed on the module applies to the
    next draw. Holds its module weakly: it lives as long as the module does (``human_source_of``)."""

    def __init__(self, module: OmniMotionModule):
        self._module = weakref.ref(module)
        self.excluded: frozenset[str] = frozenset()  # captions whose clips retrieval never draws
        self.retrieved: list[list[str]] = []  # the captions of the clip each prompt of the last retrieval drew
        self._generator: tuple[str, Any] | None = None  # (human_source, the OMG ControlNet module loaded from it)
        self._bank: tuple[tuple, dict] | None = None  # (what it was built from, the clips and caption features)
        self._bank_samples: tuple[Any, list[dict]] | None = None  # (retrieval_bank, its clips), read once

    @property
    def module(self) -> OmniMotionModule:
        return self._module()

    def human_motion(self, prompts: Sequence[str], lengths: Tensor,
                     settings: SamplingSettings) -> tuple[Tensor, Tensor]:
        """Human maa (B, T, 138) and offsets (B, 22, 3) for prompts about "a person", from ``human_source``
        (drawn with ``settings.seed``)."""
        m = self.module
        if m.human_source == "retrieval":
            return self.retrieve(prompts, lengths, settings.seed)
        return generate_human(self.generator(), prompts, lengths, m.spec.fps, settings)

    def generator(self) -> Sampler:
        """The OMG ControlNet module ``human_source`` names, loaded once, on the module's device."""
        from omg.lit.checkpoint import load_module
        from omg.lit.controlnet import ControlNetModule

        m = self.module
        source = str(m.human_source)
        if self._generator is None or self._generator[0] != source:
            self.check()
            try:
                self._generator = (source, load_module(source, expect=ControlNetModule))
            except UsageError as e:
                raise UsageError(f"model.init_args.source.human_source: {e}") from None
        generator = self._generator[1]
        if generator.device != m.device:
            generator.to(m.device)
        return generator

    def check(self) -> None:
        """One line unless ``human_source`` is ``retrieval`` or names a file (an evaluation checks it before it
        starts: a generator that is not there would otherwise fail at its first prompt)."""
        source = str(self.module.human_source)
        if source != "retrieval" and "://" not in source and not Path(source).exists():
            raise UsageError(f"model.init_args.source.human_source: no OMG ControlNet checkpoint at {source} (train "
                             "one, e.g. `omg fit --config configs/mini/controlnet.yaml`, or set it to retrieval)")

    def clips(self, motion: bool = True) -> list[dict]:
        """The human clips retrieval may draw from, exclusions not applied: ``{"motion" (T, 138) un-normalised,
        "offsets" (22, 3), "texts"}`` of ``retrieval_bank`` when set, else of the validation clips kept in the
        checkpoint (``motion=False``: texts only, which needs no weights loaded)."""
        m = self.module
        if m.retrieval_bank is not None:
            if self._bank_samples is None or self._bank_samples[0] != m.retrieval_bank:
                self._bank_samples = (m.retrieval_bank, read_retrieval_bank(m.retrieval_bank, m.human_spec,
                                                                            m.config.max_frames))
            return self._bank_samples[1]
        bank = m.human_bank
        if not bank or getattr(m, "human_bank_motion", None) is None:
            raise UsageError("this OmniMotionGPT checkpoint holds no human clips to retrieve from (trained without "
                             "captioned clips in human_data.val, or before checkpoints kept them): give the human "
                             "motion with --from_motion or --human_ckpt, or human shards as "
                             "model.init_args.source.retrieval_bank")
        if not motion:
            return [{"texts": list(t)} for t in bank["captions"]]
        clips = m.human_bank_motion.cpu().split(list(bank["lengths"]))
        return [{"motion": c, "offsets": o, "texts": list(t)}
                for c, o, t in zip(clips, m.human_bank_offsets.cpu(), bank["captions"])]

    def exclude(self, captions: Iterable[str], key: str) -> tuple[int, int]:
        """Retrieval never draws a clip captioned by one of ``captions`` (an evaluation's prompts: a generation
        must not start from the prompt's own clip); (clips left out, clips left). ``key`` names the evaluation
        in the one-line error when no clip is left."""
        m = self.module
        excluded = frozenset(caption_key(c) for c in captions)
        if m.retrieval_bank is None and not m.human_bank and m.human_spec is None:
            self.excluded = excluded  # a fit builds its bank when it starts
            return 0, 0
        clips = self.clips(motion=False)
        left = sum(not excluded & {caption_key(t) for t in c["texts"]} for c in clips)
        if not left:
            raise UsageError(f"{key}: {self._nothing_left()}")
        self.excluded = excluded
        return len(clips) - left, left

    def _nothing_left(self) -> str:
        where = self.module.retrieval_bank or "the human validation clips kept in the checkpoint"
        return (f"every clip retrieval draws from ({where}) is captioned by one of the prompts; set "
                "model.init_args.source.retrieval_bank to human shards of another split (e.g. the human training set) "
                "or model.init_args.source.human_source to an OMG ControlNet checkpoint")

    def _caption_bank(self) -> dict:
        """The clips retrieval draws from, exclusions applied, and their captions' unit features: built again when
        the clips (``retrieval_bank``, the checkpoint's clip buffer) or the exclusions change."""
        m = self.module
        built_from = (m.retrieval_bank, getattr(m, "human_bank_motion", None), self.excluded)
        if self._bank is not None and all(a is b for a, b in zip(self._bank[0], built_from)):
            return self._bank[1]
        samples = [c for c in self.clips() if not self.excluded & {caption_key(t) for t in c["texts"]}]
        if not samples:
            raise UsageError(self._nothing_left())
        captions = [(i, t) for i, s in enumerate(samples) for t in s["texts"]]
        bank = {"samples": samples, "owner": torch.tensor([i for i, _ in captions]),
                "text": F.normalize(m.sentence([t for _, t in captions]).cpu(), dim=-1)}
        self._bank = (built_from, bank)
        return bank

    def retrieve(self, prompts: Sequence[str], lengths: Tensor, seed: int) -> tuple[Tensor, Tensor]:
        """The human clips whose captions are nearest the prompts (one of the top k distinct clips, drawn with
        ``seed`` by ``retrieval_draw``; never one captioned by an excluded caption), each cut or held at its last
        frame to the prompt's length. The drawn clips' captions are kept in ``retrieved``."""
        m = self.module
        bank = self._caption_bank()
        similarity = F.normalize(m.sentence(prompts).cpu(), dim=-1) @ bank["text"].T  # (B, captions)
        gen = torch.Generator().manual_seed(seed)
        T = int(lengths.max())
        motion = torch.zeros(len(prompts), T, m.human_spec.feature_dim)
        offsets, self.retrieved = [], []
        for b, row in enumerate(similarity):
            order = row.argsort(descending=True)
            seen: list[int] = []
            for c in order.tolist():  # the top k distinct clips
                if (owner := int(bank["owner"][c])) not in seen:
                    seen.append(owner)
                if len(seen) == m.retrieval_top_k:
                    break
            if m.retrieval_draw == "similarity":  # each clip scored by its nearest caption
                best = torch.stack([row[bank["owner"] == owner].max() for owner in seen])
                pick = int(torch.multinomial(torch.softmax(best / m.retrieval_temperature, 0), 1, generator=gen))
            else:
                pick = int(torch.randint(len(seen), (1,), generator=gen))
            sample = bank["samples"][seen[pick]]
            clip = torch.as_tensor(sample["motion"])[:T]
            motion[b, : len(clip)] = clip
            motion[b, len(clip):] = clip[-1]
            offsets.append(torch.as_tensor(sample["offsets"], dtype=torch.float32))
            self.retrieved.append(list(sample["texts"]))
        return motion.to(m.device), torch.stack(offsets).to(m.device)


# the human source of each module, for as long as the module lives
_SOURCES: weakref.WeakKeyDictionary[OmniMotionModule, HumanSource] = weakref.WeakKeyDictionary()


def human_source_of(module: OmniMotionModule) -> HumanSource:
    """``module``'s one ``HumanSource``."""
    if (source := _SOURCES.get(module)) is None:
        source = _SOURCES[module] = HumanSource(module)
    return source


@MODULE_SAMPLERS.register(class_key(OmniMotionModule))
class OmniMotionSampler:
    """An OmniMotionGPT module's ``Sampler``: animal motions for prompts, each translated from a human motion
    (given, or from the module's human source)."""

    text_conditional = True

    def __init__(self, module: OmniMotionModule):
        self.module = module

    @property
    def humans(self) -> HumanSource:
        return human_source_of(self.module)

    @torch.no_grad()
    def sample(self, texts: Sequence[str] | None, lengths: Tensor | Sequence[int],
               settings: SamplingSettings | None = None, *, animal: str | None = None, human: Tensor | None = None,
               human_offsets: Tensor | None = None) -> Tensor:
        """Animal motions for prompts: (B, max(lengths), 216) un-normalised maa.

        The animal is ``animal`` when given, else the one each prompt names (``choose_animal``, the rule of
        ``omg generate``); the human motion is ``human`` (B, T, 138) with ``human_offsets``, or comes from
        the human source (drawn with ``settings.seed``; a human generator samples with the settings' steps,
        sampler and guidance). ``settings.use_ema``: the EMA weights where kept.
        """
        m = self.module
        settings = settings or SamplingSettings()
        if not texts:
            raise UsageError("OmniMotionGPT generates from prompts: give at least one")
        lengths = torch.as_tensor(lengths, device=m.device)
        names = m.animal_names
        if not names:
            raise UsageError("this OmniMotionGPT module knows no animal yet (train it first)")
        chosen = [choose_animal(t, names, animal) for t in texts]
        if human is None:
            human, human_offsets = self.humans.human_motion([to_person(t, names) for t in texts], lengths, settings)
        return m.translate(texts, human, human_offsets, lengths, chosen, use_ema=settings.use_ema)

    def check_sampling(self, settings: SamplingSettings, key: str) -> None:
        """OmniMotionGPT translates a human motion: no stance foot steps its root."""
        if settings.stance_root is not None:
            raise UsageError(f"{key}: {type(self.module).__name__} is not a diffusion model that can step its root "
                             "by the stance foot")


def generate_human(generator: Sampler, prompts: Sequence[str], lengths: Tensor, fps: float,
                   settings: SamplingSettings, progress: StepProgress | None = None) -> tuple[Tensor, Tensor]:
    """OMG's text-to-motion for prompts about "a person" -> smpl22 maa (B, T, 138) and offsets (B, 22, 3)
    at ``fps`` (the OmniMotionGPT model's rate; ``lengths`` count its frames), sampled with the settings'
    steps, sampler, guidance and seed on the weights as loaded.

    ``generator``: an OMG ControlNet module (its ``Sampler``); its features (humanml3d263) are decoded to joint
    positions and turned into rotations by IK. A generator at another rate makes the same durations
    at its own rate, resampled to ``fps`` (linear in time, as the importers resample), so that the
    animal moves at the speed the human did. ``progress`` hears the generator's sampler steps (passed to its
    ``sample`` only when given)."""
    from omg.data.sources.amass import resample

    if generator.spec.skeleton != HUMAN_SKELETON:
        raise UsageError(f"the human generator makes {generator.spec.skeleton} motion; OmniMotionGPT needs "
                         f"{HUMAN_SKELETON}")
    if generator.spec.fps <= 0:
        raise UsageError("the human generator's checkpoint records no frame rate")
    source_fps = generator.spec.fps
    lengths = torch.as_tensor(lengths).cpu()
    source_lengths = [max(2, round((n - 1) * source_fps / fps) + 1) for n in lengths.tolist()]
    watched = {} if progress is None else {"progress": progress}
    features = generator.sample(list(prompts), source_lengths, SamplingSettings(
        steps=settings.steps, sampler=settings.sampler, guidance=settings.guidance, seed=settings.seed, use_ema=False),
        **watched)
    joints = generator.representation.decode(features.float()).cpu().numpy()  # (B, T', 22, 3)
    T = int(lengths.max())
    motion = torch.zeros(len(prompts), T, (get_skeleton(HUMAN_SKELETON).num_joints + 1) * 6)
    offsets = []
    for b, n in enumerate(lengths.tolist()):
        positions = joints[b, : source_lengths[b]]
        if abs(source_fps - fps) > 1e-6:
            positions = resample(positions, source_fps, fps)
        maa, off = maa_from_positions(positions[: max(2, n)], fps)
        maa = torch.from_numpy(maa)[:T]
        motion[b, : len(maa)] = maa
        motion[b, len(maa):] = maa[-1]
        offsets.append(torch.from_numpy(off))
    return motion, torch.stack(offsets)


def read_retrieval_bank(location: str | list, human_spec: DataSpec, max_frames: int) -> list[dict]:
    """The captioned clips of human shards (``retrieval_bank``): ``{"motion" (T, 138) un-normalised, "offsets",
    "texts"}``, cut to ``max_frames``; smpl22 maa at the checkpoint's human rate."""
    from omg.data.datamodule import MotionDataModule

    key = "model.init_args.source.retrieval_bank"
    try:
        data = MotionDataModule(val=location, max_len=max_frames, min_len=2, clips="whole", num_workers=0)
        human_spec.check_compatible(data.spec, "the checkpoint's human data", "its shards")
        samples = [s for s in data.val_clips().samples if s["texts"]]
    except UsageError as e:
        message = str(e)
        raise UsageError(message if message.startswith(key) else f"{key}: {message}") from None
    if not samples:
        raise UsageError(f"{key}: {location} holds no captioned clips to retrieve from")
    return [{"motion": torch.from_numpy(np.asarray(s["motion"], dtype=np.float32)[:max_frames]),
             "offsets": torch.tensor(s["meta"]["offsets"], dtype=torch.float32), "texts": list(s["texts"])}
            for s in samples]
