"""Training step timing for benchmarks run through the real ``omg fit`` (``omg bench gpu``)."""

from __future__ import annotations

import json
import time
from pathlib import Path

import lightning as L


class StepTimer(L.Callback):
    """Times training steps (after ``warmup`` of them) and writes {"step_s", "batch", "frames"} as
    JSON to ``out`` at the end; with ``save``, the trainer also saves a checkpoint there (the
    strategy's own format: a DeepSpeed directory under ZeRO) for ``omg convert-ckpt``."""

    def __init__(self, out: str, warmup: int = 5, save: str | None = None) -> None:
        self.out, self.warmup, self.save = out, warmup, save
        self.times: list[float] = []
        self.shape: tuple[int, int] = (0, 0)

    def _sync(self) -> None:
        import torch

        if torch.cuda.is_available():
            torch.cuda.synchronize()

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx) -> None:
        self._sync()
        stream = batch["animal"] if "animal" in batch else batch  # a paired batch (OmniMotionGPT): its first set's
        self.shape = tuple(stream["mask"].shape)
        self.start = time.perf_counter()

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:
        self._sync()
        self.times.append(time.perf_counter() - self.start)

    def on_train_end(self, trainer, pl_module) -> None:
        if self.save:
            trainer.save_checkpoint(self.save)
        timed = self.times[self.warmup:] or self.times
        if trainer.is_global_zero:
            Path(self.out).write_text(json.dumps({"step_s": sum(timed) / len(timed), "batch": self.shape[0],
                                                  "frames": self.shape[1], "steps": len(timed)}))
