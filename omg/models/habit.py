"""Habit-preserved cross-category animal motion transfer ("Behave Your Motion", the model part).

- ``MotionVQVAE``: the T2M-GPT convolutional VQ-VAE. A 1-D conv encoder (two stride-2
  down-samplings: rate 4; residual blocks of dilated convolutions, dilation growing by 3, ReLU)
  reads the motion together with the category's habit latent z and its text embedding (projected
  to 256-d), a ``Quantizer`` turns each latent frame into a code of a 512-code book, and the
  decoder (nearest-neighbour up-sampling) turns codes back into motion.
- ``Quantizer``: soft sampling (squared distances -> softmax at a temperature -> a sampled
  index; the paper's) or the nearest code (option); the codebook follows an EMA of the
  encoder outputs assigned to it, and with ``code_reset`` dead codes restart at encoder outputs
  ("EMA" and "EMA-reset", the paper's two rows).
- ``HabitEncoder``: a transformer posterior q(z | m) = N(mu, sigma) for each known category.
- ``CouplingFlow`` / ``CategoryFlows``: the habit prior p(z) of each category, a normalizing flow
  of affine coupling layers over an isotropic Gaussian, trained by negative log-likelihood.
- ``HabitStatsDecoder`` / ``habit_statistics``: what the habit encoders are pretrained to tell under
  their flow priors (``habit_order: flow_prior``): the mean and standard deviation over time of each
  local joint rotation channel of a motion crop (not the root's nor the velocities: they hold the
  path), from its habit latent alone; ``flow_prior_kl``: the one-sample estimate of
  KL(q(z | m) || p_flow(z)) that regularises the posterior there instead of KL to N(0, I).

Plain torch; shapes in comments (B batch, T frames, D features, C code width, K codes, Z habit
latent width, E text embedding width, N categories).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from omg.errors import UsageError
from omg.models.positions import sinusoidal_positions
from omg.settings import overrides

QUANTIZERS = ("soft", "nearest")


@dataclass(frozen=True)
class HabitConfig:
    """Sizes of the VQ-VAE, the habit encoders and the flows. ``base`` is the paper's (T2M-GPT sizes)."""

    name: str = "custom"
    width: int = 512  # conv channels (T2M-GPT)
    depth: int = 3  # residual blocks per resolution (T2M-GPT)
    down_t: int = 2  # stride-2 down-samplings: rate 4 (paper)
    dilation_growth: int = 3  # dilation 1, 3, 9 in each residual stack (paper: dilation 3)
    code_dim: int = 512  # C
    num_codes: int = 512  # K, the codebook size (paper)
    text_dim: int = 256  # the category text embedding is mapped to 256-d (paper)
    habit_dim: int = 64  # Z, the habit latent
    habit_layers: int = 4  # habit encoder transformer (paper: 4 layers, width 512, 8 heads)
    habit_width: int = 512
    habit_heads: int = 8
    flow_layers: int = 6  # affine coupling layers of each category's prior
    flow_hidden: int = 256
    dropout: float = 0.1

    def __post_init__(self) -> None:
        if self.habit_width % self.habit_heads:
            raise UsageError(f"habit_width={self.habit_width} is not divisible by habit_heads={self.habit_heads}")
        if min(self.width, self.depth, self.down_t, self.code_dim, self.num_codes, self.text_dim, self.habit_dim,
               self.habit_layers, self.flow_layers, self.flow_hidden, self.dilation_growth) < 1:
            raise UsageError(f"habit model sizes must be positive: {self}")
        if self.habit_dim < 2:
            raise UsageError(f"habit_dim must be >= 2 (a coupling layer splits it), got {self.habit_dim}")

    @property
    def rate(self) -> int:
        """Frames per code."""
        return 2 ** self.down_t

    @classmethod
    def from_name(cls, name: str, **overrides: Any) -> HabitConfig:
        if name not in FLAVORS:
            raise UsageError(f"unknown habit flavor {name!r}; known flavors: {', '.join(FLAVORS)}")
        if unknown := set(overrides) - set(cls.__dataclass_fields__) - {"name"}:
            raise UsageError(f"unknown habit model field(s) {sorted(unknown)} (model.init_args.habit); "
                             f"fields: {', '.join(f for f in cls.__dataclass_fields__ if f != 'name')}")
        return replace(FLAVORS[name], **overrides)


