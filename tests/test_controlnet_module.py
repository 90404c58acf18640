"""OMG stage 2 as a user runs it: fine-tune the ControlNet on the mini data, guided sampling,
`omg generate` from text (with BVH files and a preview)."""

from __future__ import annotations

import json

import lightning as L
import numpy as np
import pytest
import torch

from helpers import REPO
from helpers.checkpoints import save_module
from omg.data.datamodule import MotionDataModule
from omg.io.bvh import read_bvh
from omg.lit.controlnet import ControlNetModule
from omg.lit.pretrain import PretrainModule
from omg.lit.sampling import SamplingSettings

MINI = REPO / "shards/mini/human263"
TINY = {"n_layers": 3, "d_model": 64, "n_heads": 2}
MOC = {"d_c": 32, "num_experts": 4}
# the tests share the pretrained tiny DiT: under xdist they run on one worker, which trains it once
pytestmark = pytest.mark.xdist_group("controlnet_module")


def _data(**kw):
    args = dict(batch_size=16, max_len=60, min_len=40, batches_per_epoch=1000, num_workers=0, shuffle_buffer=64,
                clip_sampling="whole")  # ControlNetModule's, which `omg fit` links
    return MotionDataModule(str(MINI / "train"), **{**args, **kw})


def _fit(module, data, steps, root):
    trainer = L.Trainer(max_steps=steps, accelerator="cpu", logger=False, enable_checkpointing=False,
                        enable_progress_bar=False, enable_model_summary=False, default_root_dir=root,
                        gradient_clip_val=1.0)
    trainer.fit(module, data)
    return trainer


@pytest.fixture(scope="session")
def pretrained(tmp_path_factory):
    """A tiny DiT pretrained for 30 steps on the mini humans; its checkpoint path. The tests here check the
    ControlNet's plumbing (weights, guidance, commands), not what the prior learned: a few steps past the
    warm-up leave an EMA that differs from the raw weights, which the EMA check needs."""
    root = tmp_path_factory.mktemp("pretrain")
    torch.manual_seed(0)
    data = _data()
    module = PretrainModule(flavor="mini", dit=TINY, spec=data.spec, ema_decay=0.99,
                            optim={"lr": 1e-3, "warmup_steps": 20})
    trainer = _fit(module, data, 30, root)
    trainer.save_checkpoint(root / "pretrain.ckpt")
    return root / "pretrain.ckpt"


def _controlnet(pretrained, **kw):
    args = dict(text_encoder="hash", moc=MOC, ema_decay=0.99, optim={"lr": 1e-3, "warmup_steps": 20})
    return ControlNetModule(pretrained=str(pretrained), spec=_data().spec, **{**args, **kw})


def test_starts_as_the_frozen_model_and_trains_only_the_controlnet(pretrained, tmp_path):
    module = _controlnet(pretrained)
    frozen = {k: v.clone() for k, v in module.model.state_dict().items()}
    saved = torch.load(pretrained, weights_only=False)
    ema_weights = saved["ema"]["shadow"]
    assert all(torch.equal(frozen[k], v) for k, v in ema_weights.items())  # fine-tuning starts from the EMA
    assert not all(torch.equal(frozen[k], saved["state_dict"][f"model.{k}"]) for k in ema_weights)  # not the raw

    x, t = torch.randn(2, 30, 263), torch.tensor([10, 900])
    text = module.encode_text(["a person walks forward", "a person jumps in place"])
    assert torch.equal(module.controlnet(x, t, text.tokens, text.mask, text.eot), module.model(x, t))

    controlnet_before = {k: v.clone() for k, v in module.controlnet.state_dict().items() if not k.startswith("base.")}
    _fit(module, _data(), 4, tmp_path)
    assert all(torch.equal(module.model.state_dict()[k], v) for k, v in frozen.items())
    changed = [k for k, v in module.controlnet.state_dict().items()
               if k in controlnet_before and not torch.equal(controlnet_before[k], v)]
    assert any(".up." in k for k in changed) and any("moc" in k or "blocks" in k for k in changed)


def test_guidance_scale_0_is_the_frozen_model_and_1_the_controlnet(pretrained):
    module = _controlnet(pretrained).eval()
    torch.manual_seed(1)
    for p in module.controlnet.trainable_parameters():  # as if trained: the residuals are not zero
        p.data.normal_(0, 0.05)
    texts, frames = ["a person walks forward"] * 2, 24
    text = module.encode_text(texts)

    def ddim(denoise):
        gen = torch.Generator().manual_seed(7)
        return module.diffusion.ddim_sample(denoise, (2, frames, 263), steps=8, generator=gen)

    only_u = ddim(lambda x, t: module.controlnet.forward_uncond(x, t))
    only_c = ddim(lambda x, t: module.controlnet(x, t, text.tokens, text.mask, text.eot))
    s0 = module.sample(texts, [frames] * 2, SamplingSettings(steps=8, seed=7, guidance=0.0, use_ema=False))
    s1 = module.sample(texts, [frames] * 2, SamplingSettings(steps=8, seed=7, guidance=1.0, use_ema=False))
    torch.testing.assert_close(s0, module.denormalize(only_u), rtol=0, atol=1e-5)
    torch.testing.assert_close(s1, module.denormalize(only_c), rtol=0, atol=1e-5)
    assert not torch.allclose(only_u, only_c, atol=1e-3)


