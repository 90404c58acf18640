"""Checkpoints in, one fp32 safetensors file out (``omg convert-ckpt``).

Training writes one of two shapes. Lightning writes a ``.ckpt`` file: a pickled dict with the
module's ``state_dict`` beside its extra keys (``hyper_parameters``, ``ema``, ``loops``, ...).
DeepSpeed ZeRO writes a directory, ``last.ckpt/{latest, checkpoint/}``: Lightning's extra keys
ride in the model-states file as DeepSpeed's client state, next to bf16 copies of the weights,
while the fp32 master weights lie flattened in the optimizer-states files, one per rank.
``load_checkpoint`` reads either, or a file written by ``convert``, into one Lightning-style
dict with fp32 weights; ``load_module`` rebuilds the LightningModule from it; ``convert``
writes the file that inference and fine-tuning load without DeepSpeed.
"""

from __future__ import annotations

import contextlib
import importlib
import io
import json
import os
import zipfile
from pathlib import Path
from typing import Any

import lightning as L
import torch
from safetensors import SafetensorError, safe_open
from safetensors.torch import save_file

from omg.cli import COMMANDS, ToolParser
from omg.data.shards import atomic_path
from omg.errors import UsageError
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


def class_path(cls: type) -> str:
    return f"{cls.__module__}.{cls.__qualname__}"


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
    elif zipfile.is_zipfile(path):  # torch.save's format
        try:
            ckpt = torch.load(path, map_location="cpu", weights_only=False)  # Lightning pickles non-tensor state
        except RuntimeError:
            ckpt = None
        if not (isinstance(ckpt, dict) and "state_dict" in ckpt):
            raise UsageError(f"{path} is a torch file but not a Lightning checkpoint; {ACCEPTED}")
    elif path.exists():
        raise UsageError(f"{path} is not a checkpoint; {ACCEPTED}")
    else:
        raise UsageError(f"{path}: no such file or directory; {ACCEPTED}")

    hparams = dict(ckpt.get("hyper_parameters") or {})
    hparams.pop("_instantiator", None)  # LightningCLI's; we call the class directly
    module_class = hparams.pop("_class_path", None) or ckpt.get("module_class")  # LightningCLI's, or ours
    state = {k: v.float() if v.is_floating_point() else v for k, v in ckpt["state_dict"].items()}
    return {**ckpt, "state_dict": state, "hyper_parameters": hparams, "ema_weights": ckpt.get("ema_weights", False),
            "module_class": module_class or (class_path(default_class) if default_class else None)}


def _read_deepspeed(path: Path) -> dict[str, Any]:
    if (path / "latest").is_file():
        root, tag = path, (path / "latest").read_text().strip()
    elif any(path.glob("*_model_states.pt")):
        root, tag = path.parent, path.name
    else:
        raise UsageError(f"{path} is a directory without a `latest` file or *_model_states.pt; {ACCEPTED}")
    from deepspeed.utils.zero_to_fp32 import get_fp32_state_dict_from_zero_checkpoint  # slow import: only here

    try:
        # it prints a line per stage and a progress bar: the command prints its own summary
        with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
            weights = get_fp32_state_dict_from_zero_checkpoint(root, tag)
    except (FileNotFoundError, ValueError) as e:
        raise UsageError(f"{path}: unreadable DeepSpeed checkpoint: {e}") from None
    model_file = root / tag / "mp_rank_00_model_states.pt"
    if not model_file.is_file():  # ZeRO-3 writes one per rank
        model_file = root / tag / "zero_pp_rank_0_mp_rank_00_model_states.pt"
    states = torch.load(model_file, map_location="cpu", weights_only=False)
    ckpt = {k: v for k, v in states.items() if k not in DEEPSPEED_KEYS}
    # ZeRO-2 weights are views into one flat fp32 buffer per group: clone so each owns its storage.
    # Lightning < 2.1 wrapped the module, so its names carry the wrapper's attribute.
    ckpt["state_dict"] = {k.removeprefix("_forward_module."): v.clone() for k, v in weights.items()}
    return ckpt


