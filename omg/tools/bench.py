"""``omg bench``: speed and memory measurements whose figures go into the README.

Every benchmark makes its own inputs (no dataset download) and prints one Markdown table row
per measurement, with the command that reproduces it. ``python -m omg.tools.bench`` is the
data benchmark's worker: one loader measured in its own process (``loader_worker``).
"""

from __future__ import annotations

import json
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Literal

import numpy as np

from omg.errors import UsageError
from omg.models.dit import FLAVORS
from omg.tools.args import (
    ClosedUnitInterval,
    NonNegativeInt,
    PositiveFiniteFloat,
    PositiveInt,
    number_type,
    run_subcommands,
)
from omg.tools.common import last_line
from omg.tools.gpu import bench_gpu
from omg.tools.plan import bench_plan

MIN_WINDOW = 60  # frames: the shortest window the data benchmark cuts (2 s at 30 fps)
USAGE_ERROR = "usage_error"  # the key of a worker's JSON line that reports bad input
WindowFrames = number_type("WindowFrames", int, [(">=", MIN_WINDOW)],
                           f"an integer >= {MIN_WINDOW} (frames: the shortest window the benchmark cuts)")
Flavor = Literal[tuple(FLAVORS)]  # type: ignore[valid-type]  # mini, base, large, huge, giant


# -- data ------------------------------------------------------------------------------------
def write_random_shards(out: Path, num_clips: int, feature_dim: int, seed: int = 0, clips_per_shard: int = 250) -> None:
    """A shard set of random features with realistic clip lengths (2-10 s at 30 fps)."""
    from omg.data.shards import ShardWriter
    from omg.motion import Clip, Representation
    from omg.skeleton import SMPL22

    class RandomFeatures(Representation):
        name = "bench-random"
        dim = feature_dim

        def encode(self, clip):
            return clip.labels.pop("features"), {}

        def decode(self, features, offsets=None):
            raise NotImplementedError

    rng = np.random.default_rng(seed)
    rest = np.zeros((1, 22, 3), np.float32)

    def clips():
        for i in range(num_clips):
            T = int(rng.integers(60, 301))
            features = rng.standard_normal((T, feature_dim), dtype=np.float32)
            yield Clip(id=f"bench{i:06d}", skeleton=SMPL22, fps=30.0, positions=np.broadcast_to(rest, (T, 22, 3)),
                       texts=[f"clip {i}"], labels={"features": features})

    ShardWriter(out, RandomFeatures(SMPL22), 30.0, max_clips=clips_per_shard, log=lambda m: None).write(clips())


def _tree_pss(pid: int) -> int:
    """Proportional set size of a process and its children: shared pages counted once."""
    import psutil

    total = 0
    try:
        root = psutil.Process(pid)
        for p in [root, *root.children(recursive=True)]:
            try:
                total += p.memory_full_info().pss
            except (psutil.NoSuchProcess, psutil.AccessDenied):
                pass
    except psutil.NoSuchProcess:
        pass
    return total


def _run_measured(cmd: list[str], what: str = "benchmark worker") -> tuple[dict, int]:
    """Run a command, sampling its process tree's memory; (its JSON result, peak PSS bytes).

    A worker that stops on bad input prints ``{"usage_error": ...}`` and exits with code 2:
    that is a ``UsageError`` here too; any other failure is a bug and a RuntimeError."""
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    peak = 0
    done = threading.Event()

    def sample():
        nonlocal peak
        while not done.is_set():
            peak = max(peak, _tree_pss(proc.pid))
            time.sleep(0.05)

    sampler = threading.Thread(target=sample, daemon=True)
    sampler.start()
    out, err = proc.communicate()
    done.set()
    sampler.join()
    if proc.returncode != 0:
        if proc.returncode == 2 and (reported := _last_json(out)) and USAGE_ERROR in reported:
            raise UsageError(f"{what}: {reported[USAGE_ERROR]}")
        reason = err.strip().splitlines()[-1] if err.strip() else proc.returncode
        raise RuntimeError(f"benchmark worker failed: {reason}")
    return json.loads(out.strip().splitlines()[-1]), peak


