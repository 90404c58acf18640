"""OMG stage 1: the PretrainModule's loss, sampling, bad configs, and kill-and-resume."""

from __future__ import annotations

import json
import signal
import sys
import time

import numpy as np
import pytest
import torch

from helpers import REPO, TINY_DIT, TINY_DIT_ARG
from helpers.forked import OmgProcess
from omg.cli import main
from omg.data.datamodule import MotionDataModule
from omg.lit.base import modes_restored, warmup_cosine
from omg.lit.pretrain import PretrainModule
from omg.lit.sampling import SamplingSettings


def test_activation_checkpointing_is_applied_once_by_configure_model(h263_shards):
    """The module switch checkpoints the blocks when the Trainer configures the model (again at
    every stage), with the same gradients and the same parameter names."""
    dm = MotionDataModule(str(h263_shards / "train"), batch_size=4, max_len=40, min_len=40, num_workers=0)
    batch = next(iter(dm.train_dataloader()))
    grads, names = [], []
    for switch in (False, True):
        torch.manual_seed(0)
        module = PretrainModule(flavor="mini", dit=TINY_DIT, spec=dm.spec, ema_decay=0, activation_checkpointing=switch)
        module.configure_model()
        module.configure_model()  # fit, then test: no error, applied once
        module._noise_gen = torch.Generator().manual_seed(1)
        module.diffusion_losses(batch)["loss"].backward()
        grads.append(torch.cat([p.grad.flatten() for p in module.model.parameters()]))
        names.append(list(module.state_dict()))
    torch.testing.assert_close(grads[0], grads[1])
    assert names[0] == names[1]


def test_loss_falls_on_a_fixed_batch_and_samples_are_finite(h263_shards):
    torch.manual_seed(0)
    dm = MotionDataModule(str(h263_shards / "train"), batch_size=8, max_len=40, min_len=40, num_workers=0,
                          shuffle_buffer=8)
    batch = next(iter(dm.train_dataloader()))
    module = PretrainModule(flavor="mini", spec=dm.spec, ema_decay=0)
    optimizer = torch.optim.AdamW(module.parameters(), lr=1e-3)
    gen = torch.Generator().manual_seed(0)
    module._noise_gen = gen

    def eval_loss():  # the same timesteps and noise every time, so the losses are comparable
        gen.manual_seed(1)
        with torch.no_grad():
            return module.diffusion_losses(batch)

    before = eval_loss()
    for _ in range(100):  # the mini DiT's loss falls to about 0.18x in 100 steps (seeds 0 and 1), 0.11x in 200
        losses = module.diffusion_losses(batch)
        optimizer.zero_grad()
        losses["loss"].backward()
        optimizer.step()
    after = eval_loss()
    assert after["loss"] < 0.3 * before["loss"], (before, after)
    assert after["simple"] < before["simple"]

    motion = module.sample(None, [37, 37], SamplingSettings(steps=10))
    assert motion.shape == (2, 37, 263) and torch.isfinite(motion).all()
    positions = module.representation.decode(motion)
    assert positions.shape == (2, 37, 22, 3) and torch.isfinite(positions).all()


def test_warmup_then_cosine():
    f = warmup_cosine(10, 110)
    assert f(0) == pytest.approx(0.1) and f(9) == pytest.approx(1.0)
    assert f(60) == pytest.approx(0.5) and f(110) == pytest.approx(0.0) and f(500) == pytest.approx(0.0)


def omg_fit(*args, root) -> OmgProcess:
    """`omg fit` on the mini config as its own process (forked from the preloaded server), run from ``root``."""
    return OmgProcess(["fit", "--config", str(REPO / "configs/mini/pretrain.yaml"), *args], cwd=root,
                      stderr=root / "fit.err")


def fit_here(*args) -> None:
    """`omg fit` on the mini config in this process, through the CLI's entry point."""
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(sys, "argv", list(sys.argv))  # omg fit sets it for LightningCLI
        main(["fit", "--config", str(REPO / "configs/mini/pretrain.yaml"), *args])