FLAVORS = {
    "base": HabitConfig("base"),
    "mini": HabitConfig("mini", width=64, depth=2, code_dim=64, num_codes=128, text_dim=64, habit_dim=16,
                        habit_layers=2, habit_width=64, habit_heads=4, flow_layers=4, flow_hidden=64, dropout=0.0),
    "tiny": HabitConfig("tiny", width=32, depth=1, code_dim=32, num_codes=32, text_dim=16, habit_dim=8,
                        habit_layers=1, habit_width=32, habit_heads=2, flow_layers=2, flow_hidden=32, dropout=0.0),
}

# model.init_args.habit of HabitVQModule: HabitConfig's fields, each None (unset) the flavor's value
HabitOverrides = overrides(HabitConfig, "HabitOverrides", __name__,
                           doc="HabitConfig fields to override in the flavor's (unset: the flavor's value).")


# ----------------------------------------------------------------------------- VQ-VAE


class ResConv1D(nn.Module):
    """x + conv1x1(relu(conv3(relu(x)))) with a dilated 3-tap conv (T2M-GPT's ResConv1DBlock)."""

    def __init__(self, channels: int, dilation: int):
        super().__init__()
        self.conv1 = nn.Conv1d(channels, channels, 3, padding=dilation, dilation=dilation)
        self.conv2 = nn.Conv1d(channels, channels, 1)

    def forward(self, x: Tensor) -> Tensor:  # (B, C, T) -> (B, C, T)
        return x + self.conv2(F.relu(self.conv1(F.relu(x))))


def res_stack(channels: int, depth: int, growth: int, reverse: bool = False) -> nn.Sequential:
    """``depth`` residual blocks with dilations growth**0, growth**1, ...; the decoder runs them reversed."""
    dilations = [growth**i for i in range(depth)]
    return nn.Sequential(*(ResConv1D(channels, d) for d in (dilations[::-1] if reverse else dilations)))


class ConvEncoder(nn.Module):
    def __init__(self, in_dim: int, c: HabitConfig):
        super().__init__()
        layers: list[nn.Module] = [nn.Conv1d(in_dim, c.width, 3, padding=1), nn.ReLU()]
        for _ in range(c.down_t):
            layers += [nn.Conv1d(c.width, c.width, 4, stride=2, padding=1), res_stack(c.width, c.depth,
                                                                                    c.dilation_growth)]
        layers.append(nn.Conv1d(c.width, c.code_dim, 3, padding=1))
        self.net = nn.Sequential(*layers)

    def forward(self, x: Tensor) -> Tensor:  # (B, D_in, T) -> (B, C, T / rate)
        return self.net(x)


class ConvDecoder(nn.Module):
    def __init__(self, out_dim: int, c: HabitConfig, cond_dim: int = 0):
        super().__init__()
        layers: list[nn.Module] = [nn.Conv1d(c.code_dim + cond_dim, c.width, 3, padding=1), nn.ReLU()]
        for _ in range(c.down_t):
            layers += [res_stack(c.width, c.depth, c.dilation_growth, reverse=True),
                       nn.Upsample(scale_factor=2, mode="nearest"), nn.Conv1d(c.width, c.width, 3, padding=1)]
        layers += [nn.Conv1d(c.width, c.width, 3, padding=1), nn.ReLU(), nn.Conv1d(c.width, out_dim, 3, padding=1)]
        self.net = nn.Sequential(*layers)

    def forward(self, x: Tensor) -> Tensor:  # (B, C (+ cond), T / rate) -> (B, D, T)
        return self.net(x)


