"""What the callbacks share: the run directory, logging to every logger, sampling without
disturbing training (module modes and the global RNG)."""

from __future__ import annotations

from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

import lightning as L
import torch
from lightning.pytorch.loggers import CSVLogger, TensorBoardLogger


def run_dir(trainer: L.Trainer) -> Path:
    """The versioned directory of this run: the CSV/TensorBoard logger's ``version_N``, the
    ``save_dir/name/version`` where Lightning puts checkpoints for other loggers (wandb), or
    ``default_root_dir`` without a logger. Call it on every rank (it broadcasts)."""
    logger = trainer.loggers[0] if trainer.loggers else None
    if logger is None:
        path = trainer.default_root_dir
    elif isinstance(logger, (CSVLogger, TensorBoardLogger)):
        path = logger.log_dir
    else:
        version = logger.version if isinstance(logger.version, str) else f"version_{logger.version}"
        path = str(Path(logger.save_dir or trainer.default_root_dir) / str(logger.name) / version)
    return Path(trainer.strategy.broadcast(path))


def log_scalars(trainer: L.Trainer, values: dict[str, float]) -> None:
    """Log at the current step to every logger (loggers write on rank 0 only) and expose the
    values to other callbacks (e.g. ModelCheckpoint(monitor="eval/fid"))."""
    for logger in trainer.loggers:
        logger.log_metrics(values, step=trainer.global_step)
    trainer.callback_metrics.update({k: torch.tensor(v) for k, v in values.items()})


@contextmanager
def sampling(module: L.LightningModule) -> Iterator[None]:
    """Sample from ``module`` mid-training: every submodule's train/eval mode and the global RNG
    states are restored afterwards, so training goes on exactly as without the callback."""
    modes = {m: m.training for m in module.modules()}
    devices = [module.device] if module.device.type == "cuda" else []
    with torch.random.fork_rng(devices=devices), torch.no_grad():
        try:
            yield
        finally:
            for m, training in modes.items():
                m.train(training)