def _last_json(out: str) -> dict | None:
    """The worker's last stdout line as a JSON object, or None."""
    lines = out.strip().splitlines()
    try:
        value = json.loads(lines[-1]) if lines else None
    except json.JSONDecodeError:
        return None
    return value if isinstance(value, dict) else None


def loader_worker(argv: list[str]) -> None:
    """Iterate one loader and print {"windows_per_s": ...} (runs in its own process).

    ``argv``: KIND (streaming or in-memory) SHARDS BATCH_SIZE WORKERS BATCHES MAX_LEN."""
    import os

    kind, shards, batch_size, workers, batches, max_len = argv[0], argv[1], *map(int, argv[2:6])
    from omg.data.datamodule import MotionDataModule, in_memory_loader

    baseline = _tree_pss(os.getpid())  # the interpreter with torch and omg imported, before any data

    dm = MotionDataModule(shards, batch_size=batch_size, max_len=max_len, min_len=60, num_workers=workers,
                          batches_per_epoch=batches + 10, shuffle_buffer=500)
    loader = dm.train_dataloader() if kind == "streaming" else in_memory_loader(
        dm.train_urls, dm.feature_dim, dm.windows, batch_size, workers, dm.collate)
    def endless():
        while True:  # the in-memory loader's epoch is one pass over the clips
            empty = True
            for batch in loader:
                empty = False
                yield batch
            if empty:  # a pass without a batch: looping again would never yield one
                raise UsageError(f"a whole pass yields no batch of {batch_size}: the shards hold fewer clips than "
                                 "--batch_size; lower --batch_size or use more clips")

    it = endless()
    for _ in range(10):  # warm-up: workers started, buffers filled
        next(it)
    start, windows = time.perf_counter(), 0
    for _ in range(batches):
        windows += len(next(it)["id"])
    print(json.dumps({"windows_per_s": windows / (time.perf_counter() - start), "baseline": baseline}))


def bench_data(
    clips: PositiveInt = 10_000,
    feature_dim: PositiveInt = 263,
    batch_size: PositiveInt = 64,
    batches: PositiveInt = 300,
    workers: NonNegativeInt = 2,
    max_len: WindowFrames = 196,
    shards: str | None = None,
    command: str = "omg bench data",
) -> dict[str, tuple[float, float, float]]:
    """Streaming vs in-memory loader: windows/s and peak memory.

    Args:
        clips: random clips to write (without --shards)
        feature_dim: features per frame of the random clips
        batch_size: windows per batch
        batches: timed batches (after 10 warm-up batches)
        workers: loader worker processes (0: load in the main process)
        max_len: longest window in frames
        shards: an existing shard directory (or URL pattern) to read instead of a random set
        command: the command line, printed with the results

    Returns:
        Per loader: windows per second, peak memory of the process tree and of the loader (MiB).
    """
    _check_data_args(clips, batch_size, shards)
    with tempfile.TemporaryDirectory(prefix="omg-bench-") as tmp:
        if shards is None:
            shards = str(Path(tmp) / "shards")
            t = time.perf_counter()
            write_random_shards(Path(shards), clips, feature_dim)
            print(f"wrote {clips} random clips ({feature_dim}-d) in {time.perf_counter() - t:.1f} s", file=sys.stderr)
        rows = {}
        for kind in ("streaming", "in-memory"):
            cmd = [sys.executable, "-m", "omg.tools.bench", kind, shards, str(batch_size), str(workers), str(batches),
                   str(max_len)]
            result, peak = _run_measured(cmd, f"the {kind} loader")
            rows[kind] = (result["windows_per_s"], peak / 2**20, (peak - result["baseline"]) / 2**20)
    print("| loader | windows/s | peak PSS, whole process tree (MiB) | of which the loader (MiB) | command |")
    print("|---|---|---|---|---|")
    for kind, (rate, total, loader) in rows.items():
        print(f"| {kind} | {rate:,.0f} | {total:,.0f} | {loader:,.0f} | `{command}` |")
    (s_rate, s_total, s_mem), (m_rate, m_total, m_mem) = rows["streaming"], rows["in-memory"]
    print(f"\nstreaming / in-memory: {s_rate / m_rate:.2f}x the rate, {s_mem / m_mem:.2f}x the loader memory "
          f"({s_total / m_total:.2f}x the whole process tree); target: >= 0.5x the rate, <= 0.25x the memory")
    return rows


