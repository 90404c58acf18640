"""The sampler registry: DDIM and the diffusers solvers (DPM-Solver++, Euler) on omg's
cosine schedule and x0-predicting parametrisation."""

import numpy as np
import pytest
import torch

from omg.diffusion import Diffusion
from omg.errors import UsageError
from omg.registry import SAMPLERS
from omg.samplers import diffusers_betas

MU, S = 0.3, 0.5  # toy data: every feature ~ N(MU, S²)


@pytest.fixture(scope="session")
def diffusion():
    return Diffusion()


def gaussian_denoiser(diffusion: Diffusion):
    """The exact x̂0 = E[x0 | x_t] for data N(MU, S²): the probability-flow ODE then carries each
    noise to one data point, which every consistent solver approaches as its steps grow. ᾱ at a
    fractional t (Euler) is interpolated in σ = √((1 − ᾱ)/ᾱ), as diffusers does."""
    a = diffusion.alphas_cumprod
    sigmas = ((1 - a) / a).sqrt().numpy()

    def denoise(x, t):
        sigma = torch.tensor(np.interp(t.double().cpu().numpy(), np.arange(len(sigmas)), sigmas))
        a_t = (1 / (1 + sigma**2)).to(x.dtype).view(-1, *[1] * (x.ndim - 1))
        return (a_t.sqrt() * S**2 * x + (1 - a_t) * MU) / (a_t * S**2 + 1 - a_t)

    return denoise


def run(name, diffusion, denoise, steps, shape=(3, 8, 4), seed=0, mask=None):
    gen = torch.Generator().manual_seed(seed)
    return SAMPLERS.get(name)(diffusion, denoise, shape, steps=steps, generator=gen, device="cpu",
                              dtype=torch.float64, mask=mask)


def test_registry_lists_the_samplers_and_names_unknown_ones():
    assert {"ddim", "dpmpp", "euler"} <= set(SAMPLERS.names())
    with pytest.raises(UsageError, match="unknown sampler 'plms'; known samplers: ddim, dpmpp"):
        SAMPLERS.get("plms")


def test_betas_reproduce_the_cosine_schedule(diffusion):
    betas = torch.tensor(diffusers_betas(diffusion), dtype=torch.float64)
    torch.testing.assert_close(torch.cumprod(1 - betas, 0), diffusion.alphas_cumprod, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("name", ["ddim", "dpmpp", "euler"])
def test_one_step_returns_the_x0_prediction_of_the_noise(diffusion, name):
    calls = []

    def denoise(x, t):
        calls.append((x.clone(), t.clone()))
        return torch.tanh(x) * 0.5 + 0.1  # any prediction

    out = run(name, diffusion, denoise, steps=1)
    noise = torch.randn((3, 8, 4), generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    assert len(calls) == 1 and int(calls[0][1][0]) == diffusion.num_timesteps - 1
    torch.testing.assert_close(calls[0][0], noise, rtol=1e-6, atol=1e-6)  # the model sees x_T ~ N(0, I) itself
    torch.testing.assert_close(out, torch.tanh(calls[0][0]) * 0.5 + 0.1)


@pytest.mark.parametrize("name, steps, tol", [("dpmpp", 100, 5e-3), ("euler", 400, 1e-2)])
def test_solvers_converge_to_the_ddim_solution(diffusion, name, steps, tol):
    denoise = gaussian_denoiser(diffusion)
    reference = run("ddim", diffusion, denoise, steps=1000)
    assert abs(float(reference.mean()) - MU) < 0.2 and abs(float(reference.std()) - S) < 0.2  # data-like
    out = run(name, diffusion, denoise, steps=steps)
    torch.testing.assert_close(out, reference, rtol=0, atol=tol)
    coarse = run(name, diffusion, denoise, steps=5)
    assert (coarse - reference).abs().max() > (out - reference).abs().max()  # more steps, closer


def test_dpmpp_needs_far_fewer_steps_than_ddim(diffusion):
    denoise = gaussian_denoiser(diffusion)
    reference = run("ddim", diffusion, denoise, steps=1000)
    error = {name: float((run(name, diffusion, denoise, steps=20) - reference).abs().max())
             for name in ("ddim", "dpmpp")}
    assert error["dpmpp"] < error["ddim"] / 10, error


@pytest.mark.parametrize("name", ["ddim", "dpmpp", "euler"])
def test_padded_frames_stay_zero(diffusion, name):
    mask = torch.arange(8)[None] < torch.tensor([[8], [5], [2]])
    out = run(name, diffusion, gaussian_denoiser(diffusion), steps=6, mask=mask)
    assert torch.equal(out[~mask], torch.zeros_like(out[~mask])) and out[mask].abs().min() > 0


@pytest.mark.parametrize("name", ["dpmpp", "euler"])
def test_diffusers_loop_never_looks_its_step_up_on_the_device(diffusion, name, monkeypatch):
    """diffusers finds its step index by comparing device tensors (a host synchronisation on a
    GPU) unless told where it begins: the loop tells it, so the lookup never runs."""
    import diffusers

    def refuse(*args, **kwargs):
        raise AssertionError("the step index was looked up")

    for cls in (diffusers.DPMSolverMultistepScheduler, diffusers.EulerDiscreteScheduler):
        monkeypatch.setattr(cls, "index_for_timestep", refuse)
    assert torch.isfinite(run(name, diffusion, gaussian_denoiser(diffusion), steps=8)).all()


@pytest.mark.parametrize("name", SAMPLERS.names())
def test_every_sampler_reports_each_step_once_in_order_and_samples_the_same(diffusion, name):
    """The progress hook hears (step, steps) after each step, the last one (steps, steps), and watching changes
    nothing: no random number drawn, no model call added, the same sample to the bit."""
    denoise = gaussian_denoiser(diffusion)
    calls, heard = [], []

    def counted(x, t):
        calls.append(len(heard))  # the steps reported before this model call
        return denoise(x, t)

    mask = torch.arange(8)[None] < torch.tensor([[8], [5], [2]])
    sampler = SAMPLERS.get(name)
    gen, alone = torch.Generator().manual_seed(3), torch.Generator().manual_seed(3)
    watched = sampler(diffusion, counted, (3, 8, 4), steps=7, generator=gen, device="cpu", dtype=torch.float64,
                      mask=mask, progress=lambda step, steps: heard.append((step, steps)))
    assert heard == [(step, 7) for step in range(1, 8)]
    assert calls == list(range(7))  # one model call per step, each step reported once it is taken
    unwatched = sampler(diffusion, denoise, (3, 8, 4), steps=7, generator=alone, device="cpu", dtype=torch.float64,
                        mask=mask)
    assert torch.equal(watched, unwatched) and torch.equal(gen.get_state(), alone.get_state())
