"""Checkpoints in, one fp32 safetensors file out (``omg convert-ckpt``).

Training writes one of two shapes. Lightning writes a ``.ckpt`` file: a pickled dict with the
module's ``state_dict`` beside its extra keys (``hyper_parameters``, ``ema``, ``loops``, ...).
DeepSpeed ZeRO writes a directory, ``last.ckpt/{latest, checkpoint/}``: Lightning's extra keys
ride in the model-states file as DeepSpeed's client state, next to bf16 copies of the weights,
while the fp32 master weights lie flattened in the optimizer-states files, one per rank.
``load_checkpoint`` reads either, or a file written by ``convert``, into one Lightning-style
dict with fp32 weights; ``load_module`` rebuilds the LightningModule from it; ``convert``
writes the file that inference and fine-tuning load without DeepSpeed.

Reading a checkpoint never runs code from it. Every pickle is read with
``torch.load(weights_only=True)``, which builds only containers, numbers, strings and tensors
plus the few classes allow-listed below, and refuses anything else (a crafted pickle's
``__reduce__`` is never called): ``UnsafeCheckpoint``. DeepSpeed's own ``zero_to_fp32`` loader
passes ``weights_only=False``; it runs here only after every pickle it will read has passed the
weights-only load, and with torch's ``TORCH_FORCE_WEIGHTS_ONLY_LOAD`` switch on, so that its
loads are weights-only too. The class a checkpoint names is imported only when it is one of
omg's (``omg.lit``) or already imported (a plugin's, the caller's own), and only a
LightningModule subclass is ever instantiated. ``torch.save`` records a CRC-32 of every entry,
which ``torch.load`` does not check: it is checked here, so zeroed or overwritten bytes are a
``CorruptCheckpoint`` rather than silently wrong weights.
"""

from __future__ import annotations

import contextlib
import importlib
import io
import json
import os
import pickle
import re
import struct
import sys
import warnings
import zipfile
import zlib
from pathlib import Path
from typing import Any, Iterable

import lightning as L
import torch
from safetensors import SafetensorError, safe_open
from safetensors.torch import save_file

from omg.errors import UsageError
from omg.files import atomic_path
from omg.lit.pretrain import PretrainModule

PathLike = str | os.PathLike
ACCEPTED = ("expected a Lightning .ckpt file, a DeepSpeed checkpoint directory (the one holding `latest`, "
            "or its tag folder) or a .safetensors file written by `omg convert-ckpt`")
# What DeepSpeed itself puts in the model-states file; everything else there is Lightning's checkpoint.
DEEPSPEED_KEYS = {
    "module", "buffer_names", "optimizer", "param_shapes", "frozen_param_shapes", "shared_params",
    "frozen_param_fragments", "lr_scheduler", "data_sampler", "random_ltd", "skipped_steps", "global_steps",
    "global_samples", "dp_world_size", "mp_world_size", "checkpoint_parallel_dimensions", "ds_config",
    "ds_version", "csr_tensor_module_names",
}
METADATA_KEYS = ("module_class", "hyper_parameters", "ema_weights")  # JSON strings in the safetensors header
OPTIONAL_METADATA_KEYS = ("fit_state",)  # a module's fit-time state, where it keeps one

# The only Python classes (beyond containers, numbers, strings, tensors, dtypes, torch.Size) that a
# checkpoint's pickles may hold, found by saving real checkpoints and listing their globals with
# torch.serialization.get_unsafe_globals_in_checkpoint. The .ckpt files that `omg fit` (LightningCLI)
# and a plain Trainer write for PretrainModule, ControlNetModule and EvaluatorModule hold none:
# hyper-parameters are plain dicts (LightningCLI stores the config's values, not jsonargparse
# Namespaces), paths are strings, the data position, EMA and RNG state are ints and tensors
# (tests/test_checkpoint_safety.py keeps this true).
LIGHTNING_SAFE_GLOBALS: tuple[str, ...] = ()
# A DeepSpeed 0.19 ZeRO-2 checkpoint (bf16, one rank, as Lightning's DeepSpeedStrategy saves it): the
# model-states file holds none; the optimizer-states file holds these. All four are plain records
# (an int enum, two loss-scaler objects restored by __dict__ update, a dataclass of two ints).
DEEPSPEED_SAFE_GLOBALS: tuple[str, ...] = (
    "deepspeed.runtime.zero.config.ZeroStageEnum",  # zero_stage
    "deepspeed.runtime.fp16.loss_scaler.LossScaler",  # loss_scaler (bf16, fp32, static fp16)
    "deepspeed.runtime.fp16.loss_scaler.DynamicLossScaler",  # loss_scaler (fp16 with dynamic scaling)
    "deepspeed.utils.tensor_fragment.fragment_address",  # param_slice_mappings
)
ZIP_MAGIC = b"PK\x03\x04"


