"""Motion ControlNet with Mixture-of-Controllers (OMG, Liang et al., CVPR 2024).

Stage 2 of OMG turns the unconditional pretrained ``MotionDiT`` into a text-to-motion model
without touching its weights. The pretrained model is frozen; a trainable copy of its
transformer blocks runs beside it, and after every controlled copy block a Mixture-of-Controllers
(MoC) block writes text information into the copy stream. Copy block i feeds frozen block i
through a zero-initialised Linear(d, d), whose output is ``block_residuals[i]``:

    h0, c, mod, rope = base.embed(x, t)                     # frozen, computed once
    h_c = h0                                                # the copy stream starts at h0
    for i:  h_c = copy_i(h_c, mod, rope)                    # trainable deepcopy of block i
            h_c = h_c + MoC_i(h_c, text)                    # only where i is in config.layers
            r_i = Z_i h_c                                   # zero-init Linear(d, d)
            h   = frozen_i(h, mod, rope) + r_i              # the frozen stream
    D_c = base.final_layer(h, c)

Every layer has its copy and its zero projection, as in ControlNet (the copy stream is a
sequential stack: a block cannot be left out of it without changing what later copies see).
``MoCConfig.layers`` only chooses where text enters; a copy block before the first controller
sees no text and learns a text-independent correction. At initialisation the zero projections
make D_c equal the frozen model bit for bit, and the zero up-projection of every MoC makes the
copy stream equal the frozen stream, so the copy starts from the pretrained features.

Classifier-free guidance needs no dropped-text training: D_u is the frozen model itself, and
``forward_guided`` returns (1 - s)·D_u + s·D_c from one embed, one controller pass and one
frozen pass on the doubled batch [x; x] with residuals on the conditional half only.

Text arrives as three tensors (the fields of ``omg.text``'s features): tokens (B, L, D_text)
per-token embeddings, text_mask (B, L) bool, True = real token, and eot (B,) long, the index of
the end-of-text token. Padded tokens never reach the output (they are zeroed, masked out of the
attention and out of the residual sum), so captions can be padded to any length; the cost grows
with L, so pass tokens trimmed to the longest caption of the batch rather than CLIP's 77.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from typing import Callable

import torch
import torch.nn.functional as F
from torch import Tensor, nn
from torch.utils.checkpoint import checkpoint

from omg.errors import UsageError
from omg.models.dit import MotionDiT, Rope

ADAIN_EPS = 1e-5


@dataclass
class MoCConfig:
    d_c: int = 256  # controller width
    num_experts: int = 12  # K, size of the expert pool
    expert_hidden: int | None = None  # hidden width of each expert; None: 2·d_c
    gamma: float = 24.0  # sharpness of the token masks
    beta: float = 0.25  # mask threshold, relative to the token's strongest frame
    gate_hidden: int | None = None  # hidden width of the gating MLP G; None: d_c
    layers: list[int] | None = None  # blocks followed by a MoC block; None: every block
    text_dim: int = 512  # D_text: width of the text token embeddings (CLIP ViT-B: 512)

    def __post_init__(self) -> None:
        if self.expert_hidden is None:
            self.expert_hidden = 2 * self.d_c
        if self.gate_hidden is None:
            self.gate_hidden = self.d_c
        for name in ("d_c", "num_experts", "expert_hidden", "gate_hidden", "text_dim"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise UsageError(f"MoCConfig.{name}={value!r} must be a positive integer")
        gamma = self.gamma
        if not (isinstance(gamma, (int, float)) and math.isfinite(gamma) and gamma > 0):
            raise UsageError(f"MoCConfig.gamma={gamma!r} must be a positive number (paper: 24)")
        if not (isinstance(self.beta, (int, float)) and 0 <= self.beta <= 1):
            raise UsageError(f"MoCConfig.beta={self.beta!r} must lie in [0, 1] (paper: 0.25)")
        if self.layers is not None:
            layers = list(self.layers)
            bad = [i for i in layers if isinstance(i, bool) or not isinstance(i, int) or i < 0]
            if not layers or bad or len(set(layers)) != len(layers):
                raise UsageError(
                    f"MoCConfig.layers={self.layers!r} must be None (every block) or a non-empty "
                    "list of distinct block indices >= 0"
                )
            self.layers = sorted(layers)

    def controlled_layers(self, n_layers: int) -> list[int]:
        """The block indices that get a MoC block, checked against the model's depth."""
        if self.layers is None:
            return list(range(n_layers))
        if max(self.layers) >= n_layers:
            raise UsageError(
                f"MoCConfig.layers={self.layers} names a block the DiT does not have; its blocks "
                f"are 0..{n_layers - 1}"
            )
        return list(self.layers)