class Quantizer(nn.Module):
    """A codebook of K codes kept by exponential moving averages (no gradient reaches it).

    ``forward`` assigns each latent a code: ``soft`` samples an index from
    softmax(-‖x − e_k‖² / temperature) (at temperature → 0 the nearest code), ``nearest`` takes
    the arg-min. In training the codebook then moves towards the mean of the latents assigned to
    each code: with n_k and s_k the count and sum of the latents assigned to code k,
    N_k ← μ N_k + (1 − μ) n_k, S_k ← μ S_k + (1 − μ) s_k, e_k = S_k / N_k for codes with N_k ≥ 1.
    A code with N_k < 1 keeps its vector, or with ``code_reset`` restarts at a random latent of
    the batch (T2M-GPT's QuantizeEMAReset). The codebook starts at the first batch's latents.
    """

    def __init__(self, num_codes: int, code_dim: int, mode: str = "soft", temperature: float = 1.0,
                 decay: float = 0.99, code_reset: bool = True):
        super().__init__()
        if mode not in QUANTIZERS:
            raise UsageError(f"quantizer must be one of {', '.join(QUANTIZERS)}, got {mode!r}")
        if not temperature > 0 or not 0 <= decay < 1:
            raise UsageError(f"quantizer temperature must be > 0 and decay in [0, 1), got {temperature}, {decay}")
        self.mode, self.temperature, self.decay, self.code_reset = mode, temperature, decay, code_reset
        self.register_buffer("codebook", torch.zeros(num_codes, code_dim))  # (K, C)
        self.register_buffer("code_sum", torch.zeros(num_codes, code_dim))  # (K, C) S
        self.register_buffer("code_count", torch.zeros(num_codes))  # (K,) N
        self.register_buffer("initialized", torch.tensor(False))

    @property
    def num_codes(self) -> int:
        return self.codebook.shape[0]

    def distances(self, x: Tensor) -> Tensor:  # (M, C) -> (M, K) squared Euclidean
        return (x.square().sum(-1, keepdim=True) - 2 * x @ self.codebook.T
                + self.codebook.square().sum(-1)[None]).clamp_min(0)

    def assign(self, x: Tensor, generator: torch.Generator | None = None, mode: str | None = None) -> Tensor:
        """(M, C) latents -> (M,) code indices, by ``mode`` (default: this quantizer's)."""
        d = self.distances(x)
        if (mode or self.mode) == "nearest":
            return d.argmin(-1)
        probs = torch.softmax(-d / self.temperature, dim=-1)
        where = generator.device if generator is not None else probs.device  # a CPU generator draws on the CPU
        return torch.multinomial(probs.to(where), 1, generator=generator).squeeze(-1).to(x.device)

    @torch.no_grad()
    def _random_latents(self, x: Tensor, count: int, generator: torch.Generator | None) -> Tensor:
        """``count`` rows of ``x`` drawn at random (repeated when x has fewer rows)."""
        repeats = math.ceil(count / len(x))
        pool = x.repeat(repeats, 1) if repeats > 1 else x
        where = generator.device if generator is not None else x.device
        return pool[torch.randperm(len(pool), generator=generator, device=where)[:count].to(x.device)]

    @torch.no_grad()
    def init_codebook(self, x: Tensor, generator: torch.Generator | None = None) -> None:
        codes = self._random_latents(x, self.num_codes, generator)
        self.codebook.copy_(codes)
        self.code_sum.copy_(codes)
        self.code_count.fill_(1.0)
        self.initialized.fill_(True)

    @torch.no_grad()
    def ema_update(self, x: Tensor, indices: Tensor, generator: torch.Generator | None = None) -> Tensor:
        """One EMA step from latents (M, C) and their codes (M,); returns the (K,) bool mask of codes reset."""
        onehot = F.one_hot(indices, self.num_codes).to(x.dtype)  # (M, K)
        mu = self.decay
        self.code_count.mul_(mu).add_(onehot.sum(0), alpha=1 - mu)  # N
        self.code_sum.mul_(mu).add_(onehot.T @ x, alpha=1 - mu)  # S
        used = self.code_count >= 1.0  # (K,)
        updated = self.code_sum / self.code_count.clamp_min(1e-12)[:, None]
        self.codebook.copy_(torch.where(used[:, None], updated, self.codebook))
        dead = ~used
        if self.code_reset and dead.any():
            fresh = self._random_latents(x, int(dead.sum()), generator)
            self.codebook[dead] = fresh
            self.code_sum[dead] = fresh
            self.code_count[dead] = 1.0
        return dead

    def forward(self, x: Tensor, generator: torch.Generator | None = None,
                mask: Tensor | None = None) -> tuple[Tensor, Tensor, dict[str, Tensor]]:
        """x (B, C, T') -> (quantized (B, C, T') with straight-through gradients, indices (B, T'),
        {commitment, embedding, perplexity}). ``mask`` (B, T') marks real latent frames: only they
        update the codebook and count in the losses."""
        B, C, Tq = x.shape
        flat = x.permute(0, 2, 1).reshape(-1, C)  # (B T', C)
        keep = mask.reshape(-1) if mask is not None else torch.ones(len(flat), dtype=torch.bool, device=x.device)
        if self.training and not bool(self.initialized):
            self.init_codebook(flat[keep].detach(), generator)
        indices = self.assign(flat.detach(), generator)  # (B T',)
        if self.training:
            self.ema_update(flat[keep].detach(), indices[keep], generator)
        codes = self.codebook[indices]  # (B T', C)
        weight = keep.to(x.dtype)[:, None] / keep.sum().clamp_min(1) / C
        # commitment pulls the encoder to its codes; the embedding term (codes to the encoder) is the
        # EMA update itself (van den Oord et al., App. A.1) and is reported, not back-propagated
        commitment = ((flat - codes.detach()).square() * weight).sum()
        embedding = ((codes - flat.detach()).square() * weight).sum()
        counts = torch.bincount(indices[keep], minlength=self.num_codes).to(x.dtype)
        probs = counts / counts.sum().clamp_min(1)
        perplexity = torch.exp(-(probs * (probs + 1e-10).log()).sum())
        quantized = flat + (codes - flat).detach()  # straight-through
        quantized = quantized.reshape(B, Tq, C).permute(0, 2, 1)
        return quantized, indices.reshape(B, Tq), {"commitment": commitment, "embedding": embedding,
                                                    "perplexity": perplexity}


