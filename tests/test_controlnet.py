import math

import pytest
import torch
import torch.nn.functional as F
from torch import nn

from omg.errors import UsageError
from omg.models.checkpointing import checkpoint_each
from omg.models.controlnet import MoCBlock, MoCConfig, MotionControlNet
from omg.models.dit import DiTConfig, MotionDiT
from omg.text import HashTextEncoder

D_TEXT = 24
SMALL_MOC = dict(d_c=32, num_experts=4, text_dim=D_TEXT)
WIRINGS = ["per_layer", "parallel_stream"]


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
    assert (cfg.token_masks, cfg.zero_init, cfg.experts, cfg.wiring) == (True, True, "moc", "per_layer")
    assert MoCConfig(layers=[3, 1]).layers == [1, 3]
    for field, value in [
        ("d_c", 0), ("num_experts", -1), ("expert_hidden", 2.5), ("gate_hidden", 0),
        ("text_dim", True), ("gamma", 0.0), ("gamma", float("inf")), ("beta", 1.5),
        ("layers", []), ("layers", [1, 1]), ("layers", [-1]), ("token_masks", 1),
        ("zero_init", "no"), ("experts", "ffn"), ("wiring", "parallel"),
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


@pytest.mark.parametrize("wiring", WIRINGS)
def test_init_equals_frozen_model_exactly(wiring):
    torch.manual_seed(0)
    base = frozen_base()
    net = MotionControlNet(base, MoCConfig(**SMALL_MOC, wiring=wiring))
    x, t = motion_batch(3, 12)
    mask = frame_mask([12, 7, 1], 12)
    tokens, text_mask, eot = text_batch([5, 2, 4])
    with torch.no_grad():
        expected = base(x, t, mask)
        assert torch.equal(net(x, t, tokens, text_mask, eot, mask), expected)
        assert torch.equal(net.forward_uncond(x, t, mask), expected)
        # Stronger than the output: every residual is exactly 0.
        h, c, mod, rope = base.embed(x, t)
        control = net.controller(h, mod, rope, mask, net.text_terms(tokens, text_mask, eot))
        for i in range(len(base.blocks)):
            r = control(i, h)
            assert torch.equal(r, torch.zeros_like(r))
            h = base.blocks[i](h, mod, rope, mask)
    # Same weights in the copies, but separate tensors.
    assert sorted(net.copy_blocks, key=int) == [str(i) for i in range(len(base.blocks))]
    for i, copy_block in net.copy_blocks.items():
        for a, b in zip(copy_block.parameters(), base.blocks[int(i)].parameters()):
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
    step 1: only each MoC's W_up gets a gradient (every residual is W_up(...) = 0 at init);
    step 2: W_up ≠ 0, so the rest of the MoC learns, except W_q's weight (its input
            f = W_down g is 0 until W_down moved) and the block copies (behind W_down = 0);
    step 3: W_q's weight and the copies get gradients.
    After 3 steps every trainable tensor has changed; the frozen model stays bit-identical.
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

    def moved():
        params = dict(net.named_parameters())
        return {name for name in init if not torch.equal(params[name], init[name])}

    step()
    assert moved() == {name for name in init if ".up." in name}
    assert all(torch.equal(v, frozen_before[k]) for k, v in base.state_dict().items())
    step()
    behind_down = {n for n in init if n.startswith("copy_blocks.") or n.endswith(".q.weight")}
    assert moved() == set(init) - behind_down
    step()
    assert moved() == set(init)
    assert all(torch.equal(v, frozen_before[k]) for k, v in base.state_dict().items())
    assert all(p.grad is None for p in base.parameters())


@pytest.mark.parametrize("wiring", WIRINGS)
def test_activation_checkpointing_gives_same_gradients(wiring):
    x, t = motion_batch(2, 8)
    tokens, text_mask, eot = text_batch([3, 2])
    mask = frame_mask([8, 5], 8)
    grads = []
    for ckpt in (False, True):
        torch.manual_seed(0)
        net = MotionControlNet(frozen_base(), MoCConfig(**SMALL_MOC, wiring=wiring))
        if ckpt:  # what ControlNetModule.configure_model applies
            checkpoint_each([*net.base.blocks, *net.copy_blocks.values(), *net.mocs.values()])
        randomize_zeros(net).train()
        net(x, t, tokens, text_mask, eot, mask).square().mean().backward()
        grads.append(torch.cat([p.grad.flatten() for p in net.trainable_parameters()]))
    torch.testing.assert_close(grads[0], grads[1])