def _check_data_args(clips: int, batch_size: int, shards: str | None) -> None:
    """Everything the loader workers would refuse, refused before any clip is written."""
    if shards is None:
        where = "--clips"
    else:
        from omg.data.datamodule import resolve_shards

        try:
            _, manifest, _ = resolve_shards(shards)
        except UsageError as e:  # its messages name the path, not the option
            raise UsageError(f"--shards: {e}" if shards in str(e) else f"--shards {shards}: {e}") from None
        clips, where = manifest["num_clips"], f"--shards {shards} (its manifest)"
    if clips < batch_size:
        raise UsageError(f"{where} gives {clips} clips, fewer than --batch_size {batch_size}: the in-memory "
                         "loader would never fill a batch; lower --batch_size or use more clips")


# -- train -----------------------------------------------------------------------------------
PRECISIONS = ("32-true", "bf16-mixed", "16-mixed", "bf16-true", "16-true", "64-true", "transformer-engine",
              "transformer-engine-float16", "32", "16", "bf16", "64")  # Lightning's Trainer(precision=...)
Precision = Literal[PRECISIONS]  # type: ignore[valid-type]
PEAK_TFLOPS = {"H100": 989.0, "H200": 989.0, "A100": 312.0, "L40S": 362.0, "A10G": 125.0}  # dense bf16


def unnormalised_spec(dim: int, fps: float) -> dict:
    """A humanml3d263 data spec with identity normalisation: the models need no dataset to time."""
    return {"representation": "humanml3d263", "skeleton": "smpl22", "fps": fps, "feature_dim": dim,
            "mean": [0.0] * dim, "std": [1.0] * dim}


def peak_memory() -> str:
    import torch

    if torch.cuda.is_available():
        return f"{torch.cuda.max_memory_allocated() / 2**30:.1f} GiB (GPU)"
    import resource

    return f"{resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20:.1f} GiB (RSS)"


def device_peak_tflops() -> tuple[str, float | None]:
    import torch

    if not torch.cuda.is_available():
        return "cpu", None
    name = torch.cuda.get_device_name()
    return name, next((v for k, v in PEAK_TFLOPS.items() if k in name), None)


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


# -- sample ----------------------------------------------------------------------------------
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
    print("| flavor | device | precision | sampler | steps | batch | s per batch | s per motion "
          "| peak memory | command |\n"
          "|---|---|---|---|---|---|---|---|---|---|")
    for batch in batch_sizes:
        prompts = ["a person walks forward and waves"] * batch
        # warm-up (and compilation): the same shapes as the timed run
        module.sample(prompts, [frames] * batch, steps=2, sampler=sampler, autocast=autocast, compile=compile,
                      stance_root=stance_root)
        if device == "cuda":
            torch.cuda.synchronize()
            torch.cuda.reset_peak_memory_stats()
        start = time.perf_counter()
        module.sample(prompts, [frames] * batch, steps=steps, sampler=sampler, autocast=autocast, compile=compile,
                      stance_root=stance_root)
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


