"""A contrastive text–motion evaluator for any skeleton and representation.

The evaluation stack (R-precision, MM-Dist, FID, diversity, ...) needs a feature extractor
that maps motions and texts into one space. HumanML3D papers use Guo et al.'s T2M evaluator
(``omg.models.t2m``), which exists only for humanml3d263; this model is trained by omg itself
on any shard set (humans on humanml3d263, animals on maa), in the style of TMR/CLIP:

    motion (B, T, D) --normalise--> frame MLP -> [CLS] + frames + sin. positions -> L blocks -> CLS -> proj -> ẑ_m
    text --frozen backbone--> tokens (B, L, C) -> Linear -> [CLS] + tokens -> L_t blocks -> CLS -> proj -> ẑ_t

Both embeddings are L2-normalised (E-d unit vectors), trained with a symmetric InfoNCE whose
temperature is learned (CLIP's parameterisation: logits = exp(s)·ẑ_t·ẑ_mᵀ, exp(s) ≤ 100).
On the unit sphere Euclidean ranking equals cosine ranking, so the metrics' Euclidean
R-precision and MM-Dist (then in [0, 2]) measure what the loss trained.

The evaluator normalises motion itself with the mean/std of the data it was trained on (kept as
buffers): generators hand it de-normalised features, whatever statistics they were trained with.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Any, Sequence

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from omg.errors import UsageError
from omg.models.positions import sinusoidal_positions
from omg.motion import DataSpec
from omg.settings import overrides
from omg.text import TextEncoder, build_text_encoder


@dataclass
class EvaluatorConfig:
    name: str = "custom"
    d_model: int = 256  # width of both the motion encoder and the text head
    n_layers: int = 4  # motion transformer blocks
    text_layers: int = 1  # text-head blocks over the frozen backbone's tokens
    n_heads: int = 4
    mlp_ratio: float = 4.0
    embed_dim: int = 256  # the shared latent E
    patch_len: int = 4  # frames per motion token (T2M also encodes 4-frame units): 16x cheaper attention
    dropout: float = 0.1
    init_temperature: float = 0.07  # CLIP's τ at initialisation
    max_logit_scale: float = 100.0  # clamp on 1/τ, as CLIP does, against runaway sharpening

    def __post_init__(self) -> None:
        if self.d_model % self.n_heads:
            raise UsageError(f"evaluator d_model={self.d_model} is not divisible by n_heads={self.n_heads}")
        if min(self.n_layers, self.embed_dim, self.d_model, self.patch_len) < 1 or self.text_layers < 0:
            raise UsageError(f"evaluator sizes must be positive (text_layers >= 0): {self}")

    @classmethod
    def from_name(cls, name: str, **overrides: Any) -> EvaluatorConfig:
        """A preset with fields overridden: ``EvaluatorConfig.from_name("base", n_layers=6)``."""
        if name not in FLAVORS:
            raise UsageError(f"unknown evaluator flavor {name!r}; known flavors: {', '.join(FLAVORS)}")
        if unknown := set(overrides) - set(cls.__dataclass_fields__):
            raise UsageError(f"unknown evaluator field(s) {sorted(unknown)} (model.init_args.evaluator); "
                             f"fields: {', '.join(cls.__dataclass_fields__)}")
        return replace(FLAVORS[name], **overrides)


FLAVORS = {
    "mini": EvaluatorConfig("mini", d_model=128, n_layers=2, text_layers=1, n_heads=4, embed_dim=128, dropout=0.1),
    "base": EvaluatorConfig("base", d_model=256, n_layers=4, text_layers=1, n_heads=4, embed_dim=256),
    "large": EvaluatorConfig("large", d_model=512, n_layers=6, text_layers=2, n_heads=8, embed_dim=512),
}

# model.init_args.evaluator of EvaluatorModule: EvaluatorConfig's fields, each None (unset) the flavor's value
EvaluatorOverrides = overrides(EvaluatorConfig, "EvaluatorOverrides", __name__,
                               doc="EvaluatorConfig fields to override in the flavor's (unset: the flavor's value).")


class Block(nn.Module):
    """Pre-norm transformer block; ``mask`` (B, S) True on real positions."""

    def __init__(self, d: int, n_heads: int, mlp_ratio: float, dropout: float) -> None:
        super().__init__()
        self.n_heads = n_heads
        self.norm1, self.norm2 = nn.LayerNorm(d), nn.LayerNorm(d)
        self.qkv, self.proj = nn.Linear(d, 3 * d), nn.Linear(d, d)
        hidden = int(mlp_ratio * d)
        self.mlp = nn.Sequential(nn.Linear(d, hidden), nn.GELU(), nn.Dropout(dropout), nn.Linear(hidden, d))
        self.drop = nn.Dropout(dropout)

    def forward(self, x: Tensor, mask: Tensor) -> Tensor:
        B, S, d = x.shape
        q, k, v = self.qkv(self.norm1(x)).view(B, S, 3, self.n_heads, d // self.n_heads).unbind(2)  # (B, S, H, hd)
        attn = F.scaled_dot_product_attention(
            q.transpose(1, 2), k.transpose(1, 2), v.transpose(1, 2),  # (B, H, S, hd)
            attn_mask=mask[:, None, None, :],  # keys: padding never attended
        )
        x = x + self.drop(self.proj(attn.transpose(1, 2).reshape(B, S, d)))
        return x + self.drop(self.mlp(self.norm2(x)))


class SequenceEncoder(nn.Module):
    """(B, S, in_dim) + mask -> (B, d): a learned [CLS] token read out after ``n_layers`` blocks.

    ``patch`` consecutive positions are concatenated into one token (a padded position is zero,
    a token is real when any of its positions is).
    """

    def __init__(self, in_dim: int, config: EvaluatorConfig, n_layers: int, patch: int = 1) -> None:
        super().__init__()
        d, self.patch = config.d_model, patch
        # motion patches get a small MLP (features are heterogeneous: velocities, rotations, contacts);
        # text tokens are already a learned embedding, a Linear suffices
        self.inp = (nn.Sequential(nn.Linear(patch * in_dim, d), nn.GELU(), nn.Linear(d, d)) if patch > 1
                    else nn.Linear(in_dim, d))
        self.cls = nn.Parameter(torch.zeros(1, 1, d))
        self.blocks = nn.ModuleList(Block(d, config.n_heads, config.mlp_ratio, config.dropout) for _ in range(n_layers))
        self.norm = nn.LayerNorm(d)
        nn.init.normal_(self.cls, std=0.02)

    def forward(self, x: Tensor, mask: Tensor) -> Tensor:
        B, S, C = x.shape
        if self.patch > 1:
            pad = -S % self.patch
            x = F.pad(x * mask[..., None], (0, 0, 0, pad)).reshape(B, -1, self.patch * C)  # (B, S/p, p·C)
            mask = F.pad(mask, (0, pad)).reshape(B, -1, self.patch).any(-1)  # (B, S/p)
            S = x.shape[1]
        h = self.inp(x) * mask[..., None]  # (B, S, d); padding stays zero
        h = h + sinusoidal_positions(S, h.shape[-1], h.device).to(h.dtype)
        h = torch.cat([self.cls.expand(B, -1, -1).to(h.dtype), h], dim=1)  # (B, 1+S, d)
        mask = torch.cat([mask.new_ones(B, 1), mask], dim=1)  # (B, 1+S)
        for block in self.blocks:
            h = block(h, mask)
        return self.norm(h[:, 0])  # (B, d)


class TextMotionEvaluator(nn.Module):
    """Motions and texts into one E-d unit-sphere space (see the module docstring).

    Args:
        spec: the training data's representation, skeleton, fps, feature_dim and per-feature
            mean/std (``MotionDataModule.spec``); mean/std become buffers.
        text_encoder: a registered text encoder name (``minilm``, ``clip-vit-l-14``, ``hash``)
            or a built one; it stays frozen.
        text_encoder_args: its keyword arguments (e.g. ``pretrained: /path/ViT-L-14.pt``).
        config: an ``EvaluatorConfig`` (or a flavor name).
    """

    def __init__(self, spec: DataSpec | dict, text_encoder: str | TextEncoder = "minilm",
                 text_encoder_args: dict[str, Any] | None = None, config: EvaluatorConfig | str = "base") -> None:
        super().__init__()
        self.spec = DataSpec.coerce(spec, "the evaluator")
        self.config = EvaluatorConfig.from_name(config) if isinstance(config, str) else config
        D = self.spec.feature_dim
        self.register_buffer("mean", torch.tensor(self.spec.mean, dtype=torch.float32))
        self.register_buffer("std", torch.tensor(self.spec.std, dtype=torch.float32))
        self.text_encoder = build_text_encoder(text_encoder, **(text_encoder_args or {}))
        self.text_encoder.requires_grad_(False)  # frozen backbone: only the head below learns
        c = self.config
        self.motion_encoder = SequenceEncoder(D, c, c.n_layers, patch=c.patch_len)
        self.text_head = SequenceEncoder(self.text_encoder.dim, c, c.text_layers)
        self.motion_proj = nn.Linear(c.d_model, c.embed_dim)
        self.text_proj = nn.Linear(c.d_model, c.embed_dim)
        self.logit_scale = nn.Parameter(torch.tensor(math.log(1.0 / c.init_temperature)))

    @property
    def device(self) -> torch.device:
        return self.mean.device

    # -- motion --------------------------------------------------------------------------
    def normalize(self, motion: Tensor) -> Tensor:
        return (motion - self.mean.to(motion.dtype)) / self.std.to(motion.dtype)

    def encode_normalized_motion(self, motion: Tensor, mask: Tensor) -> Tensor:
        """(B, T, D) features already normalised with this evaluator's stats, (B, T) bool -> (B, E) unit."""
        if motion.ndim != 3 or motion.shape[-1] != self.mean.shape[0]:
            raise ValueError(f"expected motion (B, T, {self.mean.shape[0]}) of {self.spec.representation}, "
                             f"got {tuple(motion.shape)}")
        mask = mask.to(motion.device, torch.bool)
        if not mask.any(1).all():
            raise ValueError("every motion needs at least one real frame (a row of mask is all False)")
        motion = motion * mask[..., None]  # padding carries no value, whatever the caller left there
        return F.normalize(self.motion_proj(self.motion_encoder(motion, mask)), dim=-1)

    def encode_motion(self, motion: Tensor, mask: Tensor | None = None) -> Tensor:
        """(B, T, D) UN-normalised features, (B, T) bool mask (None: all real) -> (B, E) unit vectors."""
        motion = motion.to(self.device, torch.float32)
        if mask is None:
            mask = torch.ones(motion.shape[:2], dtype=torch.bool, device=motion.device)
        return self.encode_normalized_motion(self.normalize(motion), mask)

    # -- text ----------------------------------------------------------------------------
    def encode_text(self, texts: Sequence[str]) -> Tensor:
        """B captions -> (B, E) unit vectors."""
        feats = self.text_encoder(list(texts)).to(self.device)
        return F.normalize(self.text_proj(self.text_head(feats.tokens, feats.mask)), dim=-1)

    # -- training ------------------------------------------------------------------------
    def logits(self, text_emb: Tensor, motion_emb: Tensor) -> Tensor:
        """(B, E), (B, E) -> (B, B) text×motion logits scaled by the learned 1/τ."""
        scale = self.logit_scale.clamp(max=math.log(self.config.max_logit_scale)).exp()
        return scale * text_emb.float() @ motion_emb.float().T


