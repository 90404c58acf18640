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
import inspect
import json
import os
import re
import sys
from pathlib import Path
from typing import Any

import lightning as L
import torch
from jsonargparse import Namespace
from jsonargparse.typing import NonNegativeInt
from lightning.pytorch.callbacks import ModelCheckpoint, OnExceptionCheckpoint, RichProgressBar
from lightning.pytorch.cli import LightningArgumentParser, LightningCLI, SaveConfigCallback
from lightning.pytorch.utilities import rank_zero_info, rank_zero_warn

import omg.callbacks  # noqa: F401  (short callback names: EvalCallback, RenderCallback)
import omg.lit  # noqa: F401  (imports the modules so short class names resolve)
from omg.callbacks.progress import PlainProgress
from omg.callbacks.run import InterruptCheckpoint, run_dir
from omg.data.paired import CompanionData, PairedDataModule
from omg.errors import PeerLost, UsageError
from omg.files import check_output_dir
from omg.settings import closest, regroup, set_fields, unknown_key_line
from omg.tools.args import ExactOptions, Settings, unknown_option_line

SPECIAL_CKPT_PATHS = ("last", "best", "hpc")  # resolved by Lightning at run time
FIT_HINT = "see the valid keys with `omg fit --config FILE --print_config`"  # after errors that name no key


class SaveRunConfig(SaveConfigCallback):
    """Saves the run's config.yaml into its versioned run directory (``omg.callbacks.run_dir``)
    rather than ``trainer.log_dir``, which for wandb is a directory shared by every run."""

    def setup(self, trainer: L.Trainer, pl_module: L.LightningModule, stage: str) -> None:
        if self.already_saved:
            return
        directory = run_dir(trainer)
        if trainer.is_global_zero:
            directory.mkdir(parents=True, exist_ok=True)
            # the config was checked when it was parsed: a second check would be most of the save's time
            self.parser.save(self.config, str(directory / self.config_filename), skip_none=False, skip_validation=True,
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
    (``max_epochs=-1`` made it read "Epoch 7/-2").

    Through the public hooks: after Lightning's ``on_train_epoch_start`` (and ``on_train_batch_end``,
    which makes the bar when a run resumes mid-epoch) the train task's description is set again on
    the bar's ``progress``, as RichProgressBar words it, without the total."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.retitled: tuple | None = None  # (task, epoch) whose description was last set here

    def retitle(self, trainer: L.Trainer) -> None:
        """The train task's description without the total, once per task and epoch."""
        if trainer.max_epochs is not None and trainer.max_epochs >= 0:
            return
        if self.progress is None or self.train_progress_bar_id is None:
            return
        if self.retitled == (self.train_progress_bar_id, trainer.current_epoch):
            return
        self.retitled = (self.train_progress_bar_id, trainer.current_epoch)
        description = f"Epoch {trainer.current_epoch}"
        if self.theme.description:
            description = f"[{self.theme.description}]{description}"
        self.progress.update(self.train_progress_bar_id, description=description)

    def on_train_epoch_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        super().on_train_epoch_start(trainer, pl_module)
        self.retitle(trainer)

    def on_train_batch_end(self, trainer: L.Trainer, pl_module: L.LightningModule, *args, **kwargs) -> None:
        super().on_train_batch_end(trainer, pl_module, *args, **kwargs)
        self.retitle(trainer)


def hpc_resume_path(root_dir: Any) -> str | None:
    """The SLURM requeue checkpoint Lightning loads for ``ckpt_path="hpc"`` (and on its own in a SLURM
    job without a ckpt_path): ``hpc_ckpt_N.ckpt`` with the highest N in ``root_dir``, the trainer's
    default_root_dir, joined as Lightning joins it. Lightning's own answer is a property of its
    private checkpoint connector; this is the same choice, from the folder."""
    from lightning.fabric.utilities.cloud_io import get_filesystem

    root = str(root_dir)
    fs = get_filesystem(root)
    if not fs.isdir(root):
        return None
    versions = []
    for name in (os.path.basename(str(p).rstrip("/")) for p in fs.ls(root, detail=False)):
        if "hpc_ckpt_" in name and (digits := re.sub("[^0-9]", "", name.split("hpc_ckpt_")[-1])):
            versions.append(int(digits))
    if not versions:
        return None
    name = f"hpc_ckpt_{max(versions)}.ckpt"
    return os.path.join(root, name) if "://" not in root else root.rstrip(fs.sep) + fs.sep + name


