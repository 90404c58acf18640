"""Habit transfer training: the category-conditioned VQ-VAE (``HabitVQModule``) and the per-category
flow priors of the habit latent, on ``quatvel`` shards whose clips carry their species as
``category``, in one of two orders (``HabitVQModule.habit_order``):

- ``flow_prior`` (default, the paper's order, "Behave Your Motion" Sec. 3: each category's habit
  encoder is pretrained under its flow prior, and the VQ-VAE is trained on the pretrained
  encoders). One ``omg fit`` in two phases: for the first ``habit_fraction`` of the steps the
  encoders and flows train together, the posterior q(z | m) regularised by its category's flow
  (``flow_weight`` · KL(q || p_flow), estimated with a posterior sample: log q(z | m) − log p_flow(z),
  whose gradient on the flow is the NLL of the posterior under it) while the latent alone must
  tell the crop's habit statistics (each local joint rotation's mean and spread over time: the reconstruction
  that keeps the latent informative, omg's own phase-1 design); then the
  encoders and flows are frozen and the VQ-VAE trains with no KL term. The checkpoint holds the
  flows: ``omg transfer`` and ``omg generate`` draw the habit latent from them, no stage 2.
- ``kl_then_flows`` (omg's earlier order, a named option): the encoders train inside the VQ-VAE
  with ``kl_weight`` · KL(q(z | m) || N(0, I)) from the first step, and ``HabitPriorModule`` fits
  each category's flow afterwards to the frozen posterior by NLL (stage 2).

VQ-VAE loss (the paper's): smooth L1 on the normalised motion + α · smooth L1 on its velocity
channels + β · commitment (the embedding term is the codebook's EMA update). Transfer
(``HabitVQModule.transfer``, ``omg transfer``): encode the source motion with the target category's
habit latent (a sample of its prior) and text embedding, quantize, decode with the target's condition.
"""

from __future__ import annotations

import contextlib
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from torch import Tensor
from torch.nn import functional as F

from omg.errors import UsageError
from omg.lit.base import OmgModule, OptimSettings, check_weights
from omg.losses import masked_smooth_l1
from omg.models.habit import (
    CategoryFlows,
    CategoryHabitEncoders,
    HabitConfig,
    HabitOverrides,
    HabitStatsDecoder,
    MotionVQVAE,
    Quantizer,
    flow_prior_kl,
    gaussian_kl,
    habit_statistics,
    posterior_sample,
)
from omg.motion import DataSpec, get_representation
from omg.settings import arguments, check_range, set_fields, settings, settings_dict
from omg.skeleton import get_skeleton
from omg.text.base import TextEncoderArgs, text_encoder_kwargs

HABIT_ORDERS = ("flow_prior", "kl_then_flows")


def step_lr(lr: float, lr_after: float, switch_fraction: float):
    """LR multiplier: ``lr`` until ``switch_fraction`` of the run, then ``lr_after`` (the paper: 2e-4, then 1e-5
    for the second half)."""

    def schedule(total_steps: int):
        switch = int(switch_fraction * total_steps)
        return lambda step: 1.0 if step < switch else lr_after / lr

    return schedule


@dataclass(frozen=True)
class StepOptimSettings(OptimSettings):
    """``OptimSettings`` of the paper's step schedule (``HabitVQModule.lr_factor``): ``lr`` until ``lr_switch``
    of the VQ-VAE's steps, then ``lr_after``."""

    lr_after: float = 1e-5
    lr_switch: float = 0.5

    def __post_init__(self) -> None:
        super().__post_init__()
        check_range("model.optim.lr_after", self.lr_after, self.lr_after > 0, "> 0")
        check_range("model.optim.lr_switch", self.lr_switch, 0 <= self.lr_switch <= 1, "in [0, 1]")


@dataclass(frozen=True)
class HabitLossWeights:
    """The habit model's loss weights: ``alpha`` of the velocity reconstruction term (paper: 0.5), ``beta`` of
    the commitment (paper: 0.02), ``kl_weight`` of KL(q(z | m) || N(0, I)) on the habit posterior
    (``kl_then_flows`` only), ``flow_weight`` of KL(q(z | m) || p_flow(z)) per latent dimension in the habit
    pretraining (``flow_prior``)."""

    alpha: float = 0.5
    beta: float = 0.02
    kl_weight: float = 1e-3
    flow_weight: float = 0.01

    def __post_init__(self) -> None:
        check_weights(self)