class MoCBlock(nn.Module):
    """Mixture-of-Controllers: text-token-specific experts applied where each token attends.

    For motion features h (T, d), text tokens e_1..e_L (D_text; real tokens only) and the
    end-of-text embedding e_eot, with controller width d_c and K experts:

        f    = W_down h                                      (T, d_c)   W_down zero-init
        A    = softmax_i(f W_q (e W_k)ᵀ / √d_c)               (T, L)     over real tokens
        f'   = f + A (e W_v)                                 (T, d_c)
        f̃    = (f' − μ_t(f')) / σ_t(f') · (1 + a(e_eot)) + b(e_eot)    AdaIN, real frames
        ω_i  = softmax(G(e_i))                               (K,)       G: 3-layer MLP
        F_i  = FFN(f̃; Σ_k ω_ik W1_k, Σ_k ω_ik b1_k, Σ_k ω_ik W2_k, Σ_k ω_ik b2_k)
             = (gelu(f̃ W1_i + b1_i)) W2_i + b2_i            (T, d_c)   blended parameters
        M_i  = sigmoid(γ (A_{:,i} − β · max_t A_{t,i}))      (T,)       max over real frames
        out  = W_up Σ_i M_i ⊙ F_i                            (T, d)     W_up zero-init

    W_k, W_v map D_text -> d_c directly (the text projection folded into them); (a, b) =
    ``eot_affine``(e_eot), a Linear(D_text, 2·d_c); σ_t includes ε = 1e-5. W_down alone would
    not silence the block (with f = 0 the attention is uniform, AdaIN returns the shift b and
    the experts their biases), so W_up is zero-initialised as well: the block outputs exactly 0
    at init, and the copy stream starts equal to the frozen stream.
    """

    def __init__(self, d_model: int, config: MoCConfig) -> None:
        super().__init__()
        c, K, H, D, G = (
            config.d_c,
            config.num_experts,
            config.expert_hidden,
            config.text_dim,
            config.gate_hidden,
        )
        self.config = config
        self.down = nn.Linear(d_model, c)
        self.q = nn.Linear(c, c)
        self.k = nn.Linear(D, c)
        self.v = nn.Linear(D, c)
        self.eot_affine = nn.Linear(D, 2 * c)  # EOT embedding -> AdaIN (scale, shift)
        self.gate = nn.Sequential(
            nn.Linear(D, G), nn.GELU(), nn.Linear(G, G), nn.GELU(), nn.Linear(G, K)
        )
        self.w1 = nn.Parameter(torch.empty(K, c, H))  # expert k's first layer: f @ w1[k]
        self.b1 = nn.Parameter(torch.empty(K, H))
        self.w2 = nn.Parameter(torch.empty(K, H, c))
        self.b2 = nn.Parameter(torch.empty(K, c))
        self.up = nn.Linear(c, d_model)
        self.init_weights()

    @torch.no_grad()
    def init_weights(self) -> None:
        for module in self.modules():
            if isinstance(module, nn.Linear):
                module.reset_parameters()
        # Each expert as an nn.Linear would start: U(±1/√fan_in) for weights and biases.
        for w, b in ((self.w1, self.b1), (self.w2, self.b2)):
            bound = 1 / math.sqrt(w.shape[1])
            nn.init.uniform_(w, -bound, bound)
            nn.init.uniform_(b, -bound, bound)
        for layer in (self.down, self.up):
            nn.init.zeros_(layer.weight)
            nn.init.zeros_(layer.bias)

    def attend(self, f: Tensor, tokens: Tensor, text_mask: Tensor) -> tuple[Tensor, Tensor]:
        """f (B, T, d_c), tokens (B, L, D_text) -> (f + A V (B, T, d_c), A (B, T, L)).

        A is 0 at padded tokens; a caption with no real token gets A = 0 (f passes unchanged).
        """
        q, k, v = self.q(f), self.k(tokens), self.v(tokens)  # (B, T, c), (B, L, c), (B, L, c)
        scores = q @ k.transpose(1, 2) / math.sqrt(q.shape[-1])  # (B, T, L)
        real = text_mask[:, None, :]  # (B, 1, L)
        # A finite fill (not -inf) keeps rows without any real token NaN-free; it underflows to
        # exactly 0 next to a real token, and the product with `real` zeroes those rows.
        scores = scores.masked_fill(~real, torch.finfo(scores.dtype).min)
        attn = scores.softmax(dim=-1) * real  # (B, T, L)
        return f + attn @ v, attn

    def adain(self, f: Tensor, eot_emb: Tensor, mask: Tensor | None) -> Tensor:
        """Normalise f (B, T, d_c) over real frames per channel; scale/shift from the EOT token."""
        if mask is None:
            mean = f.mean(dim=1, keepdim=True)  # (B, 1, c)
            var = f.var(dim=1, keepdim=True, unbiased=False)
        else:
            m = mask[..., None].to(f.dtype)  # (B, T, 1)
            n = m.sum(dim=1, keepdim=True).clamp_min(1)  # (B, 1, 1)
            mean = (f * m).sum(dim=1, keepdim=True) / n  # (B, 1, c)
            var = ((f - mean).square() * m).sum(dim=1, keepdim=True) / n
        scale, shift = self.eot_affine(eot_emb)[:, None, :].chunk(2, dim=-1)  # each (B, 1, c)
        return (f - mean) * torch.rsqrt(var + ADAIN_EPS) * (1 + scale) + shift

    def gates(self, tokens: Tensor) -> Tensor:
        """ω = softmax(G(e_i)): expert weights per token, (B, L, K)."""
        return self.gate(tokens).softmax(dim=-1)

    def token_masks(self, attn: Tensor, text_mask: Tensor, mask: Tensor | None) -> Tensor:
        """M_i = sigmoid(γ(A_i − β·max_frames A_i)) (B, T, L); 0 at padded tokens."""
        # A >= 0, so filling padded frames with 0 leaves the max over real frames unchanged.
        real_attn = attn if mask is None else attn.masked_fill(~mask[..., None], 0)
        peak = real_attn.amax(dim=1, keepdim=True)  # (B, 1, L)
        gamma, beta = self.config.gamma, self.config.beta
        return torch.sigmoid(gamma * (attn - beta * peak)) * text_mask[:, None, :]

    def experts(self, f: Tensor, omega: Tensor, masks: Tensor) -> Tensor:
        """Σ_i M_i ⊙ FFN_i(f) (B, T, d_c), FFN_i with parameters blended by ω_i.

        f (B, T, d_c), omega (B, L, K), masks (B, T, L). Blending is linear, so the blended
        weights are never built: layer 1 runs every expert once per frame and mixes the
        pre-activations per token; layer 2 folds M and ω into one (K, L) mix per frame before a
        single matmul with the stacked W2:
            pre_{t,i} = Σ_k ω_ik (f_t W1_k + b1_k),  g = gelu(pre)
            Σ_i M_ti (g_ti W2_i + b2_i) = Σ_k (Σ_i M_ti ω_ik g_ti) W2_k + Σ_i M_ti ω_i b2.
        Memory: pre and g are (B, T, L, H) each, the one cost that grows with B·L·T·hidden
        (base, B=64, T=300, L=20, H=512: 197M values per tensor per MoC layer, kept for
        backward unless activation checkpointing is on). FLOPs ≈ 4·B·T·K·H·(d_c + L), against
        4·B·T·L·d_c·H for per-token FFNs with materialised blended weights: ~K/L as much.
        """
        B, T, c = f.shape
        K, _, H = self.w1.shape
        u = (f @ self.w1.permute(1, 0, 2).reshape(c, K * H)).view(B, T, K, H)  # f W1_k
        pre = omega[:, None] @ u + (omega @ self.b1)[:, None]  # (B, T, L, H)
        g = F.gelu(pre)  # (B, T, L, H)
        mix = (masks[..., None] * omega[:, None]).transpose(-1, -2)  # (B, T, K, L) = M_ti ω_ik
        z = mix @ g  # (B, T, K, H)
        bias = masks @ (omega @ self.b2)  # (B, T, c)
        return z.reshape(B, T, K * H) @ self.w2.reshape(K * H, c) + bias  # (B, T, c)

    def forward(
        self,
        h: Tensor,
        tokens: Tensor,
        text_mask: Tensor,
        eot_emb: Tensor,
        mask: Tensor | None = None,
    ) -> Tensor:
        """h (B, T, d) copy-stream features, tokens (B, L, D_text), text_mask (B, L) bool,
        eot_emb (B, D_text), mask (B, T) bool real frames -> residual (B, T, d)."""
        f = self.down(h)  # (B, T, c)
        f, attn = self.attend(f, tokens, text_mask)  # (B, T, c), (B, T, L)
        f = self.adain(f, eot_emb, mask)  # (B, T, c)
        omega = self.gates(tokens)  # (B, L, K)
        masks = self.token_masks(attn, text_mask, mask)  # (B, T, L)
        return self.up(self.experts(f, omega, masks))  # (B, T, d)