class CorruptCheckpoint(UsageError):
    """A checkpoint whose bytes cannot be read back: truncated, zeroed, overwritten, or not a checkpoint."""


class UnsafeCheckpoint(UsageError):
    """A checkpoint whose pickles hold objects that a weights-only load refuses: loading it could run code."""


def class_path(cls: type) -> str:
    return f"{cls.__module__}.{cls.__qualname__}"


# -- reading pickles safely ---------------------------------------------------------------

def _globals(names: Iterable[str]) -> list[type]:
    out = []
    for name in names:
        module, _, attr = name.rpartition(".")
        out.append(getattr(importlib.import_module(module), attr))
    return out


def _check_zip(path: Path) -> None:
    """Raise CorruptCheckpoint unless every entry of the zip that ``torch.save`` wrote is whole and
    matches its CRC-32 (one sequential read of the file; entries saved without a CRC are skipped)."""
    try:
        with zipfile.ZipFile(path) as z, open(path, "rb") as f:
            for info in z.infolist():
                f.seek(info.header_offset)
                header = f.read(30)
                if len(header) < 30 or header[:4] != ZIP_MAGIC:
                    raise CorruptCheckpoint(f"{path} is corrupt: the header of its entry {info.filename} is damaged "
                                            "(zeroed or overwritten bytes); use another checkpoint")
                name_len, extra_len = struct.unpack("<HH", header[26:30])
                if info.compress_type != zipfile.ZIP_STORED or not info.CRC:
                    continue  # torch.save stores entries uncompressed, with a CRC unless switched off
                f.seek(info.header_offset + 30 + name_len + extra_len)
                remaining, crc = info.compress_size, 0
                while remaining:
                    chunk = f.read(min(remaining, 1 << 24))
                    if not chunk:
                        raise CorruptCheckpoint(f"{path} is corrupt: it ends inside its entry {info.filename} "
                                                "(truncated); use another checkpoint")
                    crc, remaining = zlib.crc32(chunk, crc), remaining - len(chunk)
                if crc != info.CRC:
                    raise CorruptCheckpoint(f"{path} is corrupt: the bytes of its entry {info.filename} do not match "
                                            "their checksum (zeroed or overwritten); use another checkpoint")
    except zipfile.BadZipFile as e:
        raise CorruptCheckpoint(f"{path} is corrupt: {e} (a truncated or damaged file); "
                                "use another checkpoint") from None


def _refusal(path: Path, error: Exception) -> str:
    found = (re.search(r"GLOBAL ([\w.]+)", str(error))
             or re.search(r"(?:function|object|got) (<[^>]+>|[\w.]+)", str(error)))
    what = f" ({found.group(1)})" if found else ""
    return (f"{path} holds pickled Python objects{what} that a checkpoint does not contain, and unpickling them could "
            "run code: refused (checkpoints are read with torch.load(weights_only=True)); load only checkpoints "
            "written by omg/Lightning from a source you trust")


def _torch_load(path: Path, allowed: tuple[str, ...] = LIGHTNING_SAFE_GLOBALS, mmap: bool = False) -> Any:
    """``torch.load`` of a torch.save zip file: CRC-checked, weights-only, with ``allowed`` classes."""
    if not zipfile.is_zipfile(path):
        raise CorruptCheckpoint(f"{path} is corrupt: a torch zip file without its central directory "
                                "(truncated?); use another checkpoint")
    _check_zip(path)
    try:
        with torch.serialization.safe_globals(_globals(allowed)):
            return torch.load(path, map_location="cpu", weights_only=True, mmap=mmap)
    except pickle.UnpicklingError as e:
        raise UnsafeCheckpoint(_refusal(path, e)) from None
    except (RuntimeError, EOFError, ValueError, KeyError, IndexError, TypeError) as e:
        reason = " ".join(str(e).split())[:200] or type(e).__name__
        raise CorruptCheckpoint(f"{path} is corrupt: torch cannot read it ({reason}); use another checkpoint") from None


@contextlib.contextmanager
def _weights_only_loads():
    """Every ``torch.load`` in the block is weights-only, also one that passes ``weights_only=False``
    (DeepSpeed's zero_to_fp32): torch's own switch, read at each call."""
    names = ("TORCH_FORCE_WEIGHTS_ONLY_LOAD", "TORCH_FORCE_NO_WEIGHTS_ONLY_LOAD")
    saved = {k: os.environ.pop(k, None) for k in names}
    os.environ["TORCH_FORCE_WEIGHTS_ONLY_LOAD"] = "1"
    try:
        yield
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def _is_torch_zip(path: Path) -> bool:
    with open(path, "rb") as f:
        return f.read(4) == ZIP_MAGIC or zipfile.is_zipfile(path)


