"""Faults injected into real runs through their configs (``class_path: helpers.faults...``, importable in
the test process and, through PYTHONPATH, in the ``omg`` processes the tests start)."""

from __future__ import annotations

import os
import signal
import time

from lightning.pytorch.callbacks import Callback


class SigtermAt(Callback):
    """Sends this process SIGTERM during a step, as a scheduler or `scancel` would."""

    def __init__(self, step: int):
        self.step = step

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx):
        if trainer.global_step == self.step:
            os.kill(os.getpid(), signal.SIGTERM)


class KillWritingLast(Callback):
    """Stands for a kill while ``last.ckpt`` is written at ``step``: the periodic checkpoint of that
    step is whole, and ``last.ckpt`` stays the older file (its write is atomic)."""

    def __init__(self, step: int):
        self.step, self.saves = step, 0

    def on_save_checkpoint(self, trainer, pl_module, checkpoint):
        if trainer.global_step == self.step:
            self.saves += 1
            if self.saves == 2:  # ModelCheckpoint writes the step's periodic file, then last.ckpt
                raise KilledWritingLast


class KilledWritingLast(Exception):
    """Raised by ``KillWritingLast``."""


class SlowAfterCtrlC(Callback):
    """Makes the step in which a stop was asked for last a minute, the time to press Ctrl-C again."""

    def on_train_batch_end(self, trainer, *args):
        if trainer.received_sigterm:
            time.sleep(60)


class SigtermAtTestEnd(Callback):
    """Sends this process SIGTERM when the test epoch ends, before the evaluation callbacks listed after it
    run their protocol: a scheduler's stop while `omg test` evaluates."""

    def on_test_epoch_end(self, trainer, pl_module):
        os.kill(os.getpid(), signal.SIGTERM)
