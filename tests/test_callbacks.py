"""EvalCallback, RenderCallback and the loggers in real (tiny) Trainer runs and through `omg`."""

from __future__ import annotations

import csv
import json

import lightning as L
import pytest
import torch
from lightning.pytorch.loggers import CSVLogger

from helpers import REPO, TINY_DIT, TINY_DIT_ARG
from helpers.checkpoints import save_module
from omg.callbacks import EvalCallback, RenderCallback
from omg.data.datamodule import MotionDataModule
from omg.errors import UsageError
from omg.lit.controlnet import ControlNetModule
from omg.lit.pretrain import PretrainModule
from omg.lit.sampling import SamplingSettings
from omg.metrics.following import CATEGORIES, load_prompts

MINI = REPO / "shards/mini/human263"
METRICS = ["fid", {"r_precision": {"pool_size": 8}}, "mm_dist", {"diversity": {"num_pairs": 8}},
           {"multimodality": {"num_pairs": 2}}, "foot_skating"]


def _data():
    return MotionDataModule(str(MINI / "train"), val=str(MINI / "val"), batch_size=4, max_len=30, min_len=20,
                            batches_per_epoch=100, num_workers=0, shuffle_buffer=8)


def _module(data, seed=0):
    torch.manual_seed(seed)
    return PretrainModule(flavor="mini", dit=TINY_DIT, spec=data.spec, ema_decay=0,
                          optim={"lr": 1e-3, "warmup_steps": 2})


def _trainer(root, steps, callbacks, logger=True):
    logger = CSVLogger(root, name="") if logger is True else logger
    return L.Trainer(max_steps=steps, accelerator="cpu", logger=logger, callbacks=callbacks, log_every_n_steps=1,
                     enable_checkpointing=False, enable_progress_bar=False, enable_model_summary=False,
                     limit_val_batches=0, limit_test_batches=1, default_root_dir=root)


@pytest.fixture(scope="session")
def evaluator_ckpt(tmp_path_factory):
    """An (untrained) contrastive evaluator saved as `omg fit` would; its path."""
    from omg.lit.evaluator import EvaluatorModule

    torch.manual_seed(0)
    module = EvaluatorModule(text_encoder="hash", flavor="mini", spec=_data().spec)
    path = tmp_path_factory.mktemp("evaluator") / "evaluator.ckpt"
    save_module(module, path)
    return path


def _eval_callback(evaluator, **kw):
    args = dict(metrics=METRICS, num_prompts=16, replications=3, mm_prompts=2, mm_repeats=3, steps=3, batch_size=8)
    return EvalCallback(str(evaluator), **{**args, **kw})


def test_registered_and_bad_arguments_are_one_clear_line(evaluator_ckpt, tmp_path):
    for kwargs, message in (({"evaluator": str(tmp_path / "nope.ckpt")}, "EvalCallback.evaluator: no evaluator"),
                            ({"replications": 0}, "EvalCallback.replications must be"),
                            ({"metrics": ["fdi"]}, "EvalCallback.metrics: unknown metric 'fdi'")):
        with pytest.raises(UsageError, match=message):
            _eval_callback(**{"evaluator": evaluator_ckpt, **kwargs})
    trainer = _trainer(tmp_path, 1, [_eval_callback(evaluator_ckpt, metrics=["diversity"])], logger=False)
    with pytest.raises(UsageError, match="num_prompts=16 is below diversity's num_pairs=300"):
        trainer.fit(_module(_data()), _data())


