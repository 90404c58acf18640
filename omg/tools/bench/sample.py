"""``omg bench sample``: seconds per motion of guided sampling, and ms per guided denoiser step
with the captions' tokens padded or trimmed and the text-only work redone or hoisted."""

from __future__ import annotations

import time
from dataclasses import replace
from typing import Literal

from omg.errors import UsageError
from omg.tools.args import ClosedUnitInterval, NonNegativeInt, PositiveInt
from omg.tools.bench.measure import Flavor, unnormalised_spec
from omg.tools.devices import peak_memory


def bench_sample(
    flavor: Flavor = "mini",
    frames: PositiveInt = 196,
    steps: NonNegativeInt = 200,
    sampler: str = "ddim",
    batch_sizes: tuple[PositiveInt, ...] = (1, 8, 32),
    text_encoder: str = "hash",
    precision: Literal["fp32", "bf16-mixed", "bf16"] | None = None,
    token_steps: NonNegativeInt = 0,
    compile: bool = False,
    stance_root: ClosedUnitInterval = 0.0,
    command: str = "omg bench sample",
) -> None:
    """Seconds per motion of guided sampling (frozen DiT + ControlNet).

    Args:
        flavor: the DiT size
        frames: frames per motion
        steps: sampling steps, at most the model's diffusion steps (0 with --token_steps: time only single steps)
        sampler: a registered sampler (ddim, dpmpp, euler)
        batch_sizes: the batch sizes to try, a list such as [1, 8, 32]
        text_encoder: the registered text encoder; it runs once per batch, and hash keeps it out of the timing
        precision: fp32; bf16-mixed (fp32 weights, the network under bf16 autocast, as omg generate
            --autocast bf16); or bf16 (weights cast to bf16). Default: bf16-mixed on a GPU, else fp32
        token_steps: also time this many single guided denoiser steps at the first batch size: text tokens
            padded to CLIP's 77 vs trimmed to the longest caption, and the text-only work (MoC keys, values,
            gates, AdaIN) done at every step vs once per caption (0: skip; with --steps 0: only this)
        compile: sample through torch.compile (compiled during the warm-up, not timed)
        stance_root: step the root of every estimate by its stance foot (``MotionDiffusionModule.stance_denoiser``)
        command: the command line, printed with the results
    """
    import torch

    from omg.diffusion import Diffusion
    from omg.lit.controlnet import ControlNetModule
    from omg.lit.sampling import SamplingSettings
    from omg.registry import SAMPLERS, TEXT_ENCODERS

    if steps > Diffusion.num_timesteps:
        raise UsageError(f"--steps must be in 1..{Diffusion.num_timesteps} (the model's diffusion steps), got {steps}")
    if steps == 0 and not token_steps:
        raise UsageError("--steps 0 times nothing: give --steps 1 or more, or --token_steps N to time only the "
                         "token padding")
    TEXT_ENCODERS.get(text_encoder)  # an unknown name is a UsageError naming the known ones
    SAMPLERS.get(sampler)
    precision = precision or ("bf16-mixed" if torch.cuda.is_available() else "fp32")
    autocast = torch.bfloat16 if precision == "bf16-mixed" else None

    spec = unnormalised_spec(263, fps=20.0)
    device = "cuda" if torch.cuda.is_available() else "cpu"
    module = ControlNetModule(base={"flavor": flavor, "dit": None, "spec": spec}, text_encoder=text_encoder)
    module = module.to(device, torch.bfloat16 if precision == "bf16" else torch.float32).eval()
    if token_steps:
        bench_guided_step(module, flavor, precision, frames, batch_sizes[0], token_steps, device, command, autocast)
        if steps == 0:
            return
    sampling = SamplingSettings(steps=steps, sampler=sampler, autocast=autocast, compile=compile,
                                stance_root=stance_root)
    print("| flavor | device | precision | sampler | steps | batch | s per batch | s per motion "
          "| peak memory | command |\n"
          "|---|---|---|---|---|---|---|---|---|---|")
    for batch in batch_sizes:
        prompts = ["a person walks forward and waves"] * batch
        # warm-up (and compilation): the same shapes as the timed run
        module.sample(prompts, [frames] * batch, replace(sampling, steps=2))
        if device == "cuda":
            torch.cuda.synchronize()
            torch.cuda.reset_peak_memory_stats()
        start = time.perf_counter()
        module.sample(prompts, [frames] * batch, sampling)
        if device == "cuda":
            torch.cuda.synchronize()
        seconds = time.perf_counter() - start
        memory = peak_memory()
        name = torch.cuda.get_device_name() if device == "cuda" else "cpu"
        print(f"| {flavor} | {name} | {precision} | {sampler} | {steps} | {batch} | {seconds:.2f} "
              f"| {seconds / batch:.3f} | {memory} | `{command}` |", flush=True)