def last_checkpoints(callback: ModelCheckpoint) -> list[Path]:
    """The ``last*.ckpt`` files in a ModelCheckpoint's folder (``last.ckpt``, ``last-v1.ckpt``, ...),
    the files Lightning looks among for ``ckpt_path="last"``."""
    from lightning.fabric.utilities.cloud_io import get_filesystem

    if callback.dirpath is None:
        return []
    fs = get_filesystem(str(callback.dirpath))
    if not fs.exists(str(callback.dirpath)):
        return []
    pattern = rf"^{re.escape(callback.CHECKPOINT_NAME_LAST)}(-(\d+))?"
    return sorted(Path(os.path.normpath(p)) for p in fs.ls(str(callback.dirpath), detail=False)
                  if Path(p).suffix == callback.FILE_EXTENSION and re.match(pattern, Path(p).stem))


def earlier_last(callback: ModelCheckpoint) -> str | None:
    """The warning for a new run whose ModelCheckpoint finds a ``last.ckpt`` of an earlier run in its
    folder: Lightning then writes ``last-vN.ckpt`` beside it, and a config that reads ``last.ckpt`` (a
    ControlNet's ``model.init_args.pretrained``) would read the old run's weights, silently. Warned
    rather than overwritten: the old file may be the only copy of a long run."""
    if not callback.save_last or callback.dirpath is None:
        return None
    folder = Path(callback.dirpath)
    name, suffix = callback.CHECKPOINT_NAME_LAST, callback.FILE_EXTENSION
    if not (folder / f"{name}{suffix}").is_file():
        return None
    version = callback.STARTING_VERSION  # the first name Lightning's version counter finds free
    while (folder / f"{name}{callback.CHECKPOINT_JOIN_CHAR}v{version}{suffix}").exists():
        version += 1
    return (f"{folder / (name + suffix)} is from an earlier run: this run writes "
            f"{name}{callback.CHECKPOINT_JOIN_CHAR}v{version}{suffix} beside it, and a config that reads "
            f"{name}{suffix} (model.init_args.pretrained) keeps reading the old one; resume it with --ckpt_path last, "
            "or give this run its own trainer.default_root_dir")


def model_clip_sampling(model: Any) -> str:
    """The ``clip_sampling`` of the model class a parsed config names (``model: CLASS`` or its
    ``class_path``): what ``data.clips: auto`` cuts; ``windows`` for a class that names none."""
    name = model.get("class_path") if hasattr(model, "get") else model
    cls = LightningSettings.model_class([("model", str(name), True)]) if name else None
    return getattr(cls, "clip_sampling", "windows")


def _fields(group: Any) -> Any:
    """A parsed settings group (a Namespace of its fields, a mapping, None) as ``set_fields`` reads it."""
    return group.as_dict() if isinstance(group, Namespace) else group


def grouped_settings(cls: type | None = None) -> dict[str, str]:
    """The settings of the model class ``cls`` that live in a group now, by their older flat name: ``{lr: optim,
    vel_weight: loss, ...}`` (``OmgModule.grouped_fields``). Where the class is not known, those of every omg
    module but the names that one of them takes as its own parameter (HabitVQModule's ``codebook.ema_decay`` is
    every other module's weight EMA, ``ema_decay``)."""
    if cls is not None:
        return cls.grouped_fields() if callable(getattr(cls, "grouped_fields", None)) else {}
    modules = [getattr(omg.lit, name) for name in omg.lit.__all__]
    own = {name for module in modules for name in inspect.signature(module.__init__).parameters}
    return {key: group for module in modules for key, group in module.grouped_fields().items() if key not in own}


def _warn_regrouped(key: str, group: str) -> None:
    rank_zero_warn(f"model.init_args.{key} is read as model.init_args.{group}.{key}, where it is set now")


