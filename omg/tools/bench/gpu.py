"""``omg bench gpu``: on a machine with one GPU, the GPU figures of docs/results/gpu_check.md, in one
command and one Markdown file (well under 30 minutes on an H100):

1. Base and Giant pretraining through the real ``omg fit`` with the shipped configs
   (``configs/pretrain_base.yaml``: bf16-mixed DDP; ``configs/pretrain_giant.yaml``: bf16 DeepSpeed
   ZeRO-2), on one GPU, a few steps on the repository's mini shards: step time, frames/s, MFU
   (``omg.callbacks.timing.StepTimer``, added to the config's callbacks);
2. Giant guided sampling at batch 1, 8 and 32 in bf16, fast (``dpmpp``, 20 steps) and as in the paper
   (``ddim``, 200 steps), through ``omg bench sample``;
3. the Giant run's DeepSpeed checkpoint converted (``omg convert-ckpt``) and loaded by ``omg generate``.

Each step's output is kept in ``OUT/<step>.log``.

Every step is a subprocess running the ``omg`` CLI, as a user would. ``--dry_run`` (for a machine
without a GPU) resolves each command with ``--print_config`` in this process (the parsers the commands use,
without six more start-ups of Lightning), builds each model on the meta device and prints the commands; nothing
trains.
"""

from __future__ import annotations

import contextlib
import importlib
import io
import json
import shlex
import subprocess
import sys
import time
from pathlib import Path

from omg.errors import UsageError
from omg.tools.args import PositiveFiniteFloat, PositiveInt
from omg.tools.devices import device_peak_tflops

TRAIN_CONFIGS = {"base": "configs/pretrain_base.yaml", "giant": "configs/pretrain_giant.yaml"}
MINI_SHARDS = "shards/mini/human263"


def commands(out: Path, train_steps: int, shards: str, python: str = sys.executable) -> dict[str, list[str]]:
    """Every command of the check, by name, in running order."""
    omg = [python, "-m", "omg.cli"]
    cmds = {}
    for flavor, config in TRAIN_CONFIGS.items():
        run = out / f"fit_{flavor}"
        timer = ["--trainer.callbacks+=omg.callbacks.timing.StepTimer",
                 f"--trainer.callbacks.init_args.out={run}/steps.json"]
        if flavor == "giant":
            timer.append(f"--trainer.callbacks.init_args.save={run}/final.ckpt")
        # one GPU, one micro-batch per optimizer step (the config's per-GPU batch), no validation
        cmds[f"fit {flavor}"] = [*omg, "fit", "--config", config, "--trainer.devices", "1", "--trainer.num_nodes", "1",
                                 "--trainer.max_steps", str(train_steps), "--trainer.accumulate_grad_batches", "1",
                                 "--trainer.limit_val_batches", "0", "--trainer.num_sanity_val_steps", "0",
                                 "--trainer.enable_progress_bar", "false",
                                 "--trainer.default_root_dir", str(run), "--data.train", f"{shards}/train",
                                 "--data.val", f"{shards}/val", "--data.num_workers", "4", *timer]
    for sampler, steps in (("dpmpp", 20), ("ddim", 200)):
        cmds[f"sample giant {sampler} {steps}"] = [
            *omg, "bench", "sample", "--flavor", "giant", "--precision", "bf16", "--sampler", sampler,
            "--steps", str(steps), "--batch_sizes", "[1, 8, 32]"]
    converted = out / "giant.safetensors"
    cmds["convert giant"] = [*omg, "convert-ckpt", str(out / "fit_giant/final.ckpt"), str(converted)]
    cmds["generate giant"] = [*omg, "generate", "--unconditional", "--ckpt", str(converted), "--num_samples", "2",
                              "--steps", "20", "--sampler", "dpmpp", "--autocast", "bf16", "--no_preview",
                              "--out", str(out / "generated")]
    return cmds


