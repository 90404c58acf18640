"""``omg bench plan``: the activation term against a real forward+backward's peak memory on the
CPU (DiT and ControlNet), the model states against DeepSpeed's estimators, the ControlNet's
trainable/frozen split against the real module's, its FLOPs against torch's counter, and the
shipped configs planned."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from helpers import REPO
from omg.cli import main
from omg.errors import UsageError
from omg.tools.plan import measure_activations, measure_controlnet_activations, model_states

# Peak resident memory of one training step of the mini DiT (bf16 autocast, as bf16-mixed), in a
# process of its own: /proc/self/clear_refs "5" resets the peak (VmHWM), so the peak minus the
# resident memory before the step is what the step added. A fixed mmap threshold makes glibc
# return every large block at once, so freed activations do not linger in the heap; one thread
# keeps torch's allocations in one arena. Gradients exist from the warm-up step before, taken on the
# batch's first sample: their size does not depend on the batch (measured/planned 1.185 / 1.077 / 1.085;
# after a full-size warm-up 1.185 / 1.077 / 1.096; after a second full-size step, 0.05-0.5% lower still).
PEAK_STEP = """
import sys, torch
from omg.models.controlnet import MoCConfig, MotionControlNet
from omg.models.checkpointing import checkpoint_each
from omg.models.dit import DiTConfig, MotionDiT
torch.set_num_threads(1)
B, T, ckpt, L = int(sys.argv[1]), int(sys.argv[2]), sys.argv[3] == "1", int(sys.argv[4])
torch.manual_seed(0)
model = MotionDiT(DiTConfig.from_name("mini"))
if ckpt:  # as the LightningModules apply it (their configure_model), without importing Lightning
    checkpoint_each(model.blocks)