# -- quality ---------------------------------------------------------------------------------
def bench_quality(
    ckpt: Path,
    evaluator: str,
    val: str,
    samplers: tuple[str, ...] = ("ddim", "dpmpp"),
    steps: tuple[PositiveInt, ...] = (5, 10, 20, 50, 100, 200),
    replications: PositiveInt = 3,
    num_prompts: PositiveInt = 64,
    max_len: PositiveInt = 196,
    batch_size: PositiveInt = 64,
    seed: NonNegativeInt = 0,
    out: Path = Path("out/quality"),
    command: str = "omg bench quality",
    prompts: str | None = None,
    samples_per_prompt: PositiveInt = 4,
) -> list[dict]:
    """FID and R-precision against sampling steps and seconds per motion, for each sampler: the
    evaluation protocol of ``omg test`` (seeded prompt sets from the validation shards, a frozen
    evaluator, mean ± 95% CI over replications) at every (sampler, steps). Writes quality.csv and
    quality.png into ``out`` and names, per sampler, the fewest steps whose FID lies within the
    95% CI of 200-step DDIM (the paper's setting).

    Args:
        ckpt: a text-conditioned checkpoint (ControlNet)
        evaluator: the evaluator checkpoint (as EvalCallback.evaluator)
        val: the validation shard directory the prompts and real motions come from
        samplers: registered samplers to compare, a list such as [ddim, dpmpp]
        steps: sampling step counts, a list such as [10, 20, 200]
        replications: prompt sets and seeds per setting (mean ± 95% CI over them)
        num_prompts: prompts per replication
        max_len: longest clip, in frames (longer clips are cropped)
        batch_size: motions sampled at once
        seed: the protocol's seed
        out: folder for quality.csv and quality.png
        command: the command line, recorded with the results
        prompts: also score prompt following (``omg.metrics.following``) on a prompt file with
            targets: ``following`` (the built-in set) or a YAML path; adds the following columns
        samples_per_prompt: generations of each prompt of the prompt file per replication

    Returns:
        One row per (sampler, steps): seconds per motion and each metric's mean and CI.
    """
    import csv

    from omg.data.datamodule import MotionDataModule
    from omg.evaluation import (
        build_evaluator,
        check_evaluator_spec,
        evaluate,
        file_prompt_set,
        parse_metrics,
        prompt_set,
        summarize,
    )
    from omg.files import check_output_dir
    from omg.lit.checkpoint import load_module
    from omg.lit.pretrain import MotionDiffusionModule
    from omg.metrics.following import CATEGORIES, load_prompts
    from omg.registry import SAMPLERS

    for name in samplers:
        SAMPLERS.get(name)
    out = check_output_dir(out)
    module = load_module(ckpt, expect=MotionDiffusionModule).eval()
    if not module.text_conditional:
        raise UsageError(f"--ckpt {ckpt}: the quality curve needs a text-conditioned (ControlNet) checkpoint")
    data = MotionDataModule(val=val, max_len=max_len, clips="whole")
    samples, windows = data.val_clips().samples, data.windows
    model = build_evaluator(evaluator, key="--evaluator")
    check_evaluator_spec(model, data.spec, key="--evaluator")
    metrics = parse_metrics(["fid", {"r_precision": {"pool_size": min(32, num_prompts)}}])
    following = None
    if prompts is not None:
        entries = load_prompts(None if prompts == "following" else prompts)
        following = file_prompt_set(entries, samples_per_prompt, data.spec.fps, max_len)
    rows = []
    for name in samplers:
        for n in steps:
            seconds, motions = 0.0, 0

            def generate(texts, lengths, batch_seed, name=name, n=n):
                nonlocal seconds, motions
                start = time.perf_counter()
                motion = module.sample(list(texts), lengths, steps=n, sampler=name, seed=batch_seed, use_ema=False)
                seconds, motions = seconds + time.perf_counter() - start, motions + len(texts)
                return motion

            runs = [evaluate(generate, model, prompt_set(samples, num_prompts, seed + r, windows), metrics, seed=seed,
                             replication=r, spec=data.spec) for r in range(replications)]
            summary = summarize(runs)
            row = {"sampler": name, "steps": n, "s_per_motion": seconds / motions}
            keys = ["fid", "r_precision/top1", "r_precision/top3"]
            if following is not None:
                summary |= summarize([evaluate(generate, None, following, {"following": {}}, seed=seed, replication=r,
                                               spec=data.spec) for r in range(replications)])
                keys += [k for k in ("following", *(f"following/{c}" for c in CATEGORIES)) if k in summary]
            for key in keys:
                row[f"{key}_mean"], row[f"{key}_ci95"] = summary[key]["mean"], summary[key]["ci95"]
            rows.append(row)
            extra = f" {row['following_mean']:.3f} ± {row['following_ci95']:.3f} |" if following is not None else ""
            print(f"| {name} | {n} | {row['s_per_motion']:.3f} | {row['fid_mean']:.3f} ± {row['fid_ci95']:.3f} "
                  f"| {row['r_precision/top3_mean']:.3f} ± {row['r_precision/top3_ci95']:.3f} |{extra}", flush=True)
    out.mkdir(parents=True, exist_ok=True)
    with open(out / "quality.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    plot_quality(rows, out / "quality.png", command)
    reference = next((r for r in rows if r["sampler"] == "ddim" and r["steps"] == 200), None)
    if reference is not None:
        for name in samplers:
            within = [r["steps"] for r in rows if r["sampler"] == name
                      and abs(r["fid_mean"] - reference["fid_mean"]) <= reference["fid_ci95"]]
            print(f"{name}: fewest steps with FID within the 95% CI of 200-step DDIM "
                  f"({reference['fid_mean']:.3f} ± {reference['fid_ci95']:.3f}): {min(within) if within else 'none'}")
    print(f"wrote {out / 'quality.csv'} and {out / 'quality.png'}  (`{command}`)")
    return rows


def plot_quality(rows: list[dict], path: Path, command: str) -> None:
    """FID and R-precision top-3 against steps and against seconds per motion, one line per sampler."""
    import textwrap

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from omg.files import atomic_path

    fig, axes = plt.subplots(2, 2, figsize=(10, 7))
    for name in dict.fromkeys(r["sampler"] for r in rows):
        mine = [r for r in rows if r["sampler"] == name]
        for row_axes, key in zip(axes, ("fid", "r_precision/top3")):
            for ax, x in zip(row_axes, ("steps", "s_per_motion")):
                ax.errorbar([r[x] for r in mine], [r[f"{key}_mean"] for r in mine],
                            yerr=[r[f"{key}_ci95"] for r in mine], marker="o", capsize=3, label=name)
                ax.set_xscale("log")
                ax.set_xlabel("sampling steps" if x == "steps" else "seconds per motion")
                ax.set_ylabel(key.replace("/", " "))
                ax.grid(True, alpha=0.3)
    axes[0][0].legend()
    fig.suptitle("\n".join(textwrap.wrap(command, 160)), fontsize=7)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=100)
    plt.close(fig)