def shown(cmd: list[str]) -> str:
    """A command as the user would type it (``omg ...`` for our interpreter's ``-m omg.cli``)."""
    if cmd[1:3] == ["-m", "omg.cli"]:
        cmd = ["omg", *cmd[3:]]
    return shlex.join(cmd)


# the commands the check runs besides `omg fit`, by the module:function that `omg` runs for each (omg.cli.COMMANDS)
_TOOLS = {"bench": "omg.tools.bench:main", "convert-ckpt": "omg.tools.convert:main",
          "generate": "omg.tools.generate:main"}


def _print_config(cmd: list[str]) -> tuple[int, str, str]:
    """``cmd --print_config`` run in this process: (exit code, stdout, stderr)."""
    command, rest = cmd[3], [*cmd[4:], "--print_config"]
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            if command == "fit":
                from omg.tools.lightning import OmgLightningCLI

                OmgLightningCLI("fit", rest)
            else:
                module, function = _TOOLS[command].split(":")
                getattr(importlib.import_module(module), function)(rest)
            code = 0
        except SystemExit as e:
            code = e.code if isinstance(e.code, int) else int(e.code is not None)
        except UsageError as e:
            print(f"omg: error: {e}", file=sys.stderr)
            code = 2
    return code, out.getvalue(), err.getvalue()


def print_dry_run(cmds: dict[str, list[str]]) -> None:
    """Each training config resolved as the real run would resolve it, each model built on the meta
    device (no memory, no GPU), each command printed."""
    import torch
    import yaml

    from omg.models.dit import DiTConfig, MotionDiT

    for name, cmd in cmds.items():
        print(f"$ {shown(cmd)}", flush=True)
        # every command parses (the same options, the same config files) without running
        code, stdout, stderr = _print_config(cmd)
        if code != 0:
            raise UsageError(f"{name}: does not resolve: {(stderr.strip().splitlines() or ['?'])[-1]}")
        # DeepSpeed's import logs to stdout ahead of the YAML: the YAML starts at its first key
        lines = stdout.splitlines()
        config = yaml.safe_load("\n".join(lines[next(i for i, line in enumerate(lines) if line[:1].isalpha()):]))
        if name.startswith("fit "):
            flavor = config["model"]["init_args"]["flavor"]
            with torch.device("meta"):
                params = sum(p.numel() for p in MotionDiT(DiTConfig.from_name(flavor)).parameters())
            timer = [c for c in config["trainer"]["callbacks"] if c["class_path"].endswith("StepTimer")]
            strategy = config["trainer"]["strategy"]
            if isinstance(strategy, dict):
                strategy = f"{strategy['class_path'].rsplit('.', 1)[-1]} ({strategy['init_args']['config']})"
            print(f"  resolves: flavor {flavor} ({params / 1e6:.0f}M parameters, built on the meta device), "
                  f"strategy {strategy}, precision {config['trainer']['precision']}, batch "
                  f"{config['data']['batch_size']} x {config['data']['max_len']} frames, max_steps "
                  f"{config['trainer']['max_steps']}, devices {config['trainer']['devices']}, "
                  f"step timer {'added' if timer else 'MISSING'}", flush=True)
        else:
            print(f"  resolves: {len(config)} options", flush=True)


