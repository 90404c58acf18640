"""OmniMotionGPT: joint human + animal motion autoencoders aligned through text space.

Trained end to end on two streams at once (losses §3.1-3.2, implementation details §5): the animal
set is the run's ``data:``, the human set ``data.human`` (``omg.data.paired.PairedDataModule``: each
training batch is ``{"animal": ..., "human": ...}``).
Per domain d (§3.1):

    L_ae^d = L_jrec (‖P − D(E(P, S), S)‖²) + w_clip · (1 − cos(E_t(Z), C)) + w_trec · ‖P − D(D_t(C, Z), S)‖²

and across domains (§3.2), with the human caption's subject replaced by the paired animal's species (C̃^a):

    L_cross = w_cons · ‖Z^h − E^a(D^a(D_t^a(C̃^a, Z^h), S^a), S^a)‖² + w_cross_clip · (1 − cos(E_t^a(Z^h), C̃^a))
              + w_ee · ‖V^h − Ṽ^a‖²   (end-effector velocities by forward kinematics on both skeletons)

plus w_translation · the root-translation error of the joint and the text paths (Appendix C). The feature
errors are in the autoencoders' own units (``standardize``: each maa number divided by its std over
the training data; with ``config.root_velocity`` the root's ground position as per-frame
displacement in m/s), the latent and velocity errors as they come. Inference (``translate``): a human
motion -> E^h -> Z^h; D_t^a(C̃, Z^h) -> D^a with the chosen animal's offsets. Where the human motion comes
from when none is given (``human_source``: retrieval or an OMG ControlNet) and the ``Sampler`` the
evaluation calls are ``omg.lit.human_source``'s.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
import torch
from torch import Tensor

from omg.data.omgpt import check_maa, check_same_stats
from omg.data.paired import CompanionData
from omg.errors import UsageError
from omg.lit.base import OmgModule, OptimSettings, check_weights, modes_restored
from omg.losses import cosine_gap, masked_mse
from omg.models.omgpt import OmniMotionConfig, OmniMotionGPT, OmniMotionOverrides, end_effector_velocity
from omg.motion import DataSpec, get_representation, length_mask
from omg.motion.maa import root_translation
from omg.settings import check_range, set_fields
from omg.skeleton import get_skeleton
from omg.text import TextEncoderArgs, build_text_encoder, text_encoder_kwargs
from omg.text.omgpt import about_animal, to_animal

HUMAN_SKELETON, ANIMAL_SKELETON = "smpl22", "smal35"


@dataclass(frozen=True)
class OmniMotionOptimSettings(OptimSettings):
    """``OptimSettings`` with the ``schedule``: ``constant`` (the paper's Adam at ``lr``, it names no schedule) or
    ``cosine`` (omg's: AdamW, warm-up over ``warmup_steps`` and cosine decay)."""

    schedule: str = "constant"

    def __post_init__(self) -> None:
        super().__post_init__()
        check_range("model.optim.schedule", self.schedule, self.schedule in ("constant", "cosine"),
                    "constant or cosine")


@dataclass(frozen=True)
class OmniMotionLossWeights:
    """OmniMotionGPT's loss weights: per domain ``jrec_weight``, ``clip_weight``, ``trec_weight`` (paper: 1, 1, 1),
    across domains ``cons_weight``, ``cross_clip_weight``, ``ee_weight`` (paper: 0.1, 1, 100) and the global
    translation's ``translation_weight`` (paper: 1, Appendix C)."""

    jrec_weight: float = 1.0
    clip_weight: float = 1.0
    trec_weight: float = 1.0
    cons_weight: float = 0.1
    cross_clip_weight: float = 1.0
    ee_weight: float = 100.0
    translation_weight: float = 1.0

    def __post_init__(self) -> None:
        check_weights(self)


@dataclass(frozen=True)
class HumanSourceSettings:
    """Where sampling takes human motion when none is given (``omg.lit.human_source.HumanSource``).

    ``human_source``: ``retrieval`` (a human clip whose caption is near the prompt made about "a person", drawn
    among the ``retrieval_top_k`` nearest clips with the sampling seed) or an OMG ControlNet checkpoint (omg's own
    text-to-motion, from the prompt made about "a person"; the paper's tables start from human motion "sampled
    from generative models", Fig. 2c, and configs/omgpt_eval.yaml names one). ``retrieval_draw``: ``uniform``
    (each of the top k equally likely: with k = 3, repeated generations of a prompt come from 3 human clips at
    most) or ``similarity`` (clip i with probability softmax(similarity_i / ``retrieval_temperature``), so a
    large k lets repeated generations differ while near captions stay likelier); the defaults are the evaluation
    protocol's, 32 clips by similarity at 0.1. The paper generates human motion with a text-to-motion model;
    retrieval is omg's stand-in. ``retrieval_bank``: human shards (smpl22 maa, captioned) that retrieval draws
    from instead of the validation clips kept in the checkpoint: an evaluation's bank must not be the split
    whose captions are its prompts (``OODEvalCallback`` also drops every clip captioned by a prompt,
    ``omg.lit.human_source.HumanSource.exclude``). ``human_source`` and ``retrieval_bank`` name files, so a
    checkpoint's are never used (``OmniMotionModule.location_hparams``): a loaded checkpoint retrieves from its
    own clips unless the config (or ``--human_ckpt``) names another source."""

    human_source: str = "retrieval"
    retrieval_top_k: int = 32
    retrieval_draw: str = "similarity"
    retrieval_temperature: float = 0.1
    retrieval_bank: str | list | None = None

    def __post_init__(self) -> None:
        check_range("model.source.retrieval_top_k", self.retrieval_top_k,
                    isinstance(self.retrieval_top_k, int) and self.retrieval_top_k >= 1, "an integer >= 1")
        check_range("model.source.retrieval_draw", self.retrieval_draw,
                    self.retrieval_draw in ("uniform", "similarity"), "uniform or similarity")
        check_range("model.source.retrieval_temperature", self.retrieval_temperature,
                    0 < self.retrieval_temperature < math.inf, "a finite number > 0")


class OmniMotionModule(OmgModule):
    """OmniMotionGPT's two autoencoders, text heads and losses.

    Args:
        human_data: the older name of ``data.human`` (the human shards, smpl22 maa): ``omg fit`` reads it as
            that key, with a warning; the module itself reads no data.
        flavor, config: network sizes, a preset (``paper``, ``mini``) and field overrides
            (``omg.models.omgpt.OmniMotionConfig``; ``OmniMotionOverrides``).
        text_encoder, text_encoder_args: the registered sentence encoder (paper: CLIP ViT-L/14).
        text_feature: the sentence feature C of L_CLIP, cross L_CLIP, D_t and the self-evaluation:
            ``projected`` (the paper's "CLIP feature": CLIP's ``encode_text``, the EOT token projected
            into the joint image-text space) or ``eot`` (the EOT token before that projection, what
            omg used before). Encoders without a projection of their own (MiniLM, hash) give the EOT
            feature either way.
        optim: Adam's lr, betas, weight_decay (paper: 1e-4, (0.9, 0.999), 0); ``schedule``: ``constant``
            (the paper names no schedule) or ``cosine`` (omg's warm-up over ``warmup_steps`` + cosine)
            (``OmniMotionOptimSettings``).
        ema_decay: weight EMA (paper: 0.99); 0 disables it.
        loss: the per-domain loss weights jrec_weight, clip_weight, trec_weight (paper: 1.0, 1.0, 1.0), the
            cross-domain cons_weight, cross_clip_weight, ee_weight (paper: 0.1, 1.0, 100) and the
            global-translation translation_weight (paper: 1.0, Appendix C) (``OmniMotionLossWeights``).
        standardize: the autoencoders read and write features standardised by the training data's
            per-dimension mean and std (floored at ``std_floor``), and the reconstruction losses
            compare standardised features; without it (``false``) both see raw maa, where the many
            near-constant 6D numbers let a network that outputs the mean pose reach a small loss.
            Not in the paper (raw maa: ``false``, the default, configs/omgpt.yaml); omg's variant
            (configs/omgpt_variant.yaml, configs/mini/omgpt.yaml) turns it on. It moves the balance
            the paper's weights were set for: reconstruction is then in std units while L_ee
            (end-effector velocity, x100) and the translation loss stay in metres per frame.
        source: where sampling takes human motion when none is given: ``human_source`` (``retrieval`` or an
            OMG ControlNet checkpoint), how retrieval draws (``retrieval_top_k``, ``retrieval_draw``,
            ``retrieval_temperature``) and from which shards (``retrieval_bank``) (``HumanSourceSettings``).
        spec: the animal data's spec (``omg fit`` links it from ``data``).

    Fit-time state, filled from the data when training starts and kept in checkpoints beside the
    weights (``checkpoint["fit_state"]``; checkpoints written before kept it in their
    hyper-parameters, which still load): ``animals`` (each animal category's mean bone offsets,
    scanned by ``PairedDataModule.category_offsets``: what ``--animal`` accepts), ``human_spec`` (the
    human data's spec) and ``human_bank`` (the captions and frame counts of the captioned human
    validation clips that retrieval draws from, whatever ``human_source``; their motion and offsets
    are the buffers ``human_bank_motion`` and ``human_bank_offsets``, so that a checkpoint retrieves
    without its human shards).

    A checkpoint is self-contained: everything inference needs (both specs, the animals' offsets,
    the retrieval clips) is inside it, and what its ``human_data``, ``source.human_source`` and
    ``source.retrieval_bank`` name (locations, ``location_hparams``) is never opened when it loads.
    """

    clip_sampling = "whole"  # a caption describes its whole clip
    frozen_prefixes = ("text_encoder.",)
    location_hparams = ("human_data", "source.human_source", "source.retrieval_bank")
    # what the weights were trained with or on; the human source, loss and optimizer settings are the run's
    architecture_hparams = ("flavor", "config", "text_encoder", "text_feature", "standardize", "std_floor", "spec")
    fit_state_keys = ("animals", "human_spec", "human_bank")  # checkpoint["fit_state"]; older: hyper-parameters
    settings_groups = {"config": OmniMotionOverrides, "text_encoder_args": TextEncoderArgs,
                       "human_data": CompanionData}

    def __init__(
        self,
        human_data: CompanionData | None = CompanionData(),
        flavor: str = "paper",
        config: OmniMotionOverrides | None = OmniMotionOverrides(),
        text_encoder: str = "clip-vit-l-14",
        text_encoder_args: TextEncoderArgs | None = TextEncoderArgs(),
        text_feature: str = "projected",
        optim: OmniMotionOptimSettings = OmniMotionOptimSettings(lr=1e-4),
        ema_decay: float = 0.99,
        loss: OmniMotionLossWeights = OmniMotionLossWeights(),
        standardize: bool = False,
        std_floor: float = 0.05,
        source: HumanSourceSettings = HumanSourceSettings(),
        spec: DataSpec | dict | None = None,
    ):
        super().__init__()
        self.optim, self.loss = self.value_group("optim", optim), self.value_group("loss", loss)
        if not 0 <= ema_decay < 1:
            raise UsageError(f"model.ema_decay must be in [0, 1) (0: no EMA), got {ema_decay!r}")
        source = self.value_group("source", source)
        # the module's own attributes, which ``HumanSource`` reads at each draw (an evaluation may set them)
        self.human_source, self.retrieval_bank = source.human_source, source.retrieval_bank or None
        self.retrieval_top_k, self.retrieval_draw = source.retrieval_top_k, source.retrieval_draw
        self.retrieval_temperature = source.retrieval_temperature
        if text_feature not in ("projected", "eot"):
            raise UsageError(f"model.text_feature must be projected or eot, got {text_feature!r}")
        self.text_feature = text_feature
        set_fields(CompanionData, human_data, "model.init_args.human_data")  # a bad key: one line, as data.human's
        if spec is None:
            raise UsageError("OmniMotionModule needs the animal data's spec (set data.train to smal35 maa shards)")
        self.spec = DataSpec.coerce(spec, "the data")
        check_maa(self.spec, "data", ANIMAL_SKELETON)
        self.save_hyperparameters()
        self.ema_decay = ema_decay
        self.weights = {name.removesuffix("_weight"): value for name, value in asdict(self.loss).items()}
        # fit-time state (fit_state_keys): the data's when training starts, else a checkpoint's
        self.animals: dict[str, Tensor] = {}
        self.animal_table: dict[str, list] | None = None  # the same offsets as found (kept as they were saved)
        self.human_spec: DataSpec | None = None
        self.human_bank: dict[str, list] | None = None
        self.text_encoder = build_text_encoder(text_encoder, **text_encoder_kwargs(text_encoder_args))
        self.config = OmniMotionConfig.from_name(flavor, **set_fields(OmniMotionOverrides, config,
                                                                      "model.init_args.config"))
        # every field, resolved: a checkpoint keeps meaning what it meant when a later version changes a default
        self.hparams["config"] = {k: v for k, v in asdict(self.config).items() if k != "name"}
        self.human_rep = get_representation("maa", get_skeleton(HUMAN_SKELETON))
        self.representation = get_representation("maa", get_skeleton(ANIMAL_SKELETON))  # what the module generates
        self.model = OmniMotionGPT(self.human_rep.skeleton, self.representation.skeleton, self.config,
                                   self.text_encoder.dim)
        if std_floor <= 0:
            raise UsageError(f"model.std_floor must be > 0, got {std_floor}")
        self.standardize, self.std_floor = standardize, std_floor
        human_dim = (self.human_rep.skeleton.num_joints + 1) * 6  # maa; its values come with human_spec
        self.register_buffer("human_mean", torch.zeros(human_dim), persistent=False)
        self.register_buffer("human_std", torch.ones(human_dim), persistent=False)
        self.register_buffer("animal_mean", torch.zeros(self.spec.feature_dim), persistent=False)
        self.register_buffer("animal_std", torch.ones(self.spec.feature_dim), persistent=False)
        self._use_stats("animal", self.spec)

    def _use_stats(self, prefix: str, spec: DataSpec) -> None:
        """Normalise the ``prefix`` (human, animal) domain by ``spec``'s mean and std."""
        mean, std = torch.tensor(spec.mean, dtype=torch.float32), torch.tensor(spec.std, dtype=torch.float32)
        getattr(self, f"{prefix}_mean").copy_(mean)
        getattr(self, f"{prefix}_std").copy_(std)
        # the autoencoders' inputs and outputs, and the reconstruction errors, are in these units;
        # ground displacement (config.root_velocity) in metres per second
        scale = std.clamp_min(self.std_floor) if self.standardize else torch.ones_like(std)
        getattr(self.model, prefix)["ae"].standardize(mean if self.standardize else torch.zeros_like(mean), scale,
                                                      1.0 / spec.fps if self.standardize and spec.fps > 0 else None)

    def use_human_spec(self, spec: DataSpec | dict) -> None:
        """The human data's spec (the data's when training starts, else the checkpoint's)."""
        self.human_spec = DataSpec.coerce(spec, "data.human")
        check_maa(self.human_spec, "data.human", HUMAN_SKELETON)
        self._use_stats("human", self.human_spec)

    # -- helpers -------------------------------------------------------------------------
    def trainable_module(self) -> torch.nn.Module:
        return self.model

    def sentence(self, texts: Sequence[str]) -> Tensor:
        """(B, D_text) sentence features C (``text_feature``: CLIP's projected embedding or the EOT token), frozen."""
        with torch.no_grad():
            features = self.text_encoder(list(texts)).to(self.device)
            if self.text_feature == "projected":
                return self.text_encoder.sentence_embedding(features).float()
            return features.eot_embedding().float()

    def raw(self, batch: dict, domain: str) -> Tensor:
        """The batch's maa features un-normalised (the model reads and writes raw maa), zero at padding."""
        mean, std = getattr(self, f"{domain}_mean"), getattr(self, f"{domain}_std")
        return (batch["motion"] * std + mean) * batch["mask"][..., None]

    @property
    def animal_names(self) -> list[str]:
        return sorted(self.animals)

    def animal_offsets(self, name: str) -> Tensor:
        if name not in self.animals:
            known = ", ".join(self.animal_names) or "none (train the model first)"
            raise UsageError(f"unknown animal {name!r}; this checkpoint knows: {known}")
        return self.animals[name].to(self.device)

    # -- losses --------------------------------------------------------------------------
    def domain_losses(self, domain: str, motion: Tensor, offsets: Tensor, mask: Tensor, text: Tensor,
                      captioned: Tensor) -> tuple[dict[str, Tensor], Tensor, Tensor]:
        """L_ae of one domain: ({jrec, clip, trec, translation}, Z, Z's mask)."""
        parts = getattr(self.model, domain)
        z, z_mask = parts["ae"].encode(motion, offsets, mask)  # (B, L, 7, C)
        rec = parts["ae"].decode(z, offsets, mask)  # joint path F_o
        rec_text = parts["ae"].decode(parts["text_decoder"](text, z, z_mask), offsets, mask)  # text path F_text
        rows = mask & captioned[:, None]
        internal = parts["ae"].normalize  # errors in the autoencoder's own (standardised) units
        target = internal(motion, mask)
        losses = {
            "jrec": masked_mse(internal(rec, mask), target, mask),
            "clip": cosine_gap(parts["text_encoder"](z, z_mask), text, captioned),
            "trec": masked_mse(internal(rec_text, mask), target, rows),
            "translation": masked_mse(root_translation(rec), root_translation(motion), mask)
            + masked_mse(root_translation(rec_text), root_translation(motion), rows),
        }
        return losses, z, z_mask

    def losses(self, animal_batch: dict, human_batch: dict) -> dict[str, Tensor]:
        out: dict[str, Tensor] = {}
        total = 0.0
        streams = {}
        for domain, batch in (("human", human_batch), ("animal", animal_batch)):
            motion, mask = self.raw(batch, domain), batch["mask"]
            captioned = torch.tensor([bool(t) for t in batch["text"]], device=self.device)
            text = self.sentence(batch["text"])
            parts, z, z_mask = self.domain_losses(domain, motion, batch["offsets"], mask, text, captioned)
            total = total + sum(self.weights[k] * v for k, v in parts.items())
            out |= {f"{domain}/{k}": v for k, v in parts.items()}
            streams[domain] = (motion, mask, z, z_mask)
        # cross-domain: human i is paired with animal i mod B_a (its category and offsets)
        motion_h, mask_h, z_h, z_mask_h = streams["human"]
        pair = torch.arange(len(motion_h), device=self.device) % len(animal_batch["text"])
        names = [animal_batch["category"][i] or "animal" for i in pair.tolist()]
        offsets_a = animal_batch["offsets"][pair]
        captioned = torch.tensor([bool(t) for t in human_batch["text"]], device=self.device)
        text_cross = self.sentence([to_animal(t, n) if t else "" for t, n in zip(human_batch["text"], names)])
        animal = self.model.animal
        z_tilde = animal["text_decoder"](text_cross, z_h, z_mask_h)
        motion_a = animal["ae"].decode(z_tilde, offsets_a, mask_h)  # P̃^a
        z_back, _ = animal["ae"].encode(motion_a, offsets_a, mask_h)
        moving = mask_h[:, 1:] & mask_h[:, :-1]
        cross = {
            "cons": masked_mse(z_back, z_h, z_mask_h),
            "cross_clip": cosine_gap(animal["text_encoder"](z_h, z_mask_h), text_cross, captioned),
            "ee": masked_mse(end_effector_velocity(self.representation, motion_a, offsets_a),
                             end_effector_velocity(self.human_rep, motion_h, human_batch["offsets"]), moving),
        }
        total = total + sum(self.weights[k] * v for k, v in cross.items())
        out |= {f"cross/{k}": v for k, v in cross.items()}
        return {"loss": total, **out}

    # -- the retrieval clips ------------------------------------------------------------
    def _register_bank(self, motion: Tensor, offsets: Tensor) -> None:
        """The retrieval clips as buffers (saved with the weights): motion (sum of lengths, D) un-normalised,
        one after another, and offsets (clips, J, 3)."""
        self.register_buffer("human_bank_motion", motion.float())
        self.register_buffer("human_bank_offsets", offsets.float())

    def load_state_dict(self, state_dict, strict: bool = True, assign: bool = False):
        # a module built without the clips (a resumed run in Python) takes them from the checkpoint
        if "human_bank_motion" in state_dict and getattr(self, "human_bank_motion", None) is None:
            self._register_bank(torch.zeros_like(state_dict["human_bank_motion"]),
                                torch.zeros_like(state_dict["human_bank_offsets"]))
        return super().load_state_dict(state_dict, strict=strict, assign=assign)

    def build_bank(self, samples: Sequence[dict]) -> None:
        """Keep the captioned ones of the human validation clips (``data.human.val``) for retrieval."""
        samples = [s for s in samples if s["texts"]]
        if not samples:
            return
        self._register_bank(torch.cat([torch.from_numpy(np.asarray(s["motion"])) for s in samples]).to(self.device),
                            torch.stack([torch.tensor(s["meta"]["offsets"]) for s in samples]).to(self.device))
        self.human_bank = {"captions": [list(s["texts"]) for s in samples],
                           "lengths": [len(s["motion"]) for s in samples]}

    # -- training ------------------------------------------------------------------------
    def check_data(self, data: Any) -> None:
        """UsageError unless ``data`` (the run's data module) holds the human set beside the animal one."""
        if getattr(data, "human", None) is None:
            raise UsageError("OmniMotionGPT trains on two shard sets: set data.human to the human shards (train, val, "
                             "batch_size, ...), smpl22 in the maa representation (older configs: "
                             "model.init_args.human_data)")
        check_maa(DataSpec.coerce(data.human.spec, "data.human"), "data.human", HUMAN_SKELETON)

    def on_fit_start(self) -> None:
        data = self.trainer.datamodule
        self.check_data(data)
        if self.human_spec is None:
            self.use_human_spec(data.human.spec)
        else:  # a resumed run's human_spec is its checkpoint's
            check_same_stats(data.human.spec, self.human_spec)
        if getattr(self, "human_bank_motion", None) is None:
            self.build_bank(data.human_val_samples())
        if not self.animals:
            self.animal_table = data.category_offsets()
            self.animals = {k: torch.tensor(v) for k, v in self.animal_table.items()}
        super().on_fit_start()  # the weight EMA

    def training_losses(self, batch: dict) -> dict[str, Tensor]:
        """``batch``: ``{"animal": ..., "human": ...}`` (``PairedDataModule``'s combined loader)."""
        return self.losses(batch["animal"], batch["human"])

    def log_training(self, losses: dict[str, Tensor], batch: dict) -> None:
        size = len(batch["animal"]["text"])
        if self.logs_terms():
            self.log_dict({f"train/{k}": v for k, v in losses.items()}, prog_bar=False, batch_size=size)
        self.log("train/loss_total", losses["loss"], prog_bar=True, batch_size=size)

    def validation_step(self, batch: dict, batch_idx: int, stage: str = "val") -> None:
        """The animal autoencoder's reconstruction errors on the validation clips."""
        motion, mask = self.raw(batch, "animal"), batch["mask"]
        captioned = torch.tensor([bool(t) for t in batch["text"]], device=self.device)
        parts, _, _ = self.domain_losses("animal", motion, batch["offsets"], mask, self.sentence(batch["text"]),
                                         captioned)
        self.log_dict({f"{stage}/{k}": v for k, v in parts.items()}, batch_size=len(batch["text"]), sync_dist=True)

    def test_step(self, batch: dict, batch_idx: int) -> None:
        self.validation_step(batch, batch_idx, stage="test")

    def make_optimizer(self, groups: list[dict]) -> torch.optim.Optimizer:
        optim = self.optim
        if optim.schedule == "cosine":  # omg's variant: AdamW, warm-up and cosine decay
            return super().make_optimizer(groups)
        return torch.optim.Adam(groups, lr=optim.lr, betas=tuple(optim.betas), weight_decay=optim.weight_decay,
                                foreach=True)  # as OmgModule.make_optimizer's

    def lr_factor(self, total_steps: int):
        return super().lr_factor(total_steps) if self.optim.schedule == "cosine" else None  # the paper: constant

    def fit_state(self) -> dict[str, Any]:
        """The fit-time state as plain types (``checkpoint["fit_state"]``)."""
        return {"animals": self.animal_table,
                "human_spec": self.human_spec.to_dict() if self.human_spec is not None else None,
                "human_bank": self.human_bank}

    def restore_fit_state(self, checkpoint: dict) -> None:
        """The fit-time state of ``checkpoint``: its ``fit_state``, or the hyper-parameters that held it
        before; the retrieval clips' buffers shaped for the weights that come next."""
        state = checkpoint.get("fit_state") or checkpoint.get("hyper_parameters") or {}
        if animals := state.get("animals"):
            self.animal_table = animals
            self.animals = {k: torch.tensor(v, dtype=torch.float32) for k, v in animals.items()}
        if (spec := state.get("human_spec")) is not None:
            self.use_human_spec(spec)
        if bank := state.get("human_bank"):
            self.human_bank = bank
            if getattr(self, "human_bank_motion", None) is None:  # shapes only: the clips come with the weights
                self._register_bank(torch.zeros(sum(bank["lengths"]), self.human_spec.feature_dim),
                                    torch.zeros(len(bank["lengths"]), self.human_rep.skeleton.num_joints, 3))

    @classmethod
    def checkpoint_hparams(cls, hparams: dict[str, Any], state: dict[str, Tensor]) -> dict[str, Any]:
        """A checkpoint's hyper-parameters as this class reads them: one written before ``fit_state`` holds the
        fit-time state there (``restore_fit_state`` reads it from the checkpoint), and its optimizer settings and
        loss weights flat (``OmgModule.checkpoint_hparams``)."""
        hparams = super().checkpoint_hparams(hparams, state)
        return {k: v for k, v in hparams.items() if k not in cls.fit_state_keys}

    def on_save_checkpoint(self, checkpoint: dict) -> None:
        super().on_save_checkpoint(checkpoint)
        checkpoint["fit_state"] = self.fit_state()

    def on_load_checkpoint(self, checkpoint: dict) -> None:
        super().on_load_checkpoint(checkpoint)
        self.restore_fit_state(checkpoint)
        # a run written before the human stream was the data's kept its position beside the loops': it joins
        # the animal loader's there, as the paired data module's combined loader restores them
        if (human := checkpoint.pop("human_stream", None)) is not None:
            loaders = checkpoint.get("loops", {}).get("fit_loop", {}).get("state_dict", {}).get("combined_loader")
            if loaders is not None and len(loaders) == 1:
                loaders.append(human)

    # -- inference -----------------------------------------------------------------------
    @torch.no_grad()
    def translate(self, texts: Sequence[str], human: Tensor, human_offsets: Tensor, lengths: Tensor | Sequence[int],
                  animals: Sequence[str], use_ema: bool = True) -> Tensor:
        """Human maa (B, T, 138) un-normalised + offsets (B, 22, 3), prompts about the animals and
        the animal names (B) -> animal maa (B, T, 216) un-normalised, on each animal's mean offsets; each
        prompt is made about its animal ("a dog jumps" for the cat: "a cat jumps")."""
        mask = length_mask(lengths, human.shape[1], device=self.device)
        prompts = [about_animal(t, a, self.animal_names) for t, a in zip(texts, animals)]
        offsets = torch.stack([self.animal_offsets(a) for a in animals])
        with modes_restored(self), self.ema_weights(use_ema):
            self.eval()
            return self.model.translate(human.to(self.device).float() * mask[..., None], human_offsets.to(self.device),
                                        mask, self.sentence(prompts), offsets)