# -- prompt following on real clips ------------------------------------------------------------
def bench_following(input: Path, prompts: Path | None = None, label: str = "content",
                    fps: PositiveFiniteFloat = 20.0, mirror: bool = False) -> list[dict]:
    """The prompt-following check (``omg.metrics.following``) on real clips: every clip of a folder
    (the bvh-dir source: motion files with a manifest.json of labels) whose ``label`` has targets
    under the prompt file's ``labels:`` is read onto SMPL-22 and scored. Real clips of a class
    should pass their own targets: the fraction that does bounds the check's own error. Prints
    one Markdown row per label value and the overall fraction.

    Args:
        input: a folder of motion files with a manifest.json (e.g. ../shared/data/bandai1)
        prompts: the prompt file whose ``labels:`` give the targets (default: the built-in set)
        label: the clip label that names the action (a Bandai-Namco take's ``content``)
        fps: the rate the clips are resampled to
        mirror: score each clip's mirror image against its mirrored label ("walk-left" -> "walk-right")

    Returns:
        One row per label value: label, passed, clips, failed (the ids of the clips that fail).
    """
    import torch

    from omg.data.sources.bvh_dir import bvh_dir_source
    from omg.metrics.following import Joints, label_targets, passes
    from omg.skeleton import SMPL22
    from omg.text.sides import mirror_caption

    table, at = label_targets(prompts), Joints()
    rows: dict[str, dict] = {}
    for item in bvh_dir_source(str(input), SMPL22, fps):
        clip = item() if callable(item) else item
        if clip is None or isinstance(clip, Exception):
            continue
        value = str(clip.labels.get(label))
        joints = torch.from_numpy(clip.positions)
        if mirror:
            value, joints = mirror_caption(value), SMPL22.mirror(joints)
        if value not in table:
            continue
        ok = all(passes(joints, target, fps, at) for target in table[value])
        row = rows.setdefault(value, {"label": value, "passed": 0, "clips": 0, "failed": []})
        row["passed"], row["clips"] = row["passed"] + ok, row["clips"] + 1
        if not ok:
            row["failed"].append(clip.id)
    if not rows:
        raise UsageError(f"--input {input}: no clip has a {label!r} label with targets in the prompt file "
                         f"(labels: {', '.join(table)})")
    print(f"| {label} | targets | real clips passing |\n|---|---|---:|")
    for value, row in sorted(rows.items()):
        targets = "; ".join(", ".join(f"{k}: {v}" for k, v in t.items()) for t in table[value])
        print(f"| {value} | {targets} | {row['passed']}/{row['clips']} |")
    passed, clips = sum(r["passed"] for r in rows.values()), sum(r["clips"] for r in rows.values())
    print(f"| all | | {passed}/{clips} ({passed / clips:.2f}) |")
    return list(rows.values())