def bench_gpu(
    out: Path = Path("runs/gpu_check"),
    train_steps: PositiveInt = 30,
    shards: str = MINI_SHARDS,
    peak_tflops: PositiveFiniteFloat | None = None,
    dry_run: bool = False,
    command: str = "omg bench gpu",
) -> Path | None:
    """Every pending GPU figure of docs/ on one GPU, written to OUT/gpu_check.md.

    Args:
        out: folder for the runs, the converted checkpoint and gpu_check.md
        train_steps: optimizer steps of each training run (the first 5 are not timed)
        shards: the shard directory (with train/ and val/) the training runs read
        peak_tflops: the GPU's dense bf16 peak, when omg does not know the GPU
        dry_run: resolve the configs and print the commands; train and sample nothing (no GPU needed)
        command: the command line, recorded with the results

    Returns:
        The markdown file written (None on a dry run).
    """
    import torch

    from omg.models.dit import DiTConfig

    if train_steps <= 5:
        raise UsageError(f"--train_steps must be above the 5 untimed warm-up steps, got {train_steps}")
    for part in ("train", "val"):
        if not (Path(shards) / part / "manifest.json").is_file():
            raise UsageError(f"--shards {shards}: no {part}/manifest.json (a shard directory with train/ and val/; "
                             "run from the repository root for the default)")
    cmds = commands(out, train_steps, shards)
    if dry_run:
        print_dry_run(cmds)
        return None
    if not torch.cuda.is_available():
        raise UsageError("no CUDA GPU here: run on a GPU machine, or check the commands with --dry_run")
    device, known = device_peak_tflops()
    peak = peak_tflops or known
    out.mkdir(parents=True, exist_ok=True)
    lines = [f"# GPU check on {device}", "", f"`{command}`", ""]
    train_rows, sample_rows, other = [], [], []
    for name, cmd in cmds.items():
        print(f"$ {shown(cmd)}", flush=True)
        start = time.perf_counter()
        result = subprocess.run(cmd, capture_output=True, text=True)
        seconds = time.perf_counter() - start
        # each step's whole output beside the table: a failed step's table row holds only its last line
        (out / f"{name.replace(' ', '_')}.log").write_text(f"$ {shown(cmd)}\n{result.stdout}\n{result.stderr}")
        if result.returncode != 0:
            # omg's one-line error where there is one (NCCL's shutdown warnings can follow it)
            errors = [line for line in result.stderr.splitlines() if line.startswith("omg: error:")]
            tail = errors[-1:] or result.stderr.strip().splitlines()[-1:] or ["(no output)"]
            other.append(f"| {name} | **failed** (exit {result.returncode}): {tail[0]} | {seconds:.0f} s "
                         f"| `{shown(cmd)}` |")
            continue
        if name.startswith("fit "):
            flavor = name.split()[1]
            timing = json.loads((out / f"fit_{flavor}" / "steps.json").read_text())
            config = DiTConfig.from_name(flavor)
            flops = 3 * config.flops(timing["batch"], timing["frames"])  # padded frames cost as much as real
            mfu = f"{100 * flops / timing['step_s'] / (peak * 1e12):.1f}%" if peak else "n/a"
            strategy = "bf16 DeepSpeed ZeRO-2" if flavor == "giant" else "bf16-mixed DDP"
            rate = timing["batch"] * timing["frames"] / timing["step_s"]
            train_rows.append(f"| {flavor} | {strategy} | {timing['batch']} x {timing['frames']} "
                              f"| {timing['step_s'] * 1000:.0f} ms | {rate:,.0f} "
                              f"| {mfu} | `{shown(cmd)}` |")
        elif name.startswith("sample "):
            sample_rows += [line for line in result.stdout.splitlines() if line.startswith("| giant |")]
        else:
            last = (result.stdout.strip().splitlines() or [""])[-1]
            other.append(f"| {name} | ok: {last} | {seconds:.0f} s | `{shown(cmd)}` |")
    lines += ["## Training step (one GPU, the shipped config's per-GPU batch)", "",
              "| flavor | precision / strategy | batch x frames | step | frames/s | MFU | command |",
              "|---|---|---|---|---|---|---|", *train_rows, "",
              "## Giant sampling", "",
              "| flavor | device | precision | sampler | steps | batch | s per batch | s per motion | peak memory "
              "| command |", "|---|---|---|---|---|---|---|---|---|---|", *sample_rows, "",
              "## Checkpoint conversion and loading (and any step that failed)", "",
              "| step | result | time | command |", "|---|---|---|---|",
              *other, ""]
    path = out / "gpu_check.md"
    path.write_text("\n".join(lines))
    print("\n".join(lines))
    print(f"wrote {path}")
    return path