@pytest.fixture(scope="session")
def finetuned(pretrained, tmp_path_factory):
    root = tmp_path_factory.mktemp("controlnet")
    torch.manual_seed(0)
    module = _controlnet(pretrained)
    trainer = _fit(module, _data(), 20, root)  # the command's plumbing, not the model's quality
    trainer.save_checkpoint(root / "controlnet.ckpt")
    return root / "controlnet.ckpt"


def test_generate_from_text(finetuned, tmp_path, capsys):
    from omg.cli import main

    prompts = tmp_path / "prompts.txt"
    prompts.write_text("a person jumps in place\n\n")
    main(["generate", "a person walks forward", "--prompts_file", str(prompts), "--ckpt", str(finetuned),
          "--length", "2", "--num_samples", "2", "--steps", "5", "--seed", "3", "--out", str(tmp_path / "out")])
    settings = json.loads((tmp_path / "out/generation.json").read_text())
    assert settings["prompts"] == ["a person walks forward", "a person jumps in place"]
    assert settings["guidance_scale"] == 4.5 and settings["seed"] == 3 and settings["frames"] == 40
    assert ([s["prompt"] for s in settings["samples"]]
            == ["a person walks forward"] * 2 + ["a person jumps in place"] * 2)
    for i in range(4):
        joints = np.load(tmp_path / f"out/sample_{i:03d}.joints.npy")
        assert joints.shape == (40, 22, 3)
    bvh = read_bvh(tmp_path / "out/sample_000.bvh")
    assert bvh.positions().shape[:2] == (40, 22) and bvh.fps == 20.0
    from PIL import Image

    assert Image.open(tmp_path / "out/preview.gif").n_frames > 1
    assert settings["sampler"] == "ddim"

    # the fast sampler, end to end; --unconditional on a ControlNet samples its frozen prior
    main(["generate", "a person walks forward", "--ckpt", str(finetuned), "--length", "2", "--num_samples", "1",
          "--sampler", "dpmpp", "--steps", "20", "--no_preview", "--out", str(tmp_path / "fast")])
    fast = json.loads((tmp_path / "fast/generation.json").read_text())
    assert fast["sampler"] == "dpmpp" and fast["steps"] == 20
    assert np.isfinite(np.load(tmp_path / "fast/sample_000.joints.npy")).all()
    main(["generate", "--unconditional", "--ckpt", str(finetuned), "--length", "2", "--num_samples", "1",
          "--steps", "3", "--no_preview", "--out", str(tmp_path / "prior")])
    assert json.loads((tmp_path / "prior/generation.json").read_text())["guidance_scale"] is None

    for argv, message in (
        (["generate", "a person waves", "--ckpt", str(finetuned), "--sampler", "plms"], "unknown sampler 'plms'"),
        (["generate", "  ", "--ckpt", str(finetuned)], "prompt 1 is empty"),
        (["generate", "a person waves", "--ckpt", str(finetuned), "--length", "99"],
         "length: expected a number of seconds in (0, 60]"),
        (["generate", "--ckpt", str(finetuned)], "give prompts"),
    ):
        with pytest.raises(SystemExit) as e:
            main(argv)
        assert e.value.code == 2 and message in capsys.readouterr().err


def test_bench_quality_writes_the_curve(finetuned, tmp_path, capsys):
    """`omg bench quality`: the evaluation protocol at every (sampler, steps), a CSV and a plot."""
    import csv

    from omg.cli import main
    from omg.lit.evaluator import EvaluatorModule

    torch.manual_seed(0)
    evaluator = EvaluatorModule(text_encoder="hash", flavor="mini", spec=_data().spec)  # untrained: the plumbing
    save_module(evaluator, tmp_path / "evaluator.ckpt")
    (tmp_path / "prompts.yaml").write_text(
        "prompts:\n"
        "  - {text: a person waves the left hand., category: sidedness, seconds: 2, "
        "targets: [{hand: left, action: wave}]}\n"
        "  - {text: a person stands still., category: plain, seconds: 2, targets: [{pace: still}]}\n")
    main(["bench", "quality", "--ckpt", str(finetuned), "--evaluator", str(tmp_path / "evaluator.ckpt"),
          "--val", str(MINI / "val"), "--max_len", "60", "--samplers", "[ddim, dpmpp]", "--steps", "[1, 3]",
          "--replications", "2", "--num_prompts", "8", "--batch_size", "8", "--out", str(tmp_path / "q"),
          "--prompts", str(tmp_path / "prompts.yaml"), "--samples_per_prompt", "3"])
    rows = list(csv.DictReader(open(tmp_path / "q/quality.csv")))
    assert [(r["sampler"], int(r["steps"])) for r in rows] == [("ddim", 1), ("ddim", 3), ("dpmpp", 1), ("dpmpp", 3)]
    assert all(float(r["s_per_motion"]) > 0 and np.isfinite(float(r["fid_mean"])) for r in rows)
    assert all(0 <= float(r[f"{k}_mean"]) <= 1 for r in rows for k in ("following", "following/sidedness"))
    # one step: both samplers return the model's x0 of the same noise, so the same motions and metrics
    for key in ("fid_mean", "following_mean", "following/plain_mean"):
        assert float(rows[0][key]) == pytest.approx(float(rows[2][key]), rel=1e-4)
    assert (tmp_path / "q/quality.png").stat().st_size > 0
    with pytest.raises(SystemExit):
        main(["bench", "quality", "--ckpt", str(finetuned), "--evaluator", str(tmp_path / "evaluator.ckpt"),
              "--val", str(MINI / "val"), "--samplers", "[plms]"])
    assert "unknown sampler 'plms'" in capsys.readouterr().err


