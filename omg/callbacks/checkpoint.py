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
(``omg.tools.lightning``) install both; DeepSpeed checkpoints are directories that DeepSpeed writes itself
(``CheckpointIO`` is not used), so this does not cover them.

``TopKHousekeeping``: a ModelCheckpoint with ``save_top_k=k`` deletes the files that fall out of
its top k, but only those its own state (restored from the checkpoint a run resumes from) names:
the files a killed run wrote after that checkpoint, and the checkpoint resumed from (which Lightning
never deletes), stayed for ever. A resumed run brings the folder back to the policy.
"""

from __future__ import annotations

import os
import re
from pathlib import Path
from typing import Any, Iterable

import lightning as L
import torch
from lightning.fabric.utilities.cloud_io import get_filesystem
from lightning.pytorch.callbacks import Callback, ModelCheckpoint
from lightning.pytorch.plugins.io import TorchCheckpointIO

from omg.files import atomic_path

# omg.files.atomic_path's temporary name for <stem><suffix>: .<stem>.<pid>.tmp<suffix>
TEMP_NAME = re.compile(r"^\.(?P<stem>.+)\.(?P<pid>\d+)\.tmp(?P<suffix>\.[^.]*)?$")
# a value ModelCheckpoint formats into a file name: an int, a float (any format spec), nan, inf
NUMBER = r"[-+]?(?:\d+(?:\.\d*)?(?:[eE][-+]?\d+)?|nan|inf)"


class AtomicCheckpointIO(TorchCheckpointIO):
    """``TorchCheckpointIO`` that writes a local checkpoint to a temporary file in its own folder
    and renames it over the final name; remote paths keep Lightning's own save."""

    def save_checkpoint(self, checkpoint: dict[str, Any], path: Any, storage_options: Any | None = None) -> None:
        from fsspec.utils import get_protocol

        if storage_options is not None or get_protocol(str(path)) != "file":  # a local file, as Lightning tells
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


def written_name(callback: ModelCheckpoint) -> re.Pattern:
    """The names of the periodic/top-k checkpoints ``callback`` writes (its ``filename`` template,
    default ``{epoch}-{step}``, with the values it formats in and its ``-vN`` version suffix); not
    its ``last`` files. A template whose names hold a folder (a metric named ``eval/fid``) matches
    nothing: what is not recognised is never deleted."""
    template = callback.filename or "{epoch}" + callback.CHECKPOINT_JOIN_CHAR + "{step}"
    parts, end = [], 0
    for field in re.finditer(r"\{([^:}]*)(?::[^}]*)?\}", template):  # as ModelCheckpoint._format_checkpoint_name
        name = field.group(1) + callback.CHECKPOINT_EQUALS_CHAR if callback.auto_insert_metric_name else ""
        parts += [re.escape(template[end:field.start()]), re.escape(name), NUMBER]
        end = field.end()
    version = rf"(?:{re.escape(callback.CHECKPOINT_JOIN_CHAR)}v\d+)?"
    return re.compile("".join([*parts, re.escape(template[end:]), version, re.escape(callback.FILE_EXTENSION)]))


def written_checkpoints(callback: ModelCheckpoint) -> list[Path]:
    """The periodic/top-k checkpoints in ``callback``'s folder that it writes (``written_name``),
    from this run or an earlier run into the same folder; never ``last*`` or a user's own files."""
    if callback.dirpath is None or not Path(callback.dirpath).is_dir():
        return []
    pattern = written_name(callback)
    return sorted(p for p in Path(callback.dirpath).iterdir() if pattern.fullmatch(p.name))


def kept_checkpoints(callback: ModelCheckpoint) -> set[Path]:
    """The files ``callback``'s state still names: its top k, best, k-th best and last."""
    named = [*callback.best_k_models, callback.best_model_path, callback.kth_best_model_path,
             callback.last_model_path]
    return {Path(p).absolute() for p in named if p}


class TopKHousekeeping(Callback):
    """For a run resumed with ``--ckpt_path last`` or from its SLURM requeue checkpoint (``omg.tools.lightning``
    adds it then): delete the files of every ``ModelCheckpoint(save_top_k=k)`` (k >= 1) that its
    restored state does not keep, at the start of training (all but the checkpoint resumed from)
    and after each later save (the checkpoint resumed from too, once it falls out of the top k).
    Only files the callback writes (``written_checkpoints``) are candidates, only when its state
    names files in its own folder (a moved folder's state names the old one), and never one that
    another checkpoint callback with the same folder keeps (``save_top_k=-1``: all of its files)."""

    def __init__(self):
        self.resumed_from: Path | None = None

    def on_train_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        if trainer.ckpt_path is not None:
            self.resumed_from = Path(trainer.ckpt_path).absolute()
            prune_to_top_k(trainer, keep={self.resumed_from})

    def on_train_batch_end(self, trainer: L.Trainer, *args) -> None:
        self._after_saves(trainer)

    def on_validation_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self._after_saves(trainer)

    def on_train_epoch_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self._after_saves(trainer)

    def on_train_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self._after_saves(trainer)

    def _after_saves(self, trainer: L.Trainer) -> None:
        # until the checkpoint resumed from is gone: Lightning never deletes it
        if self.resumed_from is not None:
            prune_to_top_k(trainer)
            if not self.resumed_from.exists():
                self.resumed_from = None


def prune_to_top_k(trainer: L.Trainer, keep: set[Path] = frozenset()) -> list[Path]:
    """Delete, on rank 0, the files of the trainer's top-k ModelCheckpoints that none of its
    checkpoint callbacks keeps (``TopKHousekeeping``), nor ``keep``; returns them."""
    callbacks = [cb for cb in trainer.checkpoint_callbacks if isinstance(cb, ModelCheckpoint) and cb.dirpath]
    kept = set(keep).union(*(kept_checkpoints(cb) for cb in callbacks))
    kept |= {p.absolute() for cb in callbacks if cb.save_top_k < 0 for p in written_checkpoints(cb)}
    removed = []
    for callback in callbacks if trainer.is_global_zero else []:
        folder = Path(callback.dirpath).absolute()
        named = kept_checkpoints(callback)
        if callback.save_top_k < 1 or not named or any(p.parent != folder for p in named):
            continue  # keeps all, writes none, or its state is not of this folder
        for path in written_checkpoints(callback):
            if path.absolute() not in kept and path.is_file():
                path.unlink(missing_ok=True)
                removed.append(path)
    return removed
