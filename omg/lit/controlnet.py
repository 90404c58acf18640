"""OMG stage 2: a Motion ControlNet with Mixture-of-Controllers fine-tuned on text.

The pretrained DiT stays frozen; only the ControlNet learns, with the pretraining loss. The
model works in the pretrained model's normalised feature space: batches normalised with the
fine-tuning data's statistics are re-normalised with the pretrained ones. Sampling mixes the
frozen model D_u and the ControlNet D_c: x̂0 = (1 − s)·D_u + s·D_c.
"""

from __future__ import annotations

import warnings
from typing import Any

import torch
from torch import Tensor

from omg.errors import UsageError
from omg.data.windows import length_mask
from omg.lit.pretrain import MotionDiffusionModule, PretrainModule, check_spec
from omg.models.controlnet import MoCConfig, MotionControlNet
from omg.text import TextFeatures, build_text_encoder

MATCHING = ("representation", "skeleton", "feature_dim")
# the frozen DiT and the text encoder stay in eval mode on purpose
warnings.filterwarnings("ignore", message=r".*module\(s\) in eval mode at the start of training.*")


class ControlNetModule(MotionDiffusionModule):
    """Text-conditioned fine-tuning of a frozen pretrained MotionDiT.

    Args:
        pretrained: the stage-1 checkpoint: a Lightning .ckpt, a DeepSpeed directory or a
            safetensors file from ``omg convert-ckpt`` (its EMA weights are used when present).
        text_encoder: registered name (``clip-vit-l-14``, ``minilm``, ``hash``).
        text_encoder_args: keyword arguments of the encoder (e.g. ``pretrained: /path/ViT-L-14.pt``).
        moc: MoCConfig fields (d_c, num_experts, gamma, beta, layers, ...; the ablation switches
            token_masks, zero_init, experts and wiring, see ``omg.models.controlnet.MoCConfig``).
        eot_drop: probability of replacing the end-of-text token with the empty text's (OMG: 0.5).
        guidance_scale: s in (1 − s)·D_u + s·D_c when sampling (OMG: 4.5).
        lr, weight_decay, warmup_steps: AdamW and schedule (OMG: 3e-5, 1e-5, 1K warm-up, cosine).
        base: the pretrained model's flavor, DiT overrides and spec; filled from ``pretrained``
            and stored in checkpoints, so that a fine-tuned checkpoint needs no other file.
        spec: the fine-tuning data's spec, linked from the data by ``omg fit``.
    """

    text_conditional = True
    clip_sampling = "whole"  # a caption describes its whole clip (HumanML3D: up to 196 frames)

    def __init__(
        self,
        pretrained: str | None = None,
        text_encoder: str = "minilm",
        text_encoder_args: dict[str, Any] | None = None,
        moc: dict[str, Any] | None = None,
        eot_drop: float = 0.5,
        guidance_scale: float = 4.5,
        lr: float = 3e-5,
        weight_decay: float = 1e-5,
        betas: tuple[float, float] = (0.9, 0.999),
        warmup_steps: int = 1000,
        vel_weight: float = 30.0,
        foot_weight: float = 30.0,
        ema_decay: float = 0.9999,
        base: dict[str, Any] | None = None,
        spec: dict | None = None,
    ):
        pretrained_weights = None
        if base is None:
            if pretrained is None:
                raise UsageError("ControlNetModule needs model.init_args.pretrained: a stage-1 checkpoint")
            base, pretrained_weights = _read_pretrained(pretrained)
        if not 0.0 <= eot_drop <= 1.0:
            raise UsageError(f"model.eot_drop must be in [0, 1], got {eot_drop}")
        super().__init__(base["flavor"], base["dit"], lr, weight_decay, warmup_steps, "uniform", base["spec"])
        self.save_hyperparameters()  # `base` now holds the pretrained model's description
        if pretrained_weights is not None:
            self.model.load_state_dict(pretrained_weights)
        self.model.requires_grad_(False)
        self.text_encoder = build_text_encoder(text_encoder, **(text_encoder_args or {}))
        self.controlnet = MotionControlNet(self.model, MoCConfig(text_dim=self.text_encoder.dim, **(moc or {})))
        self.data_spec = check_spec(spec) if spec is not None else None
        if self.data_spec is not None:
            if mismatch := [k for k in MATCHING if self.data_spec[k] != self.spec[k]]:
                raise UsageError(f"the fine-tuning data and the pretrained model differ in {', '.join(mismatch)}: "
                                 f"{ {k: self.data_spec[k] for k in mismatch} } vs { {k: self.spec[k] for k in mismatch} }")
            if (data_fps := self.data_spec["fps"]) != (prior_fps := self.spec["fps"]):
                # a motion prior learns velocities per frame: fine-tuning it at another rate, or
                # generating at its rate from clips of another, would change what every frame means
                raise UsageError(f"the fine-tuning shards are at {data_fps:g} fps but the pretrained model at {prior_fps:g} "
                                 f"fps: rebuild the shards with `omg shards build ... --fps {prior_fps:g}`, or pretrain "
                                 f"on shards at {data_fps:g} fps")
            self.register_buffer("data_mean", torch.tensor(self.data_spec["mean"]), persistent=False)
            self.register_buffer("data_std", torch.tensor(self.data_spec["std"]), persistent=False)

    def trainable_module(self) -> torch.nn.Module:
        return self.controlnet

    def state_dict(self, *args, **kwargs):
        # the text encoder is rebuilt from its own weights, never saved with ours
        state = super().state_dict(*args, **kwargs)
        return {k: v for k, v in state.items() if not k.startswith("text_encoder.")}

    def load_state_dict(self, state_dict, strict: bool = True, assign: bool = False):
        missing, unexpected = super().load_state_dict(state_dict, strict=False, assign=assign)
        missing = [k for k in missing if not k.startswith("text_encoder.")]
        if strict and (missing or unexpected):
            raise RuntimeError(f"checkpoint does not fit ControlNetModule: missing {missing[:5]}, unexpected {unexpected[:5]}")
        return missing, unexpected

    # -- text ----------------------------------------------------------------------------
    def encode_text(self, texts: list[str], drop_eot: Tensor | None = None) -> TextFeatures:
        """Text features on this device, trimmed to the longest caption (CLIP pads to 77 tokens; the
        MoC cost grows with the token count); ``drop_eot`` (B,) bool replaces those EOT tokens by the empty text's."""
        text = self.text_encoder(list(texts)).trimmed().to(self.device)
        if drop_eot is not None and drop_eot.any():
            empty = self.text_encoder([""]).to(self.device)
            tokens = text.tokens.clone()
            rows = drop_eot.nonzero().squeeze(1)
            tokens[rows, text.eot[rows]] = empty.tokens[0, empty.eot[0]].to(tokens.dtype)
            text = TextFeatures(tokens, text.mask, text.eot)
        return text

    # -- training ------------------------------------------------------------------------
    def prepare(self, batch: dict) -> dict:
        """Re-normalise into the pretrained model's feature space and encode the captions
        (dropping EOT tokens at random while training)."""
        x, mask = batch["motion"], batch["mask"]
        if self.data_spec is not None:
            x = self.normalize(x * self.data_std.to(x.dtype) + self.data_mean.to(x.dtype)) * mask[..., None]
        drop = None
        if self.training:
            drop = torch.rand(len(batch["text"]), generator=self.noise_generator(), device=self.device) < self.hparams.eot_drop
        return {**batch, "motion": x, "text_features": self.encode_text(batch["text"], drop)}

    def denoise(self, x_t: Tensor, t: Tensor, mask: Tensor | None, batch: dict) -> Tensor:
        text = batch["text_features"]
        return self.controlnet(x_t, t, text.tokens.to(x_t.dtype), text.mask, text.eot, mask)

    # -- sampling ------------------------------------------------------------------------
    @torch.no_grad()
    def generate(self, texts: list[str], frames: int, steps: int = 200, seed: int = 0,
                 scale: float | None = None, use_ema: bool = True) -> Tensor:
        """Guided DDIM samples for ``texts``, un-normalised features (len(texts), frames, D)."""
        return self.ddim(self._guided(texts, scale, None), len(texts), frames, steps, seed, use_ema)

    @torch.no_grad()
    def sample_for_eval(self, texts: list[str], lengths: Tensor, seed: int, steps: int = 200,
                        guidance: float | None = None, use_ema: bool = True) -> Tensor:
        """The evaluation hook (omg.callbacks.EvalCallback): guided samples, one per text at its own
        length (masked), (B, max(lengths), D) un-normalised; ``guidance`` defaults to guidance_scale."""
        mask = length_mask(lengths, device=self.device)
        return self.ddim(self._guided(texts, guidance, mask), len(texts), mask.shape[1], steps, seed, use_ema, mask)

    def _guided(self, texts: list[str], scale: float | None, mask: Tensor | None):
        """The ``denoise(dtype)`` factory of ``ddim`` for classifier-free-style guided sampling."""
        scale = self.hparams.guidance_scale if scale is None else scale
        text = self.encode_text(texts)

        def denoise(dtype: torch.dtype):
            tokens = text.tokens.to(dtype)
            return lambda x, t: self.controlnet.forward_guided(x, t, tokens, text.mask, text.eot, scale, mask)

        return denoise


def _read_pretrained(path: str) -> tuple[dict, dict[str, Tensor]]:
    """(the stage-1 model's flavor, DiT overrides and spec; its weights, the EMA where kept)."""
    from omg.lit.checkpoint import load_checkpoint

    ckpt = load_checkpoint(path, default_class=PretrainModule)
    hp = ckpt["hyper_parameters"]
    if "flavor" not in hp or "spec" not in hp:
        raise UsageError(f"{path} is not a stage-1 (PretrainModule) checkpoint: its hyper-parameters lack flavor/spec")
    weights = {k.removeprefix("model."): v for k, v in ckpt["state_dict"].items() if k.startswith("model.")}
    if ckpt.get("ema") and not ckpt.get("ema_weights"):
        weights.update(ckpt["ema"]["shadow"])
    return {"flavor": hp["flavor"], "dit": hp.get("dit"), "spec": hp["spec"]}, weights
