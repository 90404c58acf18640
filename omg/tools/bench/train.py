"""``omg bench train``: training step time, frames/s, MFU and peak memory of a DiT flavor."""

from __future__ import annotations

import time
from typing import Literal

from omg.errors import UsageError
from omg.tools.args import NonNegativeInt, PositiveFiniteFloat, PositiveInt
from omg.tools.bench.measure import Flavor, unnormalised_spec
from omg.tools.common import last_line
from omg.tools.devices import device_peak_tflops, peak_memory

PRECISIONS = ("32-true", "bf16-mixed", "16-mixed", "bf16-true", "16-true", "64-true", "transformer-engine",
              "transformer-engine-float16", "32", "16", "bf16", "64")  # Lightning's Trainer(precision=...)
Precision = Literal[PRECISIONS]  # type: ignore[valid-type]


def bench_train(
    flavor: Flavor = "mini",
    precision: Precision | None = None,
    strategy: str = "auto",
    batch_size: PositiveInt = 8,
    frames: PositiveInt = 300,
    steps: PositiveInt = 20,
    warmup: NonNegativeInt = 5,
    activation_checkpointing: bool = False,
    peak_tflops: PositiveFiniteFloat | None = None,
    command: str = "omg bench train",
) -> dict:
    """Training step time, frames/s, MFU and peak memory of a DiT flavor.

    Args:
        flavor: the DiT size
        precision: Lightning's Trainer precision (default: bf16-mixed on a GPU, else 32-true)
        strategy: auto, ddp, deepspeed_stage_2, ... (Lightning's strategy names)
        batch_size: motions per step
        frames: frames per motion
        steps: timed steps
        warmup: untimed steps first
        activation_checkpointing: recompute activations in the backward pass
        peak_tflops: the device's peak, when omg does not know it
        command: the command line, printed with the results

    Returns:
        The measured step time (s), frames per second and model TFLOP/s.
    """
    import lightning as L
    import torch
    from lightning.fabric.utilities.exceptions import MisconfigurationException
    from lightning.pytorch.strategies import StrategyRegistry

    from omg.lit.pretrain import PretrainModule

    precision = precision or ("bf16-mixed" if torch.cuda.is_available() else "32-true")
    strategies = ["auto", *StrategyRegistry.available_strategies()]
    if strategy not in strategies:
        raise UsageError(f"--strategy {strategy!r}: not one of Lightning's strategies ({', '.join(strategies)})")
    times: list[float] = []

    class Timer(L.Callback):
        def on_train_batch_start(self, trainer, *_):
            if torch.cuda.is_available():
                torch.cuda.synchronize()
            self.start = time.perf_counter()

        def on_train_batch_end(self, trainer, *_):
            if torch.cuda.is_available():
                torch.cuda.synchronize()
            times.append(time.perf_counter() - self.start)

    try:  # before the model: a precision or strategy this machine cannot run is refused at once
        trainer = L.Trainer(max_steps=warmup + steps, precision=precision, strategy=strategy,
                            devices=1, logger=False, enable_checkpointing=False, enable_progress_bar=False,
                            enable_model_summary=False, callbacks=[Timer()], gradient_clip_val=1.0)
    except (ValueError, TypeError, ImportError, MisconfigurationException) as e:
        raise UsageError(f"--precision {precision} --strategy {strategy}: {last_line(str(e))}") from None

    D = 263
    spec = unnormalised_spec(D, fps=30.0)
    module = PretrainModule(flavor=flavor, activation_checkpointing=activation_checkpointing, spec=spec,
                            warmup_steps=10, ema_decay=0.9999)

    class RandomBatches(torch.utils.data.IterableDataset):
        def __iter__(self):
            g = torch.Generator().manual_seed(0)
            while True:
                motion = 0.1 * torch.randn(batch_size, frames, D, generator=g)
                yield {"motion": motion, "mask": torch.ones(batch_size, frames, dtype=torch.bool)}

    trainer.fit(module, torch.utils.data.DataLoader(RandomBatches(), batch_size=None))
    step = sum(times[warmup:]) / len(times[warmup:])
    frames_per_s = batch_size * frames / step
    device, peak = device_peak_tflops()
    peak = peak_tflops or peak
    train_flops = 3 * module.config.flops(batch_size, frames)  # backward ~ 2x forward
    mfu = f"{100 * train_flops / step / (peak * 1e12):.1f}%" if peak else "n/a"
    memory = peak_memory()
    params = sum(p.numel() for p in module.model.parameters())
    print("| flavor | params | device | precision / strategy | batch x frames | step | frames/s | model TFLOP/s | MFU "
          "| peak memory | command |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    print(f"| {flavor} | {params / 1e6:.0f}M | {device} | {precision} / {strategy} | {batch_size} x {frames} "
          f"| {step * 1000:.0f} ms | {frames_per_s:,.0f} | {train_flops / step / 1e12:.3f} | {mfu} | {memory} "
          f"| `{command}` |")
    return {"step_s": step, "frames_per_s": frames_per_s, "tflops": train_flops / step / 1e12}
