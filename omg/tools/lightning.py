"""LightningCLI for omg: the data module is fixed, the model is any LightningModule by class
(short names like ``PretrainModule`` work), and the model receives the data's spec.

Each run writes into its own versioned directory: unless the config names a logger, a
CSVLogger logs to ``<default_root_dir>/version_N`` and config.yaml is saved beside its
metrics.csv, so a second run never overwrites the first. To log to Weights & Biases instead
(``offline: true`` or WANDB_MODE=offline needs no network)::

    trainer:
      logger:
        class_path: lightning.pytorch.loggers.WandbLogger
        init_args: {project: omg, save_dir: runs/NAME, offline: false}
"""

from __future__ import annotations

import importlib
import os
import re
import sys
from pathlib import Path
from typing import Any

import lightning as L
import torch
from jsonargparse import Namespace
from lightning.pytorch.callbacks import ModelCheckpoint, OnExceptionCheckpoint, RichProgressBar
from lightning.pytorch.cli import LightningArgumentParser, LightningCLI, SaveConfigCallback
from lightning.pytorch.utilities import rank_zero_info, rank_zero_warn

import omg.callbacks  # noqa: F401  (short callback names: EvalCallback, RenderCallback)
import omg.lit  # noqa: F401  (imports the modules so short class names resolve)
from omg.callbacks.run import InterruptCheckpoint, run_dir
from omg.data.datamodule import MotionDataModule
from omg.errors import UsageError
from omg.files import check_output_dir

SPECIAL_CKPT_PATHS = ("last", "best", "hpc")  # resolved by Lightning at run time


class SaveRunConfig(SaveConfigCallback):
    """Saves the run's config.yaml into its versioned run directory (``omg.callbacks.run_dir``)
    rather than ``trainer.log_dir``, which for wandb is a directory shared by every run."""

    def setup(self, trainer: L.Trainer, pl_module: L.LightningModule, stage: str) -> None:
        if self.already_saved:
            return
        directory = run_dir(trainer)
        if trainer.is_global_zero:
            directory.mkdir(parents=True, exist_ok=True)
            self.parser.save(self.config, str(directory / self.config_filename), skip_none=False,
                             overwrite=self.overwrite, multifile=self.multifile)
        self.already_saved = trainer.strategy.broadcast(True)


SMALL_MODEL_PARAMS = 20_000_000  # trainable parameters under which one intra-op thread is the faster choice


def cpu_threads_for(model: torch.nn.Module) -> int | None:
    """The intra-op threads a model trains fastest with on the CPU: 1 when it has fewer than
    ``SMALL_MODEL_PARAMS`` trainable parameters, else None (torch's default, one per core).

    A step's work scales with the trainable weights (forward, weight gradients, the optimizer), not
    with frozen modules: a frozen text encoder runs once per batch, without gradients, on a few caption
    tokens. Counting it gave the small ControlNet recipe (2.3M trainable parameters, 26M with the frozen
    MiniLM) two threads, and on a busy 2-core machine it trained several times slower than with one: a
    small model's matrices are too small for torch's threads to pay for their hand-offs, and the OpenMP
    thread spins beside MKL's while it waits. Decided from the model, not by timing at start-up: the
    thread count changes the order of float sums, so a measurement on a loaded machine would make runs
    of one config irreproducible."""
    trainable = sum(p.numel() for p in model.parameters() if p.requires_grad)
    return 1 if trainable < SMALL_MODEL_PARAMS else None


def pick_cpu_threads(trainer: L.Trainer, model: L.LightningModule) -> None:
    """``cpu_threads_for(model)`` intra-op threads for a run on the CPU; OMP_NUM_THREADS, when set,
    decides instead."""
    from lightning.pytorch.accelerators import CPUAccelerator

    if not isinstance(trainer.accelerator, CPUAccelerator) or "OMP_NUM_THREADS" in os.environ:
        return
    threads = cpu_threads_for(model)
    if threads is not None and torch.get_num_threads() != threads:
        torch.set_num_threads(threads)
        trainable = sum(p.numel() for p in model.parameters() if p.requires_grad)
        rank_zero_info(f"omg: {trainable / 1e6:.1f}M trainable parameters on the CPU: {threads} intra-op thread "
                       "(set OMP_NUM_THREADS to choose another number)")


# How torch's process-group backends word the two ways a multi-process run breaks (lower case): a peer whose
# process or node ended closes its sockets (gloo's TCP pairs, NCCL's remote-error check, the c10d store);
# a peer that stops without closing them (a frozen node, SIGSTOP, a network partition) is noticed only
# by the collective's timeout (gloo's own wait, NCCL's watchdog), which is the strategy's `timeout`.
LOST_PEER = ("connection closed by peer", "connection reset by peer", "connection was likely closed", "broken pipe",
             "remote process exited")
