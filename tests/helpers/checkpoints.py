"""Checkpoint files made by hand: a module's weights and hyper-parameters as omg's loaders read them, the
directory DeepSpeed writes for ZeRO-2, a checkpoint with zeroed weight bytes, and the data spec of the tiny
checkpoint tests (tests/test_checkpoint*.py)."""

from __future__ import annotations

from collections import OrderedDict
from pathlib import Path

import torch

SPEC = {"representation": "humanml3d263", "skeleton": "smpl22", "fps": 20.0, "feature_dim": 263,
        "mean": [0.0] * 263, "std": [1.0] * 263}


def save_module(module: torch.nn.Module, path: str | Path) -> Path:
    """What a trained run's checkpoint holds of ``module`` (weights, hyper-parameters, class), without the
    trainer's state: enough for ``omg generate``, ``omg serve`` and a ControlNet's ``pretrained``."""
    from omg.lit.checkpoint import class_path

    torch.save({"state_dict": module.state_dict(), "hyper_parameters": dict(module.hparams),
                "module_class": class_path(type(module))}, path)
    return Path(path)


def write_zero2_checkpoint(module, client_state: dict, root: Path, prefix: str = "",
                           split_groups: bool = False) -> None:
    """The directory DeepSpeed 0.19 writes for ZeRO-2 bf16 on one rank, as Lightning calls it
    (``engine.save_checkpoint(root, client_state=checkpoint minus state_dict and optimizer_states,
    tag="checkpoint")``); field for field as a real Lightning + DeepSpeed run wrote it.

    The model-states file holds bf16 copies of the weights; the fp32 master weights lie in the
    optimizer-states file as one flat vector per optimizer parameter group, in ``param_shapes``
    order (the optimizer's, not the module's: ``split_groups`` puts 1-d parameters in a first
    group, as a weight-decay split does). Each group is padded to 2 × world size in memory but
    saved without that padding (``group_paddings`` records it); ``param_alignment_paddings`` are
    0 unless ``zero_optimization.parameter_alignment`` is on. The optimizer states hold three
    DeepSpeed classes (a LossScaler, the ZeroStageEnum, fragment_address records), the classes
    omg.lit.checkpoint allow-lists for its weights-only loads.
    """
    import deepspeed
    from deepspeed.runtime.fp16.loss_scaler import LossScaler
    from deepspeed.runtime.zero.config import ZeroStageEnum
    from deepspeed.utils.tensor_fragment import fragment_address

    params = [(prefix + n, p.detach().float()) for n, p in module.named_parameters()]
    groups = [[(n, p) for n, p in params if p.ndim == 1], [(n, p) for n, p in params if p.ndim > 1]] \
        if split_groups else [params]
    flat = [torch.cat([p.flatten() for _, p in group]) for group in groups]
    tag = root / "checkpoint"
    tag.mkdir(parents=True)
    config = {"train_micro_batch_size_per_gpu": 2, "bf16": {"enabled": True}, "zero_optimization": {"stage": 2}}
    torch.save({
        "module": OrderedDict((prefix + k, v.to(torch.bfloat16)) for k, v in module.state_dict().items()),
        "buffer_names": [], "optimizer": None,
        "param_shapes": [OrderedDict((n, p.shape) for n, p in group) for group in groups],
        "frozen_param_shapes": OrderedDict(), "shared_params": {}, "frozen_param_fragments": OrderedDict(),
        "lr_scheduler": None, "data_sampler": None, "random_ltd": None, "skipped_steps": 0, "global_steps": 1,
        "global_samples": 2, "dp_world_size": 1, "mp_world_size": 1,
        "checkpoint_parallel_dimensions": {"dp_world_size": 1, "mp_world_size": 1}, "ds_config": config,
        "ds_version": deepspeed.__version__, **client_state,
    }, tag / "mp_rank_00_model_states.pt")
    torch.save({"optimizer_state_dict": {
        "loss_scaler": LossScaler(scale=1.0), "dynamic_loss_scale": False, "overflow": False, "clip_grad": 0.0,
        "base_optimizer_state": {"state": {}, "param_groups": []},
        "single_partition_of_fp32_groups": flat, "zero_stage": ZeroStageEnum.gradients,
        "group_paddings": [f.numel() % 2 for f in flat], "param_alignment_paddings": [[0] * len(g) for g in groups],
        "partition_count": [1] * len(groups), "ds_version": deepspeed.__version__,
        "param_slice_mappings": [OrderedDict((n, fragment_address(numel=p.numel(), start=start))
                                             for (n, p), start in zip(group, _starts(group))) for group in groups],
    }, "ds_config": config, "ds_version": deepspeed.__version__},
        tag / "bf16_zero_pp_rank_0_mp_rank_00_optim_states.pt")  # "bf16_" because the run is bf16
    (root / "latest").write_text("checkpoint")


def _starts(group):
    starts, offset = [], 0
    for _, p in group:
        starts.append(offset)
        offset += p.numel()
    return starts


def zero_tensor_bytes(src: Path, dst: Path, count: int = 4096) -> None:
    """``src`` with ``count`` bytes zeroed inside the data of its largest tensor: still a valid zip
    that torch.load reads without complaint, with wrong weights."""
    import zipfile

    with zipfile.ZipFile(src) as z:
        info = max(z.infolist(), key=lambda i: i.file_size)
    data = bytearray(src.read_bytes())
    start = info.header_offset + 30 + len(info.filename) + len(info.extra) + info.file_size // 2
    data[start : start + count] = bytes(count)
    dst.write_bytes(bytes(data))
