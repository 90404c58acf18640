"""Kill-and-resume helpers: a kill raised from a callback, a recorder of what each step trained on,
a tiny CPU run checkpointing every step, and a bit-for-bit comparison of the states checkpoints hold
(tests/test_resume.py, the mixture and OmniMotionGPT resume tests, tests/ddp_resume_run.py)."""

from __future__ import annotations

import lightning as L
import torch
from lightning.pytorch.callbacks import Callback, ModelCheckpoint


class Killed(Exception):
    """Stands for SIGKILL: nothing after it runs, and the next run starts from the files."""


class KillAt(Callback):
    def __init__(self, step: int):
        self.step = step

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx):
        if trainer.global_step == self.step:
            raise Killed(f"killed at the start of step {self.step}")


class Recorder(Callback):
    """What each optimizer step trained on: the batch's clip ids and lengths, and the epoch."""

    def __init__(self):
        self.steps: dict[int, tuple] = {}

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx):
        self.steps[trainer.global_step] = (trainer.current_epoch, tuple(batch["id"]), tuple(batch["lengths"].tolist()))


def run_until_killed(model, data, root, *, max_steps: int, kill_at: int | None = None, resume: bool = False,
                     callbacks=(), keep_all: bool = False, **trainer_args) -> L.Trainer:
    """``trainer.fit`` of a tiny CPU run checkpointing every step into ``root/ckpt``, killed at the
    start of step ``kill_at``, or resumed from ``root/ckpt/last.ckpt``; ``keep_all`` keeps every
    step's checkpoint. Without validation unless ``trainer_args`` ask for it."""
    checkpoints = ModelCheckpoint(dirpath=root / "ckpt", save_last=True, every_n_train_steps=1,
                                  **({"save_top_k": -1} if keep_all else {}))
    callbacks = [*callbacks, checkpoints] + ([KillAt(kill_at)] if kill_at is not None else [])
    trainer_args = {"limit_val_batches": 0, "num_sanity_val_steps": 0, **trainer_args}
    trainer = L.Trainer(accelerator="cpu", devices=1, max_steps=max_steps, logger=False, enable_progress_bar=False,
                        enable_model_summary=False, default_root_dir=root, callbacks=callbacks, **trainer_args)
    try:
        trainer.fit(model, data, ckpt_path=str(root / "ckpt" / "last.ckpt") if resume else None)
    except Killed:
        pass
    return trainer


def loop_counters(ckpt: dict) -> dict:
    """Lightning's training-loop counters in a checkpoint: epochs (ready, started, processed,
    completed), batches, optimizer and scheduler steps. The validation loop's own batch counter is
    left out: Lightning resets it at each epoch's start and, resuming from a checkpoint written
    before an epoch-end validation, counts that validation as run after the reset."""
    fit_loop = ckpt["loops"]["fit_loop"]
    return {k: v for k, v in fit_loop.items() if k != "state_dict" and not k.startswith("epoch_loop.val_loop.")}


def final_state(root) -> dict:
    ckpt = torch.load(root / "ckpt" / "last.ckpt", map_location="cpu", weights_only=False)
    return {
        "global_step": ckpt["global_step"],
        "epoch": ckpt["epoch"],
        "state_dict": ckpt["state_dict"],
        "ema": ckpt["ema"],
        "optimizer": ckpt["optimizer_states"],
        "lr": ckpt["lr_schedulers"],
        "noise_rng": ckpt["noise_rng"],
        "data": ckpt["loops"]["fit_loop"]["state_dict"]["combined_loader"],  # the stream position
        "loops": loop_counters(ckpt),
    }


def assert_identical(a, b, path="checkpoint"):
    assert type(a) is type(b), f"{path}: {type(a)} vs {type(b)}"
    if isinstance(a, torch.Tensor):
        assert a.dtype == b.dtype and a.shape == b.shape and torch.equal(a, b), f"{path} differs"
    elif isinstance(a, dict):
        assert a.keys() == b.keys(), f"{path}: keys {sorted(a)} vs {sorted(b)}"
        for k in a:
            assert_identical(a[k], b[k], f"{path}.{k}")
    elif isinstance(a, (list, tuple)):
        assert len(a) == len(b), f"{path}: length {len(a)} vs {len(b)}"
        for i, (x, y) in enumerate(zip(a, b)):
            assert_identical(x, y, f"{path}[{i}]")
    else:
        assert a == b, f"{path}: {a!r} vs {b!r}"