# -- the MoC block against a loop-based reference ----------------------------------------------


def reference_moc(moc: MoCBlock, h, tokens, text_mask, eot, mask, token_masks=True):
    """The paper's formulas, one sample, one token and one expert at a time, with the blended
    expert weights W_i = Σ_k ω_ik W_k built explicitly (M_i = 1 with ``token_masks=False``).
    Returns out, A, M, ω per sample."""
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
            if not token_masks:
                M_i = torch.ones_like(M_i)
            r = r + M_i[:, None] * F_i
            A_full[:, i], M_full[:, i], omega_full[i] = A_i, M_i, omega
        outs.append(moc.up(r))
        attns.append(A_full)
        masks.append(M_full)
        omegas.append(omega_full)
    return torch.stack(outs), torch.stack(attns), torch.stack(masks), torch.stack(omegas)


TINY_MOC = dict(d_c=8, num_experts=3, expert_hidden=10, gate_hidden=6, text_dim=12)


def run_moc(moc: MoCBlock, h, tokens, text_mask, eot_emb, mask):
    return moc(h, moc.text_terms(tokens, text_mask, eot_emb), mask)


def random_moc(**overrides) -> MoCBlock:
    torch.manual_seed(0)
    moc = randomize_zeros(MoCBlock(16, MoCConfig(**{**TINY_MOC, **overrides})), std=0.3).double()
    with torch.no_grad():  # sharper attention than the default init gives, so masks vary
        moc.q.weight.mul_(4)
    assert all(p.any() for p in moc.parameters())
    return moc


def moc_inputs():
    B, T = 3, 9
    h = torch.randn(B, T, 16, dtype=torch.double, generator=torch.Generator().manual_seed(1))
    tokens, text_mask, eot = text_batch([5, 3, 1], D=12)
    tokens = tokens.double()  # padded positions hold random values: they must not matter
    return h, tokens, text_mask, eot, frame_mask([9, 4, 6], T)


