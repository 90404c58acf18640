"""``omg bench plan``: per-GPU memory and training time of a pretraining or ControlNet run, before
renting the GPUs.

Memory per GPU = model states + communication buffers + activations:

* model states (parameters, gradients, optimizer states) are DeepSpeed's own arithmetic for
  ZeRO-2 and ZeRO-3 (``estimate_zero2_model_states_mem_needs`` / ``estimate_zero3_...``: pure
  functions of the parameter count, they run without a GPU); ZeRO-1 and DDP, which DeepSpeed
  has no estimator for, follow the same byte counts (ZeRO paper, Rajbhandari et al. 2020, Sec. 3).
  The fp32 weight EMA (``omg.lit.ema``) is a whole fp32 copy on every rank whatever the strategy.
  A ControlNet run applies all of these to its trainable part (block copies + MoC blocks: the
  optimizer's parameters, ``trainable_module()``'s EMA); its frozen parts, the pretrained DiT and
  the text encoder, are weights alone (fp32 under DDP's bf16-mixed, bf16 under DeepSpeed, which
  casts the whole module; split over the GPUs by ZeRO-3, which partitions every parameter).
* activations are measured, not modelled: the bytes autograd saves for backward
  (``torch.autograd.graph.saved_tensors_hooks``, exact and deterministic) in a forward of the
  flavor's own DiT (or ControlNet on it) with one and with two blocks, on the CPU, at a few batch
  sizes and lengths; that fits per-step, per-sample, per-frame and per-frame² terms of one block
  and of the rest, which are then scaled to the run's layers, per-GPU batch and frames.
* time per optimizer step = 3 x the model's forward FLOPs (``DiTConfig.flops``; 4 x with
  activation checkpointing, which runs each block's forward twice) / (GPUs x peak x MFU). A
  ControlNet step is 3 x its trainable part's forward (``MoCConfig.flops``) + 2 x the frozen DiT's
  (its forward, and in backward the gradients of its activations only, which carry the loss back
  to the controllers: ≈ 1 x its forward, with no weight gradients).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Callable, Literal

from omg.errors import UsageError
from omg.files import read_yaml
from omg.tools.args import PositiveInt, number_type
from omg.tools.devices import GPUS

Mfu = number_type("Mfu", float, [(">", 0.0), ("<=", 1.0)], "a number in (0, 1]")

GpuKind = Literal[tuple(GPUS)]  # type: ignore[valid-type]
Strategy = Literal["ddp", "zero1", "zero2", "zero3"]
GiB = 2**30

# lengths and batches of the activation measurement: three lengths separate the per-frame and
# per-frame² (attention) terms from the per-sample one, a second batch size the per-step one
PROBES = ((1, 16), (1, 32), (1, 64), (2, 16))


# -- activations ------------------------------------------------------------------------------
def saved_bytes(model, inputs: tuple, weights: str) -> int:
    """Bytes autograd keeps for backward in one forward ``model(*inputs)`` (storages counted once,
    parameters not: they are model states). The hook sees each tensor as the forward saves it, so no
    backward runs: on a large flavor it would take most of the plan's time and change nothing here."""
    import torch

    params = {p.untyped_storage().data_ptr() for p in model.parameters()}
    seen: dict[int, int] = {}

    def pack(tensor):
        storage = tensor.untyped_storage()
        if storage.data_ptr() not in params:
            seen[storage.data_ptr()] = storage.nbytes()
        return tensor

    autocast = torch.autocast("cpu", dtype=torch.bfloat16, enabled=weights == "fp32-autocast")
    with torch.autograd.graph.saved_tensors_hooks(pack, lambda tensor: tensor), autocast:
        model(*inputs)
    return sum(seen.values())


Terms = tuple[float, float, float, float]  # bytes per step, per sample, per frame, per frame²