@dataclass(frozen=True)
class HabitOrderSettings:
    """In which order the habit encoders, their flow priors and the VQ-VAE train (``HabitVQModule``):
    ``habit_order`` ``flow_prior`` (the paper's: the first ``habit_fraction`` of the run's steps pretrains the
    encoders under their flows) or ``kl_then_flows`` (omg's earlier order: KL to N(0, I), the flows fitted after by
    ``HabitPriorModule``)."""

    habit_order: str = "flow_prior"
    habit_fraction: float = 0.2

    def __post_init__(self) -> None:
        if self.habit_order not in HABIT_ORDERS:
            raise UsageError(f"model.order.habit_order must be one of {', '.join(HABIT_ORDERS)} (flow_prior: the "
                             "paper's encoders pretrained under their flows; kl_then_flows: KL to N(0, I), flows "
                             f"fitted after), got {self.habit_order!r}")
        if not 0 < self.habit_fraction < 1:
            raise UsageError("model.order.habit_fraction must be in (0, 1) (the share of the run that pretrains the "
                             f"habit encoders), got {self.habit_fraction}")


@dataclass(frozen=True)
class CodebookSettings:
    """How the VQ-VAE's codebook assigns and keeps its codes (``omg.models.habit.Quantizer``, which checks them):
    ``quantizer`` ``soft`` (an index sampled from the softmax over squared distances at ``temperature``, the
    paper's) or ``nearest``; ``code_reset``: dead codes restart at encoder outputs ("EMA-reset", the paper's best
    row), False: "EMA"; ``ema_decay``: the decay of the codebook's moving averages. Its size and width are the
    architecture's (``habit.num_codes``, ``habit.code_dim``), the commitment weight a loss weight
    (``loss.beta``)."""

    quantizer: str = "soft"
    temperature: float = 1.0
    code_reset: bool = True
    ema_decay: float = 0.99


@dataclass(frozen=True)
class SpeciesText:
    """The categories' text condition: ``species_file``, a YAML of extra or overriding species descriptions
    (``omg.text.habit``), read when the module is first built; ``descriptions`` and ``category_embeddings`` (their
    sentence embeddings), filled in then and kept in the checkpoint, so that no text file or encoder is needed to
    transfer to a known category. Never written by hand but ``species_file``."""

    species_file: str | None = None
    descriptions: dict[str, str] | None = None
    # a plain list: jsonargparse checks each number of a list[list[float]], and a checkpoint's 7 x 384 took
    # minutes to parse under `omg test --ckpt_path`
    category_embeddings: list | None = None


