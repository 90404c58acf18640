"""Motion ControlNet with Mixture-of-Controllers (OMG, Liang et al., CVPR 2024, Fig. 3, Sec. 3.2).

Stage 2 of OMG turns the unconditional pretrained ``MotionDiT`` into a text-to-motion model
without touching its weights. The pretrained model is frozen. Every controlled layer l (the
blocks in ``MoCConfig.layers``; default: all) gets a trainable copy of frozen block l and a
Mixture-of-Controllers (MoC) block. The copy reads h_l, the main-stream hidden state entering
frozen block l (which already carries the residuals of the layers before it); the MoC turns the
copy's output into token-masked residuals, whose sum is added to frozen block l's output:

    h_0, c, mod, rope = base.embed(x, t)        # h_0 (B, T, d), c (B, d), mod (B, 6d)
    for l in 0..n-1:
        h_{l+1} = frozen_l(h_l, mod, rope)      # (B, T, d), weights frozen
                + MoC_l(copy_l(h_l, mod, rope), text)   # (B, T, d), only where l is controlled
    D_c = base.final_layer(h_n, c)              # (B, T, D_in)

    MoC_l(g, text) = W_up Σ_i M_i ⊙ F_i(g, text)    # i over the caption's real tokens

(see ``MoCBlock``: g (B, T, d) -> W_down -> cross-attention to the tokens (B, L, D_text) ->
AdaIN from the EOT token -> K blended experts, one per token, and token masks M_i (B, T) ->
W_up, zero-initialised, back to d). A layer outside ``MoCConfig.layers`` has neither copy nor
MoC and adds nothing. At initialisation W_up = 0, so every residual is exactly 0 and D_c equals
the frozen model bit for bit, while the copies start as the pretrained blocks. The block loop is
the DiT's own (``MotionDiT.forward_embedded`` asks ``residual_fn(l, h_l)`` for each layer's
residual), with its activation checkpointing applied to the frozen blocks and, per layer, to
copy + MoC. Trainable parameters, Base (d 1024, 8 layers) with the paper's d_c 256, K 12 and
CLIP ViT-L/14 tokens (768): 122.4M = copies 84.0M + MoC 38.4M (4.8M per layer).

``MoCConfig.wiring = "parallel_stream"`` keeps an earlier, non-paper wiring for comparison: a
separate copy stream h^c (h^c_0 = h_0; h^c_{l+1} = copy_l(h^c_l) + MoC_l(copy_l(h^c_l))), which
never sees the main stream after the embedding, feeds every frozen layer through an extra
zero-initialised Linear(d, d) Z_l: h_{l+1} = frozen_l(h_l) + Z_l h^c_{l+1}. Every layer then has
a copy and a Z_l (+n·d² parameters: 8.4M for Base, 101M for Giant) and copies before the first
controller add a text-independent path into D_c.

Classifier-free guidance needs no dropped-text training: D_u is the frozen model itself, and
``forward_guided`` returns (1 - s)·D_u + s·D_c from one embed and one pass over the doubled
batch [x; x] (2B rows): each frozen block runs on all 2B rows, the copy + MoC of that layer on
the conditional half's main stream h_l[B:] (B rows), and its residual is added to the
conditional half only.

Spatial hints (``MoCConfig.hint_channels`` > 0; OmniControl's realism branch, Xie et al. ICLR 2024, Sec. 3.3):
a hint (B, T, C) per frame, the targets a user stated (``omg.lit.control.hint_features``), is embedded once,
e = H(hint) (B, T, d) with H = Linear(C, d) -> SiLU -> Linear(d, d) -> LayerNorm(d), and every block copy reads
h_l + e instead of h_l (the parallel stream: h^c_0 = h_0 + e). OmniControl's branch reads its hint at its input
alone, but its copies form one stream; here each copy reads the main stream, so each gets the hint. H starts at
PyTorch's init, not zero, and ends in a LayerNorm, so that a hint weighs in what a copy reads about as much as the
motion does from the first step: W_up = 0 already makes D_c the frozen model at initialisation, and a hint
embedded at a thirtieth of the stream's size (a zero or a plain MLP's output) was not read within a CPU run.
Hints fine-tuned onto a trained ControlNet (``ControlNetModule``'s ``pretrained``) start with H's output at zero
(``silence_hints``), so that the network starts as the text ControlNet it was. A motion
without constraints reads the empty hint (zeros, whose e is not 0 once trained), as the clips trained without
hints did (``ControlNetModule.denoiser``); given None, the copies read h_l alone.

Text arrives as three tensors (the fields of ``omg.text``'s features): tokens (B, L, D_text)
per-token embeddings, text_mask (B, L) bool, True = real token, and eot (B,) long, the index of
the end-of-text token. Padded tokens never reach the output (they are zeroed, masked out of the
attention and out of the residual sum), so captions can be padded to any length; the cost grows
with L, so pass tokens trimmed to the longest caption of the batch (``TextFeatures.trimmed``)
rather than CLIP's 77.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Iterator
from dataclasses import dataclass, replace
from typing import Callable

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from omg.errors import UsageError
from omg.models.dit import DiTConfig, MotionDiT, Rope
from omg.settings import overrides

ADAIN_EPS = 1e-5
WIRINGS = ("per_layer", "parallel_stream")
EXPERTS = ("moc", "single_ffn")

ResidualFn = Callable[[int, Tensor], "Tensor | None"]


@dataclass(frozen=True)
class MoCText:
    """Everything a MoC block computes from the caption alone, once per caption rather than
    once per denoising step (``MoCBlock.text_terms``): keys and values of the cross-attention,
    the AdaIN scale and shift from the EOT token, and the gate weights ω with their products
    with the expert biases. Fields of the single-FFN ablation's unused parts are None."""

    text_mask: Tensor  # (B, L) bool, True = real token
    keys: Tensor  # (B, L, d_c)  e W_k
    values: Tensor  # (B, L, d_c)  e W_v
    scale: Tensor  # (B, 1, d_c)  a(e_eot)
    shift: Tensor  # (B, 1, d_c)  b(e_eot)
    omega: Tensor | None = None  # (B, L, K)  softmax(G(e_i))
    omega_b1: Tensor | None = None  # (B, L, H)  Σ_k ω_ik b1_k
    omega_b2: Tensor | None = None  # (B, L, d_c)  Σ_k ω_ik b2_k