# -- reading checkpoints ------------------------------------------------------------------

def recorded_class(ckpt: dict[str, Any]) -> str | None:
    """The LightningModule class a checkpoint names: LightningCLI's ``hyper_parameters._class_path``,
    else the ``module_class`` omg's modules record; None when it names none."""
    hparams = ckpt.get("hyper_parameters") or {}
    return (hparams.get("_class_path") if isinstance(hparams, dict) else None) or ckpt.get("module_class")


def inspect_checkpoint(path: PathLike) -> dict[str, Any]:
    """Check a checkpoint without materialising its weights: ``{"kind": "lightning" | "deepspeed" |
    "safetensors", "module_class", "hyper_parameters", "fit_state"}`` (``fit_state``: what the module filled
    in from its data, None where it keeps none). Every pickle is read (weights-only, tensors
    memory-mapped) and every byte CRC-checked, so that a checkpoint that passes loads; raises
    CorruptCheckpoint, UnsafeCheckpoint or UsageError otherwise."""
    path = Path(path)
    if path.is_dir():
        _, _, states = _deepspeed_states(path)
        return {"kind": "deepspeed", "module_class": recorded_class(states),
                "hyper_parameters": states.get("hyper_parameters"), "fit_state": states.get("fit_state")}
    if path.suffix == ".safetensors" and path.is_file():
        metadata = _safetensors_metadata(path)
        return {"kind": "safetensors", "module_class": metadata["module_class"],
                "hyper_parameters": metadata["hyper_parameters"], "fit_state": metadata.get("fit_state")}
    ckpt = _read_lightning(path, mmap=True)
    return {"kind": "lightning", "module_class": recorded_class(ckpt), "hyper_parameters": ckpt.get("hyper_parameters"),
            "fit_state": ckpt.get("fit_state")}


def load_checkpoint(path: PathLike, default_class: type[L.LightningModule] | None = None) -> dict[str, Any]:
    """Any accepted checkpoint as a Lightning-style dict: fp32 ``state_dict`` (names as in
    ``LightningModule.state_dict()``), ``hyper_parameters``, ``module_class`` (``"pkg.mod.Class"``;
    ``default_class`` where the checkpoint does not say, else None), ``ema`` when the run kept one,
    and ``ema_weights``: True when the weights themselves are already the EMA."""
    path = Path(path)
    if path.is_dir():
        ckpt = _read_deepspeed(path)
    elif path.suffix == ".safetensors" and path.is_file():
        ckpt = _read_safetensors(path)
    else:
        ckpt = _read_lightning(path)

    hparams = dict(ckpt.get("hyper_parameters") or {})
    hparams.pop("_instantiator", None)  # LightningCLI's; we call the class directly
    module_class = hparams.pop("_class_path", None) or ckpt.get("module_class")  # LightningCLI's, or ours
    state = {k: v.float() if v.is_floating_point() else v for k, v in ckpt["state_dict"].items()}
    return {**ckpt, "state_dict": state, "hyper_parameters": hparams, "ema_weights": ckpt.get("ema_weights", False),
            "module_class": module_class or (class_path(default_class) if default_class else None)}


def _read_lightning(path: Path, mmap: bool = False) -> dict[str, Any]:
    if not path.exists():
        raise UsageError(f"{path}: no such file or directory; {ACCEPTED}")
    if not (path.is_file() and _is_torch_zip(path)):  # torch.save's format is a zip file
        raise UsageError(f"{path} is not a checkpoint; {ACCEPTED}")
    ckpt = _torch_load(path, LIGHTNING_SAFE_GLOBALS, mmap=mmap)
    if not (isinstance(ckpt, dict) and isinstance(ckpt.get("state_dict"), dict)):
        raise UsageError(f"{path} is a torch file but not a Lightning checkpoint; {ACCEPTED}")
    return ckpt


