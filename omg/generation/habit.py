"""Habit transfer's generator: a quadruped source motion moved onto a target species with its habits.

The target's category is the species itself when the model knows it, else the known category whose
description is nearest (``species_condition``); its habit latent is a sample of a flow prior (a
``HabitPriorModule``'s, or the VQ-VAE's own in the default ``flow_prior`` order) or the mean of the
category's posterior; ``HabitVQModule.transfer`` re-encodes and decodes the motion with it.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch

from omg.errors import UsageError
from omg.generation.progress import Batch
from omg.generation.protocol import (
    MAX_SECONDS,
    GeneratedMotion,
    GenerationCard,
    GenerationRequest,
    ModuleGenerator,
    NumberRange,
)
from omg.generation.read import read_quadruped
from omg.generation.registry import register_generator
from omg.lit.habit import HabitPriorModule, HabitVQModule
from omg.text.base import text_encoder_kwargs

QUANTIZERS = ("soft", "nearest")
TEMPERATURE = NumberRange(0.0, None, default=1.0, low_open=True)  # the prior's base Gaussian's scale


@register_generator(HabitVQModule)
@register_generator(HabitPriorModule)
class HabitGenerator(ModuleGenerator):
    """Transfers of a habit checkpoint: a ``HabitVQModule`` (with ``prior``, a ``HabitPriorModule`` fitted on it,
    drawing the habit latents) or a ``HabitPriorModule`` (its VQ-VAE's transfer, latents from its flows)."""

    takes_prior = True

    def __init__(self, module: HabitVQModule | HabitPriorModule, prior: HabitPriorModule | None = None):
        super().__init__(module)
        if isinstance(module, HabitPriorModule):
            prior = module
        self.prior = prior
        self._text_encoder = None

    @property
    def vq(self) -> HabitVQModule:
        """The VQ-VAE that transfers."""
        return self.module.vq if isinstance(self.module, HabitPriorModule) else self.module

    def with_prior(self, prior: HabitPriorModule) -> None:
        """Draw the habit latents from ``prior`` (a ``HabitPriorModule`` fitted on this VQ-VAE's categories)."""
        self.prior = prior

    def to(self, device: Any) -> HabitGenerator:
        super().to(device)
        if self.prior is not None and self.prior is not self.module:
            self.prior = self.prior.to(device).eval()
        return self

    def generation_card(self) -> GenerationCard:
        vq = self.vq
        return GenerationCard(
            family="habit", skeleton=vq.spec.skeleton, representation=vq.spec.representation, fps=vq.spec.fps,
            inputs=("motion", "species"), needs=("motion", "species"), max_frames=round(MAX_SECONDS * vq.spec.fps),
            species=tuple(vq.categories), open_species=True, source_fixes_length=True,
            options={"temperature": "scale of the prior's base Gaussian (with a prior)",
                     "quantizer": "soft or nearest (default: the checkpoint's)",
                     "species_file": "a YAML of extra species descriptions (name: description)"},
            option_ranges={"temperature": TEMPERATURE})

    def option(self, key: str, value: str) -> Any:
        if key == "quantizer":
            if value not in QUANTIZERS:
                raise UsageError(f"--option quantizer={value}: give one of {', '.join(QUANTIZERS)}")
            return value
        if key == "species_file":  # read when a species needs it
            return Path(value)
        return super().option(key, value)  # temperature

    def read_source(self, path: Path, joint_map: str | None = None) -> dict[str, Any]:
        """A quadruped motion file as the model's features: BVH or DeepMimic retargeted onto its skeleton, or a
        ``.npy`` of quatvel features (T, D) or joint positions (T, J, 3) at its frame rate."""
        return read_quadruped(Path(path), self.vq.representation, self.vq.spec.fps, joint_map)

    def text_encoder(self):
        """The sentence encoder the categories were described with (built once)."""
        if self._text_encoder is None:
            from omg.text.base import build_text_encoder

            hp = self.vq.hparams
            self._text_encoder = build_text_encoder(hp.get("text_encoder", "minilm"),
                                                    **text_encoder_kwargs(hp.get("text_encoder_args")))
        return self._text_encoder

    def species_condition(self, to: str, species_file: str | Path | None = None) -> dict[str, Any]:
        """The category whose habits are used for species ``to``: ``to`` itself when known, else the known
        category whose description is nearest ``to``'s (a species of the book, or a description of 3 words or
        more); an unseen species keeps its own description's embedding as the condition (``embedding``: the
        paper swaps only the habit latent)."""
        from omg.text.habit import SpeciesBook, nearest_category, sentence_embeddings, species_key

        vq = self.vq
        if not to or not to.strip():
            raise UsageError("--to is empty: give a species name (e.g. horse) or a description of the animal")
        # a known category in the book's spelling too: "milk cow", "Milk_Cow" and "milk_cow" are AnimalML3D's "milk cow"
        known = {species_key(name): name for name in vq.categories}
        key = species_key(to) if len(to.split()) < 3 else to
        if key in known:
            return {"target": to, "category": known[key], "retrieved": False, "distance": 0.0}
        book = SpeciesBook.load(species_file)
        description = book.describe(to)
        encoder = self.text_encoder()
        known = {name: vq.descriptions.get(name) or book.description(name) for name in vq.categories}
        name, distance = nearest_category(encoder, description, known)
        with torch.no_grad():
            embedding = sentence_embeddings(encoder, [description])[0].cpu()  # as the categories' were embedded
        return {"target": to, "description": description, "category": name, "retrieved": True, "distance": distance,
                "embedding": embedding}

    def habit_prior(self) -> HabitPriorModule | HabitVQModule | None:
        """What draws the habit latents: the prior when there is one, else the VQ-VAE's own flows
        (``flow_prior``), else None (the category's posterior mean)."""
        return self.prior if self.prior is not None else (self.vq if self.vq.flows is not None else None)

    def generate(self, request: GenerationRequest) -> list[GeneratedMotion]:
        """The source motion moved onto ``request.species`` with its habits, ``num_samples`` times with seeds
        ``seed`` + k: the habit latent is a sample of the category's flow (``habit_prior``), else the mean of the
        category's posterior; the model's rotations and root come out as they are."""
        vq, prior = self.vq, self.habit_prior()
        source, options = request.source, request.options
        condition = self.species_condition(request.species, options.get("species_file"))
        k = vq.categories.index(condition["category"])
        features = torch.from_numpy(source["features"])[None]
        start = torch.from_numpy(source["root_start"])
        rep, offsets = vq.representation, vq.category_offsets(k)
        source_joints = rep.decode(features[0], torch.from_numpy(source["offsets"]), start).numpy()
        how = (f"{condition['category']}'s habits (nearest known, distance {condition['distance']:.3f})"
               if condition["retrieved"] else f"{condition['category']}'s habits")
        motions = []
        for repeat in range(request.num_samples):
            watch = Batch(request.progress, repeat, 1, request.num_samples)  # one motion a batch, no sampler steps
            seed = request.seed + repeat
            torch.manual_seed(seed)
            if prior is not None:
                z = prior.habit_latents(k, 1, seed=seed, temperature=options.get("temperature", TEMPERATURE.default))
            else:
                z = vq.mean_habit(k)[None]
            result = vq.transfer(features, k, z, seed=seed, quantizer=options.get("quantizer"),
                                 text=condition.get("embedding"))[0].float().cpu()
            joints = rep.decode(result, offsets.cpu(), start).numpy().astype(np.float32)
            rotations, root = rep.rotations_and_root(result, start)
            motions.append(GeneratedMotion(
                features=result.numpy(), joints=joints, title=f"{request.species}: {how}",
                rotations=(rotations.numpy(), root.numpy(), offsets.cpu().numpy()),
                companions=[("source", source_joints.astype(np.float32), vq.spec.skeleton,
                             f"source: {source['name']}")],
                record={"repeat": repeat, "seed": seed}))
            watch.finish()
        return motions

    def generation_settings(self, request: GenerationRequest) -> dict[str, Any]:
        vq, prior = self.vq, self.habit_prior()
        condition = self.species_condition(request.species, request.options.get("species_file"))
        k = vq.categories.index(condition["category"])
        return {
            "source_category": request.source["category"], "to": request.species, "category": condition["category"],
            "retrieved": condition["retrieved"], "distance": condition["distance"],
            "description": condition.get("description"),
            "condition": "its own description" if condition["retrieved"] else f"{condition['category']}'s description",
            "habit": "prior sample" if prior is not None else "posterior mean", "habit_order": vq.habit_order,
            "temperature": request.options.get("temperature", TEMPERATURE.default),
            "quantizer": request.options.get("quantizer") or vq.vqvae.quantizer.mode,
            "frames": len(request.source["features"]), "target_offsets": vq.category_offsets(k).tolist()}
