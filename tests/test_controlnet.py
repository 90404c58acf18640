import math

import pytest
import torch
import torch.nn.functional as F
from torch import nn

from omg.errors import UsageError
from omg.models.controlnet import MoCBlock, MoCConfig, MotionControlNet
from omg.models.dit import DiTConfig, MotionDiT

D_TEXT = 24
SMALL_MOC = dict(d_c=32, num_experts=4, text_dim=D_TEXT)


def randomize_zeros(module: nn.Module, std: float = 0.05) -> nn.Module:
    """Give every all-zero parameter (adaLN-Zero tables, output layer, zero projections,
    MoC down/up projections) random values, so nothing is trivially zero or the identity."""
    with torch.no_grad():
        for p in module.parameters():
            if not p.any():
                p.normal_(std=std)
    return module


def frozen_base(**overrides) -> MotionDiT:
    base = randomize_zeros(MotionDiT(DiTConfig.from_name("mini", **overrides)))
    assert all(p.any() for p in base.parameters())
    return base.eval()


def text_batch(lengths, L=None, D=D_TEXT, seed=0):
    """Random token embeddings (finite garbage at padded positions), mask and EOT index."""
    g = torch.Generator().manual_seed(seed)
    lengths = torch.tensor(lengths)
    L = L or int(lengths.max())
    tokens = torch.randn(len(lengths), L, D, generator=g)
    text_mask = torch.arange(L)[None] < lengths[:, None]
    eot = (lengths - 1).clamp_min(0)
    return tokens, text_mask, eot


def frame_mask(lengths, T):
    return torch.arange(T)[None] < torch.tensor(lengths)[:, None]


def motion_batch(B, T, seed=0):
    g = torch.Generator().manual_seed(seed)
    return torch.randn(B, T, 263, generator=g), torch.randint(0, 1000, (B,), generator=g)


# -- config ---------------------------------------------------------------------------------


def test_config_defaults_and_bad_values():
    cfg = MoCConfig()
    assert (cfg.d_c, cfg.num_experts, cfg.expert_hidden, cfg.gate_hidden) == (256, 12, 512, 256)
    assert (cfg.gamma, cfg.beta, cfg.layers) == (24.0, 0.25, None)
    assert MoCConfig(layers=[3, 1]).layers == [1, 3]
    for field, value in [
        ("d_c", 0), ("num_experts", -1), ("expert_hidden", 2.5), ("gate_hidden", 0),
        ("text_dim", True), ("gamma", 0.0), ("gamma", float("inf")), ("beta", 1.5),
        ("layers", []), ("layers", [1, 1]), ("layers", [-1]),
    ]:
        with pytest.raises(UsageError, match=f"MoCConfig.{field}"):
            MoCConfig(**{field: value})
    with pytest.raises(UsageError, match="layers.*0..3"):
        MotionControlNet(MotionDiT(DiTConfig.from_name("mini")), MoCConfig(layers=[4]))


def test_text_width_mismatch_names_text_dim():
    net = MotionControlNet(frozen_base(n_layers=1), MoCConfig(**SMALL_MOC))
    x, t = motion_batch(1, 5)
    tokens, text_mask, eot = text_batch([3], D=D_TEXT + 1)
    with pytest.raises(UsageError, match="text_dim"):
        net(x, t, tokens, text_mask, eot)


# -- initialisation and training --------------------------------------------------------------


