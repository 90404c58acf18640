"""Samplers of an x0-predicting diffusion model, registered by name in ``omg.registry.SAMPLERS``.

Every sampler has one signature: ``sampler(diffusion, denoise, shape, *, steps, generator, device,
dtype, mask) -> x̂0 (shape)`` (and ``noise=``: x_T given instead of drawn, when a caller seeds each row;
``progress=``: a ``StepProgress`` that hears (step, steps) after each step, passed only when a caller watches),
with ``denoise(x_t, t) -> x̂0`` the model (guidance included) and
``mask`` (B, T) keeping padded frames at zero. ``ddim`` is omg's own (``Diffusion.ddim_sample``,
the sampler OMG reports with, 200 steps); the others are the ``diffusers`` schedulers set up with
omg's cosine schedule (its betas) and the model's parametrisation (``prediction_type="sample"``):

- ``dpmpp``: DPM-Solver++(2M) (Lu et al. 2022), second-order multistep, ~20 steps;
- ``euler``: Euler on the probability-flow ODE in σ space (Karras et al. 2022).

(Heun's method was tried and left out: on this schedule, whose σ_max is in the hundreds, it
diverges below ~50 steps, where a fast sampler is wanted.)

All of them start from the same noise x_T ~ N(0, I) (scaled to the scheduler's σ_max), and
with one step every one returns the model's x0 prediction of that noise.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor

from omg.diffusion import Denoiser, Diffusion, StepProgress
from omg.errors import UsageError
from omg.registry import SAMPLERS

Sampler = Callable[..., Tensor]


@SAMPLERS.register("ddim")
def ddim(diffusion: Diffusion, denoise: Denoiser, shape: tuple[int, ...], *, steps: int,
         generator: torch.Generator | None, device, dtype: torch.dtype, mask: Tensor | None,
         noise: Tensor | None = None, progress: StepProgress | None = None) -> Tensor:
    """DDIM, deterministic (η = 0): omg's and OMG's reference sampler."""
    return diffusion.ddim_sample(denoise, shape, steps=steps, generator=generator, device=device, dtype=dtype,
                                 mask=mask, noise=noise, progress=progress)


def diffusers_betas(diffusion: Diffusion) -> list[float]:
    """β_t of ``diffusion``'s schedule, from its ᾱ_t: β_0 = 1 − ᾱ_0, β_t = 1 − ᾱ_t / ᾱ_{t−1}."""
    a = diffusion.alphas_cumprod
    return (1 - a / torch.cat([a.new_ones(1), a[:-1]])).tolist()


def _scheduler_loop(scheduler, diffusion: Diffusion, denoise: Denoiser, shape, steps: int, generator, device,
                    dtype: torch.dtype, mask: Tensor | None, noise: Tensor | None = None,
                    progress: StepProgress | None = None) -> Tensor:
    """The diffusers loop: scale the input to the model's x_t, let the scheduler step on x̂0."""
    if not 1 <= steps <= diffusion.num_timesteps:
        raise UsageError(f"steps must be in 1..{diffusion.num_timesteps}, got {steps}")
    if device is None and mask is not None:
        device = mask.device
    keep = None if mask is None else mask[..., None].to(device=device, dtype=dtype)  # (B, T, 1)
    scheduler.set_timesteps(steps, device=device)
    # the step index then counts up from 0: diffusers would otherwise find it by comparing device
    # tensors (a host synchronisation); no other read of a device value happens in the loop
    scheduler.set_begin_index(0)
    if noise is None:
        noise = torch.randn(shape, generator=generator, device=device, dtype=dtype)  # the same x_T as ddim
    noise = noise.to(device=device, dtype=dtype)
    x = noise * scheduler.init_noise_sigma
    for step, t in enumerate(scheduler.timesteps, start=1):
        if keep is not None:
            x = x * keep
        x_t = scheduler.scale_model_input(x, t).to(dtype)  # the VP x_t the model was trained on
        x0 = denoise(x_t, t.to(device).expand(shape[0]))
        x = scheduler.step(x0, t, x).prev_sample.to(dtype)  # deterministic ODE steps: no noise drawn
        if progress is not None:
            progress(step, steps)
    return x if keep is None else x * keep


def _make(kind: str, diffusion: Diffusion):
    import diffusers  # imported only when a diffusers sampler is asked for

    common = {"num_train_timesteps": diffusion.num_timesteps, "trained_betas": diffusers_betas(diffusion),
              "prediction_type": "sample", "timestep_spacing": "trailing"}  # first step at t = T-1, as ddim
    if kind == "dpmpp":
        return diffusers.DPMSolverMultistepScheduler(**common, algorithm_type="dpmsolver++", solver_order=2,
                                                     lower_order_final=True, final_sigmas_type="zero")
    return diffusers.EulerDiscreteScheduler(**common, final_sigmas_type="zero")


def _diffusers_sampler(kind: str, doc: str) -> Sampler:
    def sample(diffusion: Diffusion, denoise: Denoiser, shape: tuple[int, ...], *, steps: int,
               generator: torch.Generator | None, device, dtype: torch.dtype, mask: Tensor | None,
               noise: Tensor | None = None, progress: StepProgress | None = None) -> Tensor:
        return _scheduler_loop(_make(kind, diffusion), diffusion, denoise, shape, steps, generator, device, dtype,
                               mask, noise, progress)

    sample.__name__, sample.__doc__ = kind, doc
    return sample


dpmpp = SAMPLERS.register("dpmpp", _diffusers_sampler("dpmpp", "DPM-Solver++(2M) (diffusers), x0-predicting."))
euler = SAMPLERS.register("euler", _diffusers_sampler("euler", "Euler on the probability-flow ODE (diffusers)."))


__all__ = ["SAMPLERS", "ddim", "diffusers_betas", "dpmpp", "euler"]
