"""MotionDiT: the diffusion transformer that OMG pretrains on unlabeled motion.

A motion clip (B, T, D_in) is projected frame by frame to d_model, run through pre-norm
transformer blocks conditioned on the diffusion timestep, and projected back to D_in as the
clean-motion estimate x̂0. Frames carry no learned position table: rotary embeddings over time
(RoPE) make attention depend on relative frame offsets only, so any clip length works.

Timestep conditioning is adaLN-single (PixArt-α, Chen et al. 2023) with the adaLN-Zero
initialisation of DiT (Peebles & Xie): one shared ``t_modulation`` maps the timestep embedding
c (B, d) to mod (B, 6d) once per forward, and each block adds its own learnable (6, d) table to
get shift/scale/gate for attention and feed-forward. The shared Linear, the tables and the
output projection start at zero, so every block starts as the identity and x̂0 starts at 0.
The feed-forward is GEGLU: fc1 d -> 2·ffn (value, gate), gelu(gate)·value, fc2 ffn -> d.

For the Motion ControlNet, ``embed`` returns what the blocks and the final layer take and
``forward_embedded`` runs the block loop and the final layer from there, asking an optional
``residual_fn(i, h_i)`` after every block for a residual to add to that block's output.
Activation checkpointing is not the model's business: the training module applies it to the
blocks from outside (``omg.models.checkpointing.checkpoint_each``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Any, Callable

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from omg.errors import UsageError
from omg.settings import overrides

Rope = tuple[Tensor, Tensor]  # (cos, sin), each (T, head_dim), float32


@dataclass
class DiTConfig:
    name: str = "custom"
    input_dim: int = 263  # humanml3d263 features per frame
    n_layers: int = 8
    d_model: int = 1024
    n_heads: int | None = None  # None: d_model // 128 (head dim 128)
    mlp_ratio: float = 2.0  # GEGLU hidden width = mlp_ratio * d_model
    rope_base: float = 10000.0
    freq_embed_dim: int = 256  # sinusoidal timestep features fed to the timestep MLP
    dropout: float = 0.0

    def __post_init__(self) -> None:
        if self.n_heads is None:
            self.n_heads = max(1, self.d_model // 128)
        if self.d_model % self.n_heads:
            raise UsageError(
                f"d_model={self.d_model} is not divisible by n_heads={self.n_heads}; "
                "pick n_heads that divides d_model"
            )
        if self.head_dim % 2:
            raise UsageError(f"head_dim={self.head_dim} must be even for rotary embeddings")

    @property
    def head_dim(self) -> int:
        return self.d_model // self.n_heads

    @property
    def ffn_dim(self) -> int:
        return int(self.mlp_ratio * self.d_model)

    @classmethod
    def from_name(cls, name: str, **overrides: Any) -> DiTConfig:
        """A preset with any field overridden: ``DiTConfig.from_name("base", n_layers=4)``."""
        if name not in FLAVORS:
            raise UsageError(f"unknown DiT flavor {name!r}; known flavors: {', '.join(FLAVORS)}")
        return replace(FLAVORS[name], **overrides)

    def flops(self, batch: int, seq_len: int) -> int:
        """Analytic forward FLOPs (2 per multiply-add) of matmuls and attention.

        Per frame: 4·D_in·d (in/out projections) + L·(8·d² + 6·d·ffn + 4·T·d)
        (qkv+out projections, GEGLU d→2·ffn→d, q·kᵀ and attn·v over T keys); per sample,
        once: 12·d² (shared adaLN-single modulation) + 4·d² (final adaLN)
        + 2·(f·d + d²) (timestep MLP, f = freq_embed_dim).
        Padded frames cost as much as real ones. Training ≈ 3x this (backward ≈ 2x forward).
        """
        d, L, T = self.d_model, self.n_layers, seq_len
        per_frame = 4 * self.input_dim * d + L * (8 * d * d + 6 * d * self.ffn_dim + 4 * T * d)
        per_sample = 12 * d * d + 4 * d * d + 2 * (self.freq_embed_dim * d + d * d)
        return batch * (T * per_frame + per_sample)


# OMG paper, Table 1; mini is ours, sized for CPU tests and README mini-runs.
# Each block holds ~10·d²: attention 4d² + GEGLU 3·d·ffn = 6d² (ffn = 2d), with only a (6, d)
# modulation table (adaLN-single); the shared Linear(d, 6d) adds 6d² once. Parameters here:
# mini 0.9M, base 94.3M, large 212.6M, huge 469.7M, giant 1.05B (paper: 88M / 201M / 1B,
# so +7%, +6%, +5%).
FLAVORS: dict[str, DiTConfig] = {
    "mini": DiTConfig(name="mini", n_layers=4, d_model=128, n_heads=4),
    "base": DiTConfig(name="base", n_layers=8, d_model=1024, n_heads=8),
    "large": DiTConfig(name="large", n_layers=12, d_model=1280, n_heads=10),
    "huge": DiTConfig(name="huge", n_layers=16, d_model=1664, n_heads=13),
    "giant": DiTConfig(name="giant", n_layers=24, d_model=2048, n_heads=16),
}

# model.init_args.dit of PretrainModule: DiTConfig's fields, each None (unset) the flavor's value
DiTOverrides = overrides(DiTConfig, "DiTOverrides", __name__, exclude=("name", "input_dim"),
                         doc="DiTConfig fields to override in the flavor's (unset: the flavor's value).")


def rotary_embedding(positions: Tensor, head_dim: int, base: float = 10000.0) -> Rope:
    """cos/sin tables (T, head_dim) for frame positions (T,), in float32."""
    inv_freq = base ** (-torch.arange(0, head_dim, 2, device=positions.device).float() / head_dim)
    angles = positions.float()[:, None] * inv_freq[None, :]  # (T, head_dim/2)
    angles = torch.cat((angles, angles), dim=-1)  # (T, head_dim), rotate-half layout
    return angles.cos(), angles.sin()


def apply_rotary(x: Tensor, rope: Rope) -> Tensor:
    """Rotate (B, H, T, hd) queries or keys by their frame angle; rotate-half convention."""
    cos, sin = rope
    xf = x.float()
    x1, x2 = xf.chunk(2, dim=-1)
    rotated = torch.cat((-x2, x1), dim=-1)
    return (xf * cos + rotated * sin).type_as(x)


def modulate(x: Tensor, shift: Tensor, scale: Tensor) -> Tensor:
    # x: (B, T, d); shift, scale: (B, 1, d)
    return x * (1 + scale) + shift


class TimestepEmbedder(nn.Module):
    """Diffusion step t (B,) -> (B, d): sinusoidal features, then an MLP (as in DiT)."""

    def __init__(self, d_model: int, freq_embed_dim: int = 256) -> None:
        super().__init__()
        self.freq_embed_dim = freq_embed_dim
        self.mlp = nn.Sequential(
            nn.Linear(freq_embed_dim, d_model), nn.SiLU(), nn.Linear(d_model, d_model)
        )

    @staticmethod
    def sinusoidal(t: Tensor, dim: int, max_period: float = 10000.0) -> Tensor:
        half = dim // 2
        freqs = torch.exp(-math.log(max_period) * torch.arange(half, device=t.device) / half)
        args = t.float()[:, None] * freqs[None]  # (B, dim/2)
        emb = torch.cat((torch.cos(args), torch.sin(args)), dim=-1)  # (B, dim)
        return F.pad(emb, (0, dim % 2))

    def forward(self, t: Tensor) -> Tensor:
        # DeepSpeed bf16 casts the weights without autocast: features follow the weights' dtype
        features = self.sinusoidal(t, self.freq_embed_dim).to(self.mlp[0].weight.dtype)
        return self.mlp(features)  # (B, d)


class Attention(nn.Module):
    def __init__(self, config: DiTConfig) -> None:
        super().__init__()
        self.n_heads, self.head_dim = config.n_heads, config.head_dim
        self.qkv = nn.Linear(config.d_model, 3 * config.d_model)
        self.proj = nn.Linear(config.d_model, config.d_model)
        self.dropout = config.dropout

    def forward(self, x: Tensor, rope: Rope, mask: Tensor | None) -> Tensor:
        B, T, d = x.shape
        qkv = self.qkv(x).view(B, T, 3, self.n_heads, self.head_dim)
        q, k, v = qkv.permute(2, 0, 3, 1, 4)  # each (B, H, T, hd)
        q, k = apply_rotary(q, rope), apply_rotary(k, rope)
        attn_mask = None
        if mask is not None:
            # A sample with no real frame would leave its rows with no key (NaN): let it see all.
            keys = mask | ~mask.any(dim=1, keepdim=True)  # (B, T)
            attn_mask = keys[:, None, None, :]  # (B, 1, 1, T), True = attend
        y = F.scaled_dot_product_attention(
            q, k, v, attn_mask=attn_mask, dropout_p=self.dropout if self.training else 0.0
        )  # (B, H, T, hd)
        return self.proj(y.transpose(1, 2).reshape(B, T, d))


class MLP(nn.Module):
    """GEGLU feed-forward: d -> (value, gate) each ffn wide -> gelu(gate)·value -> d."""

    def __init__(self, config: DiTConfig) -> None:
        super().__init__()
        self.fc1 = nn.Linear(config.d_model, 2 * config.ffn_dim)
        self.fc2 = nn.Linear(config.ffn_dim, config.d_model)

    def forward(self, x: Tensor) -> Tensor:
        value, gate = self.fc1(x).chunk(2, dim=-1)  # each (B, T, ffn)
        return self.fc2(F.gelu(gate, approximate="tanh") * value)


class DiTBlock(nn.Module):
    """Pre-norm attention + GEGLU; shift/scale/gate = shared mod + this block's (6, d) table."""

    def __init__(self, config: DiTConfig) -> None:
        super().__init__()
        d = config.d_model
        self.norm1 = nn.LayerNorm(d, elementwise_affine=False, eps=1e-6)
        self.attn = Attention(config)
        self.norm2 = nn.LayerNorm(d, elementwise_affine=False, eps=1e-6)
        self.mlp = MLP(config)
        self.modulation = nn.Parameter(torch.zeros(6, d))  # adaLN-single per-block table
        self.drop = nn.Dropout(config.dropout)

    def forward(self, x: Tensor, mod: Tensor, rope: Rope, mask: Tensor | None = None) -> Tensor:
        # x: (B, T, d); mod: (B, 6d) shared t_modulation(c); mask: (B, T) bool, True = real frame
        B, d = mod.shape[0], self.modulation.shape[1]
        params = (mod.view(B, 6, d) + self.modulation)[:, :, None, :]  # (B, 6, 1, d)
        shift_msa, scale_msa, gate_msa, shift_mlp, scale_mlp, gate_mlp = params.unbind(1)
        h = self.attn(modulate(self.norm1(x), shift_msa, scale_msa), rope, mask)
        x = x + gate_msa * self.drop(h)
        h = self.mlp(modulate(self.norm2(x), shift_mlp, scale_mlp))
        return x + gate_mlp * self.drop(h)  # (B, T, d)


