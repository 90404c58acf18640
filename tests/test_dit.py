import pytest
import torch
from torch import nn
from torch.nn.attention import SDPBackend, sdpa_kernel
from torch.utils.flop_counter import FlopCounterMode

from omg.diffusion import Diffusion
from omg.errors import UsageError
from omg.models.dit import FLAVORS, DiTConfig, MotionDiT, apply_rotary, rotary_embedding

PAPER_PARAMS = {"base": 88e6, "large": 201e6, "giant": 1e9}  # OMG paper, Table 1


def n_params(model: nn.Module) -> int:
    return sum(p.numel() for p in model.parameters())


def expected_params(cfg: DiTConfig) -> int:
    """The architecture written out: what every weight and bias of MotionDiT should add up to."""
    d, f, D, e = cfg.d_model, cfg.ffn_dim, cfg.input_dim, cfg.freq_embed_dim
    # attention, GEGLU (fc1 d -> 2f, fc2 f -> d), adaLN-single (6, d) table
    block = (4 * d * d + 4 * d) + (2 * d * f + 2 * f) + (f * d + d) + 6 * d
    embed = (D * d + d) + (e * d + d + d * d + d)  # input projection, timestep MLP
    shared = 6 * d * d + 6 * d  # shared t_modulation Linear(d, 6d)
    final = (2 * d * d + 2 * d) + (d * D + D)  # final adaLN, output projection
    return cfg.n_layers * block + embed + shared + final


def randomized(model: MotionDiT) -> MotionDiT:
    """Randomise the zero-initialised weights (shared t_modulation, per-block modulation tables,
    final adaLN and output projection) so the model is not trivial."""
    with torch.no_grad():
        for p in model.parameters():
            if not p.any():
                p.normal_(std=0.05)
    assert all(block.modulation.any() for block in model.blocks)
    assert model.t_modulation[-1].weight.any()
    return model.eval()


@pytest.mark.parametrize("flavor", list(FLAVORS))
def test_flavor_builds_on_meta_device(flavor):
    cfg = DiTConfig.from_name(flavor)
    with torch.device("meta"):
        model = MotionDiT(cfg)
    count = n_params(model)
    print(f"{flavor}: {count / 1e6:.1f}M parameters")
    assert count == expected_params(cfg)
    assert cfg.head_dim == (32 if flavor == "mini" else 128)


@pytest.mark.parametrize("flavor", [*PAPER_PARAMS, "huge"])
def test_param_count_matches_paper(flavor):
    with torch.device("meta"):
        count = n_params(MotionDiT(DiTConfig.from_name(flavor)))
    if flavor not in PAPER_PARAMS:  # the paper gives no count for huge
        print(f"{flavor}: {count / 1e6:.1f}M parameters")
        return
    print(f"{flavor}: {count / 1e6:.1f}M parameters, paper {PAPER_PARAMS[flavor] / 1e6:.0f}M")
    assert abs(count / PAPER_PARAMS[flavor] - 1) <= 0.10


def test_from_name_overrides_and_unknown_flavor():
    cfg = DiTConfig.from_name("base", n_layers=4, dropout=0.1)
    assert (cfg.n_layers, cfg.d_model, cfg.n_heads, cfg.dropout) == (4, 1024, 8, 0.1)
    assert DiTConfig(d_model=1280).n_heads == 10  # head dim 128 by default
    with pytest.raises(UsageError, match="base.*large.*huge.*giant"):
        DiTConfig.from_name("colossal")
    with pytest.raises(UsageError, match="n_heads"):
        DiTConfig.from_name("base", n_heads=7)


def test_rope_scores_depend_only_on_relative_offset():
    g = torch.Generator().manual_seed(0)
    q, k = torch.randn(2, 1, 4, 12, 64, generator=g)  # (B, H, T, hd)
    pos = torch.arange(12)

    def scores(positions):
        rope = rotary_embedding(positions, 64)
        return apply_rotary(q, rope) @ apply_rotary(k, rope).transpose(-1, -2)

    torch.testing.assert_close(scores(pos), scores(pos + 37), rtol=1e-4, atol=1e-4)
    assert not torch.allclose(scores(pos), q @ k.transpose(-1, -2), atol=1e-3)


def test_adaln_zero_init_outputs_zero_and_blocks_are_identity():
    model = MotionDiT(DiTConfig.from_name("mini")).eval()
    x, t = torch.randn(2, 16, 263), torch.tensor([3, 999])
    assert torch.equal(model(x, t), torch.zeros_like(x))
    h, c, mod, rope = model.embed(x, t)
    assert torch.equal(mod, torch.zeros(2, 6 * model.config.d_model))  # every gate is 0
    for block in model.blocks:
        assert torch.equal(block(h, mod, rope), h)