class MotionVQVAE(nn.Module):
    """The conv VQ-VAE conditioned on a habit latent z (B, Z) and a category text embedding (B, E).

    The condition (z and the 256-d projection of the text embedding) is broadcast over time and
    concatenated to the motion channels at the encoder's input (the paper); with
    ``condition_decoder`` it is also concatenated to the codes at the decoder's input.
    """

    def __init__(self, feature_dim: int, text_embedding_dim: int, config: HabitConfig, quantizer: Quantizer,
                 condition_decoder: bool = False):
        super().__init__()
        c = self.config = config
        self.text_proj = nn.Linear(text_embedding_dim, c.text_dim)  # E -> 256 (paper)
        cond = c.habit_dim + c.text_dim
        self.condition_decoder = condition_decoder
        self.encoder = ConvEncoder(feature_dim + cond, c)
        self.quantizer = quantizer
        self.decoder = ConvDecoder(feature_dim, c, cond if condition_decoder else 0)

    def condition(self, z: Tensor, text: Tensor, frames: int) -> Tensor:  # (B, Z), (B, E) -> (B, Z + 256, frames)
        cond = torch.cat([z, self.text_proj(text)], dim=-1)
        return cond[:, :, None].expand(-1, -1, frames)

    def pad(self, motion: Tensor) -> Tensor:
        """(B, T, D) zero-padded at the end to a multiple of the rate."""
        extra = -motion.shape[1] % self.config.rate
        return F.pad(motion, (0, 0, 0, extra)) if extra else motion

    def encode(self, motion: Tensor, z: Tensor, text: Tensor) -> Tensor:
        """(B, T, D) normalised motion (T a multiple of the rate) -> (B, C, T / rate) latents."""
        x = motion.transpose(1, 2)  # (B, D, T)
        return self.encoder(torch.cat([x, self.condition(z, text, x.shape[-1])], dim=1))

    def decode(self, codes: Tensor, z: Tensor, text: Tensor) -> Tensor:
        """(B, C, T') quantized latents -> (B, T' * rate, D)."""
        if self.condition_decoder:
            codes = torch.cat([codes, self.condition(z, text, codes.shape[-1])], dim=1)
        return self.decoder(codes).transpose(1, 2)

    def forward(self, motion: Tensor, z: Tensor, text: Tensor, mask: Tensor | None = None,
                generator: torch.Generator | None = None) -> tuple[Tensor, Tensor, dict[str, Tensor]]:
        """(B, T, D) -> (reconstruction (B, T, D), code indices (B, ceil(T / rate)), quantizer terms)."""
        T = motion.shape[1]
        padded = self.pad(motion)
        latent_mask = None
        if mask is not None:
            padded_mask = F.pad(mask, (0, padded.shape[1] - T))
            latent_mask = padded_mask.unflatten(1, (-1, self.config.rate)).any(-1)  # (B, T')
        quantized, indices, terms = self.quantizer(self.encode(padded, z, text), generator, latent_mask)
        return self.decode(quantized, z, text)[:, :T], indices, terms