x, t = torch.randn(B, T, 263), torch.randint(0, 1000, (B,))
mask = torch.ones(B, T, dtype=torch.bool)
mask[0, T // 2:] = False
inputs = (x, t, mask)
if L:  # the ControlNet of configs/mini/controlnet.yaml (MiniLM tokens, 384 wide) on it, L-token captions
    model = MotionControlNet(model, MoCConfig(**MOC))
    tokens, text_mask = torch.randn(B, L, 384), torch.ones(B, L, dtype=torch.bool)
    inputs = (x, t, tokens, text_mask, torch.full((B,), L - 1), mask)
def step(inputs):
    with torch.autocast("cpu", dtype=torch.bfloat16):
        out = model(*inputs)
    out.float().square().mean().backward()
def status(key):
    return int(next(line for line in open("/proc/self/status") if line.startswith(key)).split()[1]) * 1024
step(tuple(i[:1] for i in inputs))  # the warm-up: gradients and lazily built state exist before the measured step
open("/proc/self/clear_refs", "w").write("5")
before = status("VmRSS:")
step(inputs)
print(status("VmHWM:") - before)
"""


MINI_MOC = {"d_c": 64, "num_experts": 4, "text_dim": 384}  # configs/mini/controlnet.yaml with MiniLM


def peak_step_bytes(batch: int, frames: int, checkpointing: bool, text_tokens: int = 0) -> int:
    """The peak of a mini DiT's step, or with ``text_tokens`` of its ControlNet's."""
    env = {**os.environ, "MALLOC_MMAP_THRESHOLD_": "65536", "PYTHONPATH": str(REPO)}
    script = f"MOC = {MINI_MOC!r}\n{PEAK_STEP}"
    out = subprocess.run([sys.executable, "-c", script, str(batch), str(frames), str(int(checkpointing)),
                          str(text_tokens)], env=env, capture_output=True, text=True, check=True).stdout
    return int(out.strip().splitlines()[-1])


@pytest.mark.skipif(not os.access("/proc/self/clear_refs", os.W_OK), reason="needs Linux's resettable peak RSS")
@pytest.mark.parametrize("batch, frames, checkpointing", [(4, 256, False), (8, 256, True)])
def test_activation_estimate_matches_the_measured_peak(batch, frames, checkpointing):
    """The planner's activations (fitted at 16-64 frames, batch 1-2, scaled to 4 layers and the
    size here) against the measured peak of a real step 8-16x larger. The estimate is what backward
    keeps; the peak also holds backward's transient tensors (the gradients of one block's widest
    intermediates, the GEGLU's 2·ffn = 4·d wide fc1 output among them), so it may exceed the
    estimate by up to 30%, and never fall below it by more than the page rounding of the
    measurement (5%)."""
    estimate = measure_activations("mini", "fp32-autocast").bytes(4, batch, frames, checkpointing)
    measured = peak_step_bytes(batch, frames, checkpointing)
    assert 0.95 <= measured / estimate <= 1.3, (measured, estimate)


@pytest.mark.skipif(not os.access("/proc/self/clear_refs", os.W_OK), reason="needs Linux's resettable peak RSS")
def test_controlnet_activation_estimate_matches_the_measured_peak():
    """The same for the mini ControlNet (frozen DiT + copies + MoC on 4 layers, captions of CLIP's
    77 tokens): fitted at 16-64 frames, batch 1-2, checked on a step of 4 x 196 frames (HumanML3D's
    longest clips); measured/planned 1.09."""
    estimate = measure_controlnet_activations("mini", "fp32-autocast", MINI_MOC, 77).bytes(4, 4, 196)
    measured = peak_step_bytes(4, 196, False, text_tokens=77)
    assert 0.95 <= measured / estimate <= 1.3, (measured, estimate)


def test_activations_scale_with_batch_and_frames():
    act = measure_activations("mini", "bf16")
    one, two = act.bytes(4, 1, 300), act.bytes(4, 2, 300)
    assert two > 1.9 * one and act.bytes(4, 1, 600) > 1.9 * one
    assert act.bytes(4, 8, 300, checkpointing=True) < act.bytes(4, 8, 300) / 2


def test_model_states_are_deepspeeds_and_shrink_with_zero():
    from deepspeed.runtime.zero.stage_1_and_2 import estimate_zero2_model_states_mem_needs

    P = 1_000_000_000
    zero2 = model_states(P, 10**7, "zero2", 8, 8, offload=False)
    _, deepspeed_total = estimate_zero2_model_states_mem_needs(P, 8, 1, cpu_offload=False)
    assert zero2["params"] + zero2["grads"] + zero2["optimizer"] == pytest.approx(deepspeed_total, abs=1)
    totals = [sum(model_states(P, 10**7, s, 8, 8, offload=False).values()) for s in ("ddp", "zero1", "zero2", "zero3")]
    assert totals == sorted(totals, reverse=True) and len(set(totals)) == 4
    offloaded = model_states(P, 10**7, "zero2", 8, 8, offload=True)
    assert offloaded["optimizer"] == 0 and offloaded["params"] == 2 * P


def test_plan_of_shipped_configs(capsys):
    main(["bench", "plan", "--configs", "[configs/pretrain_base.yaml, configs/pretrain_large.yaml]"])
    out = capsys.readouterr().out
    table = [line for line in out.splitlines() if line.startswith("| pretrain_")]
    assert len(table) == 2 and "| ddp |" in table[0] and "| zero2 |" in table[1]
    assert "256 (32 x 1 x 8 H100) x 300" in table[0]  # global batch of the config: 32 x 8 GPUs x accumulate 1
    assert "| 1,000,000 |" in table[0]


def test_plan_keeps_a_configs_global_batch_on_other_gpu_counts(capsys):
    """--gpus raises a config's accumulation so that its global batch (micro x accumulate x its 8 GPUs)
    stays; --global_batch and --micro_batch are honoured; a line says what changed."""
    from omg.tools.plan import rebatch, run_from_config

    giant = run_from_config(REPO / "configs/pretrain_giant.yaml")  # 8 x 4 x 8 = 256
    assert rebatch(giant, 8, None, None) == (giant, None)
    one, note = rebatch(giant, 1, None, None)
    assert (one.micro_batch, one.accumulate) == (8, 32) and note == "pretrain_giant: global batch 256 kept on 1 GPU, " \
        "accumulation 4 -> 32"
    more, note = rebatch(giant, 8, 512, 16)
    assert (more.micro_batch, more.accumulate) == (16, 4)
    assert note == "pretrain_giant: global batch 256 -> 512 (--global_batch), micro-batch 8 -> 16 (--micro_batch), " \
        "accumulation 4 kept"
    with pytest.raises(UsageError, match="global batch 256 is not a multiple of micro-batch 8 x --gpus 3"):
        rebatch(giant, 3, None, None)
    # through the command, on the mini config (16 x 1 x 8 = 128): the table and the line; one config is given
    # as a plain path (the list option takes a lone value as its one item), as a list, and with `=`
    for configs in (["configs/mini/pretrain.yaml"], ["[configs/mini/pretrain.yaml]"], []):
        flag = ["--configs=configs/mini/pretrain.yaml"] if not configs else ["--configs", *configs]
        main(["bench", "plan", *flag, "--gpus", "2"])
        out = capsys.readouterr().out
        assert "| 128 (16 x 4 x 2 H100) x 120 |" in out
        assert out.rstrip().endswith("pretrain: global batch 128 kept on 2 GPUs, accumulation 1 -> 4")


def test_plan_options_refuse_bad_input(capsys):
    for argv, says in ((["--mfu", "0"], "mfu"), (["--strategy", "ddp", "--offload"], "offload"),
                       (["--global_batch", "100", "--gpus", "8"], "global_batch"),
                       (["--configs", "[configs/pretrain_giant.yaml]", "--gpus", "3"], "--gpus 3"),
                       (["--configs", "[configs/habit_vqvae.yaml]"], "ControlNetModule")):
        with pytest.raises(SystemExit) as e:
            main(["bench", "plan", *argv])
        err = capsys.readouterr().err
        assert e.value.code == 2 and says in err and len(err.strip().splitlines()) == 1, err


def test_plan_of_a_controlnet_config(capsys):
    """A ControlNet config plans: the paper's 500 epochs of HumanML3D's 23,384 clips at its global
    batch 64 are its trainer.max_steps; the frozen DiT and CLIP text tower are in the frozen column."""
    import yaml

    main(["bench", "plan", "--configs", "[configs/controlnet_base.yaml]"])
    row = next(line for line in capsys.readouterr().out.splitlines() if line.startswith("| controlnet_base"))
    max_steps = yaml.safe_load((REPO / "configs/controlnet_base.yaml").read_text())["trainer"]["max_steps"]
    assert f"| {max_steps:,} (500 epochs) |" in row and "64 (8 x 1 x 8 H100) x 196" in row
    assert "| 122M + 218M |" in row  # trainable + frozen (Base 94M + CLIP ViT-L/14's text tower 124M)


def test_controlnet_split_is_the_modules():
    """The planner's trainable and frozen counts are those of the real ControlNetModule of
    configs/controlnet_base.yaml built on the meta device: its optimizer's parameters and its
    EMA's are the trainable ones; everything else (the DiT, the text encoder) is frozen."""
    import torch
    import yaml

    from omg.lit.controlnet import ControlNetModule
    from omg.lit.ema import EMA
    from omg.tools.plan import controlnet_parts, run_from_config

    run = run_from_config(REPO / "configs/controlnet_base.yaml")
    parts = controlnet_parts(run.flavor, run.controlnet)
    args = yaml.safe_load((REPO / "configs/controlnet_base.yaml").read_text())["model"]["init_args"]
    spec = {"representation": "humanml3d263", "skeleton": "smpl22", "fps": 20.0, "feature_dim": 263,
            "mean": [0.0] * 263, "std": [1.0] * 263}
    with torch.device("meta"):
        module = ControlNetModule(**{**args, "base": {"flavor": "base", "dit": None, "spec": spec}})
        ema = EMA(module.trainable_module())
    trainable = sum(p.numel() for group in module.optimizer_groups() for p in group["params"])
    assert parts.trainable == trainable == sum(t.numel() for t in ema.shadow.values())
    assert parts.frozen_dit == sum(p.numel() for p in module.model.parameters())
    assert parts.frozen_dit + parts.frozen_text == sum(p.numel() for p in module.parameters() if not p.requires_grad)
    assert parts.moc["text_dim"] == 768 and parts.text_tokens == 77  # CLIP ViT-L/14