def _deepspeed_states(path: Path) -> tuple[Path, str, dict[str, Any]]:
    """(root, tag, rank 0's model states) of a DeepSpeed checkpoint directory, after every pickle in
    its tag folder (the model- and optimizer-states files DeepSpeed's loaders read) passed a
    weights-only load."""
    if (path / "latest").is_file():
        root, tag = path, (path / "latest").read_text().strip()
    elif any(path.glob("*_model_states.pt")):
        root, tag = path.parent, path.name
    else:
        raise UsageError(f"{path} is a directory without a `latest` file or *_model_states.pt; {ACCEPTED}")
    folder = root / tag
    model_files = sorted(folder.glob("*_model_states.pt")) if tag and folder.is_dir() else []
    if not model_files:
        raise CorruptCheckpoint(f"{path} is corrupt: its `latest` file names the tag {tag!r}, and {folder} holds no "
                                "*_model_states.pt (an interrupted save?); use another checkpoint")
    model_file = folder / "mp_rank_00_model_states.pt"
    if not model_file.is_file():  # ZeRO-3 writes one per rank
        model_file = folder / "zero_pp_rank_0_mp_rank_00_model_states.pt"
    if not model_file.is_file():
        raise CorruptCheckpoint(f"{path} is corrupt: {folder} lacks rank 0's model states file; use another checkpoint")
    states = _torch_load(model_file, DEEPSPEED_SAFE_GLOBALS)
    for file in [*model_files, *sorted(folder.glob("*_optim_states.pt"))]:
        if file != model_file:
            _torch_load(file, DEEPSPEED_SAFE_GLOBALS, mmap=True)
    if not isinstance(states, dict):
        raise UsageError(f"{model_file} is not a DeepSpeed model-states file; {ACCEPTED}")
    return root, tag, states


def _read_deepspeed(path: Path) -> dict[str, Any]:
    root, tag, states = _deepspeed_states(path)
    from deepspeed.utils.zero_to_fp32 import get_fp32_state_dict_from_zero_checkpoint  # slow import: only here

    try:
        # it prints a line per stage and a progress bar: the command prints its own summary.
        # Its loads pass weights_only=False: forced weights-only, with the same allow-list.
        with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()), \
                _weights_only_loads(), torch.serialization.safe_globals(_globals(DEEPSPEED_SAFE_GLOBALS)):
            weights = get_fp32_state_dict_from_zero_checkpoint(root, tag)
    except pickle.UnpicklingError as e:
        raise UnsafeCheckpoint(_refusal(root / tag, e)) from None
    except (FileNotFoundError, ValueError, KeyError, RuntimeError) as e:
        raise UsageError(f"{path}: unreadable DeepSpeed checkpoint: {' '.join(str(e).split())[:300]}") from None
    ckpt = {k: v for k, v in states.items() if k not in DEEPSPEED_KEYS}
    # ZeRO-2 weights are views into one flat fp32 buffer per group: clone so each owns its storage.
    # Lightning < 2.1 wrapped the module, so its names carry the wrapper's attribute.
    ckpt["state_dict"] = {k.removeprefix("_forward_module."): v.clone() for k, v in weights.items()}
    return ckpt


def _safetensors_metadata(path: Path) -> dict[str, Any]:
    try:
        with safe_open(path, "pt") as f:
            metadata = f.metadata() or {}
    except SafetensorError as e:
        raise UsageError(f"{path} is not a readable safetensors file ({e}); {ACCEPTED}") from None
    if missing := [k for k in METADATA_KEYS if k not in metadata]:
        raise UsageError(f"{path} lacks omg metadata ({', '.join(missing)}); write it with `omg convert-ckpt`")
    try:
        return {k: json.loads(metadata[k]) for k in (*METADATA_KEYS, *OPTIONAL_METADATA_KEYS) if k in metadata}
    except json.JSONDecodeError as e:
        raise UsageError(f"{path}: its omg metadata is not JSON ({e}); write it with `omg convert-ckpt`") from None


def _read_safetensors(path: Path) -> dict[str, Any]:
    metadata = _safetensors_metadata(path)
    try:
        with safe_open(path, "pt") as f:
            state = {k: f.get_tensor(k) for k in f.keys()}
    except SafetensorError as e:
        raise UsageError(f"{path} is not a readable safetensors file ({e}); {ACCEPTED}") from None
    return {"state_dict": state, **metadata}


# -- classes ------------------------------------------------------------------------------

