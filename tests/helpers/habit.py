"""The habit tests' mini quadrupeds and a short Lightning fit on them (tests/test_habit*.py,
tests/test_paper_numbers.py)."""

from __future__ import annotations

from helpers import REPO

QUATVEL = REPO / "shards" / "mini" / "animal_quatvel"
CATEGORIES = ["dog", "cat", "fox", "horse", "cow", "deer", "sheep"]


def fit(module, out, steps: int, batch_size: int = 32, seed: int = 0, callbacks=()):
    import lightning as L

    from omg.data.datamodule import MotionDataModule

    L.seed_everything(seed, verbose=False)
    data = MotionDataModule(str(QUATVEL / "train"), batch_size=batch_size, max_len=64, min_len=64, clips="windows",
                            batches_per_epoch=steps, num_workers=0, shuffle_buffer=94, verify_shards=False)
    module = module(data.spec) if callable(module) and not isinstance(module, L.LightningModule) else module
    trainer = L.Trainer(accelerator="cpu", max_steps=steps, logger=False, enable_checkpointing=False,
                        enable_progress_bar=False, enable_model_summary=False, default_root_dir=str(out),
                        gradient_clip_val=1.0, limit_val_batches=0, callbacks=list(callbacks))
    trainer.fit(module, datamodule=data)
    module.hparams["_class_path"] = f"{type(module).__module__}.{type(module).__qualname__}"  # as LightningCLI records
    path = out / "last.ckpt"
    trainer.save_checkpoint(path)
    return module, path
