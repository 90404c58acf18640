import math

import pytest
import torch

from omg.diffusion import Diffusion, cosine_alphas_cumprod
from omg.errors import UsageError


@pytest.fixture(scope="session")
def diffusion() -> Diffusion:
    return Diffusion()


def test_cosine_schedule(diffusion):
    a = diffusion.alphas_cumprod
    assert a.dtype == torch.float64 and a.shape == (1000,)
    assert (a[1:] < a[:-1]).all()
    assert a[0] > 0.9999 and a[-1] < 1e-8
    betas = 1 - a / torch.cat([a.new_ones(1), a[:-1]])
    assert betas.max() <= 0.999 + 1e-12 and betas.min() > 0
    # Away from the clipped end the closed form holds: ᾱ(t) = f(t) / f(0).
    f = lambda u: math.cos((u / 1000 + 0.008) / 1.008 * math.pi / 2) ** 2  # noqa: E731
    assert a[499].item() == pytest.approx(f(500) / f(0), rel=1e-9)
    assert torch.equal(cosine_alphas_cumprod(1000), a)


def test_q_sample_statistics(diffusion):
    g = torch.Generator().manual_seed(0)
    n = 200_000
    x0 = torch.full((n, 1), 2.0)
    for step in (0, 300, 700, 999):
        t = torch.full((n,), step)
        x_t = diffusion.q_sample(x0, t, torch.randn(n, 1, generator=g))
        a = diffusion.alphas_cumprod[step].item()
        assert x_t.mean().item() == pytest.approx(2 * math.sqrt(a), abs=0.01)
        assert x_t.var().item() == pytest.approx(1 - a, abs=0.01)


def test_sample_timesteps(diffusion):
    t = diffusion.sample_timesteps(10_000, generator=torch.Generator().manual_seed(1))
    assert t.dtype == torch.long and t.min() >= 0 and t.max() <= 999
    assert t.float().mean().item() == pytest.approx(499.5, abs=10)
    t2 = diffusion.sample_timesteps(10_000, generator=torch.Generator().manual_seed(1))
    assert torch.equal(t, t2)


def test_loss_weighting():
    t = torch.tensor([0, 300, 600, 999])
    assert torch.equal(Diffusion().loss_weight(t), torch.ones(4))
    w = Diffusion(loss_weighting="min_snr", min_snr_gamma=5.0).loss_weight(t)
    snr = Diffusion().snr(t).float()
    torch.testing.assert_close(w, torch.minimum(snr, torch.tensor(5.0)))
    assert w[0] == 5.0 and w[-1] < 1e-8
    with pytest.raises(UsageError, match="uniform"):
        Diffusion(loss_weighting="p2")


def test_loss_ignores_padded_frames(diffusion):
    x0 = torch.randn(2, 6, 3)
    x0_hat = x0.clone()
    x0_hat[0, 0] += 1.0  # error 1 on one real frame of clip 0 (4 real frames)
    x0_hat[:, 4:] += 100.0  # padding
    mask = (torch.arange(6) < 4).expand(2, 6)
    loss = diffusion.loss(x0_hat, x0, torch.tensor([0, 0]), mask)
    assert loss.item() == pytest.approx((1 / 4) / 2)


@pytest.mark.parametrize("eta", [0.0, 1.0])
def test_ddim_with_true_x0_recovers_it_exactly(diffusion, eta):
    x0 = torch.randn(3, 10, 5)
    mask = torch.arange(10)[None] < torch.tensor([[10], [7], [3]])
    x0 = x0 * mask[..., None]
    calls = []

    def oracle(x_t, t):
        calls.append(t[0].item())
        return x0

    out = diffusion.ddim_sample(oracle, x0.shape, steps=50, eta=eta, mask=mask)
    assert torch.equal(out, x0)
    assert len(calls) == 50 and calls[0] == 999 and calls[-1] == 0


@pytest.mark.parametrize(
    ("eta", "steps", "rtol"), [(0.0, 500, 0.015), (0.0, 100, 0.03), (1.0, 200, 0.03)]
)
def test_ddim_with_gaussian_oracle_matches_data_distribution(diffusion, eta, steps, rtol):
    """Data x0 ~ N(μ, s²) per feature; the oracle returns the exact posterior mean E[x0 | x_t].

    DDIM is a first-order solver: with fewer steps it slightly shrinks the spread.
    """
    mu, s = torch.tensor([1.5, -0.5]), torch.tensor([0.5, 2.0])
    a = diffusion.alphas_cumprod.float()

    def oracle(x_t, t):
        at = a[t[0]]  # one step for the whole batch
        gain = at.sqrt() * s**2 / (at * s**2 + 1 - at)
        return mu + gain * (x_t - at.sqrt() * mu)

    out = diffusion.ddim_sample(
        oracle, (50_000, 2), steps=steps, eta=eta, generator=torch.Generator().manual_seed(0)
    )
    torch.testing.assert_close(out.mean(0), mu, atol=0.03, rtol=0)
    torch.testing.assert_close(out.std(0), s, atol=0, rtol=rtol)


def test_ddim_keeps_padding_at_zero(diffusion):
    mask = torch.arange(8)[None] < torch.tensor([[8], [5]])
    seen = []

    def denoise(x_t, t):
        seen.append(x_t[1, 5:].abs().max().item())
        return torch.ones_like(x_t)

    out = diffusion.ddim_sample(denoise, (2, 8, 4), steps=10, eta=1.0, mask=mask)
    assert max(seen) == 0 and torch.equal(out[1, 5:], torch.zeros(3, 4))
    assert torch.equal(out[0], torch.ones(8, 4))


def test_ddim_determinism(diffusion):
    def denoise(x_t, t):
        return 0.5 * x_t

    def run(seed, eta):
        g = torch.Generator().manual_seed(seed)
        return diffusion.ddim_sample(denoise, (2, 6, 3), steps=20, eta=eta, generator=g)

    assert torch.equal(run(0, 1.0), run(0, 1.0))
    assert not torch.equal(run(0, 1.0), run(1, 1.0))
    # eta=0 draws only the initial noise, so fixing it fixes the sample.
    torch.manual_seed(3)
    assert torch.equal(run(0, 0.0), run(0, 0.0))


def test_ddim_rejects_bad_steps(diffusion):
    with pytest.raises(UsageError, match="steps"):
        diffusion.ddim_sample(lambda x, t: x, (1, 2), steps=0)