def resolve_class(name: str | None, src: PathLike) -> type[L.LightningModule]:
    """The LightningModule class ``name`` (``"pkg.mod.Class"``) that a checkpoint ``src`` names.

    A checkpoint's metadata is data: naming a module must not make omg import it (an import runs
    the module's code). Only omg's own modules (``omg.lit``) are imported; any other class must
    live in a module that is already imported (a plugin's, loaded from its entry point before
    anything is parsed, or the caller's own code), and it must be a LightningModule subclass.
    """
    if not name:
        raise UsageError(f"{src} does not say which LightningModule it holds; pass default_class")
    parts = name.split(".")
    if not all(p.isidentifier() for p in parts) or len(parts) < 2:
        raise UsageError(f"{src} names {name!r} as its module, which is not a class path")
    for split in range(len(parts) - 1, 0, -1):  # the longest prefix that is a module
        module = ".".join(parts[:split])
        if module in sys.modules:
            obj: Any = sys.modules[module]
            break
        if module == "omg.lit" or module.startswith("omg.lit."):
            try:
                obj = importlib.import_module(module)
            except ImportError:
                continue
            break
    else:
        raise UsageError(f"{src} holds a {name} checkpoint: omg imports only its own LightningModules (omg.lit) and "
                         f"those of modules already imported (plugins), and {name} is neither")
    try:
        for attr in parts[split:]:
            obj = getattr(obj, attr)
    except AttributeError:
        raise UsageError(f"{src} holds a {name} checkpoint, and {name} cannot be imported here") from None
    if not (isinstance(obj, type) and issubclass(obj, L.LightningModule)):
        raise UsageError(f"{src} names {name} as its module, which is not a LightningModule")
    return obj


def inert_hparams(cls: type, hparams: dict[str, Any]) -> dict[str, Any]:
    """A checkpoint's hyper-parameters without those that name data or files to open
    (``cls.location_hparams``, e.g. OmniMotionGPT's ``human_data``): a checkpoint is inert, so
    loading it never opens what its file names (a ``pipe:`` location would start a process), and
    self-contained, so it loads on a machine where those locations do not exist."""
    drop = set(getattr(cls, "location_hparams", ()))
    grouped = cls.grouped_fields() if callable(getattr(cls, "grouped_fields", None)) else {}
    out = {k: v for k, v in hparams.items() if k not in drop}
    for name in drop:  # a group's field (``source.human_source``), also as older checkpoints hold it flat
        group, _, field = name.partition(".")
        if field and isinstance(out.get(group), dict):
            out[group] = {k: v for k, v in out[group].items() if k != field}
        if field and grouped.get(field) == group:
            out.pop(field, None)
    return out


def _plain(value: Any) -> Any:
    """A hyper-parameter's value as YAML and JSON give it (tuples as lists, mappings as dicts), for comparison."""
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    return value


def _shown(value: Any, width: int = 80) -> str:
    text = json.dumps(_plain(value), default=str)
    return text if len(text) <= width else text[: width - 3] + "..."


def _contradiction(trained: Any, given: Any, key: str) -> tuple[str, str, str] | None:
    """(the key, the checkpoint's value, the run's) where ``given`` says otherwise than ``trained``; None where it
    agrees. A mapping agrees when each field it names has the checkpoint's value (``dit: {n_layers: 2}`` against
    a checkpoint trained with ``{n_layers: 2, d_model: 32}``): the fields it leaves out come from the checkpoint.
    A field the checkpoint does not name was its preset's default, which the names alone do not tell: naming it
    is a contradiction (name the checkpoint's fields only, or leave the mapping out)."""
    trained, given = _plain(trained), _plain(given)
    if trained is None and isinstance(given, dict):  # no overrides (``dit: null``): each field its default
        trained = {}
    if isinstance(trained, dict) and isinstance(given, dict):
        for field, value in given.items():
            if value is None:  # a typed group's unset field (a run's config.yaml lists them all): the checkpoint's
                continue
            if field not in trained:
                return f"{key}.{field}", "its default (the field unset)", _shown(value)
            if found := _contradiction(trained[field], value, f"{key}.{field}"):
                return found
        return None
    return None if trained == given else (key, _shown(trained), _shown(given))


