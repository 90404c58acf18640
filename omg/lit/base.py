"""What every omg LightningModule shares: the optimizer and its schedule, weights it does not
own (frozen text backbones, rebuilt from their own files) kept out of its checkpoints, and the class
recorded in them."""

from __future__ import annotations

import dataclasses
import inspect
import math
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager, nullcontext
from dataclasses import dataclass
from typing import Any

import lightning as L
import torch
from torch import Tensor, nn

from omg.lit.ema import EMA
from omg.motion import DataSpec
from omg.settings import check_range, group, regroup, set_fields


@dataclass(frozen=True)
class OptimSettings:
    """The optimizer and its schedule (``OmgModule.make_optimizer``, ``lr_factor``): ``lr``, ``weight_decay`` and
    ``betas`` of AdamW (a family's paper may name another optimizer), ``warmup_steps`` of linear warm-up. A
    family's schedule adds its own fields in a subclass (habit's ``StepOptimSettings``). Their ranges are
    checked once, when the settings are made: one line naming ``model.optim.<field>``."""

    lr: float = 1e-4
    weight_decay: float = 0.0
    betas: tuple[float, float] = (0.9, 0.999)
    warmup_steps: int = 0

    def __post_init__(self) -> None:
        check_range("model.optim.lr", self.lr, 0 < self.lr < math.inf, "a finite number > 0")
        check_range("model.optim.weight_decay", self.weight_decay, 0 <= self.weight_decay < math.inf,
                    "a finite number >= 0")
        check_range("model.optim.betas", self.betas, len(self.betas) == 2 and all(0 <= b < 1 for b in self.betas),
                    "two numbers in [0, 1)")
        check_range("model.optim.warmup_steps", self.warmup_steps,
                    isinstance(self.warmup_steps, int) and self.warmup_steps >= 0, "an integer >= 0")
        object.__setattr__(self, "betas", tuple(self.betas))


def check_weights(group: Any) -> None:
    """One line naming ``model.loss.<field>`` for a loss weight of ``group`` (a loss-weights dataclass) that is
    not a finite number >= 0: the one check of every family's loss weights."""
    for field in dataclasses.fields(group):
        value = getattr(group, field.name)
        check_range(f"model.loss.{field.name}", value, 0 <= value < math.inf, "a finite number >= 0")


def warmup_cosine(warmup_steps: int, total_steps: int):
    """LR multiplier: linear warm-up to 1, then cosine decay to 0 at ``total_steps``."""

    def factor(step: int) -> float:
        if step < warmup_steps:
            return (step + 1) / warmup_steps
        progress = min(1.0, (step - warmup_steps) / max(1, total_steps - warmup_steps))
        return 0.5 * (1.0 + math.cos(math.pi * progress))

    return factor


@contextmanager
def modes_restored(module: nn.Module) -> Iterator[None]:
    """Every submodule's train/eval mode as it was when the block began, whatever the block set
    (frozen parts stay in eval mode, a training run goes on in train mode)."""
    modes = {m: m.training for m in module.modules()}
    try:
        yield
    finally:
        for m, training in modes.items():
            m.training = training  # its own flag: Module.train() would set its whole subtree again


class NonFiniteLoss(FloatingPointError):
    """A training loss that is NaN or inf; its message names the step and the batch's clips. The
    CLI prints it as one line (``omg.tools.lightning``)."""


def check_finite(loss: torch.Tensor, step: int, batch: dict, what: str = "loss", hint: str = "lower model.optim.lr",
                 terms: dict[str, torch.Tensor] | None = None) -> None:
    """NonFiniteLoss unless ``loss`` is finite, naming the clips of ``batch`` (and the loss's
    ``terms``): data whose values overflow (garbled bytes in a set read without checksums)
    diverge like a too-high lr."""
    if torch.isfinite(loss).all():
        return
    values = ", ".join(f"{k} {float(v):.4g}" for k, v in (terms or {what: loss}).items())
    ids = [str(i) for i in batch.get("id") or []]
    clips = f" on the batch of clips {', '.join(ids[:4])}{f' and {len(ids) - 4} more' if len(ids) > 4 else ''}"
    raise NonFiniteLoss(f"non-finite {what} ({values}) at step {step}{clips if ids else ''}; {hint}, or check "
                        "the data (`omg shards inspect`, the clips' value ranges)")