@pytest.mark.parametrize("wiring, experts, layers", [("per_layer", "moc", None), ("parallel_stream", "moc", [1]),
                                                     ("per_layer", "single_ffn", [0, 2])])
def test_controlnet_flops_are_torchs_count(wiring, experts, layers):
    """MoCConfig.flops against torch's FlopCounterMode on a forward of the real module (less the
    frozen DiT's): equal but for the copies' attention (q·kᵀ, attn·v), which the counter does not
    see in the CPU attention kernel."""
    import torch
    from torch.utils.flop_counter import FlopCounterMode

    from omg.models.controlnet import MoCConfig, MotionControlNet
    from omg.models.dit import DiTConfig, MotionDiT

    dit, (B, T, L) = DiTConfig.from_name("mini"), (2, 40, 9)
    config = MoCConfig(d_c=64, num_experts=4, text_dim=96, wiring=wiring, experts=experts, layers=layers)
    net = MotionControlNet(MotionDiT(dit), config)
    x, t = torch.randn(B, T, 263), torch.randint(0, 1000, (B,))
    counts = []
    for forward in (lambda: net(x, t, torch.randn(B, L, 96), torch.ones(B, L, dtype=torch.bool),
                                torch.full((B,), L - 1)), lambda: net.base(x, t)):
        with FlopCounterMode(display=False) as counter:
            forward()
        counts.append(counter.get_total_flops())
    copies = len(net.copy_blocks)
    assert counts[0] - counts[1] == config.flops(dit, B, T, L) - copies * B * T * 4 * T * dit.d_model
