"""OMG stage 2: a Motion ControlNet with Mixture-of-Controllers fine-tuned on text.

The pretrained DiT stays frozen; only the ControlNet learns, with the pretraining loss. The
model works in the pretrained model's normalised feature space: batches normalised with the
fine-tuning data's statistics are re-normalised with the pretrained ones. Sampling mixes the
frozen model D_u and the ControlNet D_c: x̂0 = (1 − s)·D_u + s·D_c.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

from omg.diffusion import Denoiser
from omg.errors import UsageError
from omg.lit.base import OptimSettings
from omg.lit.control import Control, HintTraining, control_hint, draw_hints, hint_channels
from omg.lit.pretrain import DiffusionLossWeights, MotionDiffusionModule, PretrainModule
from omg.lit.sampling import SamplingDefaults
from omg.models.controlnet import MoCConfig, MoCOverrides, MotionControlNet
from omg.models.dit import DiTOverrides
from omg.motion import DataSpec
from omg.settings import set_fields, settings
from omg.text import TextEncoderArgs, TextFeatures, build_text_encoder, text_encoder_kwargs


@dataclass(frozen=True)
class PretrainedBase:
    """The frozen stage-1 model a ControlNet is fine-tuned on, as its checkpoint describes it: the DiT ``flavor``,
    its ``dit`` overrides (``DiTOverrides``' fields it set) and the data's ``spec`` it was pretrained on. Read from
    ``pretrained`` when the ControlNet is first built and kept in its checkpoints (it shapes the weights)."""

    flavor: str | None = None
    dit: DiTOverrides | None = None
    spec: DataSpec | dict | None = None

    def plain(self, key: str) -> dict:
        """The description as plain types, as checkpoints keep it; one line naming ``key`` when a field is missing."""
        if self.flavor is None or self.spec is None:
            raise UsageError(f"{key} must give the pretrained model's flavor and spec (it is filled in from "
                             "model.init_args.pretrained: leave it out)")
        spec = self.spec.to_dict() if isinstance(self.spec, DataSpec) else dict(self.spec)
        return {"flavor": self.flavor, "dit": set_fields(DiTOverrides, self.dit, f"{key}.dit") or None, "spec": spec}


class ControlNetModule(MotionDiffusionModule):
    """Text-conditioned fine-tuning of a frozen pretrained MotionDiT.

    Args:
        pretrained: the stage-1 checkpoint: a Lightning .ckpt, a DeepSpeed directory or a
            safetensors file from ``omg convert-ckpt`` (its EMA weights are used when present); or a ControlNet's,
            which this one then starts as (its frozen model, copies and controllers, the EMA's where kept; its text
            encoder and ``moc`` must be this run's): hints fine-tuned onto a trained ControlNet, whose hint
            embedding starts silenced (``MotionControlNet.silence_hints``).
        text_encoder: registered name (``clip-vit-l-14``, ``minilm``, ``hash``).
        text_encoder_args: the encoder's arguments (``TextEncoderArgs``, e.g. ``pretrained: /path/ViT-L-14.pt``).
        moc: MoCConfig fields to override (``MoCOverrides``; d_c, num_experts, gamma, beta, layers, ...; the
            ablation switches token_masks, zero_init, experts and wiring, see ``omg.models.controlnet.MoCConfig``).
        eot_drop: probability of replacing the end-of-text token with the empty text's (OMG: 0.5).
        guidance_scale: s in (1 − s)·D_u + s·D_c when sampling (OMG: 4.5).
        optim: AdamW and schedule (OMG: lr 3e-5, weight_decay 1e-5, 1K warm-up, cosine; ``OptimSettings``).
        loss, ema_decay: as for ``PretrainModule``.
        activation_checkpointing: recompute the activations of the frozen blocks, their trainable
            copies and the MoC blocks in backward; applied by ``configure_model``.
        sampling: the checkpoint's own sampling defaults, stance_root and smoothing (``SamplingDefaults``;
            omg's, not OMG's: 0, off), which a sampling call's settings override.
        hints: spatial hints (``omg.lit.control.HintTraining``; OmniControl's realism branch, not OMG's: off):
            with ``enabled`` the block copies read the constraints a motion is sampled with, and training draws
            them from each clip's own joints.
        base: the pretrained model's flavor, DiT overrides and spec (``PretrainedBase``); filled from
            ``pretrained`` and stored in checkpoints, so that a fine-tuned checkpoint needs no other file.
        spec: the fine-tuning data's spec, linked from the data by ``omg fit``.
    """

    text_conditional = True
    frozen_prefixes = ("text_encoder.",)  # rebuilt from its own weights, never saved with ours
    # the weights' own (the frozen model's flavor, DiT and spec are in `base`); text_encoder_args may move its files
    architecture_hparams = ("text_encoder", "moc", "hints", "base", "spec")
    settings_groups = {"moc": MoCOverrides, "text_encoder_args": TextEncoderArgs}
    clip_sampling = "whole"  # a caption describes its whole clip (HumanML3D: up to 196 frames)

    def __init__(
        self,
        pretrained: str | None = None,
        text_encoder: str = "minilm",
        text_encoder_args: TextEncoderArgs | None = TextEncoderArgs(),
        moc: MoCOverrides | None = MoCOverrides(),
        eot_drop: float = 0.5,
        guidance_scale: float = 4.5,
        optim: OptimSettings = OptimSettings(lr=3e-5, weight_decay=1e-5, warmup_steps=1000),
        loss: DiffusionLossWeights = DiffusionLossWeights(),
        ema_decay: float = 0.9999,
        activation_checkpointing: bool = False,
        sampling: SamplingDefaults = SamplingDefaults(),
        hints: HintTraining = HintTraining(),
        base: PretrainedBase | None = None,
        spec: DataSpec | dict | None = None,
    ):
        pretrained_weights = started = None
        if base is not None:  # the checkpoint's description (a mapping), or a config's
            base = settings(PretrainedBase, base, "model.init_args.base").plain("model.init_args.base")
        else:
            if pretrained is None:
                raise UsageError("ControlNetModule needs model.init_args.pretrained: a stage-1 checkpoint")
            base, weights, whole = _read_pretrained(pretrained, text_encoder, moc)
            started, pretrained_weights = (weights, None) if whole else (None, weights)
        if not 0.0 <= eot_drop <= 1.0:
            raise UsageError(f"model.eot_drop must be in [0, 1], got {eot_drop}")
        super().__init__(base["flavor"], base["dit"], base["spec"], optim=optim, loss=loss, ema_decay=ema_decay,
                         loss_weighting="uniform",
                         activation_checkpointing=activation_checkpointing, sampling=sampling)
        self.save_hyperparameters()  # `base` now holds the pretrained model's description
        if self.hparams.get("base") is None:  # LightningCLI hands save_hyperparameters its config, where base is unset
            self.save_hyperparameters({"base": base})
        self.eot_drop, self.guidance_scale = eot_drop, guidance_scale
        self.hints = self.value_group("hints", hints)
        if pretrained_weights is not None:
            self.model.load_state_dict(pretrained_weights)
        self.model.requires_grad_(False)
        self.text_encoder = build_text_encoder(text_encoder, **text_encoder_kwargs(text_encoder_args))
        moc_config = MoCConfig(text_dim=self.text_encoder.dim, **set_fields(MoCOverrides, moc, "model.init_args.moc"),
                               hint_channels=hint_channels(self.representation.skeleton) if self.hints.enabled else 0)
        self.controlnet = MotionControlNet(self.model, moc_config)
        if started is not None:  # a ControlNet's weights; the hint embedding, which it may lack, starts silenced
            if self.hints.enabled:
                self.controlnet.silence_hints()
            missing, unexpected = self.load_state_dict(started, strict=False)
            missing = [k for k in missing if not k.startswith("controlnet.hint_embed.")]
            if missing or unexpected:
                raise UsageError(f"model.init_args.pretrained: its ControlNet's weights do not fit this one "
                                 f"(missing {missing[:3]}, unexpected {sorted(unexpected)[:3]})")
        self.data_spec = None if spec is None else DataSpec.coerce(spec, "the fine-tuning data")
        if self.data_spec is not None:
            # a motion prior learns velocities per frame: fine-tuning it at another rate, or
            # generating at its rate from clips of another, would change what every frame means
            hint = ("rebuild the shards to match the pretrained model (`omg shards build "
                    f"... --fps {self.spec.fps:g}`), or pretrain on shards like these")
            if self.spec.conflicts(self.data_spec, ("fps",)):
                hint = rate_hint(self.spec.fps, self.data_spec.fps)
            self.spec.check_compatible(self.data_spec, "the pretrained model", "the fine-tuning shards", hint=hint)
            self.register_buffer("data_mean", torch.tensor(self.data_spec.mean), persistent=False)
            self.register_buffer("data_std", torch.tensor(self.data_spec.std), persistent=False)

    def trainable_module(self) -> torch.nn.Module:
        return self.controlnet

    def checkpointed_blocks(self) -> list[torch.nn.Module]:
        # gradients reach the controllers through the frozen blocks too, so theirs are recomputed as well
        c = self.controlnet
        return [*self.model.blocks, *c.copy_blocks.values(), *c.mocs.values()]

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
            drop = torch.rand(len(batch["text"]), generator=self.noise_generator(), device=self.device) < self.eot_drop
        prepared = {**batch, "motion": x, "text_features": self.encode_text(batch["text"], drop)}
        if self.hints.enabled:  # drawn from the clips' own joints, in the model's world (omg.lit.control)
            joints = self.representation.decode(self.denormalize(x).float())  # (B, T, J, 3)
            prepared["hint"] = draw_hints(joints, mask.bool(), self.hints, self.noise_generator(), self.spec.fps)
        return prepared

    def denoise(self, x_t: Tensor, t: Tensor, mask: Tensor | None, batch: dict) -> Tensor:
        text = batch["text_features"]
        return self.controlnet(x_t, t, text.tokens.to(x_t.dtype), text.mask, text.eot, mask, batch.get("hint"))

    # -- sampling ------------------------------------------------------------------------
    def denoiser(self, texts: Sequence[str] | None, mask: Tensor, guidance: float | None,
                 control: Control | None = None) -> Denoiser:
        """(1 − s)·D_u + s·D_c for ``texts`` (s = ``guidance``, default ``guidance_scale``); the
        frozen prior D_u alone for texts=None. The text is encoded once, not at every step, and so is the hint of
        ``control``'s targets that a ControlNet trained with hints reads (one without steers alone)."""
        if texts is None:
            return super().denoiser(texts, mask, guidance, control)
        scale = self.guidance_scale if guidance is None else guidance
        text = self.encode_text(list(texts))
        terms = self.controlnet.text_terms(text.tokens, text.mask, text.eot, fold_biases=True)  # once, not per step
        hint = None
        if self.hints.enabled:  # the control's targets, or the empty hint the clips trained without hints read
            dtype = next(self.controlnet.parameters()).dtype
            if control is None:
                features = torch.zeros(1, mask.shape[1], self.controlnet.config.hint_channels, device=self.device)
            elif control.frames != mask.shape[1]:
                raise ValueError(f"a control of {control.frames} frames for motions of up to {mask.shape[1]}")
            else:
                features = control_hint(control.to(self.device, dtype), self.spec.fps)
            hint = self.controlnet.embed_hint(features, dtype)
        return lambda x, t: self.controlnet.forward_guided(x, t, terms, scale, mask, hint)


def rate_hint(prior_fps: float, data_fps: float) -> str:
    """What to do when the fine-tuning data is not at the prior's rate. The prior is not resampled: it learnt
    per-frame velocities at its rate and generates at it, and HumanML3D (its features and its evaluator) exists
    at 20 fps only, so the prior is pretrained at the data's rate, its windows kept at OMG's 10 s (Sec. 3.1:
    L = 300 frames at 30 fps)."""
    return (f"pretrain the prior on shards built at the fine-tuning data's {data_fps:g} fps (`omg shards build ... "
            f"--fps {data_fps:g}`) with data.max_len {round(300 * data_fps / 30)} (OMG's L = 300 frames at 30 fps, the "
            f"same 10 s), or fine-tune on shards built at the prior's --fps {prior_fps:g}")


def _read_pretrained(path: str, text_encoder: str, moc: MoCOverrides | dict | None,
                     ) -> tuple[dict, dict[str, Tensor], bool]:
    """(the frozen model's flavor, DiT overrides and spec; the weights, the EMA's where kept; whether they are a
    ControlNet's, the whole module's, else the stage-1 model's alone)."""
    from omg.lit.checkpoint import class_path, load_checkpoint, resolve_class

    ckpt = load_checkpoint(path, default_class=PretrainModule)
    cls = resolve_class(ckpt["module_class"], path)
    hp = ckpt["hyper_parameters"]
    if issubclass(cls, ControlNetModule):
        return (*_controlnet_start(ckpt, path, text_encoder, moc), True)
    if not issubclass(cls, PretrainModule):  # another model's weights would fail as a state-dict mismatch
        raise UsageError(f"model.init_args.pretrained: {path} holds a {class_path(cls)} checkpoint, where a "
                         f"{class_path(PretrainModule)} (stage-1) or {class_path(ControlNetModule)} checkpoint is "
                         "expected")
    if "flavor" not in hp or "spec" not in hp:
        raise UsageError(f"{path} is not a stage-1 (PretrainModule) checkpoint: its hyper-parameters lack flavor/spec")
    weights = {k.removeprefix("model."): v for k, v in _with_ema(ckpt, "model").items() if k.startswith("model.")}
    return {"flavor": hp["flavor"], "dit": hp.get("dit"), "spec": hp["spec"]}, weights, False


def _controlnet_start(ckpt: dict, path: str, text_encoder: str, moc: MoCOverrides | dict | None,
                      ) -> tuple[dict, dict[str, Tensor]]:
    """(the frozen model's description, every weight: the EMA's where kept) of the ControlNet checkpoint ``ckpt``
    read from ``path``, whose text encoder and controllers must be this run's."""
    hp = ckpt["hyper_parameters"]
    ours = set_fields(MoCOverrides, moc, "model.init_args.moc") or None
    for key, theirs, mine in (("text_encoder", hp.get("text_encoder", "minilm"), text_encoder),
                              ("moc", hp.get("moc") or None, ours)):
        if theirs != mine:
            raise UsageError(f"model.init_args.{key} must be the pretrained ControlNet's {theirs!r} (its weights "
                             f"were made with it), got {mine!r}")
    weights = _with_ema(ckpt, "controlnet")
    if hp.get("base") is None:  # written by `omg fit` before checkpoints kept it: its pretrained file describes it
        if not hp.get("pretrained"):
            raise UsageError(f"model.init_args.pretrained: {path} describes no frozen model (no base, no pretrained)")
        return _read_pretrained(hp["pretrained"], text_encoder, moc)[0], weights
    return settings(PretrainedBase, hp["base"], f"{path}: base").plain(f"{path}: base"), weights


def _with_ema(ckpt: dict, trainable: str) -> dict[str, Tensor]:
    """A checkpoint's weights with the EMA's in place of those of its trainable module (``trainable``, the
    attribute the EMA tracks), where it kept an EMA and its weights are not the EMA already."""
    weights = dict(ckpt["state_dict"])
    if ckpt.get("ema") and not ckpt.get("ema_weights"):
        weights.update({f"{trainable}.{k}": v for k, v in ckpt["ema"]["shadow"].items()})
    return weights