# -- sides in the text features -----------------------------------------------------------------
def _encoder_spec(spec: str):
    """``NAME`` or ``NAME:key=value,...`` (values read as YAML: ``minilm:side_gain=2``) -> the encoder."""
    import yaml

    from omg.text import build_text_encoder

    name, _, options = spec.partition(":")
    kwargs = {}
    for item in filter(None, options.split(",")):
        key, eq, value = item.partition("=")
        if not eq or not key.strip():
            raise UsageError(f"--encoders: {spec!r}: options are key=value pairs, as in minilm:side_gain=2")
        kwargs[key.strip()] = yaml.safe_load(value)
    return build_text_encoder(name.strip(), **kwargs)


def _prompt_set_captions(prompts: str) -> list[tuple[str, str]]:
    """(text, action) of a prompt file's prompts: the action is the prompt's targets, the angle left out
    ("turns left" and "makes a 90 degree turn to the left" are one action)."""
    from omg.metrics.following import load_prompts

    entries = load_prompts(None if prompts == "following" else prompts)

    def action(targets) -> str:
        return "; ".join(", ".join(f"{k}: {v}" for k, v in sorted(t.items()) if k != "angle") for t in targets)

    return [(e["text"], action(e["targets"])) for e in entries]


def bench_sides(manifests: tuple[Path, ...] = (), prompts: str | None = "following",
                encoders: tuple[str, ...] = ("minilm",)) -> list[dict]:
    """Does sidedness survive in the text features? For each text encoder and each set of captions,
    the cosine distance between every caption that names a side and its mirror image (left <->
    right), against the distance to captions of other actions and to other captions of the same
    action (other styles, paraphrases): ``omg.text.sides.side_separation``, for the sentence (EOT)
    feature, the mean of the token features, the token sets (Chamfer) and the side word's own token.
    Prints one Markdown row per (captions, encoder, feature); its ``ratio`` reads "left/right pairs
    are <ratio> as far apart as different actions".

    Args:
        manifests: clip manifests (``{"clips": [{texts, labels: {content}}]}``), e.g.
            ../shared/data/bandai1/manifest.json, read together as one set of captions; the action of a
            caption is its clip's content label
        prompts: a prompt file (``omg.metrics.following``) read as a second set, the action of a prompt
            being its targets: ``following`` for the built-in set, ``none`` for none
        encoders: registered text encoders (minilm, clip-vit-l-14, bge, hash), a list such as [minilm, hash];
            ``NAME:key=value,...`` passes options (``minilm:side_gain=2``)

    Returns:
        One row per (captions, encoder, feature): side, same_action, action, ratio, same_ratio, rank,
        captions.
    """
    from omg.files import MANIFEST_MAX_BYTES, read_file
    from omg.text.sides import side_separation

    sets = []
    if manifests:
        captions = []
        for path in manifests:
            try:
                clips = json.loads(read_file(path, "", MANIFEST_MAX_BYTES))["clips"]
            except (OSError, ValueError, KeyError, TypeError) as e:  # ValueError: also read_file's UsageError
                raise UsageError(f"--manifests: {path} is not a clip manifest ({{\"clips\": [...]}}): {e}") from None
            captions += [(t, str((c.get("labels") or {}).get("content", t)))
                         for c in clips for t in c.get("texts") or []]
        sets.append(("manifests", "manifests", captions))
    if prompts is not None and str(prompts).lower() != "none":
        sets.append(("prompt set", "prompts", _prompt_set_captions(str(prompts))))
    if not sets:
        raise UsageError("--manifests or --prompts: no captions to measure")
    rows = []
    print("| captions | encoder | feature | sided captions | d(left, right) | d(same action) "
          "| d(other action) | ratio to other action | ratio to same action | other actions nearer than the mirror |"
          "\n|---|---|---|---:|---:|---:|---:|---:|---:|---:|")
    for spec in encoders:
        encoder = _encoder_spec(spec)
        for label, option, captions in sets:
            try:
                result = side_separation(encoder, captions)
            except ValueError as e:
                raise UsageError(f"--{option}: {e}") from None
            for feature, r in result.items():
                rows.append({"captions": label, "encoder": spec, "feature": feature, **r})
                print(f"| {label} | {spec} | {feature} | {r['captions']} | {r['side']:.4f} | {r['same_action']:.4f} "
                      f"| {r['action']:.4f} | {r['ratio']:.3f} | {r['same_ratio']:.3f} | {r['rank']:.3f} |",
                      flush=True)
    return rows


