"""Training the contrastive text–motion evaluator (``omg fit --config configs/evaluator_*.yaml``).

Each batch of captioned windows gives B text and B motion embeddings; the loss is the symmetric
InfoNCE over their B×B similarities. Rows that share a caption or a clip are not negatives of
each other (template-captioned data repeats captions within a batch, and a pushed-apart twin
makes the loss fight itself), and uncaptioned rows are dropped. Validation logs the InfoNCE,
R-precision top-1/2/3 in pools of ``r_precision_pool`` and MM-Dist with ``omg.metrics``.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import torch
import torch.nn.functional as F
from lightning.pytorch.utilities import rank_zero_warn
from torch import Tensor

from omg.errors import UsageError
from omg.lit.base import OmgModule, OptimSettings
from omg.lit.checkpoint import load_module
from omg.losses import info_nce
from omg.metrics import MMDist, RPrecision
from omg.models.evaluator import EvaluatorConfig, EvaluatorOverrides, TextMotionEvaluator, same_pairs
from omg.motion import DataSpec
from omg.settings import set_fields
from omg.text import TextEncoderArgs, text_encoder_kwargs


class EvaluatorModule(OmgModule):
    """Contrastive text–motion evaluator on any shard set with captions.

    Args:
        text_encoder: the frozen text backbone, a registered name (``minilm``, ``clip-vit-l-14``, ``hash``).
        text_encoder_args: its keyword arguments (e.g. ``pretrained: /path/ViT-L-14.pt``; ``TextEncoderArgs``).
        flavor: evaluator size preset: mini, base or large.
        evaluator: EvaluatorConfig fields to override in the flavor's (``EvaluatorOverrides``), e.g.
            ``{n_layers: 6, embed_dim: 512}``.
        optim: AdamW's lr, weight_decay, betas; warmup_steps of linear warm-up, then cosine decay (``OptimSettings``).
        r_precision_pool: pool size of the validation R-precision (HumanML3D: 32); a validation
            set with fewer samples logs loss and MM-Dist only.
        spec: the data's representation, skeleton, fps and stats; linked from the data by ``omg fit``.
    """

    clip_sampling = "whole"  # a caption describes its whole clip (omg.data.windows)
    frozen_prefixes = ("evaluator.text_encoder.",)  # the backbone is rebuilt from its own weights
    architecture_hparams = ("text_encoder", "flavor", "evaluator", "spec")  # r_precision_pool etc.: the run's
    settings_groups = {"evaluator": EvaluatorOverrides, "text_encoder_args": TextEncoderArgs}

    def __init__(
        self,
        text_encoder: str = "minilm",
        text_encoder_args: TextEncoderArgs | None = TextEncoderArgs(),
        flavor: str = "base",
        evaluator: EvaluatorOverrides | None = EvaluatorOverrides(),
        optim: OptimSettings = OptimSettings(lr=1e-4, weight_decay=1e-2, warmup_steps=500),
        r_precision_pool: int = 32,
        spec: DataSpec | dict | None = None,
    ):
        super().__init__()
        self.optim = self.value_group("optim", optim)
        if r_precision_pool < 3:
            raise UsageError(f"model.r_precision_pool must be >= 3, got {r_precision_pool}")
        self.save_hyperparameters()
        overridden = set_fields(EvaluatorOverrides, evaluator, "model.init_args.evaluator")
        config = EvaluatorConfig.from_name(flavor, **overridden)
        self.evaluator = TextMotionEvaluator(DataSpec.coerce(spec), text_encoder,
                                             text_encoder_kwargs(text_encoder_args), config)
        self.spec = self.evaluator.spec
        self.val_r_precision = RPrecision(pool_size=r_precision_pool, top_k=3)
        self.val_mm_dist = MMDist()
        self._warned_small_val = False

    # -- steps ---------------------------------------------------------------------------
    def embed(self, batch: dict) -> tuple[Tensor, Tensor, Tensor] | None:
        """(text (N, E), motion (N, E), same (N, N)) for the batch's captioned rows; None if fewer than 2."""
        keep = [i for i, t in enumerate(batch["text"]) if t.strip()]
        if len(keep) < 2:
            return None
        rows = torch.tensor(keep, device=batch["motion"].device)
        texts = [batch["text"][i] for i in keep]
        ids = [batch["id"][i] for i in keep] if "id" in batch else None
        labels = [batch["labels"][i] for i in keep] if "labels" in batch else None
        text = self.evaluator.encode_text(texts)
        motion = self.evaluator.encode_normalized_motion(batch["motion"][rows], batch["mask"][rows])
        return text, motion, same_pairs(texts, ids, labels).to(self.device)

    loss_name = "InfoNCE"

    def training_losses(self, batch: dict) -> dict[str, Tensor] | None:
        out = self.embed(batch)
        if out is None:
            rank_zero_warn("a training batch has fewer than 2 captioned clips; skipped (the evaluator needs captions)")
            return None
        text, motion, same = out
        logits = self.evaluator.logits(text, motion)
        self._pairs = len(text)  # the captioned clips the step trained on: the logged values' batch size
        # in-batch top-1 accuracy, a duplicate caption's motion counting as a hit
        hit = same[torch.arange(len(text), device=self.device), logits.argmax(1)].float().mean()
        return {"loss": info_nce(logits, same), "acc": hit}

    def log_training(self, losses: dict[str, Tensor], batch: dict) -> None:
        n = self._pairs
        self.log("train/loss", losses["loss"], prog_bar=True, batch_size=n)
        if self.logs_terms():
            self.log("train/acc", losses["acc"], prog_bar=True, batch_size=n)
            self.log("train/temperature", 1.0 / self.evaluator.logit_scale.exp().clamp(
                max=self.evaluator.config.max_logit_scale), batch_size=n)

    def validation_step(self, batch: dict, batch_idx: int) -> None:
        out = self.embed(batch)
        if out is None:
            return
        text, motion, same = out
        self.log("val/loss", info_nce(self.evaluator.logits(text, motion), same), batch_size=len(text), sync_dist=True)
        self.val_r_precision.update(text, motion)
        self.val_mm_dist.update(text, motion)

    def on_validation_epoch_end(self) -> None:
        mm_dist = self.val_mm_dist.compute()  # every rank computes: the states sync inside
        if torch.isfinite(mm_dist):
            self.log("val/mm_dist", mm_dist.float())
        try:
            for name, value in self.val_r_precision.compute().items():
                self.log(f"val/{name.replace('/', '_')}", value.float())  # val/r_precision_top1 ...
        except ValueError as e:  # fewer samples than one pool
            if not self._warned_small_val:
                rank_zero_warn(f"validation R-precision not logged: {e}")
                self._warned_small_val = True
        self.val_r_precision.reset()
        self.val_mm_dist.reset()

    # -- optimisation --------------------------------------------------------------------
    def optimizer_groups(self) -> list[dict]:
        decay, no_decay = [], []
        for name, p in self.evaluator.named_parameters():
            if p.requires_grad:  # the frozen backbone is left out
                (decay if p.ndim >= 2 and not name.endswith("cls") else no_decay).append(p)
        return [{"params": decay, "weight_decay": self.optim.weight_decay}, {"params": no_decay, "weight_decay": 0.0}]


