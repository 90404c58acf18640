"""``omg bench gpu``: its dry run on the CPU (every command resolves, nothing trains), and the
pieces it relies on run for real at mini size: ``StepTimer`` inside ``omg fit``, its checkpoint
converted by ``omg convert-ckpt`` and loaded by ``omg generate``."""

from __future__ import annotations

import json
import sys

from helpers import REPO
from omg.cli import main


def test_dry_run_resolves_every_command_and_trains_nothing(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(REPO)
    out = tmp_path / "gpu_check"
    main(["bench", "gpu", "--dry_run", "--out", str(out)])
    printed = capsys.readouterr().out
    commands = [line for line in printed.splitlines() if line.startswith("$ omg ")]
    assert [c.split()[2] for c in commands] == ["fit", "fit", "bench", "bench", "convert-ckpt", "generate"]
    assert "--config configs/pretrain_base.yaml" in commands[0]
    assert "--config configs/pretrain_giant.yaml" in commands[1]
    assert "--sampler dpmpp --steps 20" in commands[2] and "--sampler ddim --steps 200" in commands[3]
    assert "flavor giant (1047M parameters" in printed and "DeepSpeedStrategy (configs/deepspeed/zero2.json)" in printed
    assert printed.count("step timer added") == 2 and printed.count("max_steps 30, devices 1") == 2
    assert not out.exists()  # nothing ran


def test_step_timer_checkpoint_convert_and_generate_on_cpu(tmp_path, capsys, monkeypatch):
    """The GPU run's chain at mini size: the timer's JSON, its checkpoint, converted, generated from."""
    monkeypatch.chdir(REPO)
    monkeypatch.setattr(sys, "argv", list(sys.argv))  # omg fit sets it for LightningCLI
    run = tmp_path / "fit"
    main(["fit", "--config", "configs/mini/pretrain.yaml", "--trainer.max_steps", "8",
          "--trainer.limit_val_batches", "0", "--trainer.num_sanity_val_steps", "0", "--trainer.logger", "false",
          "--trainer.enable_progress_bar", "false", "--trainer.default_root_dir", str(run), "--data.num_workers", "0",
          "--trainer.callbacks+=omg.callbacks.timing.StepTimer", f"--trainer.callbacks.init_args.out={run}/steps.json",
          f"--trainer.callbacks.init_args.save={run}/final.ckpt"])
    timing = json.loads((run / "steps.json").read_text())
    assert timing["steps"] == 3 and timing["batch"] == 16 and 40 <= timing["frames"] <= 120 and timing["step_s"] > 0
    converted = tmp_path / "mini.safetensors"
    main(["convert-ckpt", str(run / "final.ckpt"), str(converted)])
    main(["generate", "--unconditional", "--ckpt", str(converted), "--num_samples", "2", "--steps", "5",
          "--sampler", "dpmpp", "--no_preview", "--length", "2", "--out", str(tmp_path / "gen"), "--device", "cpu"])
    assert sorted(p.name for p in (tmp_path / "gen").glob("sample_*.bvh")) == ["sample_000.bvh", "sample_001.bvh"]


def test_a_device_name_finds_its_most_specific_gpu_kind():
    """One table of accelerators (omg.tools.devices.GPUS) for the planner and the MFU of `omg bench train|gpu`:
    the PCIe H100 peaks at 756 TFLOP/s, not at the SXM part's 989, which a first-substring match gave it."""
    from omg.tools.devices import GPUS, gpu_kind

    names = {"NVIDIA H100 80GB HBM3": "H100", "NVIDIA H100 PCIe": "H100-PCIe", "NVIDIA H200": "H200",
             "NVIDIA A100-SXM4-80GB": "A100", "NVIDIA A100-SXM4-40GB": "A100-40GB", "NVIDIA L40S": "L40S",
             "NVIDIA A10G": "A10G", "Tesla T4": None, "NVIDIA GeForce RTX 4090": None}
    assert {name: gpu_kind(name) for name in names} == names
    assert GPUS[gpu_kind("NVIDIA H100 PCIe")][1] == 756.0