def _read_safetensors(path: Path) -> dict[str, Any]:
    try:
        with safe_open(path, "pt") as f:
            metadata, state = f.metadata() or {}, {k: f.get_tensor(k) for k in f.keys()}
    except SafetensorError as e:
        raise UsageError(f"{path} is not a readable safetensors file ({e}); {ACCEPTED}") from None
    if missing := [k for k in METADATA_KEYS if k not in metadata]:
        raise UsageError(f"{path} lacks omg metadata ({', '.join(missing)}); write it with `omg convert-ckpt`")
    return {"state_dict": state, **{k: json.loads(metadata[k]) for k in METADATA_KEYS}}


def _import_class(name: str | None, src: PathLike) -> type[L.LightningModule]:
    if name is None:
        raise UsageError(f"{src} does not say which LightningModule it holds; pass default_class")
    module, _, attr = name.rpartition(".")
    try:
        cls = getattr(importlib.import_module(module), attr)
    except (ImportError, AttributeError, ValueError):
        raise UsageError(f"{src} holds a {name} checkpoint, and {name} cannot be imported here") from None
    if not (isinstance(cls, type) and issubclass(cls, L.LightningModule)):
        raise UsageError(f"{src} names {name} as its module, which is not a LightningModule")
    return cls


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
    class (or a base class) the caller needs.
    """
    ckpt = load_checkpoint(path, default_class)
    cls = _import_class(ckpt["module_class"], path)
    if expect is not None and not issubclass(cls, expect):
        raise UsageError(f"{path} holds a {class_path(cls)} checkpoint, not a {class_path(expect)}")
    module = cls(**ckpt["hyper_parameters"])
    module.load_state_dict(ckpt["state_dict"])
    module.to(map_location)  # before the EMA is rebuilt, so that it lands on the same device
    module.on_load_checkpoint(ckpt)
    if use_ema and getattr(module, "ema", None) is not None:
        module.ema.copy_to(module.trainable_module())
    return module.eval()


def convert(src: PathLike, dst: PathLike, ema: bool = False,
            default_class: type[L.LightningModule] | None = PretrainModule) -> dict[str, Any]:
    """Write ``src``'s weights (with ``ema``: the EMA in place of the ``model.`` parameters) as one
    fp32 safetensors file whose metadata lets ``load_module`` rebuild the module."""
    dst = Path(dst)
    if dst.suffix != ".safetensors":
        raise UsageError(f"{dst}: the output file must end in .safetensors")
    ckpt = load_checkpoint(src, default_class)
    state = dict(ckpt["state_dict"])
    if ema and not ckpt["ema_weights"]:
        if "ema" not in ckpt:
            raise UsageError(f"{src} has no EMA weights (trained with model.ema_decay=0?); convert without --ema")
        shadow = ckpt["ema"]["shadow"]  # names inside module.model
        if unknown := [n for n in shadow if f"model.{n}" not in state]:
            raise UsageError(f"{src}: the EMA holds model.{unknown[0]}, which the module's weights lack")
        state.update({f"model.{n}": t.float() for n, t in shadow.items()})
    ema_weights = ema or ckpt["ema_weights"]
    metadata = {"format": "pt", "module_class": json.dumps(ckpt["module_class"]),
                "hyper_parameters": json.dumps(ckpt["hyper_parameters"]), "ema_weights": json.dumps(ema_weights)}
    dst.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(dst) as tmp:
        save_file({k: v.contiguous() for k, v in state.items()}, tmp, metadata)
    return {"path": str(dst), "parameters": sum(t.numel() for t in state.values()), "ema_weights": ema_weights,
            "bytes": dst.stat().st_size, "module_class": ckpt["module_class"]}


def main(argv: list[str]) -> None:
    parser = ToolParser(prog="omg convert-ckpt", description=COMMANDS["convert-ckpt"][1])
    parser.add_argument("src", help="a DeepSpeed checkpoint directory, a Lightning .ckpt or a converted .safetensors")
    parser.add_argument("dst", help="the .safetensors file to write")
    parser.add_argument("--ema", action="store_true", help="write the EMA weights instead of the trained ones")
    args = parser.parse_args(argv)
    s = convert(args.src, args.dst, ema=args.ema)
    print(f"wrote {s['path']}: {s['parameters'] / 1e6:.2f}M parameters, {'EMA' if s['ema_weights'] else 'trained'} "
          f"fp32 weights, {s['bytes'] / 2**20:.1f} MiB ({s['module_class']})")