# -- round trip through a model skeleton and back onto the rig -------------------------------------
# public rigs with no clip in the shared data are a real CMU clip renamed into their naming
_CMU_SPINE = {"LowerBack": "Spine", "Spine": "Spine1", "Spine1": "Spine2"}
_CMU_TOES = {"LeftToeBase": "LeftToe", "RightToeBase": "RightToe"}
RENAMED_CMU = {
    "lafan1": {**_CMU_SPINE, **_CMU_TOES},
    "mixamo": {n: f"mixamorig:{_CMU_SPINE.get(n, n)}" for n in (
        "Hips", "LowerBack", "Spine", "Spine1", "Neck", "Head", "LeftShoulder", "LeftArm", "LeftForeArm", "LeftHand",
        "RightShoulder", "RightArm", "RightForeArm", "RightHand", "LeftUpLeg", "LeftLeg", "LeftFoot", "LeftToeBase",
        "RightUpLeg", "RightLeg", "RightFoot", "RightToeBase")},
    "style100": {"LowerBack": "Chest", "Spine": "Chest2", "Spine1": "Chest3", "Neck": "Chest4", "Neck1": "Neck",
                 **{f"{s}{a}": f"{s}{b}" for s in ("Left", "Right") for a, b in (
                     ("Shoulder", "Collar"), ("Arm", "Shoulder"), ("ForeArm", "Elbow"), ("Hand", "Wrist"),
                     ("UpLeg", "Hip"), ("Leg", "Knee"), ("Foot", "Ankle"), ("ToeBase", "Toe"))}},
}  # fmt: skip
# (label, file under the motion data folder, model skeleton, joint map, renaming of the CMU rig)
RIG_CLIPS = [
    ("Bandai-Namco", "human/bandai1/dataset-1_walk_normal_001.bvh", "smpl22", "bandai", None),
    ("Bandai-Namco", "human/bandai2/dataset-2_run_normal_001.bvh", "smpl22", "bandai", None),
    ("CMU (cgspeed BVH)", "human/cmu/02_01.bvh", "smpl22", "cmu", None),
    ("DeepMimic humanoid", "human/deepmimic/humanoid3d_walk.txt", "smpl22", "deepmimic_humanoid", None),
    ("LaFAN1 (CMU 02_01 renamed)", "human/cmu/02_01.bvh", "smpl22", "lafan1", "lafan1"),
    ("100STYLE (CMU 02_01 renamed)", "human/cmu/02_01.bvh", "smpl22", "style100", "style100"),
    ("Mixamo (CMU 02_01 renamed)", "human/cmu/02_01.bvh", "smpl22", "mixamo", "mixamo"),
    ("MANN dog", "quadruped/mann_dog/D1_004_KAN01_001.bvh", "smal35", "mann_dog", None),
    ("DeepMimic dog", "quadruped/deepmimic_dog/dog3d_trot.txt", "smal35", "deepmimic_dog", None),
]