TIMED_OUT = ("timed out", "timeout")
_SOURCE = re.compile(r"^\[[^\]]*\.(?:cc|cpp|h|hpp):\d+\]\s*")  # gloo's "[.../pair.cc:561] " prefix


def distributed_failure(error: BaseException) -> str | None:
    """What broke a multi-process run, in a few words around torch's own first sentence (``lost a peer
    process (Connection closed by peer [10.0.0.2]:7380): ...``), when ``error`` is a collective's or the
    store's failure of either kind; None for anything else (a bug keeps its traceback). gloo raises a
    plain RuntimeError whose text names its source file; NCCL and the store raise ``DistError``s."""
    text = str(error).strip()
    if not (isinstance(error, torch.distributed.DistError) or "gloo/" in text):
        return None
    detail = _SOURCE.sub("", text.splitlines()[0] if text else "").split(". ")[0].rstrip(".")
    lowered = text.lower()
    if any(phrase in lowered for phrase in TIMED_OUT):
        return (f"a collective operation timed out ({detail}): another rank stopped responding for longer than the "
                "process group's timeout (trainer.strategy.init_args.timeout, 30 min unless set)")
    if any(phrase in lowered for phrase in LOST_PEER):
        return f"lost a peer process ({detail}): another rank's process or node ended; its own log says why"
    return None


class StepProgressBar(RichProgressBar):
    """Lightning's rich bar, its epoch told without a total when the run is bounded by steps
    (``max_epochs=-1`` made it read "Epoch 7/-2")."""

    def _get_train_description(self, current_epoch: int) -> str:
        if self.trainer.max_epochs is not None and self.trainer.max_epochs >= 0:
            return super()._get_train_description(current_epoch)
        return f"Epoch {current_epoch}"