def regroup_args(args: list[str], cls: type | None = None) -> list[str]:
    """``args`` with each older flat module setting (``--model.init_args.lr 1e-3``, ``--model.lr=1e-3``) of the
    model class ``cls`` given as its group's field (``--model.init_args.optim.lr``), with one warning line naming
    the new key."""
    keys, out = grouped_settings(cls), []
    for i, arg in enumerate(args):
        if arg == "--":
            return out + args[i:]
        name, sep, value = arg.partition("=")
        key = name.removeprefix("--model.").removeprefix("init_args.") if name.startswith("--model.") else None
        if key in keys:
            _warn_regrouped(key, keys[key])
            arg = f"--model.init_args.{keys[key]}.{key}{sep}{value}"
        out.append(arg)
    return null_group_fields(out, cls)


YAML_NULLS = ("null", "Null", "NULL", "~")


def null_group_fields(args: list[str], cls: type | None) -> list[str]:
    """``args`` with each group field of the model class ``cls`` set to null on the command line
    (``--model.init_args.source.retrieval_bank=null``) given as a mapping of the group
    (``--model.init_args.source={"retrieval_bank": null}``, which keeps the group's other fields). jsonargparse
    reads a null for a dotted field of a dataclass inside a subclass's ``init_args`` as the string ``'None'``."""
    groups = set(cls.value_groups()) | set(cls.settings_groups) if callable(getattr(cls, "value_groups", None)) else ()
    out, i = [], 0
    while i < len(args):
        arg = args[i]
        if arg == "--":
            return out + args[i:]
        name, sep, value = arg.partition("=")
        if not sep and i + 1 < len(args):
            value = args[i + 1]
        group_name, _, field = name.removeprefix("--model.init_args.").partition(".")
        if (name.startswith("--model.init_args.") and group_name in groups and field and "." not in field
                and value in YAML_NULLS):
            out.append(f"--model.init_args.{group_name}={json.dumps({field: None})}")
            i += 1 if sep else 2
            continue
        out.append(arg)
        i += 1
    return out


def regroup_init_args(init_args: dict[str, Any], cls: type | None = None) -> dict[str, Any]:
    """A config's ``model.init_args`` with each older flat module setting (``lr: 1e-3``) of the model class ``cls``
    moved into its group (``optim: {lr: 1e-3}``), with one warning line naming the new key; one line where both
    name a field."""
    out, moved = regroup(init_args, grouped_settings(cls))
    for key, group in moved:
        _warn_regrouped(key, group)
    return out


def _load_config(text: str) -> Any:
    """jsonargparse's YAML loader, older flat module settings in a config's ``model.init_args`` (or a
    ``--model`` file's ``init_args``) read into their groups (``regroup_init_args``)."""
    from jsonargparse import get_loader

    value = get_loader("yaml")(text)
    model = value.get("model") if isinstance(value, dict) else None
    if isinstance(value, dict) and str(value.get("class_path")).rpartition(".")[2] in omg.lit.__all__:
        model = value  # a --model file
    if isinstance(model, dict) and isinstance(model.get("init_args"), dict):
        cls = LightningSettings.model_class([("model", model, False)])
        model["init_args"] = regroup_init_args(model["init_args"], cls)
    return value


CONFIG_MODE = "omg_yaml"  # the LightningCLI parser's loader: ``_load_config``


SEED_TYPE = bool | int  # LightningCLI's --seed_everything


