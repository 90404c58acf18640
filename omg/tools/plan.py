"""``omg bench plan``: per-GPU memory and training time of a pretraining run, before renting the GPUs.

Memory per GPU = model states + communication buffers + activations:

* model states (parameters, gradients, optimizer states) are DeepSpeed's own arithmetic for
  ZeRO-2 and ZeRO-3 (``estimate_zero2_model_states_mem_needs`` / ``estimate_zero3_...``: pure
  functions of the parameter count, they run without a GPU); ZeRO-1 and DDP, which DeepSpeed
  has no estimator for, follow the same byte counts (ZeRO paper, Rajbhandari et al. 2020, Sec. 3).
  The fp32 weight EMA (``omg.lit.ema``) is a whole fp32 copy on every rank whatever the strategy.
* activations are measured, not modelled: the bytes autograd saves for backward
  (``torch.autograd.graph.saved_tensors_hooks``, exact and deterministic) in a forward of the
  flavor's own DiT with one and with two blocks, on the CPU, at a few batch sizes and lengths;
  that fits per-step, per-sample, per-frame and per-frame² terms of one block and of the rest,
  which are then scaled to the run's layers, per-GPU batch and frames.
* time per optimizer step = 3 x the model's forward FLOPs (``DiTConfig.flops``; 4 x with
  activation checkpointing, which runs each block's forward twice) / (GPUs x peak x MFU).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from omg.errors import UsageError
from omg.tools.args import PositiveInt, number_type

Mfu = number_type("Mfu", float, [(">", 0.0), ("<=", 1.0)], "a number in (0, 1]")

# GPU kinds: usable memory (GiB) and dense bf16 peak (TFLOP/s, without 2:4 sparsity), from the
# NVIDIA datasheets (H100 Tensor Core GPU datasheet, SXM and PCIe columns; H200 datasheet;
# A100 datasheet; L40S datasheet)
GPUS: dict[str, tuple[float, float]] = {
    "H100": (80.0, 989.0),  # H100 SXM 80 GB
    "H100-PCIe": (80.0, 756.0),
    "H200": (141.0, 989.0),
    "A100": (80.0, 312.0),  # A100 SXM 80 GB
    "A100-40GB": (40.0, 312.0),
    "L40S": (48.0, 362.0),
}
GpuKind = Literal[tuple(GPUS)]  # type: ignore[valid-type]
Strategy = Literal["ddp", "zero1", "zero2", "zero3"]
GiB = 2**30

# lengths and batches of the activation measurement: three lengths separate the per-frame and
# per-frame² (attention) terms from the per-sample one, a second batch size the per-step one
PROBES = ((1, 16), (1, 32), (1, 64), (2, 16))


# -- activations ------------------------------------------------------------------------------
def saved_bytes(model, x, t, mask, weights: str) -> int:
    """Bytes autograd keeps for backward in one forward of ``model`` (storages counted once,
    parameters not: they are model states)."""
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
        out = model(x, t, mask)
    out.float().square().mean().backward()
    return sum(seen.values())


@dataclass(frozen=True)
class Activations:
    """Saved bytes = step + batch x (sample + frames x frame + frames² x frame2), for one DiT block
    (``block``) and for everything else (``rest``: input and output projections, timestep MLP)."""

    block: tuple[float, float, float, float]
    rest: tuple[float, float, float, float]
    d_model: int
    residual_bytes: int  # bytes per element of the residual stream a checkpointed block keeps

    def bytes(self, layers: int, batch: int, frames: int, checkpointing: bool = False) -> float:
        def term(c):
            return c[0] + batch * (c[1] + frames * c[2] + frames**2 * c[3])

        if not checkpointing:
            return term(self.rest) + layers * term(self.block)
        # a checkpointed block keeps only its input; backward recomputes one block at a time
        return term(self.rest) + layers * batch * frames * self.d_model * self.residual_bytes + term(self.block)


Weights = Literal["fp32-autocast", "bf16"]


def measure_activations(flavor: str, weights: Weights, input_dim: int = 263) -> Activations:
    """Fit ``Activations`` of a flavor from CPU forwards of its DiT with 1 and 2 blocks.

    ``weights``: fp32-autocast is Lightning's bf16-mixed (DDP); bf16 is DeepSpeed's bf16, whose
    weights and inputs are bf16 without autocast."""
    import numpy as np
    import torch

    from omg.models.dit import DiTConfig, MotionDiT

    dtype = torch.bfloat16 if weights == "bf16" else torch.float32
    fits = []
    for layers in (1, 2):
        torch.manual_seed(0)
        model = MotionDiT(DiTConfig.from_name(flavor, n_layers=layers, input_dim=input_dim)).to(dtype)
        rows, measured = [], []
        for batch, frames in PROBES:
            x = torch.randn(batch, frames, input_dim, dtype=dtype)
            mask = torch.ones(batch, frames, dtype=torch.bool)
            mask[0, frames // 2:] = False  # padded frames, as in training windows shorter than max_len
            measured.append(saved_bytes(model, x, torch.randint(0, 1000, (batch,)), mask, weights))
            rows.append([1, batch, batch * frames, batch * frames**2])
        fits.append(np.linalg.solve(np.array(rows, float), np.array(measured, float)))
    block = fits[1] - fits[0]
    rest = fits[0] - block
    d = DiTConfig.from_name(flavor).d_model
    # under autocast the residual stream is fp32 (x + gate·h with the fp32 modulation table)
    return Activations(tuple(map(float, block)), tuple(map(float, rest)), d,
                       residual_bytes=2 if weights == "bf16" else 4)


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


def bucket_bytes(deepspeed_config: dict, params: int) -> float:
    """ZeRO's gradient reduce and parameter all-gather buffers (bf16): with overlap_comm they
    take 4.5 x the bucket sizes (DeepSpeed's configuration docs, ``overlap_comm``); a bucket
    never holds more than the model."""
    zero = deepspeed_config.get("zero_optimization", {})
    reduce = min(float(zero.get("reduce_bucket_size", 5e8)), params)
    gather = min(float(zero.get("allgather_bucket_size", 5e8)), params)
    return 2 * (reduce + gather) * (4.5 if zero.get("overlap_comm", False) else 1.0)


# -- a run ------------------------------------------------------------------------------------
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


def run_from_config(path: Path) -> Run:
    """The settings of a shipped pretraining config (``configs/pretrain_*.yaml``)."""
    import json

    import yaml

    from omg.files import read_text

    config = yaml.safe_load(read_text(path, "--configs"))
    try:
        model, data, trainer = config["model"], config["data"], config["trainer"]
        if not str(model["class_path"]).endswith("PretrainModule"):
            raise UsageError(f"--configs {path}: {model['class_path']} is not PretrainModule; the planner "
                             "covers DiT pretraining configs (configs/pretrain_*.yaml)")
        args = model.get("init_args", {})
        strategy, offload, ds = trainer.get("strategy", "ddp"), False, {}
        if isinstance(strategy, dict):  # DeepSpeedStrategy with a JSON config
            ds_path = Path(strategy["init_args"]["config"])
            ds = json.loads(read_text(ds_path, f"--configs {path}: its DeepSpeed config"))
            zero = ds.get("zero_optimization", {})
            strategy = f"zero{zero.get('stage', 0)}"
            offload = zero.get("offload_optimizer", {}).get("device", "none") == "cpu"
        if strategy not in ("ddp", "zero1", "zero2", "zero3"):
            raise UsageError(f"--configs {path}: trainer.strategy {strategy!r} is not ddp or DeepSpeed ZeRO 1-3")
        return Run(path.stem, args.get("flavor", "base"), int(data["max_len"]), int(data["batch_size"]),
                   int(trainer.get("accumulate_grad_batches", 1)), strategy,
                   bool(args.get("activation_checkpointing", False)), offload, int(trainer["max_steps"]), ds)
    except (KeyError, TypeError) as e:
        raise UsageError(f"--configs {path}: no {e} where a pretraining config has it") from None


def plan_row(run: Run, gpus: int, gpus_per_node: int, gpu: str, mfu: float,
             activations: dict[tuple[str, str], Activations] | None = None) -> dict:
    """One row of the plan: bytes per GPU by kind, step time, GPU-hours."""
    import torch

    from omg.models.dit import DiTConfig, MotionDiT

    config = DiTConfig.from_name(run.flavor)
    with torch.device("meta"):  # parameters counted from the model's own shapes, with no memory
        model = MotionDiT(config)
    params = sum(p.numel() for p in model.parameters())
    largest = max(m.weight.numel() for m in model.modules() if isinstance(m, torch.nn.Linear))
    weights = "fp32-autocast" if run.strategy == "ddp" else "bf16"
    activations = activations if activations is not None else {}
    if (run.flavor, weights) not in activations:
        activations[(run.flavor, weights)] = measure_activations(run.flavor, weights)
    act = activations[(run.flavor, weights)].bytes(config.n_layers, run.micro_batch, run.frames, run.checkpointing)
    states = model_states(params, largest, run.strategy, gpus, gpus_per_node, run.offload)
    buffers = bucket_bytes(run.deepspeed_config, params) if run.strategy != "ddp" else 4 * params  # DDP's buckets
    total = sum(states.values()) + buffers + act
    memory, peak = GPUS[gpu]
    global_batch = run.micro_batch * run.accumulate * gpus
    flops = (4 if run.checkpointing else 3) * config.flops(global_batch, run.frames)
    step = flops / (gpus * peak * 1e12 * mfu)
    return {"name": run.name, "flavor": run.flavor, "params": params, "global_batch": global_batch,
            **{f"{k}_gib": v / GiB for k, v in states.items()},
            "buffers_gib": buffers / GiB, "activations_gib": act / GiB,
            "total_gib": total / GiB, "fits": total / GiB <= memory, "step_s": step, "steps": run.steps,
            "gpu_hours": step * run.steps * gpus / 3600, "days": step * run.steps / 86400}


def bench_plan(
    configs: tuple[Path, ...] = (),
    flavor: Literal["mini", "base", "large", "huge", "giant"] = "base",
    frames: PositiveInt = 300,
    global_batch: PositiveInt = 256,
    micro_batch: PositiveInt | None = None,
    strategy: Strategy = "ddp",
    activation_checkpointing: bool = False,
    offload: bool = False,
    steps: PositiveInt = 1_000_000,
    gpus: PositiveInt = 8,
    gpus_per_node: PositiveInt = 8,
    gpu: GpuKind = "H100",
    mfu: Mfu = 0.4,
    command: str = "omg bench plan",
) -> list[dict]:
    """Per-GPU memory and training time of DiT pretraining, planned on the CPU.

    Args:
        configs: pretraining configs (configs/pretrain_*.yaml) to plan as shipped, one row each;
            without them, one row from the options below
        flavor: the DiT size
        frames: frames per window
        global_batch: windows per optimizer step, all GPUs together
        micro_batch: windows per GPU per forward (default: global_batch / gpus, no accumulation)
        strategy: ddp, or DeepSpeed ZeRO stage zero1, zero2 or zero3 (bf16)
        activation_checkpointing: recompute block activations in backward
        offload: ZeRO's optimizer states (and with zero3 its parameters) in CPU memory
        steps: optimizer steps of the run (the paper's pretraining: 1M)
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
    if configs:
        runs = [run_from_config(Path(c)) for c in configs]
    else:
        micro = micro_batch or global_batch // gpus
        if micro < 1 or global_batch % (micro * gpus):
            raise UsageError(f"--global_batch {global_batch} is not a multiple of --micro_batch {micro} x "
                             f"--gpus {gpus}")
        ds = {"zero_optimization": {"overlap_comm": True, "reduce_bucket_size": 2e8, "allgather_bucket_size": 2e8}}
        runs = [Run(f"{flavor}", flavor, frames, micro, global_batch // (micro * gpus), strategy,
                    activation_checkpointing, offload, steps, ds)]
    memory, peak = GPUS[gpu]
    measured: dict = {}
    rows = [plan_row(run, gpus, gpus_per_node, gpu, mfu, measured) for run in runs]
    print(f"| run | params | strategy | global batch (micro x accum x GPUs) x frames | params | grads | optimizer "
          f"| EMA | buffers | activations | per GPU | fits {gpu} {memory:.0f} GiB | step @ MFU {mfu:.0%} | steps "
          f"| days | GPU-hours | command |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for run, row in zip(runs, rows):
        how = run.strategy + (" + ckpt" if run.checkpointing else "") + (" + offload" if run.offload else "")
        print(f"| {row['name']} | {row['params'] / 1e6:,.0f}M | {how} | {row['global_batch']} ({run.micro_batch} x "
              f"{run.accumulate} x {gpus} {gpu}) x {run.frames} | {row['params_gib']:.1f} | {row['grads_gib']:.1f} "
              f"| {row['optimizer_gib']:.1f} | {row['ema_gib']:.1f} | {row['buffers_gib']:.1f} "
              f"| {row['activations_gib']:.1f} | {row['total_gib']:.1f} GiB | {'yes' if row['fits'] else '**no**'} "
              f"| {row['step_s'] * 1000:,.0f} ms "
              f"| {row['steps']:,} | {row['days']:.1f} | {row['gpu_hours']:,.0f} | `{command}` |")
    return rows