class OmgLightningCLI(LightningCLI):
    def __init__(self, args: list[str] | None = None):
        super().__init__(
            model_class=L.LightningModule,
            subclass_mode_model=True,
            datamodule_class=MotionDataModule,
            parser_kwargs={"exit_on_error": False},
            save_config_callback=SaveRunConfig,
            save_config_kwargs={"overwrite": True},  # only a run without a logger shares its directory
            args=args,
        )

    def instantiate_trainer(self, **kwargs) -> L.Trainer:
        """The configured Trainer, its checkpoints in the run directory, plus a checkpoint on
        SIGTERM beside them."""
        trainer = super().instantiate_trainer(**kwargs)
        # checkpoints belong to the run: a ModelCheckpoint without a dirpath writes into
        # <default_root_dir>/checkpoints (Lightning's default is the logger's version folder,
        # which a next stage's config cannot name in advance)
        default = Path(trainer.default_root_dir) / "checkpoints"
        for callback in trainer.checkpoint_callbacks:
            if isinstance(callback, ModelCheckpoint) and callback.dirpath is None:
                callback.dirpath = str(default.resolve())
        pick_cpu_threads(trainer, self.model)
        for i, callback in enumerate(trainer.callbacks):  # Lightning's default bar, not one the config names
            if type(callback) is RichProgressBar:
                trainer.callbacks[i] = StepProgressBar()
        if self.subcommand == "fit":
            saver = trainer.checkpoint_callback
            trainer.callbacks.append(InterruptCheckpoint(getattr(saver, "dirpath", None) or default))
        return trainer

    def add_arguments_to_parser(self, parser: LightningArgumentParser) -> None:
        parser.link_arguments("data", "model.init_args.spec", compute_fn=lambda data: data.spec, apply_on="instantiate")

    def before_instantiate_classes(self) -> None:
        """The default logger: a versioned CSVLogger in default_root_dir (Lightning's own default is
        TensorBoard when installed, in a lightning_logs/ subfolder)."""
        config = self.config[self.subcommand] if self.subcommand else self.config
        trainer = config.trainer
        # before anything is built or run: a file or an unwritable folder would fail only at the first write
        # (a URL, s3://..., is Lightning's to open)
        if "://" not in str(trainer.default_root_dir or ""):
            check_output_dir(trainer.default_root_dir or ".", "trainer.default_root_dir")
        if trainer.logger is None or trainer.logger is True:
            trainer.logger = Namespace(class_path="lightning.pytorch.loggers.CSVLogger",
                                       init_args=Namespace(save_dir=trainer.default_root_dir or ".", name=""))

    def _run_subcommand(self, subcommand: str) -> None:
        from omg.lit.base import NonFiniteLoss

        try:
            super()._run_subcommand(subcommand)
        except NonFiniteLoss as e:  # one line: its step and its batch's clips say where to look
            raise UsageError(str(e)) from None
        except RuntimeError as e:  # a lost peer or a collective timeout (Lightning has torn the run down)
            if (what := distributed_failure(e)) is None:
                raise
            trainer = self.trainer
            again = " with --ckpt_path last to resume from the newest checkpoint" if subcommand == "fit" else ""
            raise UsageError(f"rank {trainer.global_rank} of {trainer.world_size}, step {trainer.global_step}: "
                             f"{what}; start the job again on every node{again}") from None

    def _preflight(self) -> None:
        """Callbacks that can judge the model and the data before the run (a ``preflight(model,
        datamodule)`` method, e.g. EvalCallback's evaluator against the data) do so here: the
        Trainer's logger creates the run folder before any callback's ``setup``, which would leave
        it behind, empty, on a refusal there."""
        for callback in self.trainer.callbacks:
            if callable(check := getattr(callback, "preflight", None)):
                check(self.model, self.datamodule)

    before_fit = before_validate = before_test = before_predict = _preflight

    # -- --ckpt_path -------------------------------------------------------------------------
    # Lightning reads --ckpt_path twice: LightningCLI right after parsing, to take the model's
    # hyper-parameters from it (and its class: a checkpoint of another class replaced the
    # configured model without a word), and the Trainer when the run starts. Both are checked here
    # first (omg.lit.checkpoint: readable, CRC-checked, no pickled code), so a missing, truncated,
    # zeroed or foreign file, or a checkpoint of another class, is one UsageError line.

    def _parse_ckpt_path(self) -> None:
        from omg.lit.checkpoint import inert_hparams, inspect_checkpoint

        subcommand = self.config.get("subcommand")
        if not subcommand:
            return
        ckpt_path = self.config[subcommand].get("ckpt_path")
        if not ckpt_path or str(ckpt_path) in SPECIAL_CKPT_PATHS:
            return
        try:
            header = inspect_checkpoint(ckpt_path)
        except UsageError as e:
            raise type(e)(f"--ckpt_path {e}") from None
        if header["kind"] == "safetensors":
            raise UsageError(f"--ckpt_path {ckpt_path}: a converted .safetensors file holds weights only and cannot "
                             "restore a run; pass a Lightning .ckpt or DeepSpeed checkpoint directory (to start from "
                             "its weights, use it as the model's pretrained checkpoint or with `omg generate`)")
        strategy = self.config[subcommand].get("trainer", {}).get("strategy")
        if header["kind"] == "deepspeed" and "deepspeed" not in str(strategy).lower():
            raise UsageError(f"--ckpt_path {ckpt_path} is a DeepSpeed checkpoint directory, which only a DeepSpeed run "
                             f"restores (trainer.strategy is {strategy!r}); convert it with `omg convert-ckpt` to use "
                             "its weights elsewhere")
        model = self.config[subcommand].get("model")
        configured = model.get("class_path") if model is not None and hasattr(model, "get") else None
        cls = self._check_ckpt_class(ckpt_path, header["module_class"], configured)
        hparams = dict(header["hyper_parameters"] or {}) if header["kind"] == "lightning" else {}
        hparams.pop("_instantiator", None)
        # where the run reads data (OmniMotionGPT's human_data, a companion checkpoint) comes from the
        # run's config, never from the file: a checkpoint that named a `pipe:` command would run it
        hparams = inert_hparams(cls, hparams) if cls is not None else hparams
        if not hparams:  # as LightningCLI: a checkpoint file's hyper-parameters become the model's config
            return
        if "_class_path" in hparams:
            hparams = {"class_path": hparams.pop("_class_path"), "dict_kwargs": hparams}
        try:
            self.config = self.parser.parse_object({subcommand: {"model": hparams}}, self.config)
        except SystemExit:
            sys.stderr.write("Parsing of ckpt_path hyperparameters failed!\n")
            raise

    @staticmethod
    def _check_ckpt_class(ckpt_path: Any, recorded: str | None, configured: str | type | None) -> type | None:
        """UsageError unless the checkpoint's recorded class is the configured model's class (LightningCLI
        would otherwise replace the configured model by the recorded class, or restore its state into
        a module of another kind); the class, where known."""
        from omg.lit.checkpoint import class_path, resolve_class

        if isinstance(configured, str):
            module, _, name = configured.rpartition(".")
            try:
                configured = getattr(importlib.import_module(module), name)  # jsonargparse imported it already
            except (ImportError, AttributeError, ValueError):
                configured = None  # jsonargparse reports a bad class_path itself
        if not recorded:
            return configured
        try:
            cls = resolve_class(recorded, ckpt_path)
        except UsageError:
            cls = None  # a class that cannot be resolved here is not the configured one
        if configured is None or cls is configured:
            return cls
        hint = (" (to start a ControlNet from a stage-1 checkpoint, set model.init_args.pretrained instead)"
                if recorded.endswith("PretrainModule") else "")
        raise UsageError(f"--ckpt_path {ckpt_path} holds a {recorded} checkpoint, but the config's model is "
                         f"{class_path(configured)}: resume with a checkpoint of that class{hint}")

    def _hpc_checkpoint(self, ckpt_path: Any) -> str | None:
        """The SLURM checkpoint (``hpc_ckpt_N.ckpt`` in default_root_dir, written when SLURM requeues a
        run) that Lightning would load for ``--ckpt_path hpc``, or on its own in a SLURM job without a
        ``--ckpt_path``, after the checks every other checkpoint passes (omg.lit.checkpoint: readable,
        CRC-checked, no pickled code, the configured model's class); None where Lightning loads none."""
        from lightning.fabric.plugins.environments import SLURMEnvironment

        from omg.lit.checkpoint import inspect_checkpoint

        if ckpt_path != "hpc" and not (ckpt_path is None and SLURMEnvironment.detect()):
            return None
        what = "--ckpt_path hpc" if ckpt_path == "hpc" else "resuming this SLURM job from its requeue checkpoint"
        hpc = self.trainer._checkpoint_connector._hpc_resume_path  # Lightning's own choice: the highest N
        if hpc is None:
            if ckpt_path == "hpc":
                raise UsageError(f"--ckpt_path hpc: {self.trainer.default_root_dir} holds no hpc_ckpt_N.ckpt "
                                 "(Lightning writes one when SLURM requeues a run); pass --ckpt_path last or a file")
            return None
        try:
            header = inspect_checkpoint(hpc)
        except UsageError as e:
            raise type(e)(f"{what}: {e}") from None
        self._check_ckpt_class(hpc, header["module_class"], type(self.model))
        return hpc

    def _prepare_subcommand_kwargs(self, subcommand: str) -> dict[str, Any]:
        """Before the run: atomic checkpoint writes and no stale temporary files in the checkpoint
        folders (omg.callbacks.checkpoint); ``--ckpt_path last`` resolved here to the newest of the
        run's checkpoints that reads and passes its CRC check (``resume_candidate``: Lightning's
        ``last*.ckpt``, the ModelCheckpoints' periodic/top-k files, a SIGTERM's checkpoint), with a
        warning when a newer one does not read; ``--ckpt_path hpc`` and SLURM's own resume checked
        (``_hpc_checkpoint``). A run resumed from either then brings its top-k folders back to their
        policy (``TopKHousekeeping``); one resumed from a checkpoint named by its path does not (the
        files of the steps after it are the user's to keep)."""
        from omg.callbacks.checkpoint import TopKHousekeeping, prepare_checkpointing, written_checkpoints
        from omg.lit.checkpoint import resume_candidate

        kwargs = super()._prepare_subcommand_kwargs(subcommand)
        prepare_checkpointing(self.trainer)
        resumed = False  # from the run's own newest checkpoint, whose folder then goes back to its top-k policy
        if hpc := self._hpc_checkpoint(kwargs.get("ckpt_path")):
            kwargs["ckpt_path"], resumed = hpc, True
        if kwargs.get("ckpt_path") == "last":
            callbacks = [cb for cb in self.trainer.checkpoint_callbacks if isinstance(cb, ModelCheckpoint)]
            run = [Path(p) for cb in callbacks for p in cb._find_last_checkpoints(self.trainer)]
            run += [p for cb in callbacks for p in written_checkpoints(cb)]
            run += [Path(cb.ckpt_path) for cb in self.trainer.callbacks  # a SIGTERM's or Ctrl-C's checkpoint
                    if isinstance(cb, (InterruptCheckpoint, OnExceptionCheckpoint)) and Path(cb.ckpt_path).is_file()]
            found = resume_candidate(run, sorted({p.parent for p in run}), warn=rank_zero_warn)
            if found is not None:
                resolved, header = found
                self._check_ckpt_class(resolved, header["module_class"], type(self.model))
                kwargs["ckpt_path"], resumed = str(resolved), True
        if resumed and subcommand == "fit":
            self.trainer.callbacks.append(TopKHousekeeping())
        return kwargs