@dataclass(frozen=True)
class Activations:
    """Saved bytes = step + batch x (sample + frames x frame + frames² x frame2), for one DiT block
    (``block``) and for everything else (``rest``: input and output projections, timestep MLP).
    For a ControlNet, ``block`` is a controlled layer (frozen block + its copy + its MoC block,
    the text terms of its MoC included) and ``plain`` a layer without a controller."""

    block: Terms
    rest: Terms
    d_model: int
    residual_bytes: int  # bytes per element of the residual stream a checkpointed block keeps
    kept: int = 1  # (B, T, d) tensors a checkpointed layer keeps: its input; a ControlNet's also the copy's output
    plain: Terms = (0.0, 0.0, 0.0, 0.0)

    def bytes(self, layers: int, batch: int, frames: int, checkpointing: bool = False, plain_layers: int = 0) -> float:
        """Saved bytes of ``layers`` blocks (``plain_layers`` of them without a controller)."""

        def term(c: Terms) -> float:
            return c[0] + batch * (c[1] + frames * c[2] + frames**2 * c[3])

        controlled = layers - plain_layers
        if not checkpointing:
            return term(self.rest) + controlled * term(self.block) + plain_layers * term(self.plain)
        # a checkpointed block keeps only its inputs; backward recomputes one layer at a time
        residual = batch * frames * self.d_model * self.residual_bytes
        return term(self.rest) + (controlled * self.kept + plain_layers) * residual + term(self.block)


Weights = Literal["fp32-autocast", "bf16"]


def fit_terms(model, make_inputs: Callable[[int, int], tuple], weights: str) -> Any:
    """(step, sample, frame, frame²) bytes of ``model`` from its saved bytes at ``PROBES``;
    ``make_inputs(batch, frames)`` gives the forward's arguments."""
    import numpy as np

    rows, measured = [], []
    for batch, frames in PROBES:
        measured.append(saved_bytes(model, make_inputs(batch, frames), weights))
        rows.append([1, batch, batch * frames, batch * frames**2])
    return np.linalg.solve(np.array(rows, float), np.array(measured, float))