def test_padding_invariance():
    torch.manual_seed(0)
    model = randomized(MotionDiT(DiTConfig.from_name("mini", n_layers=2)))
    x, t = torch.randn(1, 20, 263), torch.tensor([500])
    ref = model(x, t)
    padded = torch.cat([x, torch.randn(1, 12, 263)], dim=1)
    mask = torch.arange(32)[None] < 20
    torch.testing.assert_close(model(padded, t, mask)[:, :20], ref, rtol=1e-4, atol=1e-5)

    # A batch of different lengths matches running each clip alone; an empty clip stays finite.
    x2, lengths = torch.randn(3, 20, 263), [20, 9, 0]
    mask = torch.arange(20)[None] < torch.tensor(lengths)[:, None]
    out = model(x2, torch.tensor([10, 400, 900]), mask)
    for i, n in enumerate(lengths[:2]):
        alone = model(x2[i : i + 1, :n], torch.tensor([[10, 400][i]]))
        torch.testing.assert_close(out[i : i + 1, :n], alone, rtol=1e-4, atol=1e-5)
    assert torch.isfinite(out).all()


def test_residual_fn_and_manual_block_loop():
    torch.manual_seed(0)
    model = randomized(MotionDiT(DiTConfig.from_name("mini", n_layers=3)))
    x, t = torch.randn(2, 10, 263), torch.tensor([1, 700])
    mask = torch.arange(10)[None] < torch.tensor([[10], [6]])
    res = [None, torch.randn(2, 10, model.config.d_model), None]

    h, c, mod, rope = model.embed(x, t)  # what a ControlNet driving the frozen blocks does
    torch.testing.assert_close(model.forward_embedded(h, c, mod, rope, mask, lambda i, h_i: None), model(x, t, mask))
    inputs = []

    def residual(i, h_i):
        inputs.append(h_i)
        return res[i]

    out = model.forward_embedded(h, c, mod, rope, mask, residual)
    for i, block in enumerate(model.blocks):
        torch.testing.assert_close(inputs[i], h)  # residual_fn sees block i's input
        h = block(h, mod, rope, mask)
        if res[i] is not None:
            h = h + res[i]
    torch.testing.assert_close(model.final_layer(h, c), out)
    assert not torch.allclose(out, model(x, t, mask))


def saved_for_backward(fn) -> int:
    """How many tensors autograd keeps for backward while ``fn()`` runs."""
    count = [0]

    def pack(tensor):
        count[0] += 1
        return tensor

    with torch.autograd.graph.saved_tensors_hooks(pack, lambda tensor: tensor):
        fn()
    return count[0]


def test_activation_checkpointing_from_outside_gives_same_gradients_with_less_kept():
    from omg.models.checkpointing import checkpoint_each

    x, t = torch.randn(2, 8, 263), torch.tensor([5, 50])
    grads, kept = [], []
    for ckpt in (False, True):
        torch.manual_seed(0)
        model = randomized(MotionDiT(DiTConfig.from_name("mini")))
        if ckpt:
            checkpoint_each(model.blocks)
        names = [n for n, _ in model.named_parameters()]
        model.train()
        kept.append(saved_for_backward(lambda: model(x, t).square().mean().backward()))
        grads.append(torch.cat([p.grad.flatten() for p in model.parameters()]))
        assert names == [n for n, _ in MotionDiT(DiTConfig.from_name("mini")).named_parameters()]  # names unchanged
    torch.testing.assert_close(grads[0], grads[1])
    assert kept[1] < kept[0] / 2


def test_flops_match_flop_counter():
    cfg = DiTConfig.from_name("mini", n_layers=2)
    model = MotionDiT(cfg)
    x, t = torch.randn(3, 20, 263), torch.tensor([1, 2, 3])
    mask = torch.ones(3, 20, dtype=torch.bool)
    # The math backend lowers attention to matmuls that the counter sees.
    with sdpa_kernel(SDPBackend.MATH), FlopCounterMode(display=False) as counter:
        model(x, t, mask)
    assert counter.get_total_flops() == cfg.flops(batch=3, seq_len=20)


def test_mini_overfits_one_batch():
    torch.manual_seed(0)
    g = torch.Generator().manual_seed(0)
    model, diffusion = MotionDiT(DiTConfig.from_name("mini")), Diffusion()
    x0 = torch.randn(4, 32, 263, generator=g)
    # Fixed evaluation noise at t < 0.75·T: beyond that a noisy clip barely tells which of the
    # four it came from within 200 steps, and the x0 error stays near the clips' variance.
    t_eval = torch.linspace(0, 700, 8).long().repeat_interleave(4)
    x_eval, noise_eval = x0.repeat(8, 1, 1), torch.randn(32, 32, 263, generator=g)

    @torch.no_grad()
    def eval_loss() -> float:
        model.eval()
        x0_hat = model(diffusion.q_sample(x_eval, t_eval, noise_eval), t_eval)
        return diffusion.loss(x0_hat, x_eval, t_eval).item()

    before = eval_loss()
    opt = torch.optim.Adam(model.parameters(), lr=2e-3)
    model.train()
    for _ in range(200):
        t = diffusion.sample_timesteps(4, generator=g)
        x_t = diffusion.q_sample(x0, t, torch.randn(x0.shape, generator=g))
        loss = diffusion.loss(model(x_t, t), x0, t)
        opt.zero_grad()
        loss.backward()
        opt.step()
    after = eval_loss()
    print(f"x0 loss at t < 0.75T: {before:.3f} -> {after:.4f}")
    assert after < before / 10