def rig_round_trips(data: Path) -> list[dict]:
    """``omg.retarget.rig_round_trip`` for every row of ``RIG_CLIPS`` whose file is under ``data``."""
    from dataclasses import replace

    from omg.io.read import read_motion
    from omg.retarget import rig_round_trip

    rows = []
    for label, rel, skeleton, jmap, rename in RIG_CLIPS:
        if not (Path(data) / rel).exists():
            continue
        rig = read_motion(Path(data) / rel)
        if rename:
            rig = replace(rig, names=[RENAMED_CMU[rename].get(n, n) for n in rig.names])
        rows.append({"label": label, "file": rel, **rig_round_trip(rig, skeleton, jmap)})
    return rows


def bench_rig(data: Path) -> list[dict]:
    """Round trip of real clips through the model skeletons and back onto their own rigs
    (``omg.retarget.rig_round_trip``): import onto SMPL-22 / SMAL-35, ``onto_rig`` back, errors
    against the original after one translation. Prints one Markdown row per rig.

    Args:
        data: the motion data folder (../shared/data/motion: human/, quadruped/)

    Returns:
        One row per rig: label, file, and the round trip's figures.
    """
    if not Path(data).is_dir():
        raise UsageError(f"--data {data}: not a folder (the motion data folder, e.g. ../shared/data/motion)")
    rows = rig_round_trips(data)
    if not rows:
        raise UsageError(f"--data {data}: none of the benchmark's clips is there ({RIG_CLIPS[0][1]}, ...)")
    print("| rig | clip | joints (map points) | frames | mean error cm | max error cm | mapped joints mean cm "
          "| bone length change cm | foot slide cm/s original -> back |\n|---|---|---:|---:|---:|---:|---:|---:|---:|")
    for r in rows:
        print(f"| {r['label']} | {Path(r['file']).name} | {r['joints']} ({r['mapped']}) | {r['frames']} "
              f"| {r['mean_cm']:.2f} | {r['max_cm']:.2f} | {r['mapped_mean_cm']:.2f} | {r['bone_cm']:.2f} "
              f"| {r['slide_original_cm_s']:.1f} -> {r['slide_back_cm_s']:.1f} |", flush=True)
    return rows


BENCHMARKS = {"data": (bench_data, {}), "train": (bench_train, {}), "sample": (bench_sample, {}),
              "quality": (bench_quality, {}), "following": (bench_following, {}), "sides": (bench_sides, {}),
              "plan": (bench_plan, {}), "gpu": (bench_gpu, {}), "rig": (bench_rig, {})}


def main(argv: list[str]) -> None:
    run_subcommands("omg bench", "Speed and memory measurements (one Markdown table row per measurement).",
                    BENCHMARKS, argv)


def _worker_main(argv: list[str]) -> None:
    """``python -m omg.tools.bench KIND ...`` (``loader_worker``): bad input ends as one JSON line
    on stdout and exit code 2, which the parent (``_run_measured``) turns back into a UsageError."""
    from omg.data.datamodule import TooManyBadSamples

    try:
        loader_worker(argv)
    except UsageError as e:
        message = str(e)
    except TooManyBadSamples as e:  # from a data worker: torch re-raises it with the worker's traceback as its text
        message = last_line(str(e)).removeprefix(f"{TooManyBadSamples.__module__}.TooManyBadSamples: ")
    else:
        return
    print(json.dumps({USAGE_ERROR: message}), flush=True)
    raise SystemExit(2)


if __name__ == "__main__":
    _worker_main(sys.argv[1:])
