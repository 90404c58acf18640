"""One two-rank (gloo, CPU) training run for tests/test_resume.py: ``python ddp_resume_run.py
SHARDS ROOT KILL_AT|-1 RESUME(0|1)``. Lightning's DDP launcher starts rank 1 by running this
script again with LOCAL_RANK set."""

import sys
from pathlib import Path

import lightning as L
import torch

sys.path.insert(0, str(Path(__file__).parent))
from omg.data.datamodule import MotionDataModule  # noqa: E402
from omg.lit.pretrain import PretrainModule  # noqa: E402
from test_resume import KillAt, Killed  # noqa: E402

MAX_STEPS = 7  # epochs of 3 batches: boundaries after steps 3 and 6

if __name__ == "__main__":
    shards, root, kill_at, resume = Path(sys.argv[1]), Path(sys.argv[2]), int(sys.argv[3]), sys.argv[4] == "1"
    torch.set_num_threads(1)
    L.seed_everything(0, verbose=False)
    data = MotionDataModule(str(shards), batch_size=2, max_len=30, min_len=10, batches_per_epoch=3,
                            num_workers=0, shuffle_buffer=8)
    model = PretrainModule(flavor="mini", dit={"n_layers": 1, "d_model": 32, "n_heads": 2}, lr=1e-3,
                           warmup_steps=2, ema_decay=0.9, spec=data.spec)
    callbacks = [L.pytorch.callbacks.ModelCheckpoint(dirpath=root / "ckpt", save_last=True, every_n_train_steps=1)]
    if kill_at >= 0:
        callbacks.append(KillAt(kill_at))
    trainer = L.Trainer(accelerator="cpu", devices=2, strategy="ddp", max_steps=MAX_STEPS, logger=False,
                        enable_progress_bar=False, enable_model_summary=False, limit_val_batches=0,
                        num_sanity_val_steps=0, default_root_dir=root, callbacks=callbacks)
    try:
        trainer.fit(model, data, ckpt_path=str(root / "ckpt" / "last.ckpt") if resume else None)
    except Killed:
        sys.exit(3)