def same_pairs(texts: Sequence[str], ids: Sequence[str] | None = None, labels: Sequence[dict] | None = None) -> Tensor:
    """(B, B) bool: True where two batch rows share their caption (case/space-insensitive), clip
    id, or labels (two takes labelled {content: walk, style: old} are the same motion class
    whatever their captions say, so neither is a negative of the other; rows without labels
    match on caption and id only)."""
    keys = [" ".join(t.lower().split()).rstrip(".") for t in texts]
    index = {k: i for i, k in enumerate(dict.fromkeys(keys))}
    codes = torch.tensor([index[k] for k in keys])
    same = codes[:, None] == codes[None, :]
    if ids is not None:
        id_index = {k: i for i, k in enumerate(dict.fromkeys(ids))}
        id_codes = torch.tensor([id_index[k] for k in ids])
        same |= id_codes[:, None] == id_codes[None, :]
    if labels is not None:
        keys = [tuple(sorted((str(k), str(v)) for k, v in (lab or {}).items())) for lab in labels]
        label_index = {k: i for i, k in enumerate(dict.fromkeys(keys))}
        label_codes = torch.tensor([label_index[k] for k in keys])
        labelled = torch.tensor([bool(k) for k in keys])
        same |= (label_codes[:, None] == label_codes[None, :]) & labelled[:, None] & labelled[None, :]
    return same


__all__ = ["EvaluatorConfig", "FLAVORS", "TextMotionEvaluator", "same_pairs"]