class OmgModule(L.LightningModule):
    """Base of omg's LightningModules.

    Subclasses list in ``frozen_prefixes`` the state-dict prefixes of submodules built from their
    own weight files (a text backbone): those are neither saved nor expected on load. They list in
    ``location_hparams`` the hyper-parameters that name data or files to open (a second shard set,
    a companion checkpoint): a checkpoint's values of those are never used, since a checkpoint is
    inert and self-contained (``omg.lit.checkpoint.load_module`` drops them; ``--ckpt_path`` takes
    them from the run's config). They list in ``architecture_hparams`` the hyper-parameters a
    checkpoint's weights were made with (widths, depths, the data's spec, the text encoder, the
    codebook, what the module fills in from its data): under ``--ckpt_path`` those always come from
    the checkpoint and a config that says otherwise is refused; every other one (sampling,
    evaluation, optimisation, loss weights) is the run's to set (``omg.lit.checkpoint.run_hparams``).
    They give
    their parameter groups in ``optimizer_groups`` and take an ``optim`` (``OptimSettings``, or the
    subclass their schedule reads) that ``make_optimizer`` (AdamW) and ``lr_factor`` (linear warm-up
    then cosine decay over the run) read, the hooks of a family whose paper says otherwise; their loss
    weights come as one ``loss`` group. Such groups, whose every field has a value (a constructor
    default of a dataclass that is not in ``settings_groups``), are kept in the hyper-parameters as
    the mapping of all their fields, and a checkpoint that holds their fields flat (written before
    they were grouped) is read into them (``checkpoint_hparams``).
    """

    frozen_prefixes: tuple[str, ...] = ()
    location_hparams: tuple[str, ...] = ()
    # hyper-parameter -> its typed settings group (omg.settings), e.g. {"dit": DiTOverrides}
    settings_groups: dict[str, type] = {}
    architecture_hparams: tuple[str, ...] = ()  # the weights' own: from the checkpoint under --ckpt_path
    ema_decay: float = 0.0  # the weight EMA's decay (0: none), over ``trainable_module()``
    ema: EMA | None = None
    optim: OptimSettings

    def __new__(cls, *args: Any, **kwargs: Any):
        # a Python caller's older flat keyword (``lr=``, ``retrieval_top_k=``): one line naming its group, where
        # Python's own TypeError would name only the keyword
        params = inspect.signature(cls.__init__).parameters
        for key, group_name in cls.grouped_fields().items():
            if key in kwargs and key not in params:
                raise TypeError(f"{cls.__name__}() takes {key} in its {group_name} group now: pass "
                                f"{group_name}={{{key!r}: {kwargs[key]!r}}} (model.init_args.{group_name}.{key})")
        return super().__new__(cls)

    @classmethod
    def value_groups(cls) -> dict[str, Any]:
        """The constructor's groups whose every field has a value (``optim``, ``loss``): name -> its default."""
        return {p.name: p.default for p in inspect.signature(cls.__init__).parameters.values()
                if dataclasses.is_dataclass(p.default) and not isinstance(p.default, type)
                and p.name not in cls.settings_groups}

    @classmethod
    def grouped_fields(cls) -> dict[str, str]:
        """Each field of the value groups -> its group (``{lr: optim, vel_weight: loss, ...}``)."""
        return {f.name: name for name, default in cls.value_groups().items() for f in dataclasses.fields(default)}

    @classmethod
    def value_group(cls, name: str, value: Any) -> Any:
        """The constructor's argument ``name`` (a value group: None, the group or a mapping of some of its fields)
        as the group, the fields it leaves out the class's defaults."""
        return group(cls.value_groups()[name], value, f"model.init_args.{name}")

    @classmethod
    def checkpoint_hparams(cls, hparams: dict[str, Any], state: dict[str, Tensor]) -> dict[str, Any]:
        """A checkpoint's hyper-parameters as this class reads them (``omg.lit.checkpoint.load_module``): the
        fields of a value group (``lr``, ``vel_weight``) that a checkpoint written before the groups holds
        flat, in their group."""
        return regroup(hparams, cls.grouped_fields())[0]

    def attached_trainer(self) -> L.Trainer | None:
        """The Trainer this module is attached to, None outside a run (``self.trainer`` raises there)."""
        try:
            return self.trainer
        except RuntimeError:
            return None

    def save_hyperparameters(self, *args, frame=None, **kwargs) -> None:
        super().save_hyperparameters(*args, frame=frame or inspect.currentframe().f_back, **kwargs)
        # plain types (checkpoints load weights-only, loggers write YAML); a second call updates
        # both the hyper-parameters and the initial copy that loggers record
        plain = {}
        if isinstance(spec := self.hparams.get("spec"), DataSpec):
            plain["spec"] = spec.to_dict()
        for key in self.value_groups():
            # every field, as plain types: a family's defaults may change, a checkpoint keeps what it trained with
            if key in self.hparams:
                value = self.value_group(key, self.hparams[key])
                plain[key] = {f.name: _plain(getattr(value, f.name)) for f in dataclasses.fields(value)}
        for key, overrides in self.settings_groups.items():
            # a typed group (or the mapping LightningCLI dumps of it, every field listed) kept as the
            # mapping of the keys it sets, None where it sets none (the default): what checkpoints
            # written before the groups were typed hold
            if (value := self.hparams.get(key)) is not None:
                plain[key] = set_fields(overrides, value, f"model.init_args.{key}") or None
        if plain:
            super().save_hyperparameters(plain)

    def state_dict(self, *args, **kwargs):
        state = super().state_dict(*args, **kwargs)
        return {k: v for k, v in state.items() if not k.startswith(self.frozen_prefixes)}

    def load_state_dict(self, state_dict, strict: bool = True, assign: bool = False):
        missing, unexpected = super().load_state_dict(state_dict, strict=False, assign=assign)
        missing = [k for k in missing if not k.startswith(self.frozen_prefixes)]
        if strict and (missing or unexpected):
            raise RuntimeError(f"checkpoint does not fit {type(self).__name__}: missing {missing[:5]}, "
                               f"unexpected {unexpected[:5]}")
        return missing, unexpected

    # -- one training step: the family's losses, the one guard against a non-finite loss, logging ----------
    loss_name = "loss"  # how the one-line error of a non-finite loss names it

    def training_losses(self, batch: dict) -> dict[str, Tensor] | None:
        """The batch's training losses: ``loss`` (what is minimised) and the terms to log beside it; None
        skips the batch."""
        raise NotImplementedError(f"{type(self).__name__} does not say how a batch is trained on")

    def training_step(self, batch: dict, batch_idx: int) -> Tensor | None:
        losses = self.training_losses(batch)
        if losses is None:
            return None
        check_finite(losses["loss"], self.global_step, batch, what=self.loss_name,
                     hint="lower model.optim.lr, enable gradient clipping", terms=losses)
        self.log_training(losses, batch)
        return losses["loss"]

    def log_training(self, losses: dict[str, Tensor], batch: dict) -> None:
        """Log a training step's losses as ``train/<term>``: the loss at every step, the other terms at the
        steps the logger writes (``logs_terms``)."""
        n = len(batch["motion"])
        self.log("train/loss", losses["loss"], prog_bar=True, batch_size=n)
        if self.logs_terms():
            self.log_dict({f"train/{k}": v for k, v in losses.items() if k != "loss"}, prog_bar=True, batch_size=n)

    def logs_terms(self) -> bool:
        """Whether this training step logs its terms beside the loss: at the steps whose values the logger
        writes, every ``trainer.log_every_n_steps`` optimizer steps (a step-level value logged between them
        reaches no logger), as litgpt and torchtitan log at an interval: each Lightning ``self.log`` call costs
        a small model's step a noticeable share (docs/results/performance.md). The progress bar shows the terms
        as of the last such step and the loss of every step. ``log_every_n_steps`` 0: none."""
        every = self.trainer.log_every_n_steps
        return every > 0 and ((self.global_step + 1) % every == 0 or self.trainer.should_stop)

    def trainable_module(self) -> nn.Module:
        """The part of the module that training changes (its optimizer groups and its EMA)."""
        return self

    def optimizer_groups(self) -> list[dict]:
        """The optimizer's parameter groups; by default every trainable parameter with ``weight_decay``."""
        return [{"params": [p for p in self.parameters() if p.requires_grad]}]

    def make_optimizer(self, groups: list[dict]) -> torch.optim.Optimizer:
        """The optimizer over ``groups``: AdamW with ``optim``'s lr, betas and weight_decay."""
        optim = self.optim
        # foreach: all tensors in each operation, the same numbers bit for bit. torch picks it itself for CUDA
        # tensors only; on the CPU its default loops over the parameters in Python, about a tenth of a small
        # model's step
        return torch.optim.AdamW(groups, lr=optim.lr, weight_decay=optim.weight_decay, betas=tuple(optim.betas),
                                 foreach=True)

    def lr_factor(self, total_steps: int) -> Callable[[int], float] | None:
        """The LR multiplier of each optimizer step of a run of ``total_steps`` (None: the LR stays
        ``optim.lr``): linear warm-up over ``optim.warmup_steps``, then cosine decay to 0."""
        return warmup_cosine(self.optim.warmup_steps, total_steps)

    def configure_optimizers(self):
        optimizer = self.make_optimizer(self.optimizer_groups())
        factor = self.lr_factor(int(self.trainer.estimated_stepping_batches))
        if factor is None:
            return optimizer
        scheduler = torch.optim.lr_scheduler.LambdaLR(optimizer, factor)
        return {"optimizer": optimizer, "lr_scheduler": {"scheduler": scheduler, "interval": "step"}}

    # -- the weight EMA: created at fit start, updated once per optimizer step, saved and restored
    # with the checkpoint, swapped in for sampling (``ema_weights``) --------------------------------
    def on_fit_start(self) -> None:
        if self.ema_decay > 0 and self.ema is None:
            self.ema = EMA(self.trainable_module(), self.ema_decay)

    def optimizer_step(self, *args, **kwargs) -> None:
        super().optimizer_step(*args, **kwargs)
        # Once per real optimizer step, and before checkpoint callbacks see the step (they run in
        # on_train_batch_end). Strategies that accumulate gradients themselves (DeepSpeed) get this call
        # on every micro-batch and step on the last one of each window: the EMA must not average over
        # micro-batches, or its horizon would depend on the accumulation and so on the number of GPUs.
        # Lightning offers no public "was this an accumulation step" (its fit loop's is private).
        if self.ema is not None and not self.trainer.fit_loop._should_accumulate():
            self.ema.update(self.trainable_module())

    def ema_weights(self, use_ema: bool = True):
        """A context in which ``trainable_module()`` holds the EMA weights (when kept and ``use_ema``)."""
        return self.ema.swapped_in(self.trainable_module()) if use_ema and self.ema is not None else nullcontext()

    def on_save_checkpoint(self, checkpoint: dict) -> None:
        # which class to rebuild, also for checkpoints written outside LightningCLI
        checkpoint["module_class"] = f"{type(self).__module__}.{type(self).__qualname__}"
        # when it was written, which orders a run's checkpoints for `--ckpt_path last`
        # (omg.lit.checkpoint.saved_order) also after a copy that did not keep the files' mtimes
        checkpoint["saved_time"] = time.time()
        if self.ema is not None:
            checkpoint["ema"] = self.ema.state_dict()

    def on_load_checkpoint(self, checkpoint: dict) -> None:
        if "ema" in checkpoint and self.ema_decay > 0:
            self.ema = EMA(self.trainable_module(), self.ema_decay)
            self.ema.load_state_dict(checkpoint["ema"])

    def on_train_start(self) -> None:
        start_epoch_after_restored_last_batch(self.trainer)


