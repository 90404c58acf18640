"""Plain progress lines for a run whose output is not a terminal (a log file, a SLURM job): the
progress bar redraws one line in place, which a file only receives when the run ends."""

from __future__ import annotations

import math
import time

import lightning as L


def duration(seconds: float) -> str:
    """``1h02m``, ``4m05s``, ``12s``."""
    seconds = round(seconds)
    if seconds >= 3600:
        return f"{seconds // 3600}h{seconds % 3600 // 60:02d}m"
    if seconds >= 60:
        return f"{seconds // 60}m{seconds % 60:02d}s"
    return f"{seconds}s"


class PlainProgress(L.Callback):
    """Every ``every_n_steps`` optimizer steps, one line on stdout (rank 0): the step of the run's
    total, the metrics the model shows in its progress bar (``prog_bar=True``: its losses), the
    learning rate, the optimizer steps per second since the previous line and the time left at
    that rate."""

    def __init__(self, every_n_steps: int = 50) -> None:
        self.every_n_steps = every_n_steps
        self.last: tuple[int, float] | None = None  # (step, time) of the previous line, or of the start

    def on_train_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self.last = (trainer.global_step, time.perf_counter())  # a resumed run counts from where it starts

    def on_train_batch_end(self, trainer: L.Trainer, pl_module: L.LightningModule, *args, **kwargs) -> None:
        step = trainer.global_step
        if not trainer.is_global_zero or step % self.every_n_steps or self.last is None or step == self.last[0]:
            return  # also the micro-batches of an accumulated step after its line
        now = time.perf_counter()
        rate = (step - self.last[0]) / max(now - self.last[1], 1e-9)
        self.last = (step, now)
        total = trainer.estimated_stepping_batches
        parts = [f"step {step}/{total}" if math.isfinite(total) else f"step {step}"]
        metrics = trainer.progress_bar_metrics
        parts += [f"{name} {value:.4g}" for name, value in metrics.items() if isinstance(value, (int, float))]
        if trainer.optimizers:
            parts.append(f"lr {trainer.optimizers[0].param_groups[0]['lr']:.3g}")
        parts.append(f"{rate:.3g} steps/s")
        if math.isfinite(total) and rate > 0:
            parts.append(f"{duration((total - step) / rate)} left")
        print(" | ".join(parts), flush=True)