def load_evaluator(path: str | Path, map_location: str | torch.device = "cpu"):
    """A trained contrastive evaluator (``omg.models.evaluator.TextMotionEvaluator``): an
    ``EvaluatorModule`` Lightning checkpoint (or the safetensors file ``omg convert-ckpt`` made
    from one), frozen, in eval mode, on ``map_location``. The text backbone is rebuilt from its
    own weights (named in the checkpoint's hyper-parameters)."""
    module = load_module(path, default_class=EvaluatorModule, map_location=map_location, expect=EvaluatorModule)
    return module.evaluator.to(map_location).eval().requires_grad_(False)


__all__ = ["EvaluatorModule", "load_evaluator"]


class OmniMotionSelfEvaluator(torch.nn.Module):
    """The paper's self-evaluation: motion features E_t^a(E^a(P, S)) and text features C of an
    OmniMotionGPT checkpoint, in the same sentence space. An ``EvalCallback`` evaluator::

        evaluator: {class_path: omg.lit.evaluator.OmniMotionSelfEvaluator, init_args: {checkpoint: CKPT}}

    The evaluation passes motions without their offsets: S is the mean of the known animals'
    bone offsets. Unlike omg's contrastive evaluator it shares the generator's encoders, so it
    rewards the generator's own view of text; report it beside the independent one.

    ``unit``: both features as unit vectors (omg's default: E_t is trained on 1 − cos(E_t(Z), C), so
    its output's length is arbitrary and Euclidean distances would mostly measure it), or as the
    networks give them (``false``: the paper's scale, where Diversity, MModality, MM-Dist and FID
    are comparable with its tables). The two scales differ most in Diversity and MModality.
    """

    def __init__(self, checkpoint: str, unit: bool = True):
        super().__init__()
        self.unit = unit
        from omg.lit.checkpoint import load_module
        from omg.lit.omgpt import OmniMotionModule

        self.module = load_module(checkpoint, expect=OmniMotionModule)  # EMA weights where kept
        self.spec = self.module.spec
        self.register_buffer("offsets", torch.stack(list(self.module.animals.values())).mean(0), persistent=False)

    def _scaled(self, features: Tensor) -> Tensor:
        return F.normalize(features, dim=-1) if self.unit else features

    @torch.no_grad()
    def encode_text(self, texts: Sequence[str]) -> Tensor:  # (B, D_text)
        return self._scaled(self.module.sentence(list(texts)).to(self.offsets.device))

    @torch.no_grad()
    def encode_motion(self, motion: Tensor, mask: Tensor) -> Tensor:  # (B, T, 216) un-normalised -> (B, D_text)
        animal = self.module.model.animal
        offsets = self.offsets.expand(len(motion), -1, -1)
        z, z_mask = animal["ae"].encode(motion.float() * mask[..., None], offsets, mask)
        return self._scaled(animal["text_encoder"](z, z_mask))