class LightningSettings(Settings):
    """The types of ``omg fit``'s keys, for ``omg.tools.args.locate``: ``trainer.KEY`` from the Trainer,
    ``data.KEY`` from the data module, ``model.KEY`` / ``model.init_args.KEY`` from the model class
    the settings name (``model: CLASS`` or ``model.class_path``), the subcommand's own arguments
    (``ckpt_path``, ...) from its Trainer method; deeper keys have no type here."""

    def __init__(self, command: str, options: set[str], method_arguments: list[str]):
        super().__init__(options=options)
        self.command, self.method_arguments = command, method_arguments

    @staticmethod
    def parameter_type(cls: Any, name: str) -> Any:
        import typing

        for klass in getattr(cls, "__mro__", [cls]):
            init = getattr(klass, "__init__", None)
            try:
                param = inspect.signature(init).parameters.get(name)
                hints = typing.get_type_hints(init) if param is not None else {}
            except Exception:  # noqa: BLE001 - a signature that cannot be read has no type to check
                return None
            if param is not None and param.kind not in (param.VAR_POSITIONAL, param.VAR_KEYWORD):
                hint = hints.get(name)
                if hint is None or hint is Any:
                    return None
                return typing.Optional[hint] if param.default is None else hint
        return None

    @staticmethod
    def model_class(given: list[tuple[str, Any, bool]]) -> type | None:
        name = None
        for key, value, _ in given:
            if key == "model" and isinstance(value, str):
                name = value
            elif key == "model" and isinstance(value, dict) and isinstance(value.get("class_path"), str):
                name = value["class_path"]
            elif key == "model.class_path" and isinstance(value, str):
                name = value
        if not name:
            return None
        module, _, attr = name.rpartition(".")
        if module:  # a module jsonargparse imported (omg's own are imported with this one); no import here
            return getattr(sys.modules.get(module), attr, None)
        pending, seen = [L.LightningModule], set()
        while pending:  # a short name: the LightningModule subclass of that name
            cls = pending.pop()
            if cls.__name__ == name:
                return cls
            seen.add(cls)
            pending += [c for c in cls.__subclasses__() if c not in seen]
        return None

    def name_of(self, key: str) -> str:
        """``model.KEY`` named ``model.init_args.KEY``, as the model's keys are (its class is chosen);
        ``model.class_path`` named ``model``."""
        root, _, rest = key.partition(".")
        if root == "model" and rest == "class_path":
            return "model"
        if root == "model" and rest and rest.split(".")[0] not in ("init_args", "dict_kwargs"):
            return f"model.init_args.{rest}"
        return key

    def settings_group(self, key: str, given: list[tuple[str, Any, bool]]) -> tuple[type, str] | None:
        """(the typed settings group, the field) a nested model or data key names (``model.init_args.dit.n_layers``:
        ``DiTOverrides``, ``n_layers``; ``data.human.train``: ``CompanionData``, ``train``); None for any other key."""
        import dataclasses
        import typing

        root, _, rest = key.partition(".")
        name, _, field = rest.removeprefix("init_args.").partition(".")
        cls = self.model_class(given) if root == "model" else PairedDataModule if root == "data" else None
        if not field or "." in field or cls is None:
            return None
        hint = self.parameter_type(cls, name)
        group = next((t for t in (*typing.get_args(hint), hint) if isinstance(t, type) and dataclasses.is_dataclass(t)),
                     None)
        return (group, field) if group is not None else None

    def unknown_key(self, key: str, given: list[tuple[str, Any, bool]]) -> str | None:
        import dataclasses

        if (found := self.settings_group(key, given)) is None:
            return None
        group, field = found
        accepted = [f.name for f in dataclasses.fields(group)]
        if field in accepted:
            return None
        name = self.name_of(key)
        return unknown_key_line(name, name.rpartition(".")[0], field, accepted)

    def unknown_option(self, key: str, given: list[tuple[str, Any, bool]]) -> str | None:
        """``Settings.unknown_option``; a model's keys are its class's arguments (``model.init_args.NAME``, or
        ``model.NAME``), a typed group's fields being ``unknown_key``'s to judge."""
        root, _, rest = key.partition(".")
        if root != "model" or not rest:
            return super().unknown_option(key, given)
        rest = rest.removeprefix("init_args.")
        name = rest.partition(".")[0]
        cls = self.model_class(given)
        if cls is None or name in ("class_path", "init_args", "dict_kwargs", "help"):
            return None
        try:
            params = [p.name for p in inspect.signature(cls).parameters.values()
                      if p.kind not in (p.VAR_POSITIONAL, p.VAR_KEYWORD)]
        except (TypeError, ValueError):  # a signature that cannot be read: jsonargparse judges the key
            return None
        if name in params:
            return None
        near = closest(name, params)  # the argument meant, the rest of the key as given (``los.vel_weight``)
        return unknown_option_line(self.name_of(key), f"model.init_args.{near}{rest[len(name):]}" if near else None)

    def type_of(self, key: str, given: list[tuple[str, Any, bool]], value: Any = None) -> Any:
        import typing

        if (found := self.settings_group(key, given)) is not None:  # a typed group's field
            return typing.get_type_hints(found[0]).get(found[1])

        if key in ("model", "model.class_path"):  # a class by name (a mapping would be checked without its data)
            return typing.Optional[L.LightningModule] if isinstance(value, str) else None
        root, _, rest = key.partition(".")
        if not rest:
            if key == "seed_everything":
                return SEED_TYPE
            if key == "progress_every":
                return NonNegativeInt
            if key in self.method_arguments:
                return typing.get_type_hints(getattr(L.Trainer, self.command)).get(key)
            return None
        if root == "model":
            rest = rest.removeprefix("init_args.")
            cls = self.model_class(given)
        else:
            cls = {"trainer": L.Trainer, "data": PairedDataModule}.get(root)
        if cls is None or "." in rest:
            return None
        return self.parameter_type(cls, rest)


