"""``omg bench plan``: the activation term against a real forward+backward's peak memory on the
CPU, the model states against DeepSpeed's estimators, and the shipped configs planned."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from helpers import REPO
from omg.cli import main
from omg.tools.plan import measure_activations, model_states

# Peak resident memory of one training step of the mini DiT (bf16 autocast, as bf16-mixed), in a
# process of its own: /proc/self/clear_refs "5" resets the peak (VmHWM), so the peak minus the
# resident memory before the step is what the step added. A fixed mmap threshold makes glibc
# return every large block at once, so freed activations do not linger in the heap; one thread
# keeps torch's allocations in one arena. Gradients exist from the warm-up steps before.
PEAK_STEP = """
import sys, torch
from omg.models.dit import DiTConfig, MotionDiT
from omg.lit.base import checkpoint_each
torch.set_num_threads(1)
B, T, ckpt = int(sys.argv[1]), int(sys.argv[2]), sys.argv[3] == "1"
torch.manual_seed(0)
model = MotionDiT(DiTConfig.from_name("mini"))
if ckpt:
    checkpoint_each(model.blocks)
x, t = torch.randn(B, T, 263), torch.randint(0, 1000, (B,))
mask = torch.ones(B, T, dtype=torch.bool)
mask[0, T // 2:] = False
def step():
    with torch.autocast("cpu", dtype=torch.bfloat16):
        out = model(x, t, mask)
    out.float().square().mean().backward()
def status(key):
    return int(next(line for line in open("/proc/self/status") if line.startswith(key)).split()[1]) * 1024
step(); step()
open("/proc/self/clear_refs", "w").write("5")
before = status("VmRSS:")
step()
print(status("VmHWM:") - before)
"""


def peak_step_bytes(batch: int, frames: int, checkpointing: bool) -> int:
    env = {**os.environ, "MALLOC_MMAP_THRESHOLD_": "65536", "PYTHONPATH": str(REPO)}
    out = subprocess.run([sys.executable, "-c", PEAK_STEP, str(batch), str(frames), str(int(checkpointing))],
                         env=env, capture_output=True, text=True, check=True).stdout
    return int(out.strip().splitlines()[-1])


@pytest.mark.skipif(not os.access("/proc/self/clear_refs", os.W_OK), reason="needs Linux's resettable peak RSS")
@pytest.mark.parametrize("batch, frames, checkpointing", [(4, 256, False), (8, 512, False), (8, 512, True)])
def test_activation_estimate_matches_the_measured_peak(batch, frames, checkpointing):
    """The planner's activations (fitted at 16-64 frames, batch 1-2, scaled to 4 layers and the
    size here) against the measured peak of a real step 8-64x larger. The estimate is what
    backward keeps; the peak also holds backward's transient tensors (the gradients of one
    block's widest intermediates, the GEGLU's 2·ffn = 4·d wide fc1 output among them), so it
    may exceed the estimate by up to 30%, and never fall below it by more than the page
    rounding of the measurement (5%)."""
    estimate = measure_activations("mini", "fp32-autocast").bytes(4, batch, frames, checkpointing)
    measured = peak_step_bytes(batch, frames, checkpointing)
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


def test_plan_options_refuse_bad_input(capsys):
    for argv, says in ((["--mfu", "0"], "mfu"), (["--strategy", "ddp", "--offload"], "offload"),
                       (["--global_batch", "100", "--gpus", "8"], "global_batch"),
                       (["--configs", "[configs/controlnet_base.yaml]"], "PretrainModule")):
        with pytest.raises(SystemExit) as e:
            main(["bench", "plan", *argv])
        err = capsys.readouterr().err
        assert e.value.code == 2 and says in err and len(err.strip().splitlines()) == 1, err