# ----------------------------------------------------------------------------- habit encoder


class HabitEncoder(nn.Module):
    """q(z | m) = N(mu, diag sigma²): a transformer over the motion frames with a summary token."""

    def __init__(self, feature_dim: int, c: HabitConfig):
        super().__init__()
        self.inp = nn.Linear(feature_dim, c.habit_width)
        self.summary = nn.Parameter(torch.zeros(1, 1, c.habit_width))
        layer = nn.TransformerEncoderLayer(c.habit_width, c.habit_heads, 4 * c.habit_width, c.dropout,
                                           batch_first=True, norm_first=True)
        self.blocks = nn.TransformerEncoder(layer, c.habit_layers, enable_nested_tensor=False)
        self.norm = nn.LayerNorm(c.habit_width)
        self.out = nn.Linear(c.habit_width, 2 * c.habit_dim)

    def forward(self, motion: Tensor, mask: Tensor) -> tuple[Tensor, Tensor]:
        """(B, T, D) normalised motion, (B, T) bool -> mu (B, Z), log sigma (B, Z)."""
        B, T, _ = motion.shape
        h = self.inp(motion) + sinusoidal_positions(T, self.inp.out_features, motion.device)[None]
        h = torch.cat([self.summary.expand(B, -1, -1), h], dim=1)  # (B, 1 + T, W)
        pad = torch.cat([torch.zeros(B, 1, dtype=torch.bool, device=mask.device), ~mask.bool()], dim=1)
        h = self.blocks(h, src_key_padding_mask=pad)
        mu, log_sigma = self.out(self.norm(h[:, 0])).chunk(2, dim=-1)
        return mu, log_sigma.clamp(-7.0, 2.0)