class HabitVQModule(OmgModule):
    """The motion VQ-VAE conditioned on each category's habit latent and text embedding; in the default
    ``habit_order`` it first pretrains the per-category habit encoders under their flow priors.

    Args:
        categories: the known categories (species names of the training clips' ``category``).
        order: ``habit_order`` ``flow_prior`` (default, the paper's): the first ``habit_fraction`` of the run
            trains the habit encoders with their flow priors (KL(q || p_flow) + the habit statistics), the rest
            the VQ-VAE on the frozen encoders, without a KL term; the checkpoint holds the flows.
            ``kl_then_flows`` (omg's earlier order): the encoders train inside the VQ-VAE with
            ``kl_weight`` · KL(q || N(0, I)) from the first step, and ``HabitPriorModule`` (stage 2) fits
            the flows afterwards (``HabitOrderSettings``).
        flavor: model size preset (``base``: the paper's T2M-GPT sizes; ``mini``, ``tiny`` for CPU runs).
        habit: HabitConfig fields to override in the flavor's (``HabitOverrides``).
        codebook: ``quantizer`` (``soft``: softmax sampling at ``temperature``, the paper's; or ``nearest``),
            ``code_reset`` (restart dead codes at encoder outputs, "EMA-reset"; False: "EMA") and ``ema_decay``
            (of the codebook's moving averages) (``CodebookSettings``).
        condition_decoder: also give the decoder the habit latent and text embedding. Off by default:
            the paper gives them to the encoder only. A named deviation (the mini config uses it):
            with the decoder conditioned too, the codes need not carry the category, which lets a
            short run's target habit replace the source's.
        loss: alpha (velocity reconstruction, paper: 0.5), beta (commitment, paper: 0.02), kl_weight
            (KL to N(0, I), ``kl_then_flows``) and flow_weight (KL to the flow prior in the habit pretraining)
            (``HabitLossWeights``).
        text_encoder, text_encoder_args: the registered encoder that embeds the category descriptions
            (``minilm``, offline; the paper's ``bge-base-en-v1.5``, with ``text_encoder_args: {model_dir: DIR}``).
        species: ``species_file`` (a YAML of extra or overriding species descriptions), and the ``descriptions``
            and their sentence embeddings ``category_embeddings`` filled in when the module is first built
            (``SpeciesText``).
        optim: AdamW lr until ``lr_switch`` of the VQ-VAE's steps, then ``lr_after`` (the habit pretraining
            runs at ``lr``); weight_decay, betas and a linear warm-up over warmup_steps (``StepOptimSettings``).
        spec: the data's representation (quatvel), skeleton, fps and stats; linked by ``omg fit``.
    """

    clip_sampling = "windows"  # fixed-length crops: data.min_len = data.max_len
    frozen_prefixes = ()
    # what the weights and codebook were made with (code_reset names the paper's row); quantizer and
    # temperature (how codes are drawn), habit_fraction, the loss weights and the optimizer are the run's
    architecture_hparams = ("categories", "order.habit_order", "flavor", "habit", "codebook.code_reset",
                            "condition_decoder", "text_encoder", "species.descriptions", "species.category_embeddings",
                            "spec")
    settings_groups = {"habit": HabitOverrides, "text_encoder_args": TextEncoderArgs}

    def __init__(
        self,
        categories: list[str],
        order: HabitOrderSettings = HabitOrderSettings(),
        flavor: str = "base",
        habit: HabitOverrides | None = HabitOverrides(),
        codebook: CodebookSettings = CodebookSettings(),
        condition_decoder: bool = False,
        loss: HabitLossWeights = HabitLossWeights(),
        text_encoder: str = "minilm",
        text_encoder_args: TextEncoderArgs | None = TextEncoderArgs(),
        species: SpeciesText = SpeciesText(),
        optim: StepOptimSettings = StepOptimSettings(lr=2e-4, betas=(0.9, 0.99)),
        spec: DataSpec | dict | None = None,
    ):
        super().__init__()
        if not categories or len(set(categories)) != len(categories):
            raise UsageError(f"model.categories must list distinct category names, got {categories!r}")
        order, codebook = self.value_group("order", order), self.value_group("codebook", codebook)
        species = self.value_group("species", species)
        self.optim, self.loss = self.value_group("optim", optim), self.value_group("loss", loss)
        self.save_hyperparameters()
        self.spec = DataSpec.coerce(spec)
        if self.spec.representation != "quatvel":
            raise UsageError(f"habit transfer trains on quatvel shards, got {self.spec.representation!r} "
                             "(build them with --representation quatvel)")
        self.categories = list(categories)
        self.habit_order, self.habit_fraction = order.habit_order, order.habit_fraction
        descriptions, category_embeddings = species.descriptions, species.category_embeddings
        if category_embeddings is None:  # first build: describe and embed the categories once
            descriptions, category_embeddings = embed_categories(self.categories, text_encoder,
                                                                 text_encoder_kwargs(text_encoder_args),
                                                                 species.species_file)
            self.hparams["species"] = {**self.hparams["species"], "descriptions": descriptions,
                                       "category_embeddings": category_embeddings}
        if len(category_embeddings) != len(self.categories):
            raise UsageError(f"{len(category_embeddings)} category embeddings for {len(self.categories)} categories")
        self.descriptions = dict(descriptions or {})
        self.register_buffer("category_text", torch.tensor(category_embeddings, dtype=torch.float32))  # (N, E)
        self.config = HabitConfig.from_name(flavor, **set_fields(HabitOverrides, habit, "model.init_args.habit"))
        D = self.spec.feature_dim
        self.representation = get_representation("quatvel", get_skeleton(self.spec.skeleton))
        self.num_joints = self.representation.skeleton.num_joints
        quant = Quantizer(self.config.num_codes, self.config.code_dim, codebook.quantizer, codebook.temperature,
                          codebook.ema_decay, codebook.code_reset)
        self.vqvae = MotionVQVAE(D, self.category_text.shape[1], self.config, quant, condition_decoder)
        self.habit_encoders = CategoryHabitEncoders(D, len(self.categories), self.config)
        self.flows: CategoryFlows | None = None
        if order.habit_order == "flow_prior":  # pretrained with the encoders, kept in the checkpoint for transfer
            self.flows = CategoryFlows(len(self.categories), self.config)
            self.habit_stats = HabitStatsDecoder(self.num_joints * 4 - 4, self.config)
        self.register_buffer("mean", torch.tensor(self.spec.mean, dtype=torch.float32), persistent=False)
        self.register_buffer("std", torch.tensor(self.spec.std, dtype=torch.float32), persistent=False)
        N, J, Z = len(self.categories), self.num_joints, self.config.habit_dim
        # per category: the sums behind the mean bone offsets of its training clips (the target's
        # proportions at transfer), and exponentially decayed sums behind the recent mean of its
        # posterior means (a prior-free habit: the encoder's early outputs are forgotten)
        self.register_buffer("offsets_sum", torch.zeros(N, J, 3, dtype=torch.float64))
        self.register_buffer("offsets_count", torch.zeros(N, dtype=torch.float64))
        self.register_buffer("habit_sum", torch.zeros(N, Z, dtype=torch.float64))
        self.register_buffer("habit_count", torch.zeros(N, dtype=torch.float64))
        self._generator: torch.Generator | None = None

    @classmethod
    def checkpoint_hparams(cls, hparams: dict[str, Any], state: dict[str, Tensor]) -> dict[str, Any]:
        """A checkpoint's hyper-parameters as this class reads them (``omg.lit.checkpoint.load_module``): one
        written before ``habit_order`` existed holds no flows and was trained in omg's earlier order; its
        optimizer settings and loss weights as ``OmgModule.checkpoint_hparams`` reads them."""
        hparams = super().checkpoint_hparams(hparams, state)
        order = hparams.get("order")
        if not (isinstance(order, dict) and "habit_order" in order) and not any(k.startswith("flows.") for k in state):
            return {**hparams, "order": {**(order or {}), "habit_order": "kl_then_flows"}}
        return hparams

    # -- categories and features -------------------------------------------------------
    @property
    def row_label(self) -> str:
        """The paper's table row this model is: EMA or EMA-reset (with ", KL then flows" in omg's earlier order)."""
        row = "EMA-reset" if self.vqvae.quantizer.code_reset else "EMA"
        return row if self.habit_order == "flow_prior" else f"{row}, KL then flows"

    def category_index(self, names: Sequence[str]) -> Tensor:
        try:
            return torch.tensor([self.categories.index(n) for n in names], device=self.device)
        except ValueError:
            unknown = sorted({n for n in names if n not in self.categories})
            raise UsageError(f"clip categories {unknown} are not among model.categories {self.categories}: list every "
                             "category of the training data") from None

    def normalize(self, x: Tensor) -> Tensor:
        return (x - self.mean.to(x.dtype)) / self.std.to(x.dtype)

    def denormalize(self, x: Tensor) -> Tensor:
        return x * self.std.to(x.dtype) + self.mean.to(x.dtype)

    def category_offsets(self, category: int) -> Tensor:
        """(J, 3) mean bone offsets of the category's training clips (the skeleton's rest offsets when none)."""
        count = float(self.offsets_count[category])
        if count == 0:
            return torch.as_tensor(self.representation.skeleton.rest_offsets, dtype=torch.float32, device=self.device)
        return (self.offsets_sum[category] / count).float()

    def mean_habit(self, category: int) -> Tensor:
        """(Z,) the recent mean of the category's posterior means in training."""
        return (self.habit_sum[category] / self.habit_count[category].clamp_min(1)).float()

    def generator(self) -> torch.Generator:
        if self._generator is None:
            self._generator = torch.Generator(device="cpu")  # small draws: the CPU's, on any device
            self._generator.manual_seed(torch.initial_seed() + self.global_rank)
        return self._generator

    # -- training ------------------------------------------------------------------------
    def habit_posterior(self, motion: Tensor, mask: Tensor, category: Tensor) -> tuple[Tensor, Tensor]:
        return self.habit_encoders(motion, mask, category)

    def habit_steps(self, total_steps: int | None = None) -> int:
        """The optimizer steps that pretrain the habit encoders and flows (``flow_prior``; 0 otherwise): the
        first ``habit_fraction`` of the run's ``total_steps`` (default: the fitting trainer's)."""
        if self.habit_order != "flow_prior":
            return 0
        if total_steps is None:
            trainer = self.attached_trainer()
            if trainer is None or not trainer.training:
                return 0
            cached = self.__dict__.get("_habit_steps")
            if cached is None or cached[0] is not trainer:
                self.__dict__["_habit_steps"] = cached = (trainer, int(trainer.estimated_stepping_batches))
            total_steps = cached[1]
        return int(self.habit_fraction * total_steps)

    def on_fit_start(self) -> None:
        super().on_fit_start()
        from torch.nn.parallel import DistributedDataParallel

        wrapped = self.trainer.strategy.model  # DDP has wrapped the module by now (Trainer._run: setup, then this hook)
        if (self.habit_order == "flow_prior" and isinstance(wrapped, DistributedDataParallel)
                and not wrapped.find_unused_parameters):
            raise UsageError("model.order.habit_order flow_prior trains one part of the model in each phase (the habit "
                             "encoders and flows, then the VQ-VAE), which DDP must be told: set trainer.strategy "
                             "ddp_find_unused_parameters_true")

    def pretraining(self) -> bool:
        """Whether this training step pretrains the habit encoders and flows (the first phase of ``flow_prior``)."""
        return self.training and self.global_step < self.habit_steps()

    def habit_losses(self, batch: dict, generator: torch.Generator | None = None) -> dict[str, Tensor]:
        """The habit pretraining (``flow_prior``): the crop's habit statistics (mean and spread over time of
        each local joint rotation channel but the root's, which with the velocities holds the path) from its
        posterior sample (smooth L1) + ``flow_weight`` · KL(q(z | m) || p_flow(z)) per latent dimension, a
        one-sample estimate."""
        motion, mask = batch["motion"], batch["mask"]
        category = self.category_index(batch["category"])
        mu, log_sigma = self.habit_posterior(motion, mask, category)
        z = posterior_sample(mu, log_sigma, generator) if self.training else mu
        rotations = motion[..., 4:self.num_joints * 4]  # local joint rotations but the root's: no path
        stats = F.smooth_l1_loss(self.habit_stats(z), habit_statistics(rotations, mask))
        kl = flow_prior_kl(z, mu, log_sigma, self.flows, category).mean() / z.shape[1]
        return {"loss": stats + self.loss.flow_weight * kl, "habit_stats": stats, "flow_kl": kl}

    def losses(self, batch: dict, generator: torch.Generator | None = None) -> tuple[dict[str, Tensor], Tensor, dict]:
        """The VQ-VAE's losses; in ``flow_prior`` on the frozen (pretrained) habit encoders, with no KL term."""
        motion, mask = batch["motion"], batch["mask"].float()  # (B, T, D) normalised, (B, T)
        category = self.category_index(batch["category"])
        frozen = self.flows is not None
        if frozen:
            self.habit_encoders.eval()  # pretrained: no dropout, no gradient
        with torch.no_grad() if frozen else contextlib.nullcontext():
            mu, log_sigma = self.habit_posterior(motion, batch["mask"], category)
        z = posterior_sample(mu, log_sigma, generator) if self.training else mu
        recon, _, terms = self.vqvae(motion, z, self.category_text[category], batch["mask"], generator)
        v = self.num_joints * 4  # quatvel: quaternions first, then the joint velocities
        motion_loss = masked_smooth_l1(recon, motion, mask)
        velocity_loss = masked_smooth_l1(recon[..., v:], motion[..., v:], mask)
        loss = motion_loss + self.loss.alpha * velocity_loss + self.loss.beta * terms["commitment"]
        out = {"loss": loss, "motion": motion_loss, "velocity": velocity_loss, "commitment": terms["commitment"],
               "embedding": terms["embedding"], "perplexity": terms["perplexity"]}
        if not frozen:  # kl_then_flows: the posterior kept near N(0, I) for the flows fitted after
            out["kl"] = kl = gaussian_kl(mu, log_sigma).mean()
            out["loss"] = loss + self.loss.kl_weight * kl
        return out, recon, {"category": category, "mu": mu}

    def training_losses(self, batch: dict) -> dict[str, Tensor]:
        """The habit pretraining's losses in its steps, else the VQ-VAE's. One AdamW holds every part: the part
        a phase leaves alone gets no gradient, and AdamW skips it."""
        if self.pretraining():
            return self.habit_losses(batch, self.generator())
        losses, _, extra = self.losses(batch, self.generator())
        self._accumulate(batch, extra["category"], extra["mu"])
        return losses

    habit_decay = 0.99  # per step, of the sums behind mean_habit

    @torch.no_grad()
    def _accumulate(self, batch: dict, category: Tensor, mu: Tensor) -> None:
        ones = torch.ones(len(category), dtype=torch.float64, device=self.device)
        self.habit_sum.mul_(self.habit_decay).index_add_(0, category, mu.detach().double())
        self.habit_count.mul_(self.habit_decay).index_add_(0, category, ones)
        if "offsets" in batch:
            self.offsets_sum.index_add_(0, category, batch["offsets"].to(self.device).double())
            self.offsets_count.index_add_(0, category, ones)

    def validation_step(self, batch: dict, batch_idx: int, stage: str = "val") -> None:
        losses, recon, extra = self.losses(batch)
        n = len(batch["motion"])
        self.log_dict({f"{stage}/{k}": v for k, v in losses.items()}, batch_size=n, sync_dist=True)
        if self.flows is not None:  # the habit pretraining's terms (posterior means)
            habit = self.habit_losses(batch)
            self.log_dict({f"{stage}/{k}": habit[k] for k in ("habit_stats", "flow_kl")}, batch_size=n, sync_dist=True)
        if "offsets" in batch:
            real = self.representation.decode(self.denormalize(batch["motion"]), batch["offsets"])
            pred = self.representation.decode(self.denormalize(recon), batch["offsets"])
            error = (pred - real).norm(dim=-1).mean(-1)  # (B, T)
            mask = batch["mask"].float()
            self.log(f"{stage}/mpjpe", (error * mask).sum() / mask.sum(), batch_size=n, sync_dist=True)

    def test_step(self, batch: dict, batch_idx: int) -> None:
        self.validation_step(batch, batch_idx, stage="test")

    def lr_factor(self, total_steps: int):
        """The paper's step schedule over the VQ-VAE's steps (``lr``, then ``lr_after`` from ``lr_switch`` of
        them), after a linear warm-up over ``warmup_steps``; in ``flow_prior`` the habit pretraining before it
        runs at ``lr`` after its own warm-up."""
        habit = self.habit_steps(total_steps)  # < total_steps: habit_fraction < 1
        optim = self.optim
        after, warmup = step_lr(optim.lr, optim.lr_after, optim.lr_switch)(total_steps - habit), optim.warmup_steps

        def factor(step: int) -> float:
            phase = step if step < habit else step - habit
            value = 1.0 if step < habit else after(phase)
            return value * min(1.0, (phase + 1) / warmup) if warmup else value

        return factor

    # -- transfer --------------------------------------------------------------------------
    @torch.no_grad()
    def habit_latents(self, category: int, count: int, seed: int = 0, temperature: float = 1.0) -> Tensor:
        """(count, Z) samples of the category's flow prior, pretrained with its encoder (``flow_prior``)."""
        if self.flows is None:
            raise UsageError("this VQ-VAE was trained with habit_order kl_then_flows and holds no flow priors: fit "
                             "them with `omg fit --config configs/mini/habit_prior.yaml` and pass --prior_ckpt")
        gen = torch.Generator(device="cpu").manual_seed(seed)
        return self.flows.sample(category, count, gen, temperature)

    @torch.no_grad()
    def transfer(self, motion: Tensor, target: int, z: Tensor, seed: int = 0, quantizer: str | None = None,
                 text: Tensor | None = None) -> Tensor:
        """(B, T, D) un-normalised quatvel features -> the same motion with category ``target``'s habit
        latents z (B, Z): encoded with the target's condition, quantized (sampled with ``seed``, or by
        ``quantizer``), decoded. Returns (B, T, D) un-normalised.

        ``text``: the condition's description embedding (E,); default the category's. An unseen species
        passes its own description's, so that only the habit latent is the retrieved category's (the
        paper's transfer)."""
        gen = torch.Generator(device="cpu").manual_seed(seed)
        B, T, _ = motion.shape
        if text is None:
            text = self.category_text[torch.full((B,), target, device=self.device)]
        else:
            text = torch.as_tensor(text, dtype=self.category_text.dtype, device=self.device).expand(B, -1)
        x = self.vqvae.pad(self.normalize(motion.to(self.device)))
        latents = self.vqvae.encode(x, z.to(self.device), text)  # (B, C, T')
        C = latents.shape[1]
        flat = latents.permute(0, 2, 1).reshape(-1, C)
        indices = self.vqvae.quantizer.assign(flat, gen, quantizer)  # drawn on the CPU: the same on any device
        codes = self.vqvae.quantizer.codebook[indices].reshape(B, -1, C).permute(0, 2, 1)
        return self.denormalize(self.vqvae.decode(codes, z.to(self.device), text)[:, :T])