def _fit_args(shards, root, steps):
    return [f"--data.train={shards}/train", f"--data.val={shards}/val", "--data.batch_size=4", "--data.max_len=40",
            "--data.num_workers=1", f"--trainer.max_steps={steps}", "--trainer.val_check_interval=1000",
            f"--trainer.default_root_dir={root}", f"--trainer.callbacks.dirpath={root}/checkpoints",
            "--trainer.callbacks.every_n_train_steps=4", "--trainer.enable_progress_bar=false",
            TINY_DIT_ARG, "--model.init_args.optim.warmup_steps=5"]


def test_a_block_leaves_every_modules_mode_as_it_found_it():
    """``modes_restored`` (around sampling in a training run): whatever the block sets, each submodule's mode is
    what it was, a frozen part in eval mode (a ControlNet's base, a text encoder) included."""
    from omg.models.controlnet import MoCConfig, MotionControlNet
    from omg.models.dit import DiTConfig, MotionDiT
    from omg.text import build_text_encoder

    net = MotionControlNet(MotionDiT(DiTConfig.from_name("mini", **TINY_DIT)), MoCConfig(d_c=16, text_dim=32))
    module = torch.nn.ModuleDict({"net": net, "text": build_text_encoder("hash", dim=32)}).train()
    module["net"].copy_blocks["0"].eval()  # a mode of its own inside a module in train mode
    before = {name: m.training for name, m in module.named_modules()}
    assert not before["net.base"] and not before["text"] and before["net"] and not before["net.copy_blocks.0"]
    for change in (lambda: module.eval(), lambda: module.train(), lambda: net.base.blocks[0].train()):
        with modes_restored(module):
            change()
        assert {name: m.training for name, m in module.named_modules()} == before


def test_bad_configs_exit_2_with_one_line(h263_shards, tmp_path, capsys):
    """In-process (the CLI's entry point, as the bad-input table runs it): a process each cost a minute."""
    cases = {
        "--model.init_args.flavor=colossal": "unknown DiT flavor 'colossal'",
        "--model.init_args.optim.lr=-1": "model.optim.lr must be a finite number > 0, got -1.0",
        f"--data.train={tmp_path}/missing": "no such directory",
        "--data.batch_sise=4": "batch_sise",
        "--trainer.max_steps=many": "max_steps",
    }
    for flag, message in cases.items():
        args = _fit_args(h263_shards, tmp_path, 1) + [flag]
        with pytest.raises(SystemExit) as exit_:
            main(["fit", "--config", str(REPO / "configs/mini/pretrain.yaml"), *args])
        err = capsys.readouterr().err
        assert exit_.value.code == 2, (flag, err[-2000:])
        lines = err.strip().splitlines()
        assert len(lines) == 1 and message in lines[0], (flag, err[-2000:])
    assert not (tmp_path / "checkpoints").exists()


STEPS = 16


# the tests of whole_run share it: under xdist they run on one worker, which runs it once
@pytest.fixture(scope="session")
def whole_run(h263_shards, tmp_path_factory):
    """An uninterrupted tiny run of `omg fit` (in this process: what it trains, not how a process ends); its
    root directory."""
    root = tmp_path_factory.mktemp("whole")
    fit_here(*_fit_args(h263_shards, root, STEPS))
    return root


def _final_state(path):
    return torch.load(path, map_location="cpu", weights_only=False)