class CategoryHabitEncoders(nn.Module):
    """One ``HabitEncoder`` per known category (the paper's per-category posterior)."""

    def __init__(self, feature_dim: int, num_categories: int, c: HabitConfig):
        super().__init__()
        self.encoders = nn.ModuleList(HabitEncoder(feature_dim, c) for _ in range(num_categories))
        self.habit_dim = c.habit_dim

    def forward(self, motion: Tensor, mask: Tensor, category: Tensor) -> tuple[Tensor, Tensor]:
        """(B, T, D), (B, T), (B,) category indices -> mu (B, Z), log sigma (B, Z), each row by its category's
        encoder."""
        mu = motion.new_zeros(len(motion), self.habit_dim)
        log_sigma = motion.new_zeros(len(motion), self.habit_dim)
        for k in category.unique().tolist():
            rows = category == k
            mu[rows], log_sigma[rows] = self.encoders[k](motion[rows], mask[rows])
        return mu, log_sigma


def gaussian_kl(mu: Tensor, log_sigma: Tensor) -> Tensor:
    """KL(N(mu, sigma²) || N(0, I)) per row: (B, Z) -> (B,)."""
    return 0.5 * (mu.square() + (2 * log_sigma).exp() - 1 - 2 * log_sigma).sum(-1)


def posterior_sample(mu: Tensor, log_sigma: Tensor, generator: torch.Generator | None = None) -> Tensor:
    """The reparameterised sample z = mu + sigma * eps of q(z | m), eps drawn on the CPU (the same draws on any
    device): (B, Z) -> (B, Z)."""
    return mu + log_sigma.exp() * torch.randn(mu.shape, generator=generator, device="cpu").to(mu)


def gaussian_log_prob(z: Tensor, mu: Tensor, log_sigma: Tensor) -> Tensor:
    """log N(z; mu, diag sigma²) per row: (B, Z) -> (B,)."""
    return (-0.5 * ((z - mu) / log_sigma.exp()).square() - log_sigma - 0.5 * math.log(2 * math.pi)).sum(-1)


def habit_statistics(motion: Tensor, mask: Tensor) -> Tensor:
    """(B, T, C) normalised motion channels, (B, T) bool -> (B, 2 C): each channel's mean and standard deviation
    over the real frames (a carriage is a mean, a nod or a sway a spread: the time-invariant part of a habit)."""
    w = mask.to(motion.dtype)[..., None]  # (B, T, 1)
    n = w.sum(1).clamp_min(1)  # (B, 1)
    mean = (motion * w).sum(1) / n
    std = (((motion - mean[:, None]).square() * w).sum(1) / n).clamp_min(1e-8).sqrt()
    return torch.cat([mean, std], dim=-1)


class HabitStatsDecoder(nn.Module):
    """z (B, Z) -> the ``habit_statistics`` (B, 2 C) of C motion channels: the reconstruction that makes the
    habit latent informative while each encoder is pretrained under its flow prior (an MLP shared by the
    categories: the latent alone must tell them)."""

    def __init__(self, channels: int, c: HabitConfig):
        super().__init__()
        self.net = nn.Sequential(nn.Linear(c.habit_dim, c.habit_width), nn.ReLU(),
                                 nn.Linear(c.habit_width, c.habit_width), nn.ReLU(),
                                 nn.Linear(c.habit_width, 2 * channels))

    def forward(self, z: Tensor) -> Tensor:
        return self.net(z)


# ----------------------------------------------------------------------------- flow prior


class AffineCoupling(nn.Module):
    """y = m ⊙ x + (1 − m) ⊙ (x · exp(s(m ⊙ x)) + t(m ⊙ x)), with a fixed binary mask m (RealNVP)."""

    def __init__(self, dim: int, hidden: int, mask: Tensor):
        super().__init__()
        self.register_buffer("mask", mask.float())  # (Z,)
        self.net = nn.Sequential(nn.Linear(dim, hidden), nn.ReLU(), nn.Linear(hidden, hidden), nn.ReLU(),
                                 nn.Linear(hidden, 2 * dim))
        nn.init.zeros_(self.net[-1].weight)  # starts as the identity
        nn.init.zeros_(self.net[-1].bias)

    def _scale_shift(self, x_fixed: Tensor) -> tuple[Tensor, Tensor]:
        s, t = self.net(x_fixed).chunk(2, dim=-1)
        free = 1 - self.mask
        return torch.tanh(s) * free, t * free  # tanh keeps the scales bounded

    def forward(self, x: Tensor) -> tuple[Tensor, Tensor]:  # (B, Z) -> y (B, Z), log|det dy/dx| (B,)
        s, t = self._scale_shift(x * self.mask)
        return x * s.exp() + t, s.sum(-1)

    def inverse(self, y: Tensor) -> Tensor:  # (B, Z) -> x (B, Z)
        s, t = self._scale_shift(y * self.mask)  # the fixed half is unchanged, so s, t are the same
        return (y - t) * (-s).exp()