def test_init_equals_frozen_model_exactly():
    torch.manual_seed(0)
    base = frozen_base()
    net = MotionControlNet(base, MoCConfig(**SMALL_MOC))
    x, t = motion_batch(3, 12)
    mask = frame_mask([12, 7, 1], 12)
    tokens, text_mask, eot = text_batch([5, 2, 4])
    with torch.no_grad():
        expected = base(x, t, mask)
        assert torch.equal(net(x, t, tokens, text_mask, eot, mask), expected)
        assert torch.equal(net.forward_uncond(x, t, mask), expected)
        # Stronger than the output: every residual is exactly 0, and since every MoC block
        # outputs exactly 0 the copy stream reproduces the frozen stream block by block.
        h0, c, mod, rope = base.embed(x, t)
        residuals = net.controls(h0, mod, rope, mask, tokens, text_mask, eot)
        assert all(torch.equal(r, torch.zeros_like(r)) for r in residuals)
        h_frozen, h_copy = h0, h0
        text = net._prepare_text(tokens, text_mask, eot)
        for i in range(len(base.blocks)):
            h_frozen = base.blocks[i](h_frozen, mod, rope, mask)
            h_copy = net._control_layer(i, h_copy, mod, rope, mask, text)
            assert torch.equal(h_copy, h_frozen)
    # Same weights in the copies, but separate tensors.
    for copy_block, block in zip(net.copy_blocks, base.blocks):
        for a, b in zip(copy_block.parameters(), block.parameters()):
            assert torch.equal(a, b) and a.data_ptr() != b.data_ptr()


def test_train_mode_keeps_base_frozen():
    net = MotionControlNet(frozen_base(), MoCConfig(**SMALL_MOC))
    net.train()
    assert net.training and net.copy_blocks.training and net.mocs.training
    assert not net.base.training and not any(m.training for m in net.base.modules())
    assert not any(p.requires_grad for p in net.base.parameters())
    trainable = {id(p) for p in net.trainable_parameters()}
    assert all(p.requires_grad for p in net.trainable_parameters())
    frozen = {id(p) for p in net.base.parameters()}
    assert trainable.isdisjoint(frozen)
    assert trainable | frozen == {id(p) for p in net.parameters()}


def test_training_updates_only_the_controller():
    """Adam (no weight decay, so a zero gradient means no move) on an x̂0 loss over real frames.

    The zero-initialised layers form a chain, and what we check follows it exactly:
    step 1: only the zero projections get a gradient (everything behind them sees Z = 0);
    step 2: Z ≠ 0, so the copy blocks and each MoC's W_up learn; the rest of the MoC is still
            behind W_up = 0 and does not move;
    steps 3-4: W_down, W_k, W_v, the gate MLP, the AdaIN Linear and the experts get gradients
            at step 3, W_q's weight at step 4 (its input f = W_down h is 0 until W_down moved).
    After 4 steps every trainable tensor has changed; the frozen model stays bit-identical.
    """
    torch.manual_seed(0)
    base = frozen_base()
    net = MotionControlNet(base, MoCConfig(**SMALL_MOC)).train()
    frozen_before = {k: v.clone() for k, v in base.state_dict().items()}
    init = {name: p.detach().clone() for name, p in net.named_parameters() if p.requires_grad}
    opt = torch.optim.Adam(net.trainable_parameters(), lr=1e-3)
    x, t = motion_batch(2, 10)
    target = torch.randn_like(x)
    mask = frame_mask([10, 6], 10)
    tokens, text_mask, eot = text_batch([4, 2])

    def step():
        out = net(x, t, tokens, text_mask, eot, mask)
        loss = ((out - target).square() * mask[..., None]).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()

    def changed(name):
        return not torch.equal(dict(net.named_parameters())[name], init[name])

    step()
    moved = {name for name in init if changed(name)}
    assert moved == {name for name in init if name.startswith("zero_projs.")}
    step()
    moved = {name for name in init if changed(name)}
    for name in init:
        behind_up = name.startswith("mocs.") and ".up." not in name
        assert (name in moved) != behind_up, name
    step()
    step()
    assert [name for name in init if not changed(name)] == []
    assert all(torch.equal(v, frozen_before[k]) for k, v in base.state_dict().items())
    assert all(p.grad is None for p in base.parameters())