class FinalLayer(nn.Module):
    def __init__(self, d_model: int, out_dim: int) -> None:
        super().__init__()
        self.norm = nn.LayerNorm(d_model, elementwise_affine=False, eps=1e-6)
        self.adaLN_modulation = nn.Sequential(nn.SiLU(), nn.Linear(d_model, 2 * d_model))
        self.linear = nn.Linear(d_model, out_dim)

    def forward(self, x: Tensor, c: Tensor) -> Tensor:
        shift, scale = self.adaLN_modulation(c)[:, None, :].chunk(2, dim=-1)  # each (B, 1, d)
        return self.linear(modulate(self.norm(x), shift, scale))  # (B, T, D_out)


class MotionDiT(nn.Module):
    """(x_t (B, T, D_in), t (B,)) -> x̂0 (B, T, D_in)."""

    def __init__(self, config: DiTConfig) -> None:
        super().__init__()
        self.config = config
        self.input_proj = nn.Linear(config.input_dim, config.d_model)
        self.t_embedder = TimestepEmbedder(config.d_model, config.freq_embed_dim)
        d = config.d_model
        self.t_modulation = nn.Sequential(nn.SiLU(), nn.Linear(d, 6 * d))  # adaLN-single
        self.blocks = nn.ModuleList(DiTBlock(config) for _ in range(config.n_layers))
        self.final_layer = FinalLayer(config.d_model, config.input_dim)
        self.init_weights()

    @torch.no_grad()
    def init_weights(self) -> None:
        """DiT initialisation; call again after ``to_empty`` when built on the meta device."""
        for module in self.modules():
            if isinstance(module, nn.Linear):
                nn.init.xavier_uniform_(module.weight)
                nn.init.zeros_(module.bias)
        for layer in self.t_embedder.mlp[::2]:
            nn.init.normal_(layer.weight, std=0.02)
        # adaLN-Zero: all gates are 0, so every block starts as the identity; the zero output
        # projection makes the model predict x̂0 = 0.
        for block in self.blocks:
            nn.init.zeros_(block.modulation)
        for layer in (
            self.t_modulation[-1],
            self.final_layer.adaLN_modulation[-1],
            self.final_layer.linear,
        ):
            nn.init.zeros_(layer.weight)
            nn.init.zeros_(layer.bias)

    def embed(self, x: Tensor, t: Tensor) -> tuple[Tensor, Tensor, Tensor, Rope]:
        """Frame tokens h (B, T, d), condition c (B, d) for the final layer, shared block
        modulation mod = t_modulation(c) (B, 6d), and the rotary tables."""
        h = self.input_proj(x)  # (B, T, d)
        c = self.t_embedder(t)  # (B, d)
        mod = self.t_modulation(c)  # (B, 6d)
        positions = torch.arange(x.shape[1], device=x.device)
        rope = rotary_embedding(positions, self.config.head_dim, self.config.rope_base)
        return h, c, mod, rope

    def forward_embedded(
        self,
        h: Tensor,
        c: Tensor,
        mod: Tensor,
        rope: Rope,
        mask: Tensor | None = None,
        residual_fn: Callable[[int, Tensor], Tensor | None] | None = None,
    ) -> Tensor:
        """The block loop and the final layer on ``embed``'s outputs -> x̂0 (B, T, D_in).

        ``residual_fn(i, h_i)``, if given, is called with block i's input h_i (B, T, d) and
        may return a residual (B, T, d) to add to block i's output (ControlNet), or None.
        """
        for i, block in enumerate(self.blocks):
            h_next = block(h, mod, rope, mask)  # (B, T, d)
            r = None if residual_fn is None else residual_fn(i, h)
            h = h_next if r is None else h_next + r
        return self.final_layer(h, c)  # (B, T, D_in)

    def forward(self, x: Tensor, t: Tensor, mask: Tensor | None = None) -> Tensor:
        """x: (B, T, D_in) noisy motion; t: (B,) steps; mask: (B, T) bool, True = real frame.
        Outputs at padded frames are unconstrained; callers mask them."""
        h, c, mod, rope = self.embed(x, t)
        return self.forward_embedded(h, c, mod, rope, mask)