def _plain(value: Any) -> Any:
    return [_plain(v) for v in value] if isinstance(value, (tuple, list)) else value


def start_epoch_after_restored_last_batch(trainer: L.Trainer) -> None:
    """Count the epoch that a run resumed from an epoch's last batch starts, as the run never
    killed counts it.

    A checkpoint written in ``on_train_batch_end`` of an epoch's last batch (ModelCheckpoint with
    ``every_n_train_steps`` a multiple of the epoch's batches: every periodic checkpoint of the
    shipped configs) holds that epoch as started but not processed. Lightning's ``_FitLoop.reset``
    finishes it on restore (processed, completed), but its restart stage stays "mid-epoch", so
    ``on_advance_start`` treats the next epoch as the one resumed: it neither counts it (ready,
    started) nor calls ``on_train_epoch_start``. The next checkpoint then holds counters one short,
    and a run resumed from one at the following epoch boundary (with validation there) takes the
    finished epoch for the current one: it restarts it, and the data stream replays it. Called
    from ``on_train_start``, after ``reset`` and before the first epoch starts."""
    fit_loop = trainer.fit_loop
    epochs = fit_loop.epoch_progress.total
    if fit_loop.restarted_mid_epoch and epochs.processed == epochs.started:  # reset finished the epoch
        fit_loop.reset_restart_stage()
