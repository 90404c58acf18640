"""Gaussian diffusion for x0-predicting denoisers: cosine schedule, q_sample, loss weights, DDIM.

The model predicts the clean motion x̂0 (as MDM and OMG do). Schedule math is float64; the
tensors move to the data's device and dtype where they are used. Sampling takes any
``denoise(x_t, t) -> x̂0`` callable, so classifier-free guidance is the model's business
(``omg.models.controlnet.MotionControlNet.forward_guided`` mixes D_u and D_c in one pass).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import torch
from torch import Tensor

from omg.errors import UsageError

Denoiser = Callable[[Tensor, Tensor], Tensor]  # (x_t (B, T, D), t (B,)) -> x̂0 (B, T, D)
# (steps done, steps): called by a sampler after each of its steps, with host integers only, so that watching a
# run (a progress line, the server's status) draws no random number, calls no model and waits on no device
StepProgress = Callable[[int, int], None]

LOSS_WEIGHTINGS = ("uniform", "min_snr")


def cosine_alphas_cumprod(num_timesteps: int, s: float = 0.008, max_beta: float = 0.999) -> Tensor:
    """ᾱ_t for t = 0..T-1 (Nichol & Dhariwal 2021), float64, via betas clipped at ``max_beta``."""

    def f(u: Tensor) -> Tensor:
        return torch.cos((u / num_timesteps + s) / (1 + s) * math.pi / 2) ** 2

    u = torch.arange(num_timesteps + 1, dtype=torch.float64)
    betas = (1 - f(u[1:]) / f(u[:-1])).clamp(max=max_beta)
    return torch.cumprod(1 - betas, dim=0)


@dataclass
class Diffusion:
    """T-step cosine-schedule diffusion; ``t`` indexes 0 (almost clean) .. T-1 (almost noise).

    loss_weighting picks λ_t for the x0 loss:
      "uniform": λ_t = 1, the plain x0 MSE that MDM and OMG train with;
      "min_snr": λ_t = min(SNR_t, γ), Min-SNR-γ (Hang et al. 2023) written for an x0 target,
                 i.e. the ε-MSE weighted by min(SNR_t, γ) / SNR_t, with γ = ``min_snr_gamma``.
    """

    num_timesteps: int = 1000
    loss_weighting: str = "uniform"
    min_snr_gamma: float = 5.0
    alphas_cumprod: Tensor = field(init=False, repr=False, compare=False)  # (T,) float64

    def __post_init__(self) -> None:
        if self.loss_weighting not in LOSS_WEIGHTINGS:
            raise UsageError(
                f"unknown loss_weighting {self.loss_weighting!r}; choose one of {LOSS_WEIGHTINGS}"
            )
        if self.num_timesteps < 1:
            raise UsageError(f"num_timesteps must be >= 1, got {self.num_timesteps}")
        self.alphas_cumprod = cosine_alphas_cumprod(self.num_timesteps)

    def _at(self, values: Tensor, t: Tensor, like: Tensor) -> Tensor:
        """values[t] shaped (B, 1, ..., 1) to broadcast against ``like``, in like's dtype."""
        out = values.to(t.device)[t].to(like.dtype)
        return out.view(-1, *([1] * (like.dim() - 1)))

    def sample_timesteps(
        self,
        batch: int,
        generator: torch.Generator | None = None,
        device: torch.device | str | None = None,
    ) -> Tensor:
        """Uniform t ~ U{0..T-1}, (batch,) long."""
        return torch.randint(0, self.num_timesteps, (batch,), generator=generator, device=device)

    def q_sample(self, x0: Tensor, t: Tensor, noise: Tensor) -> Tensor:
        """x_t = √ᾱ_t·x0 + √(1-ᾱ_t)·ε; x0, noise: (B, ...), t: (B,)."""
        a = self.alphas_cumprod
        return self._at(a.sqrt(), t, x0) * x0 + self._at((1 - a).sqrt(), t, x0) * noise

    def snr(self, t: Tensor) -> Tensor:
        """SNR_t = ᾱ_t / (1-ᾱ_t), (B,) float64."""
        a = self.alphas_cumprod.to(t.device)[t]
        return a / (1 - a)

    def loss_weight(self, t: Tensor) -> Tensor:
        """λ_t, (B,) float32."""
        if self.loss_weighting == "uniform":
            return torch.ones(t.shape, device=t.device)
        return self.snr(t).clamp(max=self.min_snr_gamma).float()

    def loss(self, x0_hat: Tensor, x0: Tensor, t: Tensor, mask: Tensor | None = None) -> Tensor:
        """λ_t-weighted x0 MSE: mean over real frames and features per sample, then over the batch.

        x0_hat, x0: (B, T, D); t: (B,); mask: (B, T) bool, True = real frame.
        """
        err = (x0_hat - x0).float().pow(2).mean(dim=-1)  # (B, T)
        if mask is None:
            per_sample = err.mean(dim=1)
        else:
            m = mask.to(err.dtype)
            per_sample = (err * m).sum(dim=1) / m.sum(dim=1).clamp(min=1)  # (B,)
        return (self.loss_weight(t) * per_sample).mean()

    @torch.no_grad()
    def ddim_sample(
        self,
        denoise: Denoiser,
        shape: tuple[int, ...],
        steps: int = 200,
        eta: float = 0.0,
        generator: torch.Generator | None = None,
        device: torch.device | str | None = None,
        dtype: torch.dtype = torch.float32,
        mask: Tensor | None = None,
        progress: StepProgress | None = None,
        noise: Tensor | None = None,
    ) -> Tensor:
        """DDIM (Song et al. 2021) from x_{T-1} ~ N(0, I) to x̂0 over ``steps`` evenly spaced t.

        eta=0 is deterministic given the initial noise; eta=1 is DDPM-like ancestral sampling.
        mask (B, T) bool keeps padded frames at zero; ``denoise`` should close over the same mask
        (e.g. ``lambda x, t: model(x, t, mask)``). ``noise``: x_{T-1} itself (e.g. drawn per row from
        its own seed) instead of a draw from ``generator``. ``progress`` hears (step, steps) after each step.
        Returns (shape) in ``dtype``.
        """
        if not 1 <= steps <= self.num_timesteps:
            raise UsageError(f"steps must be in 1..{self.num_timesteps}, got {steps}")
        if device is None and mask is not None:
            device = mask.device
        keep = None if mask is None else mask[..., None].to(device=device, dtype=dtype)  # (B, T, 1)
        if noise is not None:
            x = noise.to(device=device, dtype=dtype)
        else:
            x = torch.randn(shape, generator=generator, device=device, dtype=dtype)
        if keep is not None:
            x = x * keep
        # Evenly spaced from T-1 to 0; spacing >= 1 keeps them distinct after rounding.
        ts = torch.linspace(self.num_timesteps - 1, 0, steps, dtype=torch.float64).round().long()
        ts = ts.tolist()
        a = self.alphas_cumprod
        schedule = list(zip(ts, ts[1:] + [-1]))  # (t, t_prev); t_prev = -1 means ᾱ = 1
        for step, (t, t_prev) in enumerate(schedule, start=1):
            a_t = a[t].item()
            a_prev = a[t_prev].item() if t_prev >= 0 else 1.0
            x0_hat = denoise(x, torch.full((shape[0],), t, device=x.device, dtype=torch.long))
            eps = (x - math.sqrt(a_t) * x0_hat) / math.sqrt(1 - a_t)
            sigma = eta * math.sqrt((1 - a_prev) / (1 - a_t) * (1 - a_t / a_prev))
            x = math.sqrt(a_prev) * x0_hat + math.sqrt(max(1 - a_prev - sigma**2, 0.0)) * eps
            if sigma > 0:
                z = torch.randn(shape, generator=generator, device=x.device, dtype=dtype)
                x = x + sigma * z
            if keep is not None:
                x = x * keep
            if progress is not None:
                progress(step, steps)
        return x