def embed_categories(categories: list[str], text_encoder: str, text_encoder_args: dict | None,
                     species_file: str | None) -> tuple[dict[str, str], list[list[float]]]:
    """({category: description}, their sentence embeddings as lists) by the registered text encoder."""
    from omg.text.base import build_text_encoder
    from omg.text.habit import SpeciesBook, sentence_embeddings

    book = SpeciesBook.load(species_file)
    descriptions = {name: book.description(name) for name in categories}
    if torch.get_default_device().type == "meta":  # config tests build structure only
        return descriptions, [[0.0] * 8 for _ in categories]
    encoder = build_text_encoder(text_encoder, **(text_encoder_args or {}))
    with torch.device("cpu"):
        embeddings = sentence_embeddings(encoder, [descriptions[n] for n in categories]).cpu()
    return descriptions, embeddings.tolist()


HabitVQArgs = arguments(HabitVQModule, "HabitVQArgs", __name__, """The arguments of the frozen ``HabitVQModule`` a
prior is fitted on, as its checkpoint holds them: read from ``vq_ckpt`` when the prior is first built and kept in
the prior's checkpoints (they shape the VQ-VAE's weights saved with the flows). Each unset field is None.""")


class HabitPriorModule(OmgModule):
    """Stage 2 of ``habit_order: kl_then_flows``: each known category's flow prior p(z), fitted by NLL to the
    frozen stage-1 habit posterior. On a VQ-VAE of the default order (``flow_prior``, whose flows were
    pretrained with its encoders) it starts from those flows: built without fitting, it transfers as that
    checkpoint does (``omg test`` evaluates such a checkpoint directly: configs/mini/habit_eval.yaml).

    Args:
        vq_ckpt: the HabitVQModule checkpoint to fit on (frozen); read once, when the prior is first
            built: its weights and hyper-parameters are then kept in the prior's checkpoints.
        posterior_sample: fit the flows to samples z ~ q(z | m) (True) or to the posterior means.
        optim: AdamW's lr, weight_decay, betas; warmup_steps of linear warm-up, then cosine decay
            (``OptimSettings``).
        spec: linked by ``omg fit`` from the data; must match the VQ-VAE's.
        vq: the VQ-VAE's hyper-parameters (``HabitVQArgs``), filled from ``vq_ckpt``: a prior checkpoint
            holds its VQ-VAE (``vq.*`` weights), so it loads without that file, on any machine.
    """

    clip_sampling = "windows"
    frozen_prefixes = ()  # the frozen VQ-VAE is saved with the flows: the checkpoint is self-contained
    location_hparams = ("vq_ckpt",)
    architecture_hparams = ("vq", "spec")  # the frozen VQ-VAE's; posterior_sample and the optimizer are the run's

    def __init__(self, vq_ckpt: str | None = None, posterior_sample: bool = True,
                 optim: OptimSettings = OptimSettings(lr=2e-4, betas=(0.9, 0.99)),
                 spec: DataSpec | dict | None = None, vq: HabitVQArgs | None = None):
        super().__init__()
        from omg.lit.checkpoint import build_module, load_module

        self.optim = self.value_group("optim", optim)
        if vq is None and vq_ckpt is None:
            raise UsageError("HabitPriorModule needs model.init_args.vq_ckpt, the HabitVQModule checkpoint to fit on "
                             "(a prior checkpoint written before priors kept their VQ-VAE has neither: refit it)")
        if vq is None and not Path(vq_ckpt).exists() and torch.get_default_device().type != "meta":
            raise UsageError(f"model.vq_ckpt: no HabitVQModule checkpoint at {vq_ckpt}; train it first with "
                             "`omg fit --config configs/mini/habit_vqvae.yaml`")
        self.save_hyperparameters()
        self.posterior_sample = posterior_sample
        hparams_from_file = vq is None
        if vq is None:
            self.vq: HabitVQModule = load_module(vq_ckpt, default_class=HabitVQModule, expect=HabitVQModule)
            vq = dict(self.vq.hparams)
        else:  # the structure: the weights come with this checkpoint's
            vq = settings_dict(settings(HabitVQArgs, self.vq_hparams(vq), "model.init_args.vq"))
            self.vq = build_module(HabitVQModule, vq, "model.init_args.vq")
            vq = dict(self.vq.hparams)  # plain types, as the VQ-VAE keeps them
        self.hparams["vq"] = dict(vq)
        self.vq.requires_grad_(False).eval()
        self.spec = self.vq.spec
        if spec is not None:
            self.vq.spec.check_compatible(DataSpec.coerce(spec), f"the VQ-VAE {vq_ckpt or ''}".strip(), "the data")
        self.flows = CategoryFlows(len(self.vq.categories), self.vq.config)
        if vq_ckpt is not None and hparams_from_file and self.vq.flows is not None:  # flow_prior: its pretrained flows
            self.flows.load_state_dict(self.vq.flows.state_dict())

    @staticmethod
    def vq_hparams(vq: Any) -> Any:
        """A checkpoint's ``vq`` as ``HabitVQModule`` reads it: a prior written before ``habit_order`` existed fitted
        a VQ-VAE of omg's earlier order; one written before the VQ-VAE's settings were grouped holds them flat."""
        return HabitVQModule.checkpoint_hparams(vq, {}) if isinstance(vq, dict) else vq

    @classmethod
    def checkpoint_hparams(cls, hparams: dict[str, Any], state: dict[str, Tensor]) -> dict[str, Any]:
        """A checkpoint's hyper-parameters as this class reads them: its own and its VQ-VAE's (``vq_hparams``)."""
        hparams = super().checkpoint_hparams(hparams, state)
        return {**hparams, "vq": cls.vq_hparams(hparams["vq"])} if "vq" in hparams else hparams

    @property
    def categories(self) -> list[str]:
        return self.vq.categories

    def train(self, mode: bool = True):
        super().train(mode)
        self.vq.eval()  # frozen: the posterior's dropout stays off
        return self

    def nll(self, batch: dict, generator: torch.Generator | None = None) -> Tensor:
        """Mean NLL per latent dimension of the batch's habit latents under their category's flow."""
        category = self.vq.category_index(batch["category"])
        with torch.no_grad():
            mu, log_sigma = self.vq.habit_posterior(batch["motion"], batch["mask"], category)
        z = posterior_sample(mu, log_sigma, generator) if self.posterior_sample and self.training else mu
        return -self.flows.log_prob(z, category).mean() / z.shape[1]

    loss_name = "NLL"

    def training_losses(self, batch: dict) -> dict[str, Tensor]:
        return {"loss": self.nll(batch, self.vq.generator())}

    def log_training(self, losses: dict[str, Tensor], batch: dict) -> None:
        self.log("train/nll", losses["loss"], prog_bar=True, batch_size=len(batch["motion"]))

    def validation_step(self, batch: dict, batch_idx: int) -> None:
        self.log("val/nll", self.nll(batch), batch_size=len(batch["motion"]), sync_dist=True)

    def test_step(self, batch: dict, batch_idx: int) -> None:
        self.log("test/nll", self.nll(batch), batch_size=len(batch["motion"]), sync_dist=True)

    def optimizer_groups(self) -> list[dict]:
        return [{"params": list(self.flows.parameters())}]

    @torch.no_grad()
    def habit_latents(self, category: int, count: int, seed: int = 0, temperature: float = 1.0) -> Tensor:
        """(count, Z) samples of the category's prior."""
        gen = torch.Generator(device="cpu").manual_seed(seed)
        return self.flows.sample(category, count, gen, temperature)


__all__ = ["HabitPriorModule", "HabitVQModule", "embed_categories"]