def run_hparams(cls: type | None, hparams: dict[str, Any], given: dict[str, Any], src: PathLike) -> dict[str, Any]:
    """The hyper-parameters a run under ``--ckpt_path`` takes from the checkpoint ``src``: checkpoint < config
    files < command line. ``given``: the model's arguments that the run's config files and command line set
    (their defaults left out). The class's ``architecture_hparams`` (``OmgModule``: what the weights were made
    with) always come from the checkpoint, and a run that gives one of them another value is refused in one
    line naming it; every other hyper-parameter the run gives (sampling, evaluation, the optimizer, loss
    weights) is the run's, and those it does not give are the checkpoint's. A ``null`` given for an
    architecture hyper-parameter (a run's saved config.yaml lists ``base: null``, ``animals: null``, the
    values the module fills in) leaves it to the checkpoint. A value group (``OmgModule.value_groups``: ``optim``,
    ``loss``) is read field by field: the fields the run gives are the run's, the others the checkpoint's."""
    architecture = set(getattr(cls, "architecture_hparams", ()))
    for name in sorted(architecture):  # a hyper-parameter, or a field of a value group (``codebook.code_reset``)
        key, _, field = name.partition(".")
        if key not in given or key not in hparams:
            continue
        trained, says = hparams[key], given[key]
        if field:
            trained = trained.get(field) if isinstance(trained, dict) else None
            says = says.get(field) if isinstance(says, dict) else None
        if says is not None and (found := _contradiction(trained, says, name)):
            name, trained, says = found
            raise UsageError(f"--model.init_args.{name}: the checkpoint {src} was trained with {trained}; this run's "
                             f"config says {says} (what shapes the weights comes from the checkpoint: leave it out, "
                             "or pass a checkpoint trained with it)")
    taken = {k: v for k, v in hparams.items() if k in architecture or k not in given}
    groups = cls.value_groups() if callable(getattr(cls, "value_groups", None)) else {}
    for key in set(groups) & set(given) & set(hparams):
        if isinstance(hparams[key], dict) and isinstance(given[key], dict):
            taken[key] = {f: v for f, v in hparams[key].items() if given[key].get(f) is None}
    return taken


def _check_rebuildable(ckpt: dict[str, Any], src: PathLike) -> None:
    """UsageError for a file that holds weights but nothing to rebuild the module from."""
    if not ckpt["hyper_parameters"] and not recorded_class(ckpt):
        raise UsageError(f"{src} is a bare state dict: it holds weights without the module's hyper-parameters or "
                         f"class, so omg cannot rebuild the model from it; {ACCEPTED}, saved with its "
                         "hyper-parameters (what `omg fit` writes)")


def build_module(cls: type[L.LightningModule], hparams: dict[str, Any], src: PathLike, device: str | None = None):
    """``cls(**hparams)`` without the location hyper-parameters; on the meta device (structure only,
    no weights read) when asked."""
    from lightning.pytorch.core.mixins.hparams_mixin import _given_hyperparameters

    # LightningCLI hands the module it instantiates its config through this variable, which every
    # save_hyperparameters() in that block reads: a module rebuilt here while another is built
    # (HabitPriorModule's VQ-VAE) must record its own hyper-parameters, not the outer module's
    token = _given_hyperparameters.set(None)
    try:
        with torch.device(device) if device else contextlib.nullcontext(), warnings.catch_warnings():
            # a module that loads weights while it is built (ControlNetModule's frozen base) copies onto meta
            warnings.filterwarnings("ignore", message=".*non-meta parameter in the checkpoint to a meta parameter")
            return cls(**inert_hparams(cls, hparams))
    except TypeError as e:
        raise UsageError(f"{src}: its hyper-parameters do not fit {class_path(cls)} ({e})") from None
    finally:
        _given_hyperparameters.reset(token)


def checkpoint_hparams(cls: type, hparams: dict[str, Any], state: dict[str, torch.Tensor]) -> dict[str, Any]:
    """A checkpoint's hyper-parameters as ``cls`` reads them: a class with a ``checkpoint_hparams(hparams,
    state)`` static method reads its older checkpoints' through it (HabitVQModule's from before
    ``habit_order``; OmniMotionModule's from before ``fit_state``)."""
    if callable(upgrade := getattr(cls, "checkpoint_hparams", None)):
        return upgrade(hparams, state)
    return hparams


def rebuild_module(cls: type[L.LightningModule], ckpt: dict[str, Any], src: PathLike, device: str | None = None):
    """``build_module`` from the checkpoint's hyper-parameters (``checkpoint_hparams``), then its fit-time state
    restored (a ``restore_fit_state(ckpt)`` method: what the module filled in from its data, which shapes
    buffers the weights then fill), so that the weights can be checked against it."""
    # the locations dropped first: never read, also where an older checkpoint holds one both flat and grouped
    hparams = checkpoint_hparams(cls, inert_hparams(cls, ckpt["hyper_parameters"]), ckpt["state_dict"])
    module = build_module(cls, hparams, src, device)
    if callable(restore := getattr(module, "restore_fit_state", None)):
        restore(ckpt)
    return module


def _trainable_prefix(module: L.LightningModule, src: PathLike) -> str:
    """The state-dict prefix of the submodule whose parameters the module's EMA tracks
    (``module.trainable_module()``: ``model.`` for PretrainModule, ``controlnet.`` for ControlNetModule)."""
    trainable = module.trainable_module() if callable(getattr(module, "trainable_module", None)) else None
    for name, sub in module.named_modules():
        if sub is trainable:
            return f"{name}." if name else ""
    raise UsageError(f"{src}: {class_path(type(module))} does not say which of its submodules its EMA tracks "
                     "(a trainable_module() method); convert without --ema")