def test_hints_start_from_a_trained_controlnet_train_their_embedding_and_are_read_when_sampling(finetuned,
                                                                                                  tmp_path):
    """Spatial hints fine-tuned onto a trained text ControlNet (its checkpoint as ``pretrained``): at the start it is
    that ControlNet (its EMA weights) whatever the hint; training reaches the hint embedding and nothing frozen; the
    checkpoint loads with its hints; sampling with a control hands its targets to the network (the same control on
    the text ControlNet steers alone)."""
    from omg.lit.checkpoint import load_module
    from omg.lit.control import Control, control_hint
    from omg.motion import length_mask

    source = load_module(finetuned).eval()
    torch.manual_seed(0)
    module = ControlNetModule(pretrained=str(finetuned), text_encoder="hash", moc=MOC, spec=_data().spec,
                              hints={"enabled": True}, ema_decay=0.99, optim={"lr": 1e-3, "warmup_steps": 2})
    assert module.controlnet.config.hint_channels == 9 * 22 and module.hparams["hints"]["enabled"]
    x, t = torch.randn(2, 30, 263), torch.tensor([10, 900])
    texts = ["a person walks forward", "a person jumps in place"]
    text = module.encode_text(texts)
    hint = torch.randn(2, 30, 9 * 22)
    with torch.no_grad(), source.ema_weights(True):
        expected = source.controlnet(x, t, text.tokens, text.mask, text.eot)
        assert torch.equal(module.eval().controlnet(x, t, text.tokens, text.mask, text.eot, hint=hint), expected)
    frozen = {k: v.clone() for k, v in module.model.state_dict().items()}
    trainer = _fit(module.train(), _data(), 3, tmp_path)
    assert module.controlnet.hint_embed[-1].weight.abs().sum() > 0  # the hints reach the loss
    assert all(torch.equal(module.model.state_dict()[k], v) for k, v in frozen.items())
    trainer.save_checkpoint(tmp_path / "hints.ckpt")
    loaded = load_module(tmp_path / "hints.ckpt").eval()
    assert loaded.hints.enabled and loaded.controlnet.config.hint_channels == 9 * 22

    frames, J = 30, 22
    mask = length_mask([frames, frames])
    targets = torch.zeros(1, frames, J, 3)
    targets[0, :, 0, 2] = torch.linspace(0, 2, frames)
    axes = torch.zeros(1, frames, J, 3, dtype=torch.bool)
    axes[0, :, 0] = True
    weights = axes.any(-1).float()
    control = Control(targets=targets, axes=axes, weights=weights, tolerance=torch.zeros_like(weights),
                      groups=torch.where(weights > 0, 0, -1), names=("path",))
    with torch.no_grad():
        plain, hinted = loaded.denoiser(texts, mask, None)(x, t), loaded.denoiser(texts, mask, None, control)(x, t)
        words = loaded.encode_text(texts)
        terms = loaded.controlnet.text_terms(words.tokens, words.mask, words.eot, fold_biases=True)
        def by_hand(hint):
            e = loaded.controlnet.embed_hint(hint, x.dtype)
            return loaded.controlnet.forward_guided(x, t, terms, loaded.guidance_scale, mask, e)

        assert not torch.allclose(plain, hinted, atol=1e-6)
        torch.testing.assert_close(hinted, by_hand(control_hint(control, 20.0)), rtol=0, atol=0)
        # without constraints it reads the empty hint, as the clips drawn without hints trained it to
        torch.testing.assert_close(plain, by_hand(torch.zeros(1, frames, 9 * J)), rtol=0, atol=0)
        assert torch.equal(source.denoiser(texts, mask, None, control)(x, t), source.denoiser(texts, mask, None)(x, t))


def test_a_pretrained_controlnet_that_does_not_fit_is_one_line(finetuned):
    """(A checkpoint of another kind: test_checkpoint_safety.py.)"""
    from omg.errors import UsageError

    spec = _data().spec
    for kwargs, message in (
        ({"pretrained": str(finetuned), "moc": {"d_c": 16}}, "model.init_args.moc must be the pretrained ControlNet"),
        ({"pretrained": str(finetuned), "text_encoder": "minilm"}, "model.init_args.text_encoder must be"),
    ):
        with pytest.raises(UsageError, match=message):
            ControlNetModule(**{"text_encoder": "hash", "moc": MOC, "spec": spec, **kwargs})