@pytest.mark.slow  # a killed `omg fit` process: about 20 s on 2 cores
@pytest.mark.xdist_group("pretrain_whole_run")
def test_killed_run_resumes_to_the_same_state(h263_shards, whole_run, tmp_path):
    steps = STEPS

    killed_root = tmp_path / "killed"
    run = omg_fit(*_fit_args(h263_shards, killed_root, steps), root=tmp_path)
    deadline = time.time() + 300
    while not list((killed_root / "checkpoints").glob("*step=8*.ckpt")):
        assert run.poll() is None and time.time() < deadline, "the run ended before its second checkpoint"
        time.sleep(0.05)
    run.send_signal(signal.SIGKILL)
    run.wait()
    assert not list((killed_root / "checkpoints").glob("*step=16*"))

    fit_here(*_fit_args(h263_shards, killed_root, steps), "--ckpt_path=last")  # the killed process was the real one

    a = _final_state(whole_run / "checkpoints/last.ckpt")
    b = _final_state(killed_root / "checkpoints/last.ckpt")
    assert a["global_step"] == b["global_step"] == steps
    assert a["lr_schedulers"][0]["last_epoch"] == b["lr_schedulers"][0]["last_epoch"]
    assert a["optimizer_states"][0]["param_groups"][0]["lr"] == b["optimizer_states"][0]["param_groups"][0]["lr"]
    assert a["ema"]["updates"] == b["ema"]["updates"] == steps
    for name, value in a["ema"]["shadow"].items():
        torch.testing.assert_close(b["ema"]["shadow"][name], value, rtol=0, atol=1e-6)

    def loops(c):
        return c["loops"]["fit_loop"]["state_dict"]["combined_loader"]

    assert loops(a) == loops(b)  # the same data stream position
    for name, value in a["state_dict"].items():
        torch.testing.assert_close(b["state_dict"][name], value, rtol=0, atol=1e-6)


@pytest.mark.xdist_group("pretrain_whole_run")
def test_generate_unconditional_writes_reproducible_motions(whole_run, tmp_path, capsys):
    from omg.cli import main

    args = ["generate", "--unconditional", "--ckpt", str(whole_run / "checkpoints/last.ckpt"), "--num_samples", "3",
            "--length", "1.5", "--steps", "5", "--batch_size", "2"]
    main([*args, "--out", str(tmp_path / "a")])
    main([*args, "--out", str(tmp_path / "b")])
    settings = json.loads((tmp_path / "a/generation.json").read_text())
    assert settings["frames"] == 30 and settings["seed"] == 0 and settings["steps"] == 5 and settings["ema"]
    for i in range(3):
        features = np.load(tmp_path / f"a/sample_{i:03d}.features.npy")
        joints = np.load(tmp_path / f"a/sample_{i:03d}.joints.npy")
        assert features.shape == (30, 263) and joints.shape == (30, 22, 3) and np.isfinite(joints).all()
        np.testing.assert_array_equal(features, np.load(tmp_path / f"b/sample_{i:03d}.features.npy"))
    bad = {"--length": "0", "--steps": "-1"}
    for flag, value in bad.items():
        with pytest.raises(SystemExit) as e:
            main([*args, flag, value, "--out", str(tmp_path / "c")])
        assert e.value.code == 2
    with pytest.raises(SystemExit):
        main(["generate", "a person jumps", "--ckpt", str(whole_run / "checkpoints/last.ckpt")])
    assert "unconditional pretraining checkpoint" in capsys.readouterr().err


def test_trains_with_weights_cast_to_bf16(h263_shards):
    """DeepSpeed's bf16 mode casts the module and the batch to bf16 and runs without autocast."""
    dm = MotionDataModule(str(h263_shards / "train"), batch_size=4, max_len=30, min_len=30, num_workers=0,
                          shuffle_buffer=4)
    batch = next(iter(dm.train_dataloader()))
    batch["motion"] = batch["motion"].to(torch.bfloat16)
    module = PretrainModule(flavor="mini", dit=TINY_DIT, spec=dm.spec).to(torch.bfloat16)
    losses = module.diffusion_losses(batch)
    assert all(torch.isfinite(v) for v in losses.values())
    losses["loss"].backward()
    assert module.model.input_proj.weight.grad.dtype == torch.bfloat16
    assert module.sample(None, [12], SamplingSettings(steps=3)).dtype == torch.bfloat16