def test_moc_matches_loop_reference():
    moc = random_moc()
    h, tokens, text_mask, eot, mask = moc_inputs()
    B = h.shape[0]
    out = moc(h, moc.text_terms(tokens, text_mask, tokens[torch.arange(B), eot]), mask)
    ref_out, ref_attn, ref_masks, ref_omega = reference_moc(moc, h, tokens, text_mask, eot, mask)
    torch.testing.assert_close(out, ref_out, rtol=1e-10, atol=1e-10)  # every frame, padded too

    f, attn = moc.attend(moc.down(h), moc.text_terms(tokens, text_mask, tokens[:, 0]))
    masks = moc.token_masks(attn, text_mask, mask)
    omega = moc.gates(tokens) * text_mask[..., None]
    torch.testing.assert_close(attn, ref_attn, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(masks, ref_masks, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(omega, ref_omega, rtol=1e-12, atol=1e-12)
    real = text_mask[:, None, :] & mask[..., None]
    assert masks[real].min() < 0.1 and masks[real].max() > 0.9  # the masks do select frames


def test_ablation_without_token_masks_is_the_moc_with_m_1():
    """token_masks=False: same parameters, same attention and gates; only M_i ≡ 1."""
    full, ablated = random_moc(), random_moc(token_masks=False)
    assert ablated.state_dict().keys() == full.state_dict().keys()
    ablated.load_state_dict(full.state_dict())
    h, tokens, text_mask, eot, mask = moc_inputs()
    eot_emb = tokens[torch.arange(len(eot)), eot]
    out = run_moc(ablated, h, tokens, text_mask, eot_emb, mask)
    ref = reference_moc(full, h, tokens, text_mask, eot, mask, token_masks=False)[0]
    torch.testing.assert_close(out, ref, rtol=1e-10, atol=1e-10)
    assert not torch.allclose(out, run_moc(full, h, tokens, text_mask, eot_emb, mask), atol=1e-3)
    _, attn = ablated.attend(ablated.down(h), ablated.text_terms(tokens, text_mask, tokens[:, 0]))
    assert torch.equal(ablated.token_masks(attn, text_mask, mask), text_mask[:, None].double().expand_as(attn))


def test_ablation_single_ffn():
    """experts="single_ffn": no gate or expert pool; out = W_up FFN(AdaIN(attend(W_down h)))."""
    full, ablated = random_moc(), random_moc(experts="single_ffn")
    keys, full_keys = set(ablated.state_dict()), set(full.state_dict())
    expert_pool = {"w1", "b1", "w2", "b2"} | {k for k in full_keys if k.startswith("gate.")}
    assert keys == (full_keys - expert_pool) | {"ffn.0.weight", "ffn.0.bias", "ffn.2.weight", "ffn.2.bias"}
    assert ablated.ffn[0].weight.shape == (10, 8) and ablated.ffn[2].weight.shape == (8, 10)
    ablated.load_state_dict({k: v for k, v in full.state_dict().items() if k in keys}, strict=False)
    h, tokens, text_mask, eot, mask = moc_inputs()
    out = run_moc(ablated, h, tokens, text_mask, tokens[torch.arange(len(eot)), eot], mask)
    for b in range(h.shape[0]):  # one sample at a time, real tokens and real frames only
        e = tokens[b, text_mask[b]]
        f = ablated.down(h[b])
        A = torch.softmax(ablated.q(f) @ ablated.k(e).T / math.sqrt(8), dim=-1)
        f = f + A @ ablated.v(e)
        real = f[mask[b]]
        scale, shift = ablated.eot_affine(tokens[b, eot[b]]).chunk(2)
        f = (f - real.mean(0)) / torch.sqrt(real.var(0, unbiased=False) + 1e-5) * (1 + scale) + shift
        W1, b1, W2, b2 = ablated.ffn[0].weight, ablated.ffn[0].bias, ablated.ffn[2].weight, ablated.ffn[2].bias
        ref = ablated.up(F.gelu(f @ W1.T + b1) @ W2.T + b2)
        torch.testing.assert_close(out[b], ref, rtol=1e-10, atol=1e-10)


def test_moc_is_nan_free_without_real_tokens_or_frames():
    moc = randomize_zeros(MoCBlock(16, MoCConfig(d_c=8, num_experts=3, text_dim=12)))
    h = torch.randn(2, 5, 16)
    tokens, _, eot = text_batch([3, 3], D=12)
    text_mask = torch.tensor([[False] * 3, [True] * 3])
    mask = torch.tensor([[True] * 5, [False] * 5])
    text = moc.text_terms(tokens, text_mask, tokens[:, 0])
    out = moc(h, text, mask)
    assert torch.isfinite(out).all()
    _, attn = moc.attend(moc.down(h), text)
    assert torch.equal(attn[0], torch.zeros(5, 3)) and torch.isfinite(attn).all()
    # No real token: no attention, no residual; the block adds only W_up's bias.
    torch.testing.assert_close(out[0], moc.up.bias.expand(5, -1))


# -- the ControlNet -------------------------------------------------------------------------


def trained_like(layers=None, **overrides) -> MotionControlNet:
    """A ControlNet whose zero-initialised layers were randomised, so D_c differs from D_u."""
    moc = {k: overrides.pop(k) for k in ("wiring", "token_masks", "experts") if k in overrides}
    torch.manual_seed(0)
    net = MotionControlNet(frozen_base(**overrides), MoCConfig(**SMALL_MOC, layers=layers, **moc))
    return randomize_zeros(net).eval()


def reference_fig3(net: MotionControlNet, x, t, tokens, text_mask, eot, mask, hint=None):
    """Paper Fig. 3, written out: layer l's copy reads h_l (the main stream entering frozen
    layer l; with a hint, h_l + H(hint)), the MoC turns the copy's output into token-masked residuals (the
    loop-based MoC reference), and they are added to the frozen layer's output h_{l+1}."""
    base = net.base
    h, c, mod, rope = base.embed(x, t)
    e = 0 if hint is None else net.hint_embed(hint)
    for layer, frozen in enumerate(base.blocks):
        h_next = frozen(h, mod, rope, mask)
        if str(layer) in net.mocs:
            g = net.copy_blocks[str(layer)](h + e, mod, rope, mask)
            h_next = h_next + reference_moc(net.mocs[str(layer)], g, tokens, text_mask, eot, mask)[0]
        h = h_next
    return base.final_layer(h, c)


def reference_parallel_stream(net: MotionControlNet, x, t, tokens, text_mask, eot, mask, hint=None):
    base = net.base
    h, c, mod, rope = base.embed(x, t)
    h_c = h if hint is None else h + net.hint_embed(hint)
    for layer, frozen in enumerate(base.blocks):
        h_c = net.copy_blocks[str(layer)](h_c, mod, rope, mask)
        if str(layer) in net.mocs:
            h_c = h_c + reference_moc(net.mocs[str(layer)], h_c, tokens, text_mask, eot, mask)[0]
        h = frozen(h, mod, rope, mask) + net.zero_projs[layer](h_c)
    return base.final_layer(h, c)


@pytest.mark.parametrize("wiring, layers", [("per_layer", None), ("per_layer", [0, 2]), ("parallel_stream", [1, 3])])
def test_controlnet_matches_loop_reference(wiring, layers):
    net = trained_like(layers=layers, wiring=wiring).double()
    with torch.no_grad():  # sharper attention, so the token masks select frames
        for moc in net.mocs.values():
            moc.q.weight.mul_(8)
    assert all(p.any() for p in net.parameters())  # up-projections included: nothing trivial
    x, t = motion_batch(2, 9)
    x = x.double()
    mask = frame_mask([9, 6], 9)
    tokens, text_mask, eot = text_batch([5, 3])
    tokens = tokens.double()
    reference = reference_fig3 if wiring == "per_layer" else reference_parallel_stream
    with torch.no_grad():
        out = net(x, t, tokens, text_mask, eot, mask)
        expected = reference(net, x, t, tokens, text_mask, eot, mask)
        torch.testing.assert_close(out, expected, rtol=1e-9, atol=1e-9)
        assert not torch.allclose(out, net.forward_uncond(x, t, mask), atol=1e-3)
        if wiring == "per_layer":  # a layer without a controller adds nothing
            h, _, mod, rope = net.base.embed(x, t)
            control = net.controller(h, mod, rope, mask, net.text_terms(tokens, text_mask, eot))
            skipped = [i for i in range(4) if str(i) not in net.mocs]
            assert all(control(i, h) is None for i in skipped)


@pytest.mark.parametrize("wiring", WIRINGS)
def test_a_hint_starts_as_no_change_and_is_read_by_every_copy(wiring):
    """Spatial hints (OmniControl's realism branch): a new hinted ControlNet is the frozen model whatever the hint
    (W_up = 0); one given the trained controllers of a network without hints, its hint embedding silenced (as a
    ControlNet given as ``pretrained`` does), is that network bit for bit; once the embedding has weights, each
    copy reads h_l + H(hint) (the references above), and guidance mixes the frozen model with the hinted D_c."""
    net = trained_like(layers=[0, 2], wiring=wiring).double()
    x, t = motion_batch(2, 9)
    x, mask = x.double(), frame_mask([9, 6], 9)
    tokens, text_mask, eot = text_batch([5, 3])
    tokens, hint = tokens.double(), torch.randn(2, 9, 12, dtype=torch.float64)
    config = MoCConfig(**SMALL_MOC, layers=[0, 2], wiring=wiring, hint_channels=12)
    hinted = MotionControlNet(net.base, config).double()
    with torch.no_grad():
        assert hinted.hint_embed[-1].weight.any()  # PyTorch's init: the MoC's zero W_up silences it
        if wiring == "per_layer":  # (the parallel stream's zero projections do the same)
            torch.testing.assert_close(hinted(x, t, tokens, text_mask, eot, mask, hint), net.forward_uncond(x, t, mask),
                                       rtol=0, atol=1e-12)
    missing, unexpected = hinted.load_state_dict(net.state_dict(), strict=False)
    assert sorted(missing) == [f"hint_embed.{i}.{p}" for i in (0, 2, 3) for p in ("bias", "weight")]
    assert not unexpected
    hinted.silence_hints()
    reference = reference_fig3 if wiring == "per_layer" else reference_parallel_stream
    with torch.no_grad():
        plain = net(x, t, tokens, text_mask, eot, mask)
        assert torch.equal(hinted(x, t, tokens, text_mask, eot, mask, hint), plain)
        hinted.hint_embed[-1].weight.normal_(std=0.05)
        out = hinted(x, t, tokens, text_mask, eot, mask, hint)
        torch.testing.assert_close(out, reference(hinted, x, t, tokens, text_mask, eot, mask, hint), rtol=1e-9,
                                   atol=1e-9)
        assert not torch.allclose(out, plain, atol=1e-4)
        assert torch.equal(hinted(x, t, tokens, text_mask, eot, mask), plain)  # no hint: as without hints
        e = hinted.embed_hint(hint, x.dtype)
        guided = hinted.forward_guided(x, t, hinted.text_terms(tokens, text_mask, eot), 2.5, mask, e)
        torch.testing.assert_close(guided, -1.5 * hinted.forward_uncond(x, t, mask) + 2.5 * out, rtol=1e-9,
                                   atol=1e-9)
        with pytest.raises(UsageError, match="not trained with spatial hints"):
            net.embed_hint(hint, x.dtype)


def test_layers_choose_where_controllers_sit():
    net = trained_like(layers=[1, 3])
    assert sorted(net.mocs) == sorted(net.copy_blocks) == ["1", "3"]
    assert not hasattr(net, "zero_projs")
    parallel = trained_like(layers=[1, 3], wiring="parallel_stream")
    assert sorted(parallel.mocs) == ["1", "3"] and len(parallel.copy_blocks) == len(parallel.zero_projs) == 4
    x, t = motion_batch(1, 6)
    tokens, text_mask, eot = text_batch([3])
    with torch.no_grad():
        h0, c, mod, rope = parallel.base.embed(x, t)
        a = parallel.controller(h0, mod, rope, None, parallel.text_terms(tokens, text_mask, eot))
        b = parallel.controller(h0, mod, rope, None, parallel.text_terms(tokens + 1, text_mask, eot))
        ra, rb = [a(i, h0) for i in range(4)], [b(i, h0) for i in range(4)]
    # The parallel stream's copy before the first controller is a text-independent path.
    assert torch.equal(ra[0], rb[0]) and not torch.equal(ra[0], torch.zeros_like(ra[0]))
    assert all(not torch.allclose(ra[i], rb[i]) for i in (1, 2, 3))


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


@pytest.mark.parametrize("wiring, with_mask", [("per_layer", False), ("per_layer", True), ("parallel_stream", True)])
def test_forward_guided_is_the_cfg_mix(wiring, with_mask):
    net = trained_like(layers=[0, 1, 3], wiring=wiring)
    B, T = 3, 11
    x, t = motion_batch(B, T)
    mask = frame_mask([11, 5, 8], T) if with_mask else None
    tokens, text_mask, eot = text_batch([4, 1, 3])
    with torch.no_grad():
        cond = net(x, t, tokens, text_mask, eot, mask)
        uncond = net.forward_uncond(x, t, mask)
        assert not torch.allclose(cond, uncond, atol=1e-3)
        for s in (0.0, 1.0, 4.5):  # s = 0: exactly uncond, s = 1: exactly cond
            guided = net.forward_guided(x, t, net.text_terms(tokens, text_mask, eot), s, mask)
            torch.testing.assert_close(guided, (1 - s) * uncond + s * cond, rtol=1e-5, atol=1e-5)
        s = torch.tensor([0.0, 1.0, 4.5])[:, None, None]  # one scale per sample
        guided = net.forward_guided(x, t, net.text_terms(tokens, text_mask, eot), s.flatten(), mask)
        torch.testing.assert_close(guided, (1 - s) * uncond + s * cond, rtol=1e-5, atol=1e-5)
        torch.testing.assert_close(guided[0], uncond[0], rtol=1e-5, atol=1e-5)
        torch.testing.assert_close(guided[1], cond[1], rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("wiring", WIRINGS)
def test_text_terms_folded_once_give_the_per_step_output(wiring):
    """Sampling computes the text-only terms once (ω·b1, ω·b2 folded in): the same D_c as the
    training path, which leaves those products to the experts."""
    net = trained_like(wiring=wiring)
    x, t = motion_batch(3, 9)
    tokens, text_mask, eot = text_batch([4, 1, 3])
    mask = frame_mask([9, 5, 7], 9)
    with torch.no_grad():
        folded = net.text_terms(tokens, text_mask, eot, fold_biases=True)
        assert all(terms.omega_b1 is not None and terms.omega_b2 is not None for terms in folded.values())
        assert all(terms.omega_b1 is None for terms in net.text_terms(tokens, text_mask, eot).values())
        for s in (1.0, 4.5):
            torch.testing.assert_close(net.forward_guided(x, t, folded, s, mask),
                                       net.forward_guided(x, t, net.text_terms(tokens, text_mask, eot), s, mask),
                                       rtol=1e-6, atol=1e-6)


def test_forward_guided_shares_work():
    net = trained_like(layers=[0, 2])
    calls = []

    def record(kind):
        return lambda module, args, out: calls.append((kind, args[0].shape[0]))

    net.base.input_proj.register_forward_hook(record("embed"))
    for block in net.base.blocks:
        block.register_forward_hook(record("frozen"))
    for block in net.copy_blocks.values():
        block.register_forward_hook(record("copy"))
    for moc in net.mocs.values():
        moc.register_forward_hook(record("moc"))
    x, t = motion_batch(2, 7)
    with torch.no_grad():
        net.forward_guided(x, t, net.text_terms(*text_batch([3, 2])), 3.0)
    expected = [("embed", 2)] + [("frozen", 4)] * 4 + [("copy", 2)] * 2 + [("moc", 2)] * 2
    assert sorted(calls) == sorted(expected)


# -- ablations on the whole ControlNet ------------------------------------------------------


def test_ablation_zero_init_off_changes_only_the_projections():
    torch.manual_seed(0)
    base = frozen_base()
    nets = {}
    for zero_init in (True, False):
        torch.manual_seed(1)
        nets[zero_init] = MotionControlNet(base, MoCConfig(**SMALL_MOC, zero_init=zero_init))
    on, off = (nets[z].state_dict() for z in (True, False))
    assert on.keys() == off.keys()
    differ = {k for k in on if not torch.equal(on[k], off[k])}
    assert differ == {k for k in on if k.startswith("mocs.") and (".down." in k or ".up." in k)}
    x, t = motion_batch(2, 8)
    with torch.no_grad():
        d_u = base(x, t)
        assert torch.equal(nets[True](x, t, *text_batch([3, 2])), d_u)
        assert not torch.allclose(nets[False](x, t, *text_batch([3, 2])), d_u, atol=1e-4)


def test_ablation_switches_build_what_they_name():
    n_params = {}
    for name, extra in [("moc", {}), ("ffn", {"experts": "single_ffn"}), ("nomask", {"token_masks": False})]:
        torch.manual_seed(0)
        net = MotionControlNet(frozen_base(), MoCConfig(**SMALL_MOC, **extra))
        n_params[name] = {k: v.shape for k, v in net.state_dict().items()}
    assert n_params["nomask"] == n_params["moc"]  # a switch of the forward pass only
    assert not any(".gate." in k or k.endswith((".w1", ".w2")) for k in n_params["ffn"])
    assert {k for k in n_params["moc"] if ".ffn." in k} == set()


# -- text tokens: trimming CLIP-style padding -------------------------------------------------


def test_trimmed_tokens_give_the_same_outputs():
    """CLIP pads every caption to 77 tokens; the hash encoder pads to the longest caption, so
    it is made to pad like CLIP here. Trimming to the longest caption changes no output."""
    encoder = HashTextEncoder(dim=D_TEXT, max_tokens=77)
    encoder.pad_to_max = True  # CLIP's fixed context
    texts = ["a person walks forward", "a person jumps", "someone waves with the left hand twice"]
    padded = encoder(texts)
    trimmed = padded.trimmed()
    assert padded.tokens.shape[1] == 77 and trimmed.tokens.shape[1] == 9  # start + 7 words + end
    assert trimmed.trimmed() is trimmed and torch.equal(trimmed.eot, padded.eot)
    assert torch.equal(trimmed.padded(77).tokens, padded.tokens)
    assert torch.equal(trimmed.padded(77).mask, padded.mask)
    assert torch.equal(encoder.__class__(dim=D_TEXT, max_tokens=77)(texts).tokens, trimmed.tokens)

    net = trained_like()
    x, t = motion_batch(3, 10)
    mask = frame_mask([10, 6, 8], 10)
    with torch.no_grad():
        for dtype, tol in ((torch.float32, 1e-6), (torch.float64, 1e-12)):  # float32: summation order
            net, x = net.to(dtype), x.to(dtype)
            for run, gain in (  # guidance s = 4.5 scales D_c's differences by s
                (lambda f: net(x, t, f.tokens.to(dtype), f.mask, f.eot, mask), 1.0),
                (lambda f: net.forward_guided(x, t, net.text_terms(f.tokens.to(dtype), f.mask, f.eot), 4.5, mask), 4.5),
            ):
                torch.testing.assert_close(run(trimmed), run(padded), rtol=tol, atol=tol * gain)


def test_controlnet_module_encodes_trimmed_text():
    from omg.lit.controlnet import ControlNetModule

    spec = {"representation": "humanml3d263", "skeleton": "smpl22", "fps": 20.0, "feature_dim": 263,
            "mean": [0.0] * 263, "std": [1.0] * 263}
    module = ControlNetModule(base={"flavor": "mini", "dit": {"n_layers": 1}, "spec": spec}, text_encoder="hash",
                              text_encoder_args={"max_tokens": 77}, moc={"d_c": 8, "num_experts": 2})
    module.text_encoder.pad_to_max = True
    assert module.text_encoder(["a person walks"]).tokens.shape[1] == 77
    text = module.encode_text(["a person walks", "a person walks forward"], drop_eot=torch.tensor([True, False]))
    assert text.tokens.shape[1] == 6 and text.mask.all(0).tolist() == [True] * 5 + [False]


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


@pytest.mark.parametrize("flavor, wiring", [("mini", "per_layer"), ("base", "per_layer"), ("base", "parallel_stream")])
def test_parameter_counts_on_meta_device(flavor, wiring):
    cfg = MoCConfig(text_dim=768, wiring=wiring)  # CLIP ViT-L/14 tokens, paper's d_c 256, K 12
    with torch.device("meta"):
        base = MotionDiT(DiTConfig.from_name(flavor))
        net = MotionControlNet(base, cfg)
    d, n = base.config.d_model, base.config.n_layers
    frozen = sum(p.numel() for p in base.parameters())
    copies = sum(p.numel() for p in net.copy_blocks.parameters())
    mocs = sum(p.numel() for p in net.mocs.parameters())
    projs = sum(p.numel() for p in net.zero_projs.parameters()) if wiring == "parallel_stream" else 0
    trainable = sum(p.numel() for p in net.trainable_parameters())
    print(
        f"{flavor} {wiring}: frozen {frozen / 1e6:.2f}M, trainable {trainable / 1e6:.2f}M = copies "
        f"{copies / 1e6:.2f}M + MoC {mocs / 1e6:.2f}M ({mocs // n / 1e6:.3f}M per layer) + "
        f"zero projections {projs / 1e6:.2f}M"
    )
    assert copies == sum(p.numel() for p in base.blocks.parameters())
    assert mocs == n * moc_params(d, cfg)
    assert projs == (n * (d * d + d) if wiring == "parallel_stream" else 0)
    assert trainable == copies + mocs + projs
    assert sum(p.numel() for p in net.parameters()) == frozen + trainable
    if flavor == "base":
        assert round(trainable / 1e5) == {"per_layer": 1224, "parallel_stream": 1308}[wiring]
    with torch.device("meta"):  # a controller on half the layers: half the copies and MoCs
        half = MotionControlNet(base, MoCConfig(text_dim=768, layers=list(range(0, n, 2))))
    assert sum(p.numel() for p in half.trainable_parameters()) == (copies + mocs) // 2