class OmgLightningParser(ExactOptions, LightningArgumentParser):
    """LightningCLI's parser taking each option only as spelled in full (``ExactOptions``): also the parsers
    jsonargparse builds below it, for the model's class and the callbacks'."""


class OmgLightningCLI(LightningCLI):
    """``omg fit|validate|test|predict ARGS``: LightningCLI without its own subcommands (``run=False``),
    the command's Trainer-method arguments (``--ckpt_path``, ...) added as LightningCLI adds them, and
    the run started here (``run_command``): checks of ``--ckpt_path`` and the resolution of ``last``
    and ``hpc`` before it, one-line errors after. Parse errors are one UsageError line
    (``omg.tools.args``), dashed option names (``--trainer.max-steps``) taken as the underscored
    ones, and a component refusing its value (a ValueError while the classes are built) is one
    line too. Only LightningCLI's and jsonargparse's public methods are overridden or called."""

    def __init__(self, command: str, args: list[str]):
        import docstring_parser
        import yaml
        from jsonargparse import set_loader

        set_loader(CONFIG_MODE, _load_config, exceptions=(yaml.YAMLError,))
        self.command = command  # LightningCLI's own ``subcommand`` stays None (run=False)
        self.ckpt_fit_state: dict[str, Any] | None = None  # --ckpt_path's, for the module once built
        self.method_arguments: list[str] = []
        doc = docstring_parser.parse(getattr(L.Trainer, command).__doc__ or "").short_description or ""
        super().__init__(
            model_class=L.LightningModule,
            subclass_mode_model=True,
            datamodule_class=PairedDataModule,
            parser_kwargs={"exit_on_error": False, "prog": f"omg {command}", "description": doc,
                           "parser_mode": CONFIG_MODE},
            parser_class=OmgLightningParser,
            save_config_callback=SaveRunConfig,
            save_config_kwargs={"overwrite": True},  # only a run without a logger shares its directory
            args=args,
            run=False,
        )

    # -- parsing --------------------------------------------------------------------------------
    def add_arguments_to_parser(self, parser: LightningArgumentParser) -> None:
        from lightning.pytorch.cli import LRSchedulerTypeTuple
        from torch.optim import Optimizer

        parser.link_arguments("data", "model.init_args.spec", compute_fn=lambda data: data.spec, apply_on="instantiate")
        # what data.clips=auto cuts: the model's clip_sampling, known once the config names its class
        parser.link_arguments("model", "data.clip_sampling", compute_fn=model_clip_sampling, apply_on="parse")
        # the optimizer and scheduler options LightningCLI adds next (added here, so that the command's
        # arguments follow them, in the order of LightningCLI's own subcommands), then the command's
        parser.add_optimizer_args((Optimizer,))
        parser.add_lr_scheduler_args(LRSchedulerTypeTuple)
        skip = set(self.subcommands()[self.command])
        self.method_arguments = list(parser.add_method_arguments(L.Trainer, self.command, skip=skip))
        # every command takes it, so that a fit's saved config.yaml configures omg test and validate too
        parser.add_argument("--progress_every", type=NonNegativeInt, default=50,
                            help="omg fit, when its output is not a terminal: a progress line every N optimizer steps "
                                 "(step, losses, lr, steps/s, time left); 0: none")

    def parse_arguments(self, parser: LightningArgumentParser, args: list[str]) -> None:
        from jsonargparse import ArgumentError

        from omg.tools.args import explain, given_settings, locate, underscore_options

        try:
            keys = list(parser.get_defaults().keys())
        except Exception:  # noqa: BLE001 - defaults that do not parse are reported by the parse itself
            keys = []
        options = {"--config", "--print_config", "-c"} | {f"--{key}" for key in keys}
        settings = LightningSettings(self.command, options, self.method_arguments)
        args = underscore_options(list(args), options)
        args = regroup_args(args, settings.model_class(given_settings(args, settings)))
        self.args = args  # parsed again without defaults under --ckpt_path (``given_model_args``)
        try:
            self.config = parser.parse_args(args)
        except ArgumentError as e:
            raise UsageError(explain(e, hint=FIT_HINT, where=locate(args, settings))) from None

    # -- building -------------------------------------------------------------------------------
    def before_instantiate_classes(self) -> None:
        """``--ckpt_path`` checked (and its hyper-parameters taken, as LightningCLI does); the default
        logger: a versioned CSVLogger in default_root_dir (Lightning's own default is TensorBoard when
        installed, in a lightning_logs/ subfolder)."""
        self.check_ckpt_path()
        self.route_human_data()
        trainer = self.config.trainer
        # before anything is built or run: a file or an unwritable folder would fail only at the first write
        # (a URL, s3://..., is Lightning's to open)
        if "://" not in str(trainer.default_root_dir or ""):
            check_output_dir(trainer.default_root_dir or ".", "trainer.default_root_dir")
        if trainer.logger is None or trainer.logger is True:
            trainer.logger = Namespace(class_path="lightning.pytorch.loggers.CSVLogger",
                                       init_args=Namespace(save_dir=trainer.default_root_dir or ".", name=""))

    def route_human_data(self) -> None:
        """``model.init_args.human_data``, the older place of OmniMotionGPT's human shards, read as ``data.human``
        (one warning line); both set is refused."""
        init_args = (self.config.get("model") or {}).get("init_args")
        human_data = init_args.get("human_data") if init_args is not None else None
        if not set_fields(CompanionData, _fields(human_data), "model.init_args.human_data"):
            return
        if set_fields(CompanionData, _fields((self.config.get("data") or {}).get("human")), "data.human"):
            raise UsageError("model.init_args.human_data and data.human both name the human shards: keep data.human "
                             "only (model.init_args.human_data is its older name)")
        rank_zero_warn("model.init_args.human_data is read as data.human, where the human shards are set now")
        self.config.data.human = human_data
        init_args.human_data = None

    def instantiate_classes(self) -> None:
        from omg.tools.args import explain

        try:
            super().instantiate_classes()
        except UnicodeDecodeError:
            raise
        except ValueError as e:  # a component refused its value (jsonargparse may wrap it in a union check)
            raise UsageError(explain(e)) from None
        if self.ckpt_fit_state is not None and callable(restore := getattr(self.model, "restore_fit_state", None)):
            restore(self.ckpt_fit_state)

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
        if self.command == "fit":
            # a log file gets the bar's redrawn line only at the end: plain lines instead (a terminal keeps the bar)
            if self.config.get("progress_every") and not sys.stdout.isatty():
                trainer.callbacks.append(PlainProgress(self.config.progress_every))
            saver = trainer.checkpoint_callback
            trainer.callbacks.append(InterruptCheckpoint(getattr(saver, "dirpath", None) or default))
        return trainer

    # -- running --------------------------------------------------------------------------------
    def run_command(self) -> None:
        """The command's Trainer method on the model and data, as LightningCLI's subcommands run it,
        after the preflight checks and with the checkpoint to resume from resolved; a non-finite
        loss, a lost peer or a collective timeout ends as one line."""
        from omg.lit.base import NonFiniteLoss

        try:
            self.preflight()
            getattr(self.trainer, self.command)(**self.command_kwargs())
        except NonFiniteLoss as e:  # one line: its step and its batch's clips say where to look
            raise UsageError(str(e)) from None
        except RuntimeError as e:  # a lost peer or a collective timeout (Lightning has torn the run down)
            if (what := distributed_failure(e)) is None:
                raise
            trainer = self.trainer
            again = " with --ckpt_path last to resume from the newest checkpoint" if self.command == "fit" else ""
            raise PeerLost(f"rank {trainer.global_rank} of {trainer.world_size}, step {trainer.global_step}: "
                           f"{what}; start the job again on every node{again}") from None

    def preflight(self) -> None:
        """Callbacks that can judge the model and the data before the run (a ``preflight(model,
        datamodule)`` method, e.g. EvalCallback's evaluator against the data) do so here: the
        Trainer's logger creates the run folder before any callback's ``setup``, which would leave
        it behind, empty, on a refusal there."""
        if self.command == "fit" and callable(check := getattr(self.model, "check_data", None)):
            check(self.datamodule)  # a model that trains on more than data's set (OmniMotionGPT: data.human)
        for callback in self.trainer.callbacks:
            if callable(check := getattr(callback, "preflight", None)):
                check(self.model, self.datamodule)

    # -- --ckpt_path -------------------------------------------------------------------------
    # Lightning reads --ckpt_path twice: LightningCLI right after parsing, to take the model's
    # hyper-parameters from it (and its class: a checkpoint of another class replaced the
    # configured model without a word), and the Trainer when the run starts. Both are checked here
    # first (omg.lit.checkpoint: readable, CRC-checked, no pickled code), so a missing, truncated,
    # zeroed or foreign file, or a checkpoint of another class, is one UsageError line.
    # LightningCLI lets the checkpoint's hyper-parameters override the config and the command line
    # alike; here what the user writes wins (omg.lit.checkpoint.run_hparams), except where it
    # contradicts what the weights were made with.

    def given_model_args(self) -> dict[str, Any]:
        """The model's arguments that this run's config files and command line set, without the
        defaults that the parse adds (jsonargparse's ``defaults=False``)."""
        from jsonargparse import ArgumentError

        from omg.tools.args import explain

        try:
            given = self.parser.parse_args(self.args, defaults=False)
        except ArgumentError as e:  # the same arguments parsed with their defaults: not expected
            raise UsageError(explain(e, hint=FIT_HINT)) from None
        model = given.get("model")
        init_args = model.get("init_args") if isinstance(model, Namespace) else None
        return init_args.as_dict() if isinstance(init_args, Namespace) else {}

    def check_ckpt_path(self) -> None:
        """``--ckpt_path FILE`` checked, and its hyper-parameters become the model's config (as
        LightningCLI does for its subcommands), minus what would read data or run code, and under
        what the run's config files and command line set: checkpoint < config files < command line,
        except for what shapes the weights, which comes from the checkpoint (a run that says
        otherwise is refused; ``omg.lit.checkpoint.run_hparams``)."""
        from omg.lit.checkpoint import checkpoint_hparams, inert_hparams, inspect_checkpoint, run_hparams

        ckpt_path = self.config.get("ckpt_path")
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
        strategy = self.config.get("trainer", {}).get("strategy")
        if header["kind"] == "deepspeed" and "deepspeed" not in str(strategy).lower():
            raise UsageError(f"--ckpt_path {ckpt_path} is a DeepSpeed checkpoint directory, which only a DeepSpeed run "
                             f"restores (trainer.strategy is {strategy!r}); convert it with `omg convert-ckpt` to use "
                             "its weights elsewhere")
        model = self.config.get("model")
        configured = model.get("class_path") if model is not None and hasattr(model, "get") else None
        cls = self.check_ckpt_class(ckpt_path, header["module_class"], configured)
        hparams = dict(header["hyper_parameters"] or {}) if header["kind"] == "lightning" else {}
        # what the module filled in from its data (OmniMotionGPT's human spec, animals, retrieval clips): the
        # module takes it once built, so that the checks before the run (preflight) see the checkpoint's
        self.ckpt_fit_state = {"fit_state": header.get("fit_state"), "hyper_parameters": dict(hparams)}
        hparams.pop("_instantiator", None)
        # where the run reads data (OmniMotionGPT's human_data, a companion checkpoint) comes from the
        # run's config, never from the file: a checkpoint that named a `pipe:` command would run it
        hparams = inert_hparams(cls, hparams) if cls is not None else hparams
        if cls is not None:  # an older checkpoint's, as the class reads them (its fit-time state is restored later)
            hparams = checkpoint_hparams(cls, hparams, {})
        class_path = hparams.pop("_class_path", None)  # LightningCLI's record of the class
        hparams = run_hparams(cls, hparams, self.given_model_args(), ckpt_path)
        if not hparams and class_path is None:  # as LightningCLI: the checkpoint's hyper-parameters become the model's
            return
        if class_path is not None:
            hparams = {"class_path": class_path, "dict_kwargs": hparams}
        try:
            self.config = self.parser.parse_object({"model": hparams}, self.config)
        except SystemExit:
            sys.stderr.write("Parsing of ckpt_path hyperparameters failed!\n")
            raise

    @staticmethod
    def check_ckpt_class(ckpt_path: Any, recorded: str | None, configured: str | type | None) -> type | None:
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

    def hpc_checkpoint(self, ckpt_path: Any) -> str | None:
        """The SLURM checkpoint (``hpc_ckpt_N.ckpt`` in default_root_dir, written when SLURM requeues a
        run) that Lightning would load for ``--ckpt_path hpc``, or on its own in a SLURM job without a
        ``--ckpt_path``, after the checks every other checkpoint passes (omg.lit.checkpoint: readable,
        CRC-checked, no pickled code, the configured model's class); None where Lightning loads none."""
        from lightning.fabric.plugins.environments import SLURMEnvironment

        from omg.lit.checkpoint import inspect_checkpoint

        if ckpt_path != "hpc" and not (ckpt_path is None and SLURMEnvironment.detect()):
            return None
        what = "--ckpt_path hpc" if ckpt_path == "hpc" else "resuming this SLURM job from its requeue checkpoint"
        hpc = hpc_resume_path(self.trainer.default_root_dir)  # Lightning's own choice: the highest N
        if hpc is None:
            if ckpt_path == "hpc":
                raise UsageError(f"--ckpt_path hpc: {self.trainer.default_root_dir} holds no hpc_ckpt_N.ckpt "
                                 "(Lightning writes one when SLURM requeues a run); pass --ckpt_path last or a file")
            return None
        try:
            header = inspect_checkpoint(hpc)
        except UsageError as e:
            raise type(e)(f"{what}: {e}") from None
        self.check_ckpt_class(hpc, header["module_class"], type(self.model))
        return hpc

    def command_kwargs(self) -> dict[str, Any]:
        """The Trainer method's arguments, as LightningCLI passes them (the model, the data module,
        the command's own arguments); before the run: atomic checkpoint writes and no stale
        temporary files in the checkpoint folders (omg.callbacks.checkpoint); ``--ckpt_path last``
        resolved here to the newest of the run's checkpoints that reads and passes its CRC check
        (``resume_candidate``: Lightning's ``last*.ckpt``, the ModelCheckpoints' periodic/top-k
        files, a SIGTERM's checkpoint), with a warning when a newer one does not read;
        ``--ckpt_path hpc`` and SLURM's own resume checked (``hpc_checkpoint``). A run resumed from
        either then brings its top-k folders back to their policy (``TopKHousekeeping``); one
        resumed from a checkpoint named by its path does not (the files of the steps after it are
        the user's to keep)."""
        from omg.callbacks.checkpoint import TopKHousekeeping, prepare_checkpointing, written_checkpoints
        from omg.lit.checkpoint import resume_candidate

        kwargs = {key: self.config_init[key] for key in self.method_arguments if key in self.config_init}
        kwargs["model"] = self.model
        if self.datamodule is not None:
            kwargs["datamodule"] = self.datamodule
        prepare_checkpointing(self.trainer)
        resumed = False  # from the run's own newest checkpoint, whose folder then goes back to its top-k policy
        if hpc := self.hpc_checkpoint(kwargs.get("ckpt_path")):
            kwargs["ckpt_path"], resumed = hpc, True
        if kwargs.get("ckpt_path") == "last":
            callbacks = [cb for cb in self.trainer.checkpoint_callbacks if isinstance(cb, ModelCheckpoint)]
            run = [p for cb in callbacks for p in last_checkpoints(cb)]
            run += [p for cb in callbacks for p in written_checkpoints(cb)]
            run += [Path(cb.ckpt_path) for cb in self.trainer.callbacks  # a SIGTERM's or Ctrl-C's checkpoint
                    if isinstance(cb, (InterruptCheckpoint, OnExceptionCheckpoint)) and Path(cb.ckpt_path).is_file()]
            found = resume_candidate(run, sorted({p.parent for p in run}), warn=rank_zero_warn)
            if found is not None:
                resolved, header = found
                self.check_ckpt_class(resolved, header["module_class"], type(self.model))
                kwargs["ckpt_path"], resumed = str(resolved), True
        if resumed and self.command == "fit":
            self.trainer.callbacks.append(TopKHousekeeping())
        if self.command == "fit" and kwargs.get("ckpt_path") is None:  # a resumed run goes on writing its last.ckpt
            for callback in self.trainer.checkpoint_callbacks:
                if isinstance(callback, ModelCheckpoint) and (warning := earlier_last(callback)):
                    rank_zero_warn(warning)
        return kwargs