def test_eval_during_fit_and_the_protocol_at_test(evaluator_ckpt, tmp_path):
    data = _data()
    plain = _module(data)
    _trainer(tmp_path / "plain", 4, [], logger=False).fit(plain, data)

    module, callback = _module(data), _eval_callback(evaluator_ckpt, every_n_steps=2)
    trainer = _trainer(tmp_path / "run", 4, [callback])
    trainer.fit(module, data)
    for name, value in plain.state_dict().items():  # sampling mid-training changes nothing in training
        torch.testing.assert_close(module.state_dict()[name], value, rtol=0, atol=0)
    assert module.training

    with open(tmp_path / "run/version_0/metrics.csv") as f:
        rows = [r for r in csv.DictReader(f) if r.get("eval/fid")]
    assert [int(r["step"]) for r in rows] == [2, 4]
    assert rows[0]["eval/r_precision/top1"] and rows[0]["eval/real/diversity"] and rows[0]["eval/foot_skating"]

    results = trainer.test(module, data)[0]
    assert {"eval/fid", "eval/fid_ci95", "eval/multimodality", "test/simple"} <= set(results)
    report = json.loads((tmp_path / "run/version_0/eval.json").read_text())
    assert report["settings"]["replications"] == 3 and len(report["metrics"]["fid"]["values"]) == 3
    assert results["eval/fid"] == pytest.approx(report["metrics"]["fid"]["mean"])
    assert "| fid |" in (tmp_path / "run/version_0/eval.md").read_text()

    # replication 0 is the fixed set of fit: same weights, same values
    for key in ("fid", "r_precision/top1", "multimodality"):
        assert report["metrics"][key]["values"][0] == pytest.approx(float(rows[-1][f"eval/{key}"]), rel=1e-9)
    assert len(set(report["metrics"]["fid"]["values"])) == 3  # other replications: other prompts and seeds


def test_controlnet_samples_follow_lengths_and_guidance():
    data = _data()
    torch.manual_seed(0)
    module = ControlNetModule(base={"flavor": "mini", "dit": TINY_DIT, "spec": data.spec}, text_encoder="hash",
                              moc={"d_c": 32, "num_experts": 2}, spec=data.spec, ema_decay=0).eval()
    for p in module.controlnet.parameters():  # as if trained: neither the prior's output nor the residuals are zero
        p.data.normal_(0, 0.05)
    texts = ["a person walks forward", "a person jumps"]
    out = module.sample(texts, torch.tensor([12, 20]), SamplingSettings(seed=3, steps=4))
    assert out.shape == (2, 20, 263) and torch.isfinite(out).all()
    torch.testing.assert_close(module.sample(texts, torch.tensor([12, 20]), SamplingSettings(seed=3, steps=4)), out)
    full = [16, 16]
    prior = module.sample(None, full, SamplingSettings(seed=1, steps=4))  # no texts: the frozen prior alone
    guided = {s: module.sample(texts, full, SamplingSettings(seed=1, steps=4, guidance=s)) for s in (0.0, 2.0)}
    torch.testing.assert_close(guided[0.0], prior, rtol=0, atol=1e-5)
    assert not torch.allclose(guided[2.0], prior, atol=1e-3)
    assert module.text_conditional and not PretrainModule.text_conditional

    # bf16 autocast: the network's matmuls in bf16, the sample in float32 and close to the float32 one
    dtypes = []
    module.controlnet.base.input_proj.register_forward_hook(lambda m, args, out: dtypes.append(out.dtype))
    mixed = module.sample(texts, full, SamplingSettings(seed=1, steps=4, autocast=torch.bfloat16))
    reference = module.sample(texts, full, SamplingSettings(seed=1, steps=4))
    assert dtypes[0] == torch.bfloat16 and dtypes[-1] == torch.float32
    assert mixed.dtype == torch.float32 and torch.isfinite(mixed).all()
    assert (mixed - reference).abs().max() < 0.05 * reference.abs().max()
    # torch.compile (sample()'s one compile step, the same for every OMG diffusion model): the same sample,
    # compiled once for these shapes. Checked on the prior alone: inductor compiles every distinct kernel with a
    # C++ compiler on the CPU, and the ControlNet's kernels would double what this test spends on it
    prior = _module(data).eval()
    eager = prior.sample(None, full, SamplingSettings(seed=1, steps=4))
    compiled = prior.sample(None, full, SamplingSettings(seed=1, steps=4, compile=True))
    torch.testing.assert_close(compiled, eager, rtol=0, atol=1e-4)

    # sample() switches to eval mode and gives every submodule its own mode back (the frozen prior stays in eval)
    module.train()
    modes = {name: m.training for name, m in module.named_modules()}
    module.sample(texts, full, SamplingSettings(seed=1, steps=2))
    assert {name: m.training for name, m in module.named_modules()} == modes and not module.controlnet.base.training
    module.eval()

    # what depends only on the text runs once per sample() call, what depends on the motion at every step
    calls = {"k": 0, "gate": 0, "eot_affine": 0, "q": 0}
    for moc in module.controlnet.mocs.values():
        for name in calls:
            getattr(moc, name).register_forward_hook(lambda *_, name=name: calls.__setitem__(name, calls[name] + 1))
    module.sample(texts, full, SamplingSettings(seed=1, steps=4))
    layers = len(module.controlnet.mocs)
    assert calls == {"k": layers, "gate": layers, "eot_affine": layers, "q": 4 * layers}