def check_weights(module: L.LightningModule, state: dict[str, torch.Tensor], src: PathLike) -> None:
    """UsageError unless ``state`` holds exactly the module's weights, with their shapes."""
    expected = module.state_dict()
    name = class_path(type(module))
    if missing := [k for k in expected if k not in state]:
        raise UsageError(f"{src} lacks {len(missing)} of the {len(expected)} weights of a {name} (e.g. {missing[0]}): "
                         "not a complete checkpoint of that module")
    if unexpected := [k for k in state if k not in expected]:
        raise UsageError(f"{src} holds {len(unexpected)} weights a {name} does not have (e.g. {unexpected[0]}): "
                         "a checkpoint of another model")
    for k, t in expected.items():
        if tuple(state[k].shape) != tuple(t.shape):
            raise UsageError(f"{src}: {k} has the shape {tuple(state[k].shape)}, where a {name} built from the "
                             f"checkpoint's hyper-parameters has {tuple(t.shape)}")


def load_module(
    path: PathLike,
    default_class: type[L.LightningModule] | None = PretrainModule,
    use_ema: bool = True,
    map_location: str | torch.device = "cpu",
    expect: type[L.LightningModule] | None = None,
) -> L.LightningModule:
    """Rebuild the module from its hyper-parameters and load its weights (strict), in eval mode.

    The module restores its own extras (the EMA) through ``on_load_checkpoint``; with
    ``use_ema`` the EMA weights then replace the trained ones for inference. ``expect``: the
    class (or a base class) the caller needs. A class with a ``checkpoint_hparams(hparams, state)``
    static method reads its older checkpoints' hyper-parameters through it (HabitVQModule's from
    before ``habit_order``).
    """
    ckpt = load_checkpoint(path)
    _check_rebuildable(ckpt, path)
    cls = resolve_class(ckpt["module_class"] or (class_path(default_class) if default_class else None), path)
    if expect is not None and not issubclass(cls, expect):
        raise UsageError(f"{path} holds a {class_path(cls)} checkpoint, not a {class_path(expect)}")
    module = rebuild_module(cls, ckpt, path)
    check_weights(module, ckpt["state_dict"], path)
    module.load_state_dict(ckpt["state_dict"])
    module.to(map_location)  # before the EMA is rebuilt, so that it lands on the same device
    module.on_load_checkpoint(ckpt)
    if use_ema and getattr(module, "ema", None) is not None:
        module.ema.copy_to(module.trainable_module())
    return module.eval()


def convert(src: PathLike, dst: PathLike, ema: bool = False,
            default_class: type[L.LightningModule] | None = PretrainModule) -> dict[str, Any]:
    """Write ``src``'s weights (with ``ema``: the EMA in place of the parameters it tracks, those of
    the module's ``trainable_module()``) as one fp32 safetensors file whose metadata lets
    ``load_module`` rebuild the module. The weights must be exactly those of the module the
    checkpoint names (checked on a structure-only build, on the meta device)."""
    dst = Path(dst)
    if dst.suffix != ".safetensors":
        raise UsageError(f"{dst}: the output file must end in .safetensors")
    ckpt = load_checkpoint(src)
    _check_rebuildable(ckpt, src)
    ckpt["module_class"] = ckpt["module_class"] or (class_path(default_class) if default_class else None)
    cls = resolve_class(ckpt["module_class"], src)
    ckpt["hyper_parameters"] = inert_hparams(cls, ckpt["hyper_parameters"])  # locations are not copied either
    module = rebuild_module(cls, ckpt, src, "meta")  # structure only: names and shapes
    state = dict(ckpt["state_dict"])
    check_weights(module, state, src)
    if ema and not ckpt["ema_weights"]:
        if "ema" not in ckpt:
            raise UsageError(f"{src} has no EMA weights (trained with model.ema_decay=0?); convert without --ema")
        prefix = _trainable_prefix(module, src)
        shadow = ckpt["ema"]["shadow"]  # names inside module.trainable_module()
        if unknown := [n for n in shadow if f"{prefix}{n}" not in state]:
            raise UsageError(f"{src}: the EMA holds {prefix}{unknown[0]}, which the module's weights lack")
        for n, t in shadow.items():
            if tuple(t.shape) != tuple(state[f"{prefix}{n}"].shape):
                raise UsageError(f"{src}: the EMA's {prefix}{n} has the shape {tuple(t.shape)}, the weight "
                                 f"{tuple(state[f'{prefix}{n}'].shape)}")
        state.update({f"{prefix}{n}": t.float() for n, t in shadow.items()})
    ema_weights = ema or ckpt["ema_weights"]
    metadata = {"format": "pt", "module_class": json.dumps(ckpt["module_class"]),
                "hyper_parameters": json.dumps(ckpt["hyper_parameters"]), "ema_weights": json.dumps(ema_weights)}
    if ckpt.get("fit_state") is not None:  # what the module filled in from its data (OmniMotionModule's)
        metadata["fit_state"] = json.dumps(ckpt["fit_state"])
    try:
        dst.parent.mkdir(parents=True, exist_ok=True)
        with atomic_path(dst) as tmp:
            save_file(_unshared(state), tmp, metadata)
    except (OSError, SafetensorError) as e:
        reason = getattr(e, "strerror", None) or " ".join(str(e).split())
        raise UsageError(f"{dst}: cannot write the converted checkpoint there ({reason})") from None
    return {"path": str(dst), "parameters": sum(t.numel() for t in state.values()), "ema_weights": ema_weights,
            "bytes": dst.stat().st_size, "module_class": ckpt["module_class"]}


