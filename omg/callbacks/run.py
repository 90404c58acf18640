"""What the callbacks share: the run directory, logging to every logger, sampling without
disturbing training (module modes and the global RNG)."""

from __future__ import annotations

import os
import signal
import threading
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

import lightning as L
import torch
from lightning.pytorch.callbacks import Callback
from lightning.pytorch.loggers import CSVLogger, TensorBoardLogger
from lightning.pytorch.utilities.exceptions import SIGTERMException

from omg.lit.base import modes_restored


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
    devices = [module.device] if module.device.type == "cuda" else []
    with torch.random.fork_rng(devices=devices), torch.no_grad(), modes_restored(module):
        yield


def stop_if_signalled(trainer: L.Trainer) -> None:
    """End ``omg test``'s evaluation when SIGTERM has come: Lightning's handler only sets a flag, which its
    loops read at a step's end, and an evaluation protocol (replications of generation after the test
    epoch) has no step, so it ran on to its end. Raised as the fit loop raises it (``omg.cli`` says it in
    one line, exit 143). Ctrl-C needs nothing: outside ``fit`` it is Python's KeyboardInterrupt."""
    if trainer.testing and trainer.received_sigterm:
        error = SIGTERMException()
        error.omg_stop = {"during": "the evaluation"}  # read by omg.cli
        raise error


class InterruptCheckpoint(Callback):
    """On SIGTERM (preemption, ``scancel``, a scheduler's time limit) or Ctrl-C (SIGINT) save
    ``interrupted.ckpt`` beside the run's checkpoints at the end of the step in which the signal
    came, the point where ModelCheckpoint saves too, so ``--ckpt_path last`` resumes from it exactly
    (``omg.tools.lightning`` counts it among the run's checkpoints and takes the newest). Lightning's loops
    then stop. Other exceptions save nothing: a crash mid-step leaves a state that must not be
    resumed from. (Not Lightning's OnExceptionCheckpoint: with one of those, every ``fit`` without a
    ``--ckpt_path`` silently resumes from the newest checkpoint in the folder.)

    Ctrl-C takes Lightning's SIGTERM path (Lightning's own KeyboardInterrupt handling saves nothing
    and exits 1): the first one asks for the stop, a second aborts at once. Its handler is set in
    ``setup``, before the data workers fork, so that they, which get a terminal's Ctrl-C too, go on
    serving the last step rather than die with a KeyboardInterrupt.

    A step whose batch read is stalled would never get to its end: ``omg.data.deadline`` then gives the
    read ``STOP_GRACE_S`` and raises the ``SIGTERMException`` the loop would have raised (no
    interrupted.ckpt: the step did not end; the line names the last periodic checkpoint).

    On several ranks Lightning shares the signal through collectives of its own at points that
    differ between ranks, and a checkpoint (a collective too) cannot be slotted in safely: the
    run stops at its last periodic checkpoint. ``omg fit`` then exits non-zero (``omg.cli``)
    unless the stop was a SLURM requeue, and its last line says which and where the checkpoint is.
    """

    def __init__(self, dirpath: str | Path):
        self.ckpt_path = str(Path(dirpath) / "interrupted.ckpt")
        self.started, self.saved_step = time.time(), None
        self.signal = "SIGTERM"  # what stopped the run, when something did
        self._trainer: L.Trainer | None = None
        self._pid, self._previous_sigint = None, None

    def setup(self, trainer: L.Trainer, pl_module: L.LightningModule, stage: str) -> None:
        if stage == "fit" and threading.current_thread() is threading.main_thread():
            self._trainer, self._pid = trainer, os.getpid()
            # what Ctrl-C does when no fit runs: kept after the fit, for `_on_sigint` to hand on to
            self._previous_sigint = signal.signal(signal.SIGINT, self._on_sigint)

    def _on_sigint(self, signum, frame) -> None:
        if self._trainer is None:
            # no fit runs: a fit that raised ends with Lightning putting back the handlers it saw after `setup`,
            # this one among them (after `on_exception` gave the previous one back), so it hands on
            previous = self._previous_sigint if self._previous_sigint is not None else signal.SIG_DFL
            signal.signal(signal.SIGINT, previous)
            if callable(previous):
                previous(signum, frame)
            elif previous == signal.SIG_DFL:
                signal.raise_signal(signal.SIGINT)
            return
        if os.getpid() != self._pid:
            return  # a forked data worker: the main process stops the run
        signal.signal(signal.SIGINT, signal.SIG_DFL)  # a second Ctrl-C aborts at once
        self.signal = "SIGINT"
        self._trainer._signal_connector.received_sigterm = True  # what Lightning's SIGTERM handler sets
        os.write(2, b"omg: Ctrl-C: stopping after this step to save a checkpoint (Ctrl-C again aborts at once)\n")

    def on_train_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        if self.signal == "SIGINT":  # Ctrl-C before Lightning set its signal handlers, which clears the flag
            trainer._signal_connector.received_sigterm = True

    def teardown(self, trainer: L.Trainer, pl_module: L.LightningModule, stage: str) -> None:
        self._give_back_ctrl_c()

    def _give_back_ctrl_c(self) -> None:
        """The Ctrl-C handler the fit found, back, however the fit ends: else a later Ctrl-C in the same
        process (a notebook's) would only set a flag on a finished trainer (``_on_sigint`` hands on where
        Lightning puts this one back). After a Ctrl-C the process is on its way out: a second one still
        aborts at once."""
        if self._pid == os.getpid() and self._previous_sigint is not None and self.signal != "SIGINT":
            signal.signal(signal.SIGINT, self._previous_sigint)
        self._trainer, self._pid = None, None

    def on_train_batch_end(self, trainer: L.Trainer, pl_module: L.LightningModule, *args) -> None:
        if trainer.received_sigterm and trainer.world_size == 1 and self.saved_step is None:
            trainer.save_checkpoint(self.ckpt_path)
            self.saved_step = trainer.global_step

    def on_exception(self, trainer: L.Trainer, pl_module: L.LightningModule, exception: BaseException) -> None:
        self._give_back_ctrl_c()
        if not isinstance(exception, SIGTERMException) or trainer.state.fn != "fit":
            return
        if self.saved_step is not None:
            checkpoint = self.ckpt_path
        else:
            saver = trainer.checkpoint_callback
            checkpoint = getattr(saver, "last_model_path", "") or getattr(saver, "best_model_path", "") or None
        hpc = sorted(Path(trainer.default_root_dir).glob("hpc_ckpt_*.ckpt"), key=lambda p: p.stat().st_mtime)
        requeued = (self.signal == "SIGTERM" and bool(hpc) and hpc[-1].stat().st_mtime >= self.started
                    and "SLURM_JOB_ID" in os.environ)
        exception.omg_stop = {"step": trainer.global_step, "checkpoint": checkpoint, "requeued": requeued,
                              "signal": self.signal}