class CouplingFlow(nn.Module):
    """p(z): u = f(z) ~ N(0, I) through alternating affine couplings; log p(z) = log N(f(z)) + log|det ∂f/∂z|."""

    def __init__(self, dim: int, layers: int, hidden: int):
        super().__init__()
        half = torch.arange(dim) % 2 == 0
        self.layers = nn.ModuleList(AffineCoupling(dim, hidden, half if i % 2 == 0 else ~half) for i in range(layers))
        self.dim = dim

    def forward(self, z: Tensor) -> tuple[Tensor, Tensor]:  # (B, Z) -> u (B, Z), log|det| (B,)
        log_det = z.new_zeros(len(z))
        for layer in self.layers:
            z, ld = layer(z)
            log_det = log_det + ld
        return z, log_det

    def log_prob(self, z: Tensor) -> Tensor:  # (B, Z) -> (B,)
        u, log_det = self(z)
        return -0.5 * (u.square().sum(-1) + self.dim * math.log(2 * math.pi)) + log_det

    def inverse(self, u: Tensor) -> Tensor:  # (B, Z) base samples -> z (B, Z)
        for layer in reversed(self.layers):
            u = layer.inverse(u)
        return u

    def sample(self, count: int, generator: torch.Generator | None = None, temperature: float = 1.0) -> Tensor:
        device = self.layers[0].mask.device
        u = torch.randn(count, self.dim, generator=generator, device="cpu").to(device) * temperature
        return self.inverse(u)


class CategoryFlows(nn.Module):
    """One ``CouplingFlow`` prior per known category."""

    def __init__(self, num_categories: int, c: HabitConfig):
        super().__init__()
        self.flows = nn.ModuleList(CouplingFlow(c.habit_dim, c.flow_layers, c.flow_hidden)
                                   for _ in range(num_categories))

    def log_prob(self, z: Tensor, category: Tensor) -> Tensor:  # (B, Z), (B,) -> (B,)
        out = z.new_zeros(len(z))
        for k in category.unique().tolist():
            rows = category == k
            out[rows] = self.flows[k].log_prob(z[rows])
        return out

    def sample(self, category: int, count: int, generator: torch.Generator | None = None,
               temperature: float = 1.0) -> Tensor:  # -> (count, Z)
        return self.flows[category].sample(count, generator, temperature)


def flow_prior_kl(z: Tensor, mu: Tensor, log_sigma: Tensor, flows: CategoryFlows, category: Tensor) -> Tensor:
    """KL(q(z | m) || p_flow(z)) per row, estimated with the posterior sample z (B, Z): log q(z | m) −
    log p_flow(z) under each row's category's flow. Its gradient trains the encoder (through the
    reparameterised z and mu, sigma) and the flow (the NLL of the posterior sample under it): (B,)."""
    return gaussian_log_prob(z, mu, log_sigma) - flows.log_prob(z, category)


__all__ = [
    "AffineCoupling", "CategoryFlows", "CategoryHabitEncoders", "CouplingFlow", "FLAVORS", "HabitConfig",
    "HabitEncoder", "HabitStatsDecoder", "MotionVQVAE", "QUANTIZERS", "Quantizer", "flow_prior_kl", "gaussian_kl",
    "gaussian_log_prob", "habit_statistics", "posterior_sample",
]  # fmt: skip