ControlText = dict[str, MoCText]  # per controlled layer (str index): MotionControlNet.text_terms


@dataclass
class MoCConfig:
    """The controller's size and, as switches, the paper's ablations (Sec. 4.4).

    Ablation switches (defaults: the full OMG model):
      token_masks=False   "w/o token masks": M_i ≡ 1 for every real token, so each token's
                          expert acts on every frame.
      zero_init=False     "w/o zero initialisation": W_down and W_up (and, with the parallel
                          stream, the projections Z_l) keep PyTorch's default Linear init, so
                          D_c differs from D_u from the first step.
      experts="single_ffn"  "cross-attention + FFN": the expert pool is replaced by one FFN
                          (d_c -> expert_hidden -> d_c) on the attended, AdaIN-normalised
                          features; no gate, no blending, no token masks (num_experts,
                          gate_hidden, gamma, beta and token_masks are unused).
      layers              which blocks get a controller (copy + MoC); None: every block.
      wiring              "per_layer" (paper, Fig. 3) or "parallel_stream" (see the module
                          docstring), for comparison only.
    """

    d_c: int = 256  # controller width
    num_experts: int = 12  # K, size of the expert pool
    expert_hidden: int | None = None  # hidden width of each expert; None: 2·d_c
    gamma: float = 24.0  # sharpness of the token masks
    beta: float = 0.25  # mask threshold, relative to the token's strongest frame
    gate_hidden: int | None = None  # hidden width of the gating MLP G; None: d_c
    layers: list[int] | None = None  # blocks with a controller; None: every block
    text_dim: int = 512  # D_text: width of the text token embeddings (CLIP ViT-B: 512)
    token_masks: bool = True  # ablation "w/o token masks" when False
    zero_init: bool = True  # ablation "w/o zero initialisation" when False
    experts: str = "moc"  # "moc" (K blended experts per token) | "single_ffn" (ablation)
    wiring: str = "per_layer"  # "per_layer" (paper) | "parallel_stream" (comparison)
    hint_channels: int = 0  # C: spatial-hint channels a frame, read by the block copies (0: none; MotionControlNet)

    def __post_init__(self) -> None:
        if self.expert_hidden is None:
            self.expert_hidden = 2 * self.d_c
        if self.gate_hidden is None:
            self.gate_hidden = self.d_c
        for name in ("d_c", "num_experts", "expert_hidden", "gate_hidden", "text_dim"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise UsageError(f"MoCConfig.{name}={value!r} must be a positive integer")
        if isinstance(self.hint_channels, bool) or not isinstance(self.hint_channels, int) or self.hint_channels < 0:
            raise UsageError(f"MoCConfig.hint_channels={self.hint_channels!r} must be an integer >= 0")
        gamma = self.gamma
        if not (isinstance(gamma, (int, float)) and math.isfinite(gamma) and gamma > 0):
            raise UsageError(f"MoCConfig.gamma={gamma!r} must be a positive number (paper: 24)")
        if not (isinstance(self.beta, (int, float)) and 0 <= self.beta <= 1):
            raise UsageError(f"MoCConfig.beta={self.beta!r} must lie in [0, 1] (paper: 0.25)")
        for name in ("token_masks", "zero_init"):
            if not isinstance(getattr(self, name), bool):
                raise UsageError(f"MoCConfig.{name}={getattr(self, name)!r} must be true or false")
        for name, choices in (("experts", EXPERTS), ("wiring", WIRINGS)):
            if getattr(self, name) not in choices:
                raise UsageError(
                    f"MoCConfig.{name}={getattr(self, name)!r} must be one of {', '.join(choices)}"
                )
        if self.layers is not None:
            layers = list(self.layers)
            bad = [i for i in layers if isinstance(i, bool) or not isinstance(i, int) or i < 0]
            if not layers or bad or len(set(layers)) != len(layers):
                raise UsageError(
                    f"MoCConfig.layers={self.layers!r} must be None (every block) or a non-empty "
                    "list of distinct block indices >= 0"
                )
            self.layers = sorted(layers)

    def flops(self, dit: DiTConfig, batch: int, seq_len: int, text_len: int) -> int:
        """Analytic forward FLOPs (2 per multiply-add) of the trainable part on ``dit``: the block
        copies, the MoC blocks and (parallel stream) the zero projections, for ``text_len`` tokens.

        Per frame and controlled layer, MoC: W_down, W_q, W_up 2·(2·d·c + c²), attention 4·L·c,
        the experts 4·K·H·(c + L) (``MoCBlock.experts``), the bias mix 2·L·c; single FFN instead of
        the experts and the mix: 4·c·H. Per sample and controlled layer, the text terms: keys and
        values 4·L·D·c, AdaIN from the EOT 4·D·c, with experts the gate MLP 2·L·(D·G + G² + G·K) and
        ω·b1, ω·b2 2·L·K·(H + c). A copy costs what its frozen block costs (``DiTConfig.flops``);
        a zero projection 2·d² per frame. Elementwise work (AdaIN, masks, gelu) is not counted."""
        d, c, L, D = dit.d_model, self.d_c, text_len, self.text_dim
        K, H, G = self.num_experts, self.expert_hidden, self.gate_hidden
        controlled = len(self.controlled_layers(dit.n_layers))
        copies = dit.n_layers if self.wiring == "parallel_stream" else controlled
        block = 8 * d * d + 6 * d * dit.ffn_dim + 4 * seq_len * d  # one block, per frame (DiTConfig.flops)
        moc_frame = 2 * (2 * d * c + c * c) + 4 * L * c
        moc_sample = 4 * L * D * c + 4 * D * c
        if self.experts == "single_ffn":
            moc_frame += 4 * c * H
        else:
            moc_frame += 4 * K * H * (c + L) + 2 * L * c
            moc_sample += 2 * L * (D * G + G * G + G * K) + 2 * L * K * (H + c)
        per_frame = copies * block + controlled * moc_frame
        if self.hint_channels:  # the hint embedding, once per frame
            per_frame += 2 * (self.hint_channels * d + d * d)
        if self.wiring == "parallel_stream":
            per_frame += dit.n_layers * 2 * d * d
        return batch * (seq_len * per_frame + controlled * moc_sample)

    def controlled_layers(self, n_layers: int) -> list[int]:
        """The block indices that get a controller, checked against the model's depth."""
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
    at init, and the ControlNet starts as the frozen model.

    Ablations (``MoCConfig``): token_masks=False sets M_i = 1 for every real token;
    zero_init=False keeps W_down, W_up at PyTorch's default init; experts="single_ffn" replaces
    the gate, the expert pool and the masks by one FFN: out = W_up FFN(f̃), with
    FFN(f̃) = gelu(f̃ W1 + b1) W2 + b2 (d_c -> expert_hidden -> d_c).
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
        if config.experts == "single_ffn":  # ablation: one FFN, no gate, no token masks
            self.ffn = nn.Sequential(nn.Linear(c, H), nn.GELU(), nn.Linear(H, c))
        else:
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
        if self.config.experts == "moc":
            # Each expert as an nn.Linear would start: U(±1/√fan_in) for weights and biases.
            for w, b in ((self.w1, self.b1), (self.w2, self.b2)):
                bound = 1 / math.sqrt(w.shape[1])
                nn.init.uniform_(w, -bound, bound)
                nn.init.uniform_(b, -bound, bound)
        if self.config.zero_init:
            for layer in (self.down, self.up):
                nn.init.zeros_(layer.weight)
                nn.init.zeros_(layer.bias)

    def text_terms(self, tokens: Tensor, text_mask: Tensor, eot_emb: Tensor, fold_biases: bool = False) -> MoCText:
        """What this block needs of a caption: tokens (B, L, D_text), text_mask (B, L) bool,
        eot_emb (B, D_text) -> ``MoCText`` (computed once, used at every step).

        ``fold_biases`` also computes ω·b1 and ω·b2 here (sampling). Training leaves them to
        ``experts``, where they are used: ω then receives its four gradient terms in the same
        order as when nothing is hoisted, so training rounds exactly as before."""
        scale, shift = self.eot_affine(eot_emb)[:, None, :].chunk(2, dim=-1)  # each (B, 1, c)
        text = MoCText(text_mask, self.k(tokens), self.v(tokens), scale, shift)
        if self.config.experts == "single_ffn":
            return text
        omega = self.gates(tokens)  # (B, L, K)
        if not fold_biases:
            return replace(text, omega=omega)
        return replace(text, omega=omega, omega_b1=omega @ self.b1, omega_b2=omega @ self.b2)

    def attend(self, f: Tensor, text: MoCText) -> tuple[Tensor, Tensor]:
        """f (B, T, d_c) -> (f + A V (B, T, d_c), A (B, T, L)).

        A is 0 at padded tokens; a caption with no real token gets A = 0 (f passes unchanged).
        """
        q, k, v = self.q(f), text.keys, text.values  # (B, T, c), (B, L, c), (B, L, c)
        scores = q @ k.transpose(1, 2) / math.sqrt(q.shape[-1])  # (B, T, L)
        real = text.text_mask[:, None, :]  # (B, 1, L)
        # A finite fill (not -inf) keeps rows without any real token NaN-free; it underflows to
        # exactly 0 next to a real token, and the product with `real` zeroes those rows.
        scores = scores.masked_fill(~real, torch.finfo(scores.dtype).min)
        attn = scores.softmax(dim=-1) * real  # (B, T, L)
        return f + attn @ v, attn

    def adain(self, f: Tensor, text: MoCText, mask: Tensor | None) -> Tensor:
        """Normalise f (B, T, d_c) over real frames per channel; scale/shift from the EOT token."""
        if mask is None:
            mean = f.mean(dim=1, keepdim=True)  # (B, 1, c)
            var = f.var(dim=1, keepdim=True, unbiased=False)
        else:
            m = mask[..., None].to(f.dtype)  # (B, T, 1)
            n = m.sum(dim=1, keepdim=True).clamp_min(1)  # (B, 1, 1)
            mean = (f * m).sum(dim=1, keepdim=True) / n  # (B, 1, c)
            var = ((f - mean).square() * m).sum(dim=1, keepdim=True) / n
        return (f - mean) * torch.rsqrt(var + ADAIN_EPS) * (1 + text.scale) + text.shift

    def gates(self, tokens: Tensor) -> Tensor:
        """ω = softmax(G(e_i)): expert weights per token, (B, L, K)."""
        return self.gate(tokens).softmax(dim=-1)

    def token_masks(self, attn: Tensor, text_mask: Tensor, mask: Tensor | None) -> Tensor:
        """M_i = sigmoid(γ(A_i − β·max_frames A_i)) (B, T, L); 0 at padded tokens.

        With ``MoCConfig.token_masks`` off (ablation): M_i = 1 at every real token."""
        if not self.config.token_masks:
            return text_mask[:, None, :].to(attn.dtype).expand_as(attn)
        # A >= 0, so filling padded frames with 0 leaves the max over real frames unchanged.
        real_attn = attn if mask is None else attn.masked_fill(~mask[..., None], 0)
        peak = real_attn.amax(dim=1, keepdim=True)  # (B, 1, L)
        gamma, beta = self.config.gamma, self.config.beta
        return torch.sigmoid(gamma * (attn - beta * peak)) * text_mask[:, None, :]

    def experts(self, f: Tensor, text: MoCText, masks: Tensor) -> Tensor:
        """Σ_i M_i ⊙ FFN_i(f) (B, T, d_c), FFN_i with parameters blended by ω_i.

        f (B, T, d_c), text.omega (B, L, K) with ω·b1, ω·b2, masks (B, T, L). Blending is linear, so the blended
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
        omega = text.omega
        # (B, T, L, H): ω·b1 is made after ω·u, as without hoisting (see text_terms)
        pre = omega[:, None] @ u + (omega @ self.b1 if text.omega_b1 is None else text.omega_b1)[:, None]
        g = F.gelu(pre)  # (B, T, L, H)
        mix = (masks[..., None] * omega[:, None]).transpose(-1, -2)  # (B, T, K, L) = M_ti ω_ik
        z = mix @ g  # (B, T, K, H)
        bias = masks @ (omega @ self.b2 if text.omega_b2 is None else text.omega_b2)  # (B, T, c)
        return z.reshape(B, T, K * H) @ self.w2.reshape(K * H, c) + bias  # (B, T, c)

    def forward(self, h: Tensor, text: MoCText, mask: Tensor | None = None) -> Tensor:
        """h (B, T, d) the block copy's output, ``text_terms`` of the caption, mask (B, T) bool
        real frames -> residual (B, T, d)."""
        f = self.down(h)  # (B, T, c)
        f, attn = self.attend(f, text)  # (B, T, c), (B, T, L)
        f = self.adain(f, text, mask)  # (B, T, c)
        if self.config.experts == "single_ffn":
            return self.up(self.ffn(f))  # (B, T, d)
        masks = self.token_masks(attn, text.text_mask, mask)  # (B, T, L)
        return self.up(self.experts(f, text, masks))  # (B, T, d)


# model.init_args.moc of ControlNetModule: MoCConfig's fields but text_dim (the text encoder's) and hint_channels
# (the skeleton's, with model.init_args.hints), each None (unset) MoCConfig's default
MoCOverrides = overrides(MoCConfig, "MoCOverrides", __name__, exclude=("text_dim", "hint_channels"),
                         doc="MoCConfig fields to override (unset: MoCConfig's default).")


class MotionControlNet(nn.Module):
    """Frozen ``MotionDiT`` + per-layer trainable block copies and MoC blocks.

    ``forward`` is D_c, ``forward_uncond`` is D_u (the frozen model alone), ``forward_guided``
    the classifier-free-guidance mix. ``copy_blocks`` and ``mocs`` are keyed by block index
    (str). After loading new weights into ``base`` (or after ``to_empty`` from the meta
    device), call ``init_weights`` to re-copy the blocks and reset the controllers.
    """

    def __init__(self, base: MotionDiT, config: MoCConfig) -> None:
        super().__init__()
        self.config = config
        n_layers, d = len(base.blocks), base.config.d_model
        self.controlled = config.controlled_layers(n_layers)
        parallel = config.wiring == "parallel_stream"
        copied = range(n_layers) if parallel else self.controlled
        self.copy_blocks = nn.ModuleDict({str(i): copy.deepcopy(base.blocks[i]) for i in copied})
        self.mocs = nn.ModuleDict({str(i): MoCBlock(d, config) for i in self.controlled})
        if parallel:
            self.zero_projs = nn.ModuleList(nn.Linear(d, d) for _ in range(n_layers))
        if config.hint_channels:
            self.hint_embed = nn.Sequential(nn.Linear(config.hint_channels, d), nn.SiLU(), nn.Linear(d, d),
                                            nn.LayerNorm(d))
        self.base = base.requires_grad_(False).eval()
        for p in self.trainable_parameters():
            p.requires_grad_(True)
        self.init_weights()

    @torch.no_grad()
    def init_weights(self) -> None:
        """Copy the frozen blocks into the trainable ones, reset the MoC blocks (and the
        parallel stream's projections)."""
        for i, copy_block in self.copy_blocks.items():
            for dst, src in zip(copy_block.parameters(), self.base.blocks[int(i)].parameters()):
                dst.copy_(src)
        for moc in self.mocs.values():
            moc.init_weights()
        for proj in getattr(self, "zero_projs", ()):
            proj.reset_parameters()
            if self.config.zero_init:
                nn.init.zeros_(proj.weight)
                nn.init.zeros_(proj.bias)
        for layer in getattr(self, "hint_embed", ()):  # PyTorch's init: W_up = 0 keeps D_c = D_u whatever it reads
            if isinstance(layer, (nn.Linear, nn.LayerNorm)):
                layer.reset_parameters()

    @torch.no_grad()
    def silence_hints(self) -> None:
        """Zero the hint embedding's output (its LayerNorm's gain and shift), so that a hint changes nothing: the
        start of hints fine-tuned onto a trained ControlNet, whose W_up is no longer zero."""
        nn.init.zeros_(self.hint_embed[-1].weight)
        nn.init.zeros_(self.hint_embed[-1].bias)

    def trainable_parameters(self) -> Iterator[nn.Parameter]:
        """What the optimiser gets: everything but the frozen ``base``."""
        for name, module in self.named_children():
            if name != "base":
                yield from module.parameters()

    def train(self, mode: bool = True) -> MotionControlNet:
        super().train(mode)
        self.base.eval()  # frozen: no dropout, whatever the trainer asks for
        return self

    # -- pieces ---------------------------------------------------------------------------

    def text_terms(self, tokens: Tensor, text_mask: Tensor, eot: Tensor, fold_biases: bool = False) -> ControlText:
        """Every controller's ``MoCText`` for a caption batch: tokens (B, L, D_text), text_mask
        (B, L) bool, eot (B,) long. What depends only on the text is computed here, once: a
        sampler passes the result (``fold_biases=True``, see ``MoCBlock.text_terms``) to
        ``forward_guided`` at every step."""
        if tokens.shape[-1] != self.config.text_dim:
            raise UsageError(
                f"text tokens have width {tokens.shape[-1]} but MoCConfig.text_dim="
                f"{self.config.text_dim}; set text_dim to the text encoder's token width"
            )
        text_mask = text_mask.bool()
        dtype = next(iter(self.mocs.values())).k.weight.dtype
        tokens = tokens.masked_fill(~text_mask[..., None], 0).to(dtype)  # (B, L, D_text): padding zeroed
        eot_emb = tokens[torch.arange(tokens.shape[0], device=tokens.device), eot]  # (B, D_text)
        return {i: moc.text_terms(tokens, text_mask, eot_emb, fold_biases) for i, moc in self.mocs.items()}

    def embed_hint(self, hint: Tensor | None, dtype: torch.dtype) -> Tensor | None:
        """hint (B or 1, T, C) -> e (B or 1, T, d) that the block copies add to what they read; None without one.
        A network without hint channels refuses a hint (it would be ignored)."""
        if hint is None:
            return None
        if not self.config.hint_channels:
            raise UsageError("this ControlNet was not trained with spatial hints (model.init_args.hints): "
                             "its constraints are met by steering alone")
        if hint.shape[-1] != self.config.hint_channels:
            raise ValueError(f"a hint of {hint.shape[-1]} channels for a ControlNet of {self.config.hint_channels}")
        return self.hint_embed(hint.to(dtype))

    def _layer_residual(
        self, i: int, h: Tensor, mod: Tensor, rope: Rope, mask: Tensor | None, text: ControlText
    ) -> Tensor:
        """Per-layer wiring: MoC_i(copy_i(h_i)) (B, T, d) from block i's input h_i (B, T, d)."""
        return self.mocs[str(i)](self.copy_blocks[str(i)](h, mod, rope, mask), text[str(i)], mask)

    def _stream_layer(
        self, i: int, h: Tensor, mod: Tensor, rope: Rope, mask: Tensor | None, text: ControlText
    ) -> Tensor:
        """Parallel-stream wiring: the copy stream's next state (B, T, d)."""
        h = self.copy_blocks[str(i)](h, mod, rope, mask)
        if str(i) in self.mocs:
            h = h + self.mocs[str(i)](h, text[str(i)], mask)
        return h

    def controller(self, h0: Tensor, mod: Tensor, rope: Rope, mask: Tensor | None, text: ControlText,
                   hint: Tensor | None = None) -> ResidualFn:
        """The ``residual_fn(i, h_i)`` that ``MotionDiT.forward_embedded`` calls after block i:
        block i's residual (B, T, d) from its input h_i (B, T, d), or None for a layer without
        a controller. h0, mod, rope come from ``base.embed`` (h0 only feeds the parallel
        stream, whose function keeps the stream's state and must be called for i = 0, 1, ...);
        ``text`` from ``text_terms``; ``hint`` the embedded hint (B or 1, T, d) the copies add to what they
        read (``embed_hint``), or None."""
        if self.config.wiring == "per_layer":

            def residual(i: int, h: Tensor) -> Tensor | None:
                if str(i) not in self.mocs:
                    return None
                return self._layer_residual(i, h if hint is None else h + hint, mod, rope, mask, text)

            return residual

        stream = [h0 if hint is None else h0 + hint]

        def stream_residual(i: int, h: Tensor) -> Tensor:
            stream[0] = self._stream_layer(i, stream[0], mod, rope, mask, text)
            return self.zero_projs[i](stream[0])

        return stream_residual

    # -- the three denoisers --------------------------------------------------------------

    def forward(
        self,
        x: Tensor,
        t: Tensor,
        text_tokens: Tensor,
        text_mask: Tensor,
        eot: Tensor,
        mask: Tensor | None = None,
        hint: Tensor | None = None,
    ) -> Tensor:
        """D_c: x (B, T, D_in) noisy motion, t (B,), text_tokens (B, L, D_text), text_mask
        (B, L) bool, eot (B,) long, mask (B, T) bool real frames, hint (B, T, C) spatial hints
        (``MoCConfig.hint_channels``; None: none) -> x̂0 (B, T, D_in)."""
        h0, c, mod, rope = self.base.embed(x, t)
        control = self.controller(h0, mod, rope, mask, self.text_terms(text_tokens, text_mask, eot),
                                  self.embed_hint(hint, h0.dtype))
        return self.base.forward_embedded(h0, c, mod, rope, mask, control)

    def forward_uncond(self, x: Tensor, t: Tensor, mask: Tensor | None = None) -> Tensor:
        """D_u: the frozen pretrained model alone, (B, T, D_in)."""
        return self.base(x, t, mask)

    def forward_guided(
        self, x: Tensor, t: Tensor, text: ControlText, scale: float | Tensor, mask: Tensor | None = None,
        hint: Tensor | None = None,
    ) -> Tensor:
        """(1 − s)·D_u + s·D_c (B, T, D_in) for the caption terms ``text = text_terms(tokens,
        text_mask, eot)``, computed once per caption by the sampler; scale s is a number or one
        per sample (B,); ``hint`` (B or 1, T, d) an embedded hint (``embed_hint``) for D_c, computed once per
        request too (the frozen D_u reads none).

        One embed on B rows, then one pass over the doubled batch [x; x] (2B rows): the frozen
        blocks run on all rows, each controller on the conditional half's main stream
        h_i[B:] (B rows), its residual added to that half only.
        """
        B = x.shape[0]
        h0, c, mod, rope = self.base.embed(x, t)
        control = self.controller(h0, mod, rope, mask, text, hint)

        def residual(i: int, h: Tensor) -> Tensor | None:  # h (2B, T, d) = [uncond; cond]
            r = control(i, h[B:])  # (B, T, d)
            return None if r is None else torch.cat([torch.zeros_like(r), r])

        mask2 = None if mask is None else torch.cat([mask, mask])
        out = self.base.forward_embedded(
            torch.cat([h0, h0]), torch.cat([c, c]), torch.cat([mod, mod]), rope, mask2, residual
        )  # (2B, T, D_in)
        uncond, cond = out[:B], out[B:]
        if isinstance(scale, Tensor) and scale.ndim > 0:
            scale = scale.to(out.dtype).view(-1, 1, 1)  # (B, 1, 1)
        return (1 - scale) * uncond + scale * cond