def motion_inputs(batch: int, frames: int, input_dim: int, dtype) -> tuple:
    """(x, t, mask) of a probe: noisy motion, timesteps and a frame mask with padding."""
    import torch

    x = torch.randn(batch, frames, input_dim, dtype=dtype)
    mask = torch.ones(batch, frames, dtype=torch.bool)
    mask[0, frames // 2:] = False  # padded frames, as in training windows shorter than max_len
    return x, torch.randint(0, 1000, (batch,)), mask


def measure_activations(flavor: str, weights: Weights, input_dim: int = 263) -> Activations:
    """Fit ``Activations`` of a flavor from CPU forwards of its DiT with 1 and 2 blocks.

    ``weights``: fp32-autocast is Lightning's bf16-mixed (DDP); bf16 is DeepSpeed's bf16, whose
    weights and inputs are bf16 without autocast."""
    import torch

    from omg.models.dit import DiTConfig, MotionDiT

    dtype = torch.bfloat16 if weights == "bf16" else torch.float32
    fits = []
    for layers in (1, 2):
        torch.manual_seed(0)
        model = MotionDiT(DiTConfig.from_name(flavor, n_layers=layers, input_dim=input_dim)).to(dtype)
        fits.append(fit_terms(model, lambda b, f: motion_inputs(b, f, input_dim, dtype), weights))
    block = fits[1] - fits[0]
    rest = fits[0] - block
    d = DiTConfig.from_name(flavor).d_model
    # under autocast the residual stream is fp32 (x + gate·h with the fp32 modulation table)
    return Activations(tuple(map(float, block)), tuple(map(float, rest)), d,
                       residual_bytes=2 if weights == "bf16" else 4)


def measure_controlnet_activations(flavor: str, weights: Weights, moc: dict[str, Any], text_tokens: int,
                                   input_dim: int = 263) -> Activations:
    """Fit ``Activations`` of a Motion ControlNet on a flavor from CPU forwards of the real
    ``MotionControlNet`` on a DiT with 1 and 2 blocks, every one controlled (and, when ``moc``
    names its ``layers``, with 2 blocks of which only the first is: the difference is a layer
    without a controller). Every caption has ``text_tokens`` real tokens: a batch's tokens are
    trimmed to its longest caption, so the context length (CLIP: 77) bounds what a batch saves.

    The frozen blocks save what the gradients of their inputs need (the loss reaches the
    controllers through them); the text tokens are the encoder's output, saved by the MoC's
    key/value/gate projections; the encoder itself runs without grad and saves nothing."""
    import torch

    from omg.models.controlnet import MoCConfig, MotionControlNet
    from omg.models.dit import DiTConfig, MotionDiT

    dtype = torch.bfloat16 if weights == "bf16" else torch.float32
    config = MoCConfig(**moc)

    def inputs(batch: int, frames: int) -> tuple:
        x, t, mask = motion_inputs(batch, frames, input_dim, dtype)
        tokens = torch.randn(batch, text_tokens, config.text_dim, dtype=dtype)
        text_mask = torch.ones(batch, text_tokens, dtype=torch.bool)
        return x, t, tokens, text_mask, torch.full((batch,), text_tokens - 1), mask

    def fit(layers: int, controlled: list[int] | None) -> Any:
        torch.manual_seed(0)
        base = MotionDiT(DiTConfig.from_name(flavor, n_layers=layers, input_dim=input_dim))
        net = MotionControlNet(base, MoCConfig(**{**moc, "layers": controlled})).to(dtype)
        return fit_terms(net, inputs, weights)

    one, two = fit(1, None), fit(2, None)
    block = two - one
    rest = one - block
    plain = fit(2, [0]) - one if config.layers is not None else [0.0] * 4
    d = DiTConfig.from_name(flavor).d_model
    # per layer, checkpointing keeps the block's input h_l (the frozen block's and the copy's) and
    # the copy's output (the MoC's input); the parallel stream also its own state
    kept = 3 if config.wiring == "parallel_stream" else 2
    return Activations(tuple(map(float, block)), tuple(map(float, rest)), d,
                       residual_bytes=2 if weights == "bf16" else 4, kept=kept, plain=tuple(map(float, plain)))


# -- model states -----------------------------------------------------------------------------
def model_states(params: int, largest_layer: int, strategy: str, gpus: int, gpus_per_node: int,
                 offload: bool) -> dict[str, float]:
    """Bytes per GPU of parameters, gradients and optimizer states (Adam), and the fp32 EMA.

    ZeRO-2/3 totals are DeepSpeed's estimators' (they also apply to ZeRO-1/DDP's split below);
    the split by kind follows the comment inside them: 2 bytes bf16 parameters, 2 bf16
    gradients, 4 fp32 gradients, 4 fp32 master weights, 8 Adam moments (momentum, variance)."""
    from deepspeed.runtime.zero.stage3 import estimate_zero3_model_states_mem_needs
    from deepspeed.runtime.zero.stage_1_and_2 import estimate_zero2_model_states_mem_needs

    P, N = params, gpus
    if strategy == "ddp":  # Lightning bf16-mixed: fp32 weights, fp32 gradients, fp32 Adam, all replicated
        states = {"params": 4 * P, "grads": 4 * P, "optimizer": 8 * P}
    elif strategy == "zero1":  # bf16 weights and gradients replicated; fp32 grads, master, Adam split
        states = {"params": 2 * P, "grads": 2 * P + 4 * P / N, "optimizer": 12 * P / N}
        if offload:
            states = {"params": 2 * P, "grads": 2 * P, "optimizer": 0}
    elif strategy == "zero2":
        _, total = estimate_zero2_model_states_mem_needs(P, gpus_per_node, N // gpus_per_node, cpu_offload=offload)
        states = {"params": 2 * P, "grads": 0 if offload else 6 * P / N, "optimizer": 0 if offload else 12 * P / N}
        assert abs(sum(states.values()) - total) <= 1, (states, total)  # the split adds up to DeepSpeed's total
    else:  # zero3: everything split; the largest layer is gathered whole in fp32 (DeepSpeed's rule)
        _, total, largest = estimate_zero3_model_states_mem_needs(
            P, largest_layer, gpus_per_node, N // gpus_per_node, cpu_offload=offload, cpu_offload_params=offload)
        # DeepSpeed's ZeRO-3 rule: 18 bytes per parameter over the GPUs; the bf16 gradient
        # partitions are reduced into fp32 ones on the fly, so 4 bytes of gradients are left
        states = {"params": largest + (0 if offload else 2 * P / N), "grads": 0 if offload else 4 * P / N,
                  "optimizer": 0 if offload else 12 * P / N}
        assert abs(sum(states.values()) - total) <= 1, (states, total)
    return {**states, "ema": 4 * P}


def frozen_bytes(params: int, strategy: str, gpus: int, offload: bool) -> float:
    """Bytes per GPU of frozen weights (no gradients, optimizer states or EMA): fp32 under DDP's
    bf16-mixed, bf16 under DeepSpeed (its engine casts the whole module), split over the GPUs by
    ZeRO-3 (it partitions every parameter, trainable or not) and moved to the CPU by its offload."""
    if strategy == "ddp":
        return 4 * params
    if strategy == "zero3":
        return 0 if offload else 2 * params / gpus
    return 2 * params


def bucket_bytes(deepspeed_config: dict, params: int) -> float:
    """ZeRO's gradient reduce and parameter all-gather buffers (bf16): with overlap_comm they
    take 4.5 x the bucket sizes (DeepSpeed's configuration docs, ``overlap_comm``); a bucket
    never holds more than the model."""
    zero = deepspeed_config.get("zero_optimization", {})
    reduce = min(float(zero.get("reduce_bucket_size", 5e8)), params)
    gather = min(float(zero.get("allgather_bucket_size", 5e8)), params)
    return 2 * (reduce + gather) * (4.5 if zero.get("overlap_comm", False) else 1.0)


# -- a run ------------------------------------------------------------------------------------
# The paper's fine-tuning set (OMG Sec. 4.1: 500 epochs of HumanML3D): HumanML3D's training split,
# 23,384 motions with their mirrors (Guo et al., CVPR 2022; the configs' data.batches_per_epoch)
HUMANML3D_TRAIN_CLIPS = 23_384


@dataclass(frozen=True)
class ControlNetStage:
    """What a ControlNet config adds to a run: the MoC settings, its text encoder and the budget."""

    moc: dict[str, Any]  # MoCConfig fields as the config gives them (text_dim comes from the encoder)
    text_encoder: str
    text_encoder_args: dict[str, Any]
    epochs: int = 500  # OMG Sec. 4.1


@dataclass
class Run:
    name: str
    flavor: str
    frames: int
    micro_batch: int
    accumulate: int
    strategy: str
    checkpointing: bool
    offload: bool
    steps: int
    deepspeed_config: dict
    controlnet: ControlNetStage | None = None  # None: DiT pretraining


def pretrained_flavor(path: Path, args: dict) -> str:
    """The flavor of a ControlNet config's frozen DiT: ``model.init_args.base.flavor`` where the
    config gives it, else that of the pretraining config beside it whose run folder
    (``trainer.default_root_dir``) holds ``model.init_args.pretrained``: the checkpoint need not
    exist yet when a run is planned."""
    if isinstance(args.get("base"), dict) and "flavor" in args["base"]:
        return str(args["base"]["flavor"])
    pretrained = Path(str(args.get("pretrained") or ""))
    for other in sorted(path.parent.glob("*.y*ml")):
        try:  # the configs beside it, read as the one given (a FIFO or a python tag among them is not one)
            config = read_yaml(other, f"--configs {path}: the config beside it")
        except UsageError:
            continue
        try:
            model, root = config["model"], Path(config["trainer"]["default_root_dir"])
        except (KeyError, TypeError):
            continue
        if (isinstance(model, dict) and str(model.get("class_path", "")).endswith("PretrainModule")
                and pretrained.is_relative_to(root)):
            return str((model.get("init_args") or {}).get("flavor", "base"))
    raise UsageError(f"--configs {path}: no pretraining config in {path.parent} writes model.init_args.pretrained "
                     f"{str(pretrained)!r} (its trainer.default_root_dir); set model.init_args.base.flavor")


def run_from_config(path: Path, epochs: int = 500) -> Run:
    """The settings of a shipped pretraining or ControlNet config (``configs/pretrain_*.yaml``,
    ``configs/controlnet_*.yaml``); a ControlNet run lasts ``epochs`` epochs."""
    import json

    from omg.files import read_text

    config = read_yaml(path, "--configs")  # the safe loader: a python tag is one line, never run
    kind = "training"  # the module's class, once read
    try:
        model, data, trainer = config["model"], config["data"], config["trainer"]
        kind = str(model["class_path"]).rpartition(".")[2]
        if kind not in ("PretrainModule", "ControlNetModule"):
            raise UsageError(f"--configs {path}: {model['class_path']} is not PretrainModule or ControlNetModule; the "
                             "planner covers DiT pretraining and ControlNet configs (configs/pretrain_*.yaml, "
                             "configs/controlnet_*.yaml)")
        args = model.get("init_args") or {}
        strategy, offload, ds = trainer.get("strategy", "ddp"), False, {}
        if isinstance(strategy, dict):  # DeepSpeedStrategy with a JSON config
            ds_path = Path(strategy["init_args"]["config"])
            try:
                ds = json.loads(read_text(ds_path, f"--configs {path}: its DeepSpeed config"))
            except json.JSONDecodeError as e:
                raise UsageError(f"--configs {path}: its DeepSpeed config {ds_path} is not valid JSON ({e})") from None
            zero = ds.get("zero_optimization", {})
            strategy = f"zero{zero.get('stage', 0)}"
            offload = zero.get("offload_optimizer", {}).get("device", "none") == "cpu"
        if strategy not in ("ddp", "zero1", "zero2", "zero3"):
            raise UsageError(f"--configs {path}: trainer.strategy {strategy!r} is not ddp or DeepSpeed ZeRO 1-3")
        stage, flavor = None, args.get("flavor", "base")
        if kind == "ControlNetModule":  # ControlNetModule's defaults where the config gives none
            from omg.models.controlnet import MoCOverrides
            from omg.settings import set_fields
            from omg.text import text_encoder_kwargs

            # read as the module reads them (a run's saved config.yaml lists every key, null where unset)
            moc = set_fields(MoCOverrides, args.get("moc"), f"--configs {path}: model.init_args.moc")
            stage = ControlNetStage(moc, str(args.get("text_encoder", "minilm")),
                                    text_encoder_kwargs(args.get("text_encoder_args")), epochs)
            flavor = pretrained_flavor(path, args)
        return Run(path.stem, flavor, int(data["max_len"]), int(data["batch_size"]),
                   int(trainer.get("accumulate_grad_batches", 1)), strategy,
                   bool(args.get("activation_checkpointing", False)), offload, int(trainer["max_steps"]), ds, stage)
    except (KeyError, TypeError) as e:
        raise UsageError(f"--configs {path}: no {e} where a {kind} config has it") from None


# The shipped configs' global batch is data.batch_size x accumulate_grad_batches x one 8-GPU node
# (their headers); launch/*.sh keep it on N nodes x G GPUs by recomputing the accumulation
CONFIG_GPUS = 8


def rebatch(run: Run, gpus: int, global_batch: int | None, micro_batch: int | None) -> tuple[Run, str | None]:
    """``run`` on ``gpus`` GPUs at ``global_batch`` (default: the config's own, on its 8 GPUs) with
    ``micro_batch`` windows per GPU (default: the config's): the accumulation is what makes up the
    global batch, as launch/*.sh set it. Returns the run and a line saying what changed (None: nothing)."""
    own = run.micro_batch * run.accumulate * CONFIG_GPUS
    target, micro = global_batch or own, micro_batch or run.micro_batch
    if target % (micro * gpus):
        raise UsageError(f"{run.name}: global batch {target} is not a multiple of micro-batch {micro} x --gpus {gpus}; "
                         "set --micro_batch (or --global_batch)")
    accumulate = target // (micro * gpus)
    if (target, micro, accumulate) == (own, run.micro_batch, run.accumulate) and gpus == CONFIG_GPUS:
        return run, None
    changed = [f"global batch {own} -> {target} (--global_batch)" if target != own
               else f"global batch {own} kept on {gpus} GPU{'s' if gpus > 1 else ''}"]
    if micro != run.micro_batch:
        changed.append(f"micro-batch {run.micro_batch} -> {micro} (--micro_batch)")
    changed.append(f"accumulation {run.accumulate} -> {accumulate}" if accumulate != run.accumulate
                   else f"accumulation {accumulate} kept")
    return replace(run, micro_batch=micro, accumulate=accumulate), f"{run.name}: {', '.join(changed)}"


@dataclass(frozen=True)
class ControlNetParts:
    """Parameter counts of a ControlNet run, from the modules built on the meta device."""

    trainable: int  # block copies + MoC blocks (+ zero projections): the optimizer's and the EMA's
    frozen_dit: int  # the pretrained DiT
    frozen_text: int  # the text encoder
    largest: int  # the largest parameter tensor (ZeRO-3 gathers it whole)
    moc: dict[str, Any]  # MoCConfig fields, text_dim the encoder's
    text_tokens: int  # the encoder's context: the most tokens a batch keeps after trimming


def controlnet_parts(flavor: str, stage: ControlNetStage) -> ControlNetParts:
    """Build the text encoder, the flavor's DiT and the ``MotionControlNet`` on it on the meta
    device (shapes only, no memory, no weight files read) and count their parameters."""
    import torch

    from omg.models.controlnet import MoCConfig, MotionControlNet
    from omg.models.dit import DiTConfig, MotionDiT
    from omg.text import build_text_encoder

    with torch.device("meta"):
        encoder = build_text_encoder(stage.text_encoder, **stage.text_encoder_args)
        moc = {**stage.moc, "text_dim": encoder.dim}
        net = MotionControlNet(MotionDiT(DiTConfig.from_name(flavor)), MoCConfig(**moc))
    trainable = sum(p.numel() for p in net.trainable_parameters())
    return ControlNetParts(trainable, sum(p.numel() for p in net.base.parameters()),
                           sum(p.numel() for p in encoder.parameters()), max(p.numel() for p in net.parameters()),
                           moc, encoder.max_tokens)


def plan_row(run: Run, gpus: int, gpus_per_node: int, gpu: str, mfu: float,
             activations: dict[tuple, Activations] | None = None, clips: int = HUMANML3D_TRAIN_CLIPS,
             text_tokens: int | None = None) -> dict:
    """One row of the plan: bytes per GPU by kind, step time, GPU-hours. A ControlNet run lasts
    its epochs of ``clips`` clips; its captions have ``text_tokens`` tokens (default: the text
    encoder's context)."""
    import torch

    from omg.models.dit import DiTConfig, MotionDiT

    config = DiTConfig.from_name(run.flavor)
    weights = "fp32-autocast" if run.strategy == "ddp" else "bf16"
    activations = activations if activations is not None else {}
    global_batch = run.micro_batch * run.accumulate * gpus
    ckpt = run.checkpointing
    if run.controlnet is None:
        with torch.device("meta"):  # parameters counted from the model's own shapes, with no memory
            model = MotionDiT(config)
        params, frozen, steps = sum(p.numel() for p in model.parameters()), 0, run.steps
        largest = max(m.weight.numel() for m in model.modules() if isinstance(m, torch.nn.Linear))
        key: tuple = (run.flavor, weights)
        if key not in activations:
            activations[key] = measure_activations(run.flavor, weights)
        act = activations[key].bytes(config.n_layers, run.micro_batch, run.frames, ckpt)
        flops = (4 if ckpt else 3) * config.flops(global_batch, run.frames)
    else:
        from omg.models.controlnet import MoCConfig

        parts = controlnet_parts(run.flavor, run.controlnet)
        params, largest = parts.trainable, parts.largest
        frozen = parts.frozen_dit + parts.frozen_text
        tokens = text_tokens or parts.text_tokens
        if tokens > parts.text_tokens:
            raise UsageError(f"--text_tokens {tokens}: {run.name}'s text encoder {run.controlnet.text_encoder} "
                             f"keeps at most {parts.text_tokens} tokens")
        moc = MoCConfig(**parts.moc)
        key = (run.flavor, weights, repr(sorted(parts.moc.items())), tokens)  # moc.layers is a list
        if key not in activations:
            activations[key] = measure_controlnet_activations(run.flavor, weights, parts.moc, tokens)
        plain = config.n_layers - len(moc.controlled_layers(config.n_layers))
        act = activations[key].bytes(config.n_layers, run.micro_batch, run.frames, ckpt, plain_layers=plain)
        # the frozen DiT: its forward, and the gradients of its activations in backward (no weight
        # gradients); the controllers: forward and a full backward; checkpointing runs both forwards
        # twice. The text encoder is left out: its LRU cache (100,000 captions) encodes each caption
        # once per rank, not once per step; even per step, one CLIP ViT-L/14 caption (2 x 85M
        # transformer weights x ~20 tokens ≈ 3.4 GFLOP) is ~1.5% of a Base sample's step (≈ 220 GFLOP)
        flops = ((4 if ckpt else 3) * moc.flops(config, global_batch, run.frames, tokens)
                 + (3 if ckpt else 2) * config.flops(global_batch, run.frames))
        steps = run.controlnet.epochs * clips // global_batch
    states = model_states(params, largest, run.strategy, gpus, gpus_per_node, run.offload)
    states = {"params": states.pop("params"), "frozen": frozen_bytes(frozen, run.strategy, gpus, run.offload),
              **states}
    buffers = bucket_bytes(run.deepspeed_config, params) if run.strategy != "ddp" else 4 * params  # DDP's buckets
    total = sum(states.values()) + buffers + act
    memory, peak = GPUS[gpu]
    step = flops / (gpus * peak * 1e12 * mfu)
    return {"name": run.name, "flavor": run.flavor, "params": params, "frozen": frozen, "global_batch": global_batch,
            **{f"{k}_gib": v / GiB for k, v in states.items()},
            "buffers_gib": buffers / GiB, "activations_gib": act / GiB,
            "total_gib": total / GiB, "fits": total / GiB <= memory, "step_s": step, "steps": steps,
            "epochs": run.controlnet.epochs if run.controlnet else None,
            "gpu_hours": step * steps * gpus / 3600, "days": step * steps / 86400}


def bench_plan(
    configs: tuple[Path, ...] = (),
    flavor: Literal["mini", "base", "large", "huge", "giant"] = "base",
    frames: PositiveInt = 300,
    global_batch: PositiveInt | None = None,
    micro_batch: PositiveInt | None = None,
    strategy: Strategy = "ddp",
    activation_checkpointing: bool = False,
    offload: bool = False,
    steps: PositiveInt = 1_000_000,
    epochs: PositiveInt = 500,
    clips: PositiveInt = HUMANML3D_TRAIN_CLIPS,
    text_tokens: PositiveInt | None = None,
    gpus: PositiveInt = 8,
    gpus_per_node: PositiveInt = 8,
    gpu: GpuKind = "H100",
    mfu: Mfu = 0.4,
    command: str = "omg bench plan",
) -> list[dict]:
    """Per-GPU memory and training time of DiT pretraining and of the Motion ControlNet, planned on the CPU.

    Args:
        configs: pretraining and ControlNet configs (configs/pretrain_*.yaml, configs/controlnet_*.yaml)
            to plan as shipped, one row each; without them, one pretraining row from the options below
        flavor: the DiT size
        frames: frames per window
        global_batch: windows per optimizer step, all GPUs together (default: a config's own, its
            data.batch_size x accumulate_grad_batches x the 8 GPUs it is written for; else 256); a config's
            accumulation is raised or lowered to keep it on --gpus, as launch/*.sh do
        micro_batch: windows per GPU per forward (default: a config's data.batch_size; else global_batch /
            gpus, no accumulation)
        strategy: ddp, or DeepSpeed ZeRO stage zero1, zero2 or zero3 (bf16)
        activation_checkpointing: recompute block activations in backward
        offload: ZeRO's optimizer states (and with zero3 its parameters) in CPU memory
        steps: optimizer steps of the run (the paper's pretraining: 1M)
        epochs: epochs of a ControlNet config's run (the paper's fine-tuning: 500), in steps at its global batch
        clips: clips in an epoch of the fine-tuning set (default: HumanML3D's training split, 23,384
            motions with their mirrors; Guo et al., CVPR 2022)
        text_tokens: caption tokens a ControlNet step sees (default: the text encoder's context, CLIP's 77:
            a batch is trimmed to its longest caption, so this bounds its memory)
        gpus: GPUs in all
        gpus_per_node: GPUs per node (DeepSpeed's estimators take nodes x GPUs per node)
        gpu: the GPU kind: its memory and dense bf16 peak
        mfu: assumed model FLOP utilisation, in (0, 1]
        command: the command line, printed with the results

    Returns:
        One dict per row (memory in GiB, step time in s, GPU-hours).
    """
    if gpus % gpus_per_node and gpus > gpus_per_node:
        raise UsageError(f"--gpus {gpus} is not a whole number of nodes of --gpus_per_node {gpus_per_node}")
    gpus_per_node = min(gpus, gpus_per_node)
    if offload and strategy == "ddp":
        raise UsageError("--offload needs a ZeRO --strategy (zero1, zero2, zero3); DDP keeps everything on the GPU")
    notes: list[str] = []
    if configs:
        runs = []
        for c in configs:
            run, note = rebatch(run_from_config(Path(c), epochs), gpus, global_batch, micro_batch)
            runs.append(run)
            notes += [note] if note else []
    else:
        global_batch = global_batch or 256
        micro = micro_batch or global_batch // gpus
        if micro < 1 or global_batch % (micro * gpus):
            raise UsageError(f"--global_batch {global_batch} is not a multiple of --micro_batch {micro} x "
                             f"--gpus {gpus}")
        ds = {"zero_optimization": {"overlap_comm": True, "reduce_bucket_size": 2e8, "allgather_bucket_size": 2e8}}
        runs = [Run(f"{flavor}", flavor, frames, micro, global_batch // (micro * gpus), strategy,
                    activation_checkpointing, offload, steps, ds)]
    memory, peak = GPUS[gpu]
    measured: dict = {}
    rows = [plan_row(run, gpus, gpus_per_node, gpu, mfu, measured, clips, text_tokens) for run in runs]
    print(f"| run | params (trainable + frozen) | strategy | global batch (micro x accum x GPUs) x frames | params "
          f"| frozen | grads | optimizer | EMA | buffers | activations | per GPU | fits {gpu} {memory:.0f} GiB "
          f"| step @ MFU {mfu:.0%} | steps | wall clock | GPU-hours | command |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for run, row in zip(runs, rows):
        how = run.strategy + (" + ckpt" if run.checkpointing else "") + (" + offload" if run.offload else "")
        count = f"{row['params'] / 1e6:,.0f}M" + (f" + {row['frozen'] / 1e6:,.0f}M" if row["frozen"] else "")
        steps_cell = f"{row['steps']:,}" + (f" ({row['epochs']} epochs)" if row["epochs"] else "")
        wall = f"{row['days']:.1f} d" if row["days"] >= 2 else f"{row['days'] * 24:.1f} h"
        print(f"| {row['name']} | {count} | {how} | {row['global_batch']} ({run.micro_batch} x "
              f"{run.accumulate} x {gpus} {gpu}) x {run.frames} | {row['params_gib']:.1f} "
              f"| {row['frozen_gib']:.1f} | {row['grads_gib']:.1f} | {row['optimizer_gib']:.1f} | {row['ema_gib']:.1f} "
              f"| {row['buffers_gib']:.1f} | {row['activations_gib']:.1f} | {row['total_gib']:.1f} GiB "
              f"| {'yes' if row['fits'] else '**no**'} | {row['step_s'] * 1000:,.0f} ms "
              f"| {steps_cell} | {wall} | {row['gpu_hours']:,.0f} | `{command}` |")
    for note in notes:
        print(f"\n{note}")
    return rows