def test_activation_checkpointing_gives_same_gradients():
    x, t = motion_batch(2, 8)
    tokens, text_mask, eot = text_batch([3, 2])
    mask = frame_mask([8, 5], 8)
    grads = []
    for ckpt in (False, True):
        torch.manual_seed(0)
        net = MotionControlNet(frozen_base(activation_checkpointing=ckpt), MoCConfig(**SMALL_MOC))
        randomize_zeros(net).train()
        net(x, t, tokens, text_mask, eot, mask).square().mean().backward()
        grads.append(torch.cat([p.grad.flatten() for p in net.trainable_parameters()]))
    torch.testing.assert_close(grads[0], grads[1])


# -- the MoC block against a loop-based reference ----------------------------------------------


def reference_moc(moc: MoCBlock, h, tokens, text_mask, eot, mask):
    """The paper's formulas, one sample, one token and one expert at a time, with the blended
    expert weights W_i = Σ_k ω_ik W_k built explicitly. Returns out, A, M, ω per sample."""
    cfg = moc.config
    outs, attns, masks, omegas = [], [], [], []
    for b in range(h.shape[0]):
        real_tokens = text_mask[b].nonzero().flatten().tolist()
        real_frames = mask[b].nonzero().flatten()
        e = tokens[b]  # (L, D)
        f = moc.down(h[b])  # (T, c)
        q, k, v = moc.q(f), moc.k(e[real_tokens]), moc.v(e[real_tokens])
        A = torch.softmax(q @ k.T / math.sqrt(cfg.d_c), dim=-1)  # (T, L_real)
        f = f + A @ v
        real = f[real_frames]
        mean, var = real.mean(0), real.var(0, unbiased=False)
        scale, shift = moc.eot_affine(e[eot[b]]).chunk(2)
        f = (f - mean) / torch.sqrt(var + 1e-5) * (1 + scale) + shift
        r = torch.zeros_like(f)
        A_full = torch.zeros(h.shape[1], tokens.shape[1], dtype=h.dtype)
        M_full = torch.zeros_like(A_full)
        omega_full = torch.zeros(tokens.shape[1], cfg.num_experts, dtype=h.dtype)
        for j, i in enumerate(real_tokens):
            omega = torch.softmax(moc.gate(e[i]), dim=-1)  # (K,)
            W1, B1 = torch.zeros_like(moc.w1[0]), torch.zeros_like(moc.b1[0])
            W2, B2 = torch.zeros_like(moc.w2[0]), torch.zeros_like(moc.b2[0])
            for kk in range(cfg.num_experts):
                W1, B1 = W1 + omega[kk] * moc.w1[kk], B1 + omega[kk] * moc.b1[kk]
                W2, B2 = W2 + omega[kk] * moc.w2[kk], B2 + omega[kk] * moc.b2[kk]
            F_i = F.gelu(f @ W1 + B1) @ W2 + B2  # (T, c)
            A_i = A[:, j]
            M_i = torch.sigmoid(cfg.gamma * (A_i - cfg.beta * A_i[real_frames].max()))
            r = r + M_i[:, None] * F_i
            A_full[:, i], M_full[:, i], omega_full[i] = A_i, M_i, omega
        outs.append(moc.up(r))
        attns.append(A_full)
        masks.append(M_full)
        omegas.append(omega_full)
    return torch.stack(outs), torch.stack(attns), torch.stack(masks), torch.stack(omegas)