def test_render_writes_gifs_into_the_run_directory(tmp_path):
    from PIL import Image

    data = _data()
    callback = RenderCallback(num_prompts=2, num_samples=2, seconds=1.0, every_n_steps=2, steps=2, max_frames=5, dpi=30)
    _trainer(tmp_path, 2, [callback]).fit(_module(data), data)
    gifs = sorted((tmp_path / "version_0/renders").rglob("*.gif"))
    assert [p.relative_to(tmp_path / "version_0/renders").as_posix() for p in gifs] == [
        "step_0000002/prompt_00.gif", "step_0000002/prompt_01.gif"]  # rendered once, not again at the end
    image = Image.open(gifs[0])
    assert image.n_frames > 1 and image.size[0] > image.size[1]  # two samples side by side


def test_offline_wandb_run_writes_its_files(tmp_path, monkeypatch):
    pytest.importorskip("wandb")
    from lightning.pytorch.loggers import WandbLogger

    for name in ("WANDB_DIR", "WANDB_CONFIG_DIR", "WANDB_CACHE_DIR", "WANDB_DATA_DIR"):
        monkeypatch.setenv(name, str(tmp_path / "wandb-home"))
    monkeypatch.setenv("WANDB_MODE", "offline")
    monkeypatch.setenv("WANDB_SILENT", "true")
    data = _data()
    logger = WandbLogger(project="omg-test", save_dir=str(tmp_path), offline=True)
    render = RenderCallback(num_prompts=1, num_samples=1, seconds=0.5, every_n_steps=1, steps=2, max_frames=3, dpi=30)
    _trainer(tmp_path, 1, [render], logger=logger).fit(_module(data), data)
    logger.experiment.finish()
    runs = list((tmp_path / "wandb").glob("offline-run-*"))
    assert len(runs) == 1 and list(runs[0].glob("run-*.wandb"))
    assert list(runs[0].rglob("media/videos/render_*.gif"))  # the preview, logged as a wandb.Video
    assert list((tmp_path / "omg-test" / logger.version / "renders").rglob("*.gif"))  # and kept in the run dir


def _cli(*argv):
    from omg.cli import main

    main(list(argv))