def _unshared(state: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """Tensors that own their storage: safetensors refuses shared ones, and a module's state_dict
    shares them where one submodule holds another (ControlNetModule: ``controlnet.base`` is ``model``)."""
    out, seen = {}, set()
    for k, v in state.items():
        v = v.contiguous()
        storage = v.untyped_storage()
        if storage.data_ptr() in seen or storage.nbytes() != v.nbytes:
            v = v.clone()
        seen.add(v.untyped_storage().data_ptr())
        out[k] = v
    return out


# -- resuming -----------------------------------------------------------------------------

def _mtime(path: Path) -> float:
    try:
        return path.stat().st_mtime
    except OSError:
        return float("-inf")


def saved_order(path: PathLike) -> tuple[float, int]:
    """When a checkpoint was written, to order a run's checkpoints: the save time it records
    (``saved_time``, which omg's modules write), else its file's mtime; then its global step. Read
    from its pickle alone (weights-only, tensors memory-mapped, no CRC): a file that does not read
    sorts by its mtime, and ``inspect_checkpoint`` decides whether it is whole."""
    path = Path(path)
    if not (path.is_file() and zipfile.is_zipfile(path)):
        return _mtime(path), -1
    try:
        header = torch.load(path, map_location="cpu", weights_only=True, mmap=True)
    except (pickle.UnpicklingError, zipfile.BadZipFile, OSError, RuntimeError, EOFError, ValueError, KeyError,
            IndexError, TypeError):
        return _mtime(path), -1
    if not isinstance(header, dict):
        return _mtime(path), -1
    saved, step = header.get("saved_time"), header.get("global_step")
    return (float(saved) if isinstance(saved, (int, float)) else _mtime(path),
            int(step) if isinstance(step, int) else -1)


def resume_candidate(candidates: Iterable[PathLike], directories: Iterable[PathLike],
                     warn=lambda message: None) -> tuple[Path, dict[str, Any]] | None:
    """What ``--ckpt_path last`` resumes from, with its ``inspect_checkpoint`` header: the newest
    (``saved_order``) of ``candidates`` (the run's checkpoints: Lightning's ``last*.ckpt``, the files
    its ModelCheckpoints write, the ``interrupted.ckpt`` of a SIGTERM or Ctrl-C) that reads and
    passes its CRC check. A ``last.ckpt`` whose write was killed is the older file, and the newer
    periodic checkpoint written just before it wins. When a newer one does not read (truncated, zeroed),
    ``warn`` names it and the one taken. None when there is no candidate at all (Lightning then
    starts afresh, as with its own "last"); a UsageError when none reads (``directories`` name where
    they were looked for), and UnsafeCheckpoint as soon as one holds pickled code."""
    existing = [Path(p) for p in dict.fromkeys(str(Path(c)) for c in candidates) if Path(p).exists()]
    if not existing:
        return None
    problems = []
    for candidate in sorted(existing, key=saved_order, reverse=True):
        try:
            header = inspect_checkpoint(candidate)
        except UnsafeCheckpoint:
            raise
        except UsageError as e:
            problems.append(str(e))
            continue
        if problems:
            warn(f"--ckpt_path last: {problems[0]}; resuming from {candidate} instead, the newest readable "
                 "checkpoint there")
        return candidate, header
    directories = [str(d) for d in directories] or sorted({str(p.parent) for p in existing})
    raise UsageError(f"--ckpt_path last: {problems[0]}; and no other checkpoint in {', '.join(directories)} "
                     "reads; pass a checkpoint with --ckpt_path PATH, or leave it out to start afresh")