CAPTIONS = ["a person walks forward and waves", "a man jumps in place twice",
            "someone turns around slowly, then sits down on a chair", "a person kicks with the right leg"]


def bench_guided_step(module, flavor: str, precision: str, frames: int, batch: int, token_steps: int, device: str,
                      command: str, autocast=None, context: int = 77) -> None:
    """ms per guided denoiser step (one D_u + D_c pass): the captions' tokens padded to CLIP's
    77-token context vs trimmed to the longest caption of the batch, and the text-only work of the
    MoC blocks (``MotionControlNet.text_terms``) redone at every step vs done once per caption, as
    ``sample`` does; the hoisted step's output is checked against the per-step one."""
    import torch

    dtype = next(module.controlnet.parameters()).dtype
    net = module.controlnet
    trimmed = module.encode_text([CAPTIONS[i % len(CAPTIONS)] for i in range(batch)])
    padded = trimmed.padded(max(context, trimmed.tokens.shape[1]))
    g = torch.Generator().manual_seed(0)
    x = torch.randn(batch, frames, module.spec.feature_dim, generator=g).to(device, dtype)
    t = torch.full((batch,), 500, device=device)
    scale = module.guidance_scale

    def per_step(text):  # the text terms recomputed inside every step
        return lambda: net.forward_guided(x, t, net.text_terms(text.tokens, text.mask, text.eot), scale)

    def hoisted(text):
        terms = net.text_terms(text.tokens, text.mask, text.eot, fold_biases=True)
        return lambda: net.forward_guided(x, t, terms, scale)

    def ms_per_step(step) -> float:
        with torch.no_grad(), torch.autocast(device, dtype=autocast or torch.float32, enabled=autocast is not None):
            step()  # warm-up
            if device == "cuda":
                torch.cuda.synchronize()
            start = time.perf_counter()
            for _ in range(token_steps):
                step()
            if device == "cuda":
                torch.cuda.synchronize()
        return 1000 * (time.perf_counter() - start) / token_steps

    with torch.no_grad():
        difference = float((per_step(trimmed)() - hoisted(trimmed)()).abs().max())
    name = torch.cuda.get_device_name() if device == "cuda" else "cpu"
    L, L77 = trimmed.tokens.shape[1], padded.tokens.shape[1]
    rows = {(f"{L77} (padded like CLIP)", "every step"): ms_per_step(per_step(padded)),
            (f"{L} (trimmed)", "every step"): ms_per_step(per_step(trimmed)),
            (f"{L} (trimmed)", "once per caption"): ms_per_step(hoisted(trimmed))}
    print("| flavor | device | precision | batch x frames | text tokens | text work | ms per guided step | command |\n"
          "|---|---|---|---|---|---|---|---|")
    for (tokens, work), ms in rows.items():
        print(f"| {flavor} | {name} | {precision} | {batch} x {frames} | {tokens} | {work} | {ms:.1f} | `{command}` |")
    first, trimmed_ms, hoisted_ms = rows.values()
    print(f"\ntrimming: {first / trimmed_ms:.2f}x faster per step; text work once per caption: "
          f"{trimmed_ms / hoisted_ms:.2f}x faster (max |output difference| {difference:.1e}); "
          f"both: {first / hoisted_ms:.2f}x\n", flush=True)
