"""Checkpoint files that survive a kill: written atomically beside their final name, and the
temporary files a killed write leaves behind removed when the next run starts there.

Lightning's ``TorchCheckpointIO`` saves through fsspec's local transaction, which writes the
whole file to ``tempfile.mkstemp()`` (the system temp folder, often another filesystem) and then
moves it onto the checkpoint's name: across filesystems that move is a copy, so a kill during it
leaves a truncated ``last.ckpt``, and a kill before it leaves a nameless ``/tmp/tmpXXXXXXXX`` that
nothing ever cleans. ``AtomicCheckpointIO`` writes ``.<name>.<pid>.tmp.ckpt`` in the checkpoint's
own folder (``omg.files.atomic_path``: fsync, then an atomic rename), so ``last.ckpt`` is
always the old file or the whole new one, and a leftover temporary file has a name that says
whose it is. ``remove_stale_temp_files`` deletes those (and those of omg's other atomic writes:
shards, manifests, eval.json) whose writer process is gone. ``omg fit|validate|test|predict``
(``omg.lit.cli``) install both; DeepSpeed checkpoints are directories that DeepSpeed writes itself
(``CheckpointIO`` is not used), so this does not cover them.
"""

from __future__ import annotations

import os
import re
from pathlib import Path
from typing import Any, Iterable

import lightning as L
import torch
from lightning.fabric.utilities.cloud_io import get_filesystem
from lightning.pytorch.callbacks import ModelCheckpoint
from lightning.pytorch.plugins.io import TorchCheckpointIO

from omg.files import atomic_path

# omg.files.atomic_path's temporary name for <stem><suffix>: .<stem>.<pid>.tmp<suffix>
TEMP_NAME = re.compile(r"^\.(?P<stem>.+)\.(?P<pid>\d+)\.tmp(?P<suffix>\.[^.]*)?$")


class AtomicCheckpointIO(TorchCheckpointIO):
    """``TorchCheckpointIO`` that writes a local checkpoint to a temporary file in its own folder
    and renames it over the final name; remote paths keep Lightning's own save."""

    def save_checkpoint(self, checkpoint: dict[str, Any], path: Any, storage_options: Any | None = None) -> None:
        from lightning.fabric.utilities.cloud_io import _is_local_file_protocol

        if storage_options is not None or not _is_local_file_protocol(path):
            return super().save_checkpoint(checkpoint, path, storage_options)
        path = Path(path)
        get_filesystem(path).makedirs(str(path.parent), exist_ok=True)
        with atomic_path(path) as tmp:
            torch.save(checkpoint, tmp)


def _running(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OSError):
        return True  # someone else's live process (or we cannot tell): leave its file alone
    return True


def stale_temp_files(directory: str | Path) -> list[Path]:
    """The temporary files of interrupted atomic writes in ``directory`` (not recursive): omg's
    ``.<stem>.<pid>.tmp<suffix>`` names whose process no longer runs on this machine."""
    directory = Path(directory)
    if not directory.is_dir():
        return []
    out = []
    for path in directory.iterdir():
        match = TEMP_NAME.match(path.name)
        if match and path.is_file() and not _running(int(match["pid"])):
            out.append(path)
    return sorted(out)


def remove_stale_temp_files(directories: Iterable[str | Path]) -> list[Path]:
    """Delete ``stale_temp_files`` of each directory; returns what was removed."""
    removed = []
    for directory in dict.fromkeys(Path(d) for d in directories):
        for path in stale_temp_files(directory):
            try:
                path.unlink()
            except FileNotFoundError:  # another rank got there first
                continue
            removed.append(path)
    return removed


def checkpoint_dirs(trainer: L.Trainer) -> list[Path]:
    """The folders a run writes checkpoints into: every ModelCheckpoint's ``dirpath`` that is set."""
    return [Path(cb.dirpath) for cb in trainer.checkpoint_callbacks
            if isinstance(cb, ModelCheckpoint) and cb.dirpath is not None]


def prepare_checkpointing(trainer: L.Trainer) -> list[Path]:
    """At the start of a run: atomic checkpoint writes (unless the trainer has its own CheckpointIO)
    and no stale temporary files in the checkpoint folders, the run's root folder and its
    ``version_*`` run folders. Returns the files removed."""
    strategy = trainer.strategy
    if type(strategy.checkpoint_io) is TorchCheckpointIO:
        strategy.checkpoint_io = AtomicCheckpointIO()
    root = Path(trainer.default_root_dir)
    runs = sorted(root.glob("version_*")) if root.is_dir() else []
    return remove_stale_temp_files([*checkpoint_dirs(trainer), root, *runs])