def test_omg_fit_versions_runs_and_omg_test_prints_the_protocol(evaluator_ckpt, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    common = [f"--data.train={MINI}/train", f"--data.val={MINI}/val", "--data.batch_size=4", "--data.max_len=30",
              "--data.min_len=20", "--data.num_workers=0", "--trainer.enable_progress_bar=false",
              "--trainer.enable_model_summary=false"]
    fit = ["fit", "--config", str(REPO / "configs/mini/pretrain.yaml"), *common, "--trainer.max_steps=2",
           "--trainer.val_check_interval=1000", "--trainer.default_root_dir=pre",
           "--trainer.callbacks.dirpath=pre/checkpoints",
           TINY_DIT_ARG]
    _cli(*fit)
    _cli(*fit, "--trainer.max_steps=1")
    for version, steps in (("version_0", 2), ("version_1", 1)):  # a second run never clashes with the first
        assert f"max_steps: {steps}" in (tmp_path / "pre" / version / "config.yaml").read_text()

    _cli("fit", "--config", str(REPO / "configs/mini/controlnet.yaml"), *common, "--trainer.max_steps=1",
         "--trainer.val_check_interval=1000", "--trainer.default_root_dir=cn",
         "--trainer.callbacks.dirpath=cn/checkpoints", "--model.init_args.pretrained=pre/checkpoints/last.ckpt",
         "--model.init_args.text_encoder=hash",
         '--model.init_args.moc={"d_c": 32, "num_experts": 2}')
    capsys.readouterr()
    _cli("test", "--config", str(REPO / "configs/mini/eval.yaml"), *common, "--trainer.default_root_dir=ev",
         "--ckpt_path=cn/checkpoints/last.ckpt", f"--trainer.callbacks.evaluator={evaluator_ckpt}",
         "--trainer.callbacks.num_prompts=16", "--trainer.callbacks.replications=2", "--trainer.callbacks.steps=2",
         f"--trainer.callbacks.metrics={json.dumps(METRICS)}", "--trainer.callbacks.mm_prompts=2",
         "--trainer.callbacks.mm_repeats=2", "--trainer.limit_test_batches=1")
    out = capsys.readouterr().out
    assert "| metric | mean | ±95% CI (2 replications) |" in out and "| fid |" in out
    report = json.loads((tmp_path / "ev/version_0/eval.json").read_text())
    assert report["settings"]["model"] == "ControlNetModule" and report["settings"]["checkpoint"].endswith("last.ckpt")
    assert (tmp_path / "ev/version_0/config.yaml").exists()

    # prompt following with the built-in prompt file: no evaluator, every prompt generated and scored
    _cli("test", "--config", str(REPO / "configs/small/following.yaml"), *common, "--trainer.default_root_dir=fo",
         "--ckpt_path=cn/checkpoints/last.ckpt", "--trainer.callbacks.samples_per_prompt=1",
         "--trainer.callbacks.replications=1", "--trainer.callbacks.steps=2", "--trainer.limit_test_batches=1")
    report = json.loads((tmp_path / "fo/version_0/eval.json").read_text())
    assert report["settings"]["prompts"] == len(load_prompts()) and report["settings"]["evaluator"] is None
    for key in ("following", "following/parts", "foot_skating", *(f"following/{c}" for c in CATEGORIES)):
        assert 0 <= report["metrics"][key]["mean"] <= 1, key
    assert "real/following" not in report["metrics"]


def test_callbacks_pass_stance_root_to_the_sampler_and_refuse_it_for_other_models(tmp_path):
    from omg.callbacks.eval import check_generative

    data = _data()
    module = _module(data)
    seen, sample = [], module.sample

    def spy(texts, lengths, settings):
        seen.append(settings.stance_root)
        return sample(texts, lengths, settings)

    module.sample = spy
    render = RenderCallback(num_prompts=1, num_samples=1, seconds=0.5, every_n_steps=1, steps=2, max_frames=3, dpi=30,
                            stance_root=1.0)
    _trainer(tmp_path, 1, [render]).fit(module, data)
    assert seen and set(seen) == {1.0}

    from omg.lit.omgpt import OmniMotionModule

    class OtherFamily(OmniMotionModule):  # a sampler without a stance foot to step by
        def __init__(self): ...

    with pytest.raises(UsageError, match="EvalCallback.stance_root: OtherFamily is not a diffusion model"):
        check_generative(OtherFamily(), "EvalCallback", SamplingSettings(stance_root=1.0))
    check_generative(OtherFamily(), "EvalCallback", SamplingSettings(steps=2))  # not asked for: no check