def test_moc_matches_loop_reference():
    torch.manual_seed(0)
    cfg = MoCConfig(d_c=8, num_experts=3, expert_hidden=10, gate_hidden=6, text_dim=12)
    moc = randomize_zeros(MoCBlock(16, cfg), std=0.3).double()
    with torch.no_grad():  # sharper attention than the default init gives, so masks vary
        moc.q.weight.mul_(4)
    assert all(p.any() for p in moc.parameters())
    B, T = 3, 9
    h = torch.randn(B, T, 16, dtype=torch.double)
    tokens, text_mask, eot = text_batch([5, 3, 1], D=12)
    tokens = tokens.double()  # padded positions hold random values: they must not matter
    mask = frame_mask([9, 4, 6], T)

    out = moc(h, tokens, text_mask, tokens[torch.arange(B), eot], mask)
    ref_out, ref_attn, ref_masks, ref_omega = reference_moc(moc, h, tokens, text_mask, eot, mask)
    torch.testing.assert_close(out, ref_out, rtol=1e-10, atol=1e-10)  # every frame, padded too

    f, attn = moc.attend(moc.down(h), tokens, text_mask)
    masks = moc.token_masks(attn, text_mask, mask)
    omega = moc.gates(tokens) * text_mask[..., None]
    torch.testing.assert_close(attn, ref_attn, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(masks, ref_masks, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(omega, ref_omega, rtol=1e-12, atol=1e-12)
    real = text_mask[:, None, :] & mask[..., None]
    assert masks[real].min() < 0.1 and masks[real].max() > 0.9  # the masks do select frames


def test_moc_is_nan_free_without_real_tokens_or_frames():
    moc = randomize_zeros(MoCBlock(16, MoCConfig(d_c=8, num_experts=3, text_dim=12)))
    h = torch.randn(2, 5, 16)
    tokens, _, eot = text_batch([3, 3], D=12)
    text_mask = torch.tensor([[False] * 3, [True] * 3])
    mask = torch.tensor([[True] * 5, [False] * 5])
    out = moc(h, tokens, text_mask, tokens[:, 0], mask)
    assert torch.isfinite(out).all()
    _, attn = moc.attend(moc.down(h), tokens, text_mask)
    assert torch.equal(attn[0], torch.zeros(5, 3)) and torch.isfinite(attn).all()
    # No real token: no attention, no residual; the block adds only W_up's bias.
    torch.testing.assert_close(out[0], moc.up.bias.expand(5, -1))


# -- the ControlNet -------------------------------------------------------------------------


def trained_like(layers=None, **overrides) -> MotionControlNet:
    """A ControlNet whose zero-initialised layers were randomised, so D_c differs from D_u."""
    torch.manual_seed(0)
    net = MotionControlNet(frozen_base(**overrides), MoCConfig(**SMALL_MOC, layers=layers))
    return randomize_zeros(net).eval()


def test_padding_of_frames_and_tokens_does_not_leak():
    net = trained_like()
    x, t = motion_batch(2, 14)
    mask = frame_mask([14, 8], 14)
    tokens, text_mask, eot = text_batch([4, 2], L=6)
    with torch.no_grad():
        out = net(x, t, tokens, text_mask, eot, mask)
        x2, tokens2 = x.clone(), tokens.clone()
        x2[1, 8:] = 100.0
        tokens2[~text_mask] = float("nan")
        out2 = net(x2, t, tokens2, text_mask, eot, mask)
        # The second clip alone, unpadded, with its caption alone, unpadded.
        alone = net(x[1:, :8], t[1:], tokens[1:, :2], text_mask[1:, :2], eot[1:])
    assert torch.isfinite(out2).all()
    torch.testing.assert_close(out2[mask], out[mask], rtol=0, atol=1e-5)
    torch.testing.assert_close(out[1:, :8], alone, rtol=1e-4, atol=1e-5)


def test_layers_choose_where_text_enters():
    net = trained_like(layers=[1, 3])
    assert sorted(net.mocs) == ["1", "3"]
    assert len(net.copy_blocks) == len(net.zero_projs) == 4
    x, t = motion_batch(1, 6)
    tokens, text_mask, eot = text_batch([3])
    with torch.no_grad():
        h0, c, mod, rope = net.base.embed(x, t)
        a = net.controls(h0, mod, rope, None, tokens, text_mask, eot)
        b = net.controls(h0, mod, rope, None, tokens + 1, text_mask, eot)
    assert torch.equal(a[0], b[0])  # before the first controller: text-independent
    assert all(not torch.allclose(a[i], b[i]) for i in (1, 2, 3))


@pytest.mark.parametrize("with_mask", [False, True])
def test_forward_guided_is_the_cfg_mix(with_mask):
    net = trained_like()
    B, T = 3, 11
    x, t = motion_batch(B, T)
    mask = frame_mask([11, 5, 8], T) if with_mask else None
    tokens, text_mask, eot = text_batch([4, 1, 3])
    with torch.no_grad():
        cond = net(x, t, tokens, text_mask, eot, mask)
        uncond = net.forward_uncond(x, t, mask)
        assert not torch.allclose(cond, uncond, atol=1e-3)
        for s in (0.0, 1.0, 4.5):  # s = 0: exactly uncond, s = 1: exactly cond
            guided = net.forward_guided(x, t, tokens, text_mask, eot, s, mask)
            torch.testing.assert_close(guided, (1 - s) * uncond + s * cond, rtol=1e-5, atol=1e-5)
        s = torch.tensor([0.0, 1.0, 4.5])[:, None, None]  # one scale per sample
        guided = net.forward_guided(x, t, tokens, text_mask, eot, s.flatten(), mask)
        torch.testing.assert_close(guided, (1 - s) * uncond + s * cond, rtol=1e-5, atol=1e-5)
        torch.testing.assert_close(guided[0], uncond[0], rtol=1e-5, atol=1e-5)
        torch.testing.assert_close(guided[1], cond[1], rtol=1e-5, atol=1e-5)


def test_forward_guided_shares_work():
    net = trained_like()
    calls = []

    def record(kind):
        return lambda module, args, out: calls.append((kind, args[0].shape[0]))

    net.base.input_proj.register_forward_hook(record("embed"))
    for block in net.base.blocks:
        block.register_forward_hook(record("frozen"))
    for block in net.copy_blocks:
        block.register_forward_hook(record("copy"))
    x, t = motion_batch(2, 7)
    with torch.no_grad():
        net.forward_guided(x, t, *text_batch([3, 2]), 3.0)
    assert sorted(calls) == sorted([("embed", 2)] + [("frozen", 4)] * 4 + [("copy", 2)] * 4)


# -- sizes ----------------------------------------------------------------------------------


def moc_params(d: int, cfg: MoCConfig) -> int:
    c, K, H, D, G = cfg.d_c, cfg.num_experts, cfg.expert_hidden, cfg.text_dim, cfg.gate_hidden
    return (
        (d * c + c)  # W_down
        + (c * c + c) + 2 * (D * c + c)  # W_q, W_k, W_v
        + (D * 2 * c + 2 * c)  # AdaIN scale/shift from the EOT token
        + (D * G + G) + (G * G + G) + (G * K + K)  # gate MLP
        + K * (c * H + H + H * c + c)  # experts
        + (c * d + d)  # W_up
    )


@pytest.mark.parametrize("flavor", ["mini", "base"])
def test_parameter_counts_on_meta_device(flavor):
    cfg = MoCConfig(text_dim=512)
    with torch.device("meta"):
        base = MotionDiT(DiTConfig.from_name(flavor))
        net = MotionControlNet(base, cfg)
    d, n = base.config.d_model, base.config.n_layers
    frozen = sum(p.numel() for p in base.parameters())
    copies = sum(p.numel() for p in net.copy_blocks.parameters())
    mocs = sum(p.numel() for p in net.mocs.parameters())
    projs = sum(p.numel() for p in net.zero_projs.parameters())
    trainable = sum(p.numel() for p in net.trainable_parameters())
    print(
        f"{flavor}: frozen {frozen / 1e6:.2f}M, trainable {trainable / 1e6:.2f}M = copies "
        f"{copies / 1e6:.2f}M + MoC {mocs / 1e6:.2f}M ({mocs // n / 1e6:.3f}M per layer) + "
        f"zero projections {projs / 1e6:.2f}M"
    )
    assert copies == sum(p.numel() for p in base.blocks.parameters())
    assert mocs == n * moc_params(d, cfg)
    assert projs == n * (d * d + d)
    assert trainable == copies + mocs + projs
    assert sum(p.numel() for p in net.parameters()) == frozen + trainable