def test_a_single_frame_window_trains(h263_shards, tmp_path):
    """OMG Sec. 3.1 draws l ~ U[1, L]: a window may be one keyframe. Padded into a batch of longer windows, its
    prediction is its prediction alone (the padding is masked out of attention, RoPE at position 0), and `omg fit`
    trains on windows of one frame only, to finite weights."""
    from omg.cli import main

    torch.manual_seed(0)
    model = PretrainModule(flavor="mini", dit=TINY_DIT, spec=MotionDataModule(str(h263_shards / "train")).spec).model
    for p in model.parameters():  # past the zero-initialised output and gates, so the outputs say something
        p.data.normal_(0, 0.05)
    x, t = torch.randn(3, 30, model.config.input_dim), torch.tensor([10, 500, 999])
    mask = torch.arange(30)[None] < torch.tensor([1, 30, 7])[:, None]
    with torch.no_grad():
        padded, alone = model(x, t, mask), model(x[:1, :1], t[:1])
    assert alone.abs().mean() > 0.01
    torch.testing.assert_close(padded[:1, :1], alone)

    root = tmp_path / "run"
    main(["fit", "--config", str(REPO / "configs/mini/pretrain.yaml"), f"--data.train={h263_shards}/train",
          "--data.val=null", "--data.max_len=1", "--data.min_len=1", "--data.batch_size=4", "--data.num_workers=0",
          "--trainer.max_steps=2", "--trainer.limit_val_batches=0", "--trainer.callbacks.every_n_train_steps=2",
          f"--trainer.default_root_dir={root}", f"--trainer.callbacks.dirpath={root}/checkpoints",
          "--trainer.enable_progress_bar=false", TINY_DIT_ARG])
    state = _final_state(root / "checkpoints/last.ckpt")
    assert state["global_step"] == 2
    assert all(torch.isfinite(v).all() for v in state["state_dict"].values() if v.is_floating_point())


def test_the_loss_is_logged_every_step_and_its_terms_at_the_steps_the_logger_writes(h263_shards, tmp_path):
    """``train/loss`` at every step (the progress bar's); the terms beside it, the LR and the throughput at the
    steps the logger writes (``trainer.log_every_n_steps``): every term in each row the logger keeps, the
    throughput over the steps since the last row, and no term logged in between."""
    import csv

    import lightning as L
    from lightning.pytorch.loggers import CSVLogger

    seen = []  # (loss, simple term) in the metrics as each step left them

    class Watch(L.Callback):
        def on_train_batch_end(self, trainer, module, outputs, batch, batch_idx):
            metrics = trainer.callback_metrics
            seen.append((float(metrics["train/loss"]),
                         float(metrics["train/simple"]) if "train/simple" in metrics else None))

    torch.manual_seed(0)
    dm = MotionDataModule(str(h263_shards / "train"), batch_size=4, max_len=30, min_len=30, num_workers=0,
                          shuffle_buffer=4)
    module = PretrainModule(flavor="mini", dit=TINY_DIT, spec=dm.spec, ema_decay=0)
    trainer = L.Trainer(max_steps=9, log_every_n_steps=4, accelerator="cpu", enable_checkpointing=False,
                        enable_progress_bar=False, enable_model_summary=False, limit_val_batches=0,
                        logger=CSVLogger(tmp_path), callbacks=[Watch()])
    trainer.fit(module, dm)
    assert len({loss for loss, _ in seen}) == 9  # a new loss at every step
    simple = [s for _, s in seen]
    assert simple[:3] == [None] * 3 and simple[3] is not None  # first logged at step 3 (the 4th)
    assert simple[3:7] == [simple[3]] * 4 and simple[7] != simple[3] and simple[8] == simple[7]  # then at step 7 only
    with open(next(tmp_path.rglob("metrics.csv"))) as f:
        rows = list(csv.DictReader(f))
    assert [int(r["step"]) for r in rows] == [3, 7]
    for row in rows:
        for term in ("loss", "simple", "vel", "foot", "lr", "samples_per_s", "frames_per_s"):
            assert row[f"train/{term}"] != "", (term, row)
    # the throughput's frames and samples counted over one window: every sample here has 30 real frames
    assert all(float(r["train/frames_per_s"]) == pytest.approx(30 * float(r["train/samples_per_s"])) for r in rows)
    seen.clear()  # a trainer that never logs (`log_every_n_steps` 0) trains with the loss alone in its metrics
    L.Trainer(max_steps=2, log_every_n_steps=0, accelerator="cpu", enable_checkpointing=False, logger=False,
              enable_progress_bar=False, enable_model_summary=False, limit_val_batches=0, callbacks=[Watch()]).fit(
        PretrainModule(flavor="mini", dit=TINY_DIT, spec=dm.spec, ema_decay=0), dm)
    assert [s for _, s in seen] == [None, None]
