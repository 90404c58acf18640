"""One gloo (CPU) training run for tests/test_resume.py: ``python ddp_resume_run.py SHARDS ROOT
KILL_AT|-1 RESUME(0|1|CKPT) [DEVICES [RECORD]]`` (two devices unless given); RESUME 1 resumes from
ROOT/ckpt/last.ckpt, a path from that checkpoint (another run's). With RECORD, each rank
writes ROOT/RECORD-rank{r}.pt: what each step trained on, and the state it started training from.
The test starts each rank with LOCAL_RANK set, as torchrun does (Lightning then launches nothing)."""

import sys
from pathlib import Path

import lightning as L
import torch
from lightning.pytorch.callbacks import Callback

sys.path.insert(0, str(Path(__file__).parent))
from helpers import TINY_DIT  # noqa: E402
from helpers.resume import KillAt, Killed, Recorder  # noqa: E402
from omg.data.datamodule import MotionDataModule  # noqa: E402
from omg.lit.pretrain import PretrainModule  # noqa: E402

MAX_STEPS = 7  # epochs of 3 batches: boundaries after steps 3 and 6


class StartState(Callback):
    """The state training starts from (after any checkpoint is restored), as a checkpoint holds it."""

    def on_train_start(self, trainer, pl_module):
        self.state = {"global_step": trainer.global_step, "state_dict": pl_module.state_dict(),
                      "ema": pl_module.ema.state_dict(), "optimizer_states": [trainer.optimizers[0].state_dict()],
                      "lr_schedulers": [trainer.lr_scheduler_configs[0].scheduler.state_dict()],
                      "noise_rng": pl_module.noise_generator().get_state()}
        self.state = {k: _copy(v) for k, v in self.state.items()}


def _copy(value):
    if isinstance(value, torch.Tensor):
        return value.clone()
    if isinstance(value, dict):
        return {k: _copy(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_copy(v) for v in value]
    return value


if __name__ == "__main__":
    shards, root, kill_at = Path(sys.argv[1]), Path(sys.argv[2]), int(sys.argv[3])
    resume = {"0": None, "1": str(root / "ckpt" / "last.ckpt")}.get(sys.argv[4], sys.argv[4])
    devices = int(sys.argv[5]) if len(sys.argv) > 5 else 2
    record = sys.argv[6] if len(sys.argv) > 6 else None
    torch.set_num_threads(1)
    L.seed_everything(0, verbose=False)
    data = MotionDataModule(str(shards), batch_size=2, max_len=30, min_len=10, batches_per_epoch=3,
                            num_workers=0, shuffle_buffer=8)
    model = PretrainModule(flavor="mini", dit=TINY_DIT,
                           ema_decay=0.9, spec=data.spec, optim={"lr": 1e-3, "warmup_steps": 2})
    recorder, start = Recorder(), StartState()
    # every step's checkpoint stays: a run killed at the start of step k leaves the checkpoint of step k,
    # which tests/test_resume.py resumes from the run never killed instead of starting a killed run
    callbacks = [L.pytorch.callbacks.ModelCheckpoint(dirpath=root / "ckpt", save_last=True, every_n_train_steps=1,
                                                     save_top_k=-1),
                 recorder, start]
    if kill_at >= 0:
        callbacks.append(KillAt(kill_at))
    trainer = L.Trainer(accelerator="cpu", devices=devices, strategy="ddp" if devices > 1 else "auto",
                        max_steps=MAX_STEPS, logger=False, enable_progress_bar=False, enable_model_summary=False,
                        limit_val_batches=0, num_sanity_val_steps=0, default_root_dir=root, callbacks=callbacks)
    try:
        trainer.fit(model, data, ckpt_path=resume)
        code = 0
    except Killed:
        code = 3
    if record:
        torch.save({"steps": recorder.steps, "start": start.state}, root / f"{record}-rank{trainer.global_rank}.pt")
    sys.exit(code)