class MotionControlNet(nn.Module):
    """Frozen ``MotionDiT`` + trainable block copies + MoC blocks + zero projections.

    ``forward`` is D_c, ``forward_uncond`` is D_u (the frozen model alone), ``forward_guided``
    the classifier-free-guidance mix. After loading new weights into ``base`` (or after
    ``to_empty`` from the meta device), call ``init_weights`` to re-copy the blocks and reset
    the controller.
    """

    def __init__(self, base: MotionDiT, config: MoCConfig) -> None:
        super().__init__()
        self.config = config
        n_layers, d = len(base.blocks), base.config.d_model
        self.controlled = config.controlled_layers(n_layers)
        self.copy_blocks = copy.deepcopy(base.blocks)  # (n_layers,) DiTBlock
        self.mocs = nn.ModuleDict({str(i): MoCBlock(d, config) for i in self.controlled})
        self.zero_projs = nn.ModuleList(nn.Linear(d, d) for _ in range(n_layers))
        self.base = base.requires_grad_(False).eval()
        for p in self.trainable_parameters():
            p.requires_grad_(True)
        self.init_weights()

    @torch.no_grad()
    def init_weights(self) -> None:
        """Copy the frozen blocks into the trainable ones, reset the MoC blocks, zero the
        projections."""
        for copy_block, block in zip(self.copy_blocks, self.base.blocks):
            for dst, src in zip(copy_block.parameters(), block.parameters()):
                dst.copy_(src)
        for moc in self.mocs.values():
            moc.init_weights()
        for proj in self.zero_projs:
            nn.init.zeros_(proj.weight)
            nn.init.zeros_(proj.bias)

    def trainable_parameters(self) -> Iterator[nn.Parameter]:
        """What the optimiser gets: copy blocks, MoC blocks and zero projections."""
        for module in (self.copy_blocks, self.mocs, self.zero_projs):
            yield from module.parameters()

    def train(self, mode: bool = True) -> MotionControlNet:
        super().train(mode)
        self.base.eval()  # frozen: no dropout, whatever the trainer asks for
        return self

    # -- pieces ---------------------------------------------------------------------------

    def _maybe_checkpoint(self, fn: Callable[..., Tensor], *args) -> Tensor:
        if self.base.config.activation_checkpointing and self.training and torch.is_grad_enabled():
            return checkpoint(fn, *args, use_reentrant=False)
        return fn(*args)

    def _prepare_text(
        self, tokens: Tensor, text_mask: Tensor, eot: Tensor
    ) -> tuple[Tensor, Tensor, Tensor]:
        """Zero the padded tokens (whatever they hold), follow the weights' dtype, pick the EOT
        embedding: -> tokens (B, L, D_text), text_mask (B, L) bool, eot_emb (B, D_text)."""
        if tokens.shape[-1] != self.config.text_dim:
            raise UsageError(
                f"text tokens have width {tokens.shape[-1]} but MoCConfig.text_dim="
                f"{self.config.text_dim}; set text_dim to the text encoder's token width"
            )
        text_mask = text_mask.bool()
        dtype = self.zero_projs[0].weight.dtype
        tokens = tokens.masked_fill(~text_mask[..., None], 0).to(dtype)  # (B, L, D_text)
        eot_emb = tokens[torch.arange(tokens.shape[0], device=tokens.device), eot]  # (B, D_text)
        return tokens, text_mask, eot_emb

    def _control_layer(
        self, i: int, h: Tensor, mod: Tensor, rope: Rope, mask: Tensor | None, text: tuple
    ) -> Tensor:
        h = self.copy_blocks[i](h, mod, rope, mask)  # (B, T, d)
        if str(i) in self.mocs:
            h = h + self.mocs[str(i)](h, *text, mask)
        return h

    def controls(
        self,
        h0: Tensor,
        mod: Tensor,
        rope: Rope,
        mask: Tensor | None,
        tokens: Tensor,
        text_mask: Tensor,
        eot: Tensor,
    ) -> list[Tensor]:
        """The copy stream from the frozen embedding h0 (B, T, d) -> one residual (B, T, d)
        per frozen block."""
        text = self._prepare_text(tokens, text_mask, eot)
        h, residuals = h0, []
        for i, proj in enumerate(self.zero_projs):
            h = self._maybe_checkpoint(self._control_layer, i, h, mod, rope, mask, text)
            residuals.append(proj(h))  # (B, T, d)
        return residuals

    def _frozen(
        self,
        h: Tensor,
        c: Tensor,
        mod: Tensor,
        rope: Rope,
        mask: Tensor | None,
        residuals: Sequence[Tensor],
        offset: int = 0,
    ) -> Tensor:
        """The frozen blocks and final layer; residual i is added to rows offset: of block i's
        output (offset = B on the doubled batch of ``forward_guided``)."""
        for block, r in zip(self.base.blocks, residuals):
            h = self._maybe_checkpoint(block, h, mod, rope, mask)  # (B', T, d)
            h = h + r if offset == 0 else torch.cat([h[:offset], h[offset:] + r])
        return self.base.final_layer(h, c)  # (B', T, D_in)

    # -- the three denoisers --------------------------------------------------------------

    def forward(
        self,
        x: Tensor,
        t: Tensor,
        text_tokens: Tensor,
        text_mask: Tensor,
        eot: Tensor,
        mask: Tensor | None = None,
    ) -> Tensor:
        """D_c: x (B, T, D_in) noisy motion, t (B,), text_tokens (B, L, D_text), text_mask
        (B, L) bool, eot (B,) long, mask (B, T) bool real frames -> x̂0 (B, T, D_in)."""
        h0, c, mod, rope = self.base.embed(x, t)
        residuals = self.controls(h0, mod, rope, mask, text_tokens, text_mask, eot)
        return self._frozen(h0, c, mod, rope, mask, residuals)

    def forward_uncond(self, x: Tensor, t: Tensor, mask: Tensor | None = None) -> Tensor:
        """D_u: the frozen pretrained model alone, (B, T, D_in)."""
        return self.base(x, t, mask)

    def forward_guided(
        self,
        x: Tensor,
        t: Tensor,
        text_tokens: Tensor,
        text_mask: Tensor,
        eot: Tensor,
        scale: float | Tensor,
        mask: Tensor | None = None,
    ) -> Tensor:
        """(1 − s)·D_u + s·D_c (B, T, D_in); scale s is a number or one per sample (B,).

        One embed, one controller pass on B, one frozen pass on [x; x] (2B) with residuals on
        the conditional half only.
        """
        B = x.shape[0]
        h0, c, mod, rope = self.base.embed(x, t)
        residuals = self.controls(h0, mod, rope, mask, text_tokens, text_mask, eot)
        mask2 = None if mask is None else torch.cat([mask, mask])
        out = self._frozen(
            torch.cat([h0, h0]), torch.cat([c, c]), torch.cat([mod, mod]), rope, mask2,
            residuals, offset=B,
        )  # (2B, T, D_in)
        uncond, cond = out[:B], out[B:]
        if isinstance(scale, Tensor) and scale.ndim > 0:
            scale = scale.to(out.dtype).view(-1, 1, 1)  # (B, 1, 1)
        return (1 - scale) * uncond + scale * cond
