"""``omg bench``: speed and memory measurements whose figures go into the README.

Every benchmark makes its own inputs (no dataset download) and prints one Markdown table row
per measurement, with the command that reproduces it.
"""

from __future__ import annotations

import json
import shlex
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from omg.cli import ToolParser, last_line, nonneg_int, positive_float, positive_int
from omg.errors import UsageError

MIN_WINDOW = 60  # frames: the shortest window the data benchmark cuts (2 s at 30 fps)
USAGE_ERROR = "usage_error"  # the key of a worker's JSON line that reports bad input


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
        raise RuntimeError(f"benchmark worker failed: {err.strip().splitlines()[-1] if err.strip() else proc.returncode}")
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
    """Iterate one loader and print {"windows_per_s": ...} (runs in its own process)."""
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
                                 "--batch-size; lower --batch-size or use more clips")

    it = endless()
    for _ in range(10):  # warm-up: workers started, buffers filled
        next(it)
    start, windows = time.perf_counter(), 0
    for _ in range(batches):
        windows += len(next(it)["id"])
    print(json.dumps({"windows_per_s": windows / (time.perf_counter() - start), "baseline": baseline}))


def bench_data(argv: list[str]) -> None:
    p = ToolParser(prog="omg bench data", description="Streaming vs in-memory loader: windows/s and peak memory.")
    p.add_argument("--clips", type=positive_int, default=10_000, help="random clips to write (without --shards)")
    p.add_argument("--feature-dim", type=positive_int, default=263, help="features per frame of the random clips")
    p.add_argument("--batch-size", type=positive_int, default=64)
    p.add_argument("--batches", type=positive_int, default=300, help="timed batches (after 10 warm-up batches)")
    p.add_argument("--workers", type=nonneg_int, default=2, help="loader worker processes (0: load in the main process)")
    p.add_argument("--max-len", type=positive_int, default=196, help=f"longest window in frames (>= {MIN_WINDOW})")
    p.add_argument("--shards", help="an existing shard directory (or URL pattern) to read instead of a random set")
    args = p.parse_args(argv)
    _check_data_args(args)
    with tempfile.TemporaryDirectory(prefix="omg-bench-") as tmp:
        shards = args.shards
        if shards is None:
            shards = str(Path(tmp) / "shards")
            t = time.perf_counter()
            write_random_shards(Path(shards), args.clips, args.feature_dim)
            print(f"wrote {args.clips} random clips ({args.feature_dim}-d) in {time.perf_counter() - t:.1f} s", file=sys.stderr)
        rows = {}
        for kind in ("streaming", "in-memory"):
            cmd = [sys.executable, "-m", "omg.bench", "_loader", kind, shards, str(args.batch_size), str(args.workers),
                   str(args.batches), str(args.max_len)]
            result, peak = _run_measured(cmd, f"the {kind} loader")
            rows[kind] = (result["windows_per_s"], peak / 2**20, (peak - result["baseline"]) / 2**20)
    command = "omg bench data " + shlex.join(argv)
    print("| loader | windows/s | peak PSS, whole process tree (MiB) | of which the loader (MiB) | command |")
    print("|---|---|---|---|---|")
    for kind, (rate, total, loader) in rows.items():
        print(f"| {kind} | {rate:,.0f} | {total:,.0f} | {loader:,.0f} | `{command}` |")
    (s_rate, s_total, s_mem), (m_rate, m_total, m_mem) = rows["streaming"], rows["in-memory"]
    print(f"\nstreaming / in-memory: {s_rate / m_rate:.2f}x the rate, {s_mem / m_mem:.2f}x the loader memory "
          f"({s_total / m_total:.2f}x the whole process tree); target: >= 0.5x the rate, <= 0.25x the memory")


def _check_data_args(args) -> None:
    """Everything the loader workers would refuse, refused before any clip is written."""
    if args.max_len < MIN_WINDOW:
        raise UsageError(f"--max-len must be >= {MIN_WINDOW} frames (the shortest window the benchmark cuts), "
                         f"got {args.max_len}")
    if args.shards is None:
        clips, where = args.clips, "--clips"
    else:
        from omg.data.datamodule import resolve_shards

        try:
            _, manifest, _ = resolve_shards(args.shards)
        except UsageError as e:  # its messages name the path, not the option
            raise UsageError(f"--shards: {e}" if args.shards in str(e) else f"--shards {args.shards}: {e}") from None
        clips, where = manifest["num_clips"], f"--shards {args.shards} (its manifest)"
    if clips < args.batch_size:
        raise UsageError(f"{where} gives {clips} clips, fewer than --batch-size {args.batch_size}: the in-memory "
                         "loader would never fill a batch; lower --batch-size or use more clips")


# -- train -----------------------------------------------------------------------------------
PRECISIONS = ("32-true", "bf16-mixed", "16-mixed", "bf16-true", "16-true", "64-true", "transformer-engine",
              "transformer-engine-float16", "32", "16", "bf16", "64")  # Lightning's Trainer(precision=...)
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


def bench_train(argv: list[str]) -> None:
    import lightning as L
    import torch
    from lightning.fabric.utilities.exceptions import MisconfigurationException
    from lightning.pytorch.strategies import StrategyRegistry

    from omg.lit.pretrain import PretrainModule
    from omg.models.dit import FLAVORS

    p = ToolParser(prog="omg bench train", description="Training step time, frames/s, MFU and peak memory of a DiT flavor.")
    p.add_argument("--flavor", default="mini", choices=list(FLAVORS))
    p.add_argument("--precision", default="bf16-mixed" if torch.cuda.is_available() else "32-true", choices=PRECISIONS)
    p.add_argument("--strategy", default="auto", choices=["auto", *StrategyRegistry.available_strategies()],
                   metavar="STRATEGY", help="auto, ddp, deepspeed_stage_2, ... (Lightning's strategy names)")
    p.add_argument("--batch-size", type=positive_int, default=8)
    p.add_argument("--frames", type=positive_int, default=300)
    p.add_argument("--steps", type=positive_int, default=20, help="timed steps")
    p.add_argument("--warmup", type=nonneg_int, default=5, help="untimed steps first")
    p.add_argument("--activation-checkpointing", action="store_true")
    p.add_argument("--peak-tflops", type=positive_float, help="the device's peak, when omg does not know it")
    args = p.parse_args(argv)

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
        trainer = L.Trainer(max_steps=args.warmup + args.steps, precision=args.precision, strategy=args.strategy,
                            devices=1, logger=False, enable_checkpointing=False, enable_progress_bar=False,
                            enable_model_summary=False, callbacks=[Timer()], gradient_clip_val=1.0)
    except (ValueError, TypeError, ImportError, MisconfigurationException) as e:
        raise UsageError(f"--precision {args.precision} --strategy {args.strategy}: {last_line(str(e))}") from None

    D = 263
    spec = unnormalised_spec(D, fps=30.0)
    module = PretrainModule(flavor=args.flavor, dit={"activation_checkpointing": args.activation_checkpointing},
                            spec=spec, warmup_steps=10, ema_decay=0.9999)

    class RandomBatches(torch.utils.data.IterableDataset):
        def __iter__(self):
            g = torch.Generator().manual_seed(0)
            while True:
                motion = 0.1 * torch.randn(args.batch_size, args.frames, D, generator=g)
                yield {"motion": motion, "mask": torch.ones(args.batch_size, args.frames, dtype=torch.bool)}

    trainer.fit(module, torch.utils.data.DataLoader(RandomBatches(), batch_size=None))
    step = sum(times[args.warmup:]) / len(times[args.warmup:])
    frames_per_s = args.batch_size * args.frames / step
    device, peak = device_peak_tflops()
    peak = args.peak_tflops or peak
    train_flops = 3 * module.config.flops(args.batch_size, args.frames)  # backward ~ 2x forward
    mfu = f"{100 * train_flops / step / (peak * 1e12):.1f}%" if peak else "n/a"
    memory = peak_memory()
    params = sum(p.numel() for p in module.model.parameters())
    print("| flavor | params | device | precision / strategy | batch x frames | step | frames/s | model TFLOP/s | MFU "
          "| peak memory | command |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    print(f"| {args.flavor} | {params / 1e6:.0f}M | {device} | {args.precision} / {args.strategy} | {args.batch_size} x {args.frames} "
          f"| {step * 1000:.0f} ms | {frames_per_s:,.0f} | {train_flops / step / 1e12:.3f} | {mfu} | {memory} "
          f"| `omg bench train {shlex.join(argv)}` |")


# -- sample ----------------------------------------------------------------------------------
def batch_sizes(text: str) -> list[int]:
    """An argparse ``type``: comma-separated positive integers."""
    import argparse

    try:
        sizes = [positive_int(part.strip()) for part in text.split(",")]
    except (ValueError, argparse.ArgumentTypeError):
        raise argparse.ArgumentTypeError(f"expected comma-separated integers >= 1 such as 1,8,32, got {text!r}") from None
    return sizes


def bench_sample(argv: list[str]) -> None:
    import torch

    from omg.diffusion import Diffusion
    from omg.lit.controlnet import ControlNetModule
    from omg.models.dit import FLAVORS
    from omg.registry import TEXT_ENCODERS

    p = ToolParser(prog="omg bench sample", description="Seconds per motion of guided DDIM sampling (frozen DiT + ControlNet).")
    p.add_argument("--flavor", default="mini", choices=list(FLAVORS))
    p.add_argument("--frames", type=positive_int, default=196)
    p.add_argument("--steps", type=nonneg_int, default=200,
                   help=f"DDIM steps, 1..{Diffusion.num_timesteps} (0 with --token-steps: time only the token padding)")
    p.add_argument("--batch-sizes", type=batch_sizes, default="1,8,32", help="comma-separated batch sizes to try")
    p.add_argument("--text-encoder", default="hash", choices=TEXT_ENCODERS.names(),
                   help="the encoder runs once per batch; hash keeps it out of the timing")
    p.add_argument("--precision", default="bf16" if torch.cuda.is_available() else "fp32", choices=("fp32", "bf16"))
    p.add_argument("--token-steps", type=nonneg_int, default=0,
                   help="also time this many guided denoiser steps with text tokens padded to CLIP's 77 vs trimmed "
                        "to the longest caption, at the first batch size (0: skip; with --steps 0: only this)")
    args = p.parse_args(argv)
    if args.steps > Diffusion.num_timesteps:
        raise UsageError(f"--steps must be in 1..{Diffusion.num_timesteps} (the model's diffusion steps), got {args.steps}")
    if args.steps == 0 and not args.token_steps:
        raise UsageError("--steps 0 times nothing: give --steps 1 or more, or --token-steps N to time only the "
                         "token padding")

    spec = unnormalised_spec(263, fps=20.0)
    device = "cuda" if torch.cuda.is_available() else "cpu"
    module = ControlNetModule(base={"flavor": args.flavor, "dit": None, "spec": spec}, text_encoder=args.text_encoder)
    module = module.to(device, torch.bfloat16 if args.precision == "bf16" else torch.float32).eval()
    if args.token_steps:
        bench_token_padding(module, args, argv, device)
        if args.steps == 0:
            return
    print("| flavor | device | precision | batch | s per batch | s per motion | peak memory | command |\n|---|---|---|---|---|---|---|---|")
    for batch in args.batch_sizes:
        prompts = ["a person walks forward and waves"] * batch
        module.generate(prompts, args.frames, steps=2)  # warm-up
        if device == "cuda":
            torch.cuda.synchronize()
            torch.cuda.reset_peak_memory_stats()
        start = time.perf_counter()
        module.generate(prompts, args.frames, steps=args.steps)
        if device == "cuda":
            torch.cuda.synchronize()
        seconds = time.perf_counter() - start
        memory = peak_memory()
        name = torch.cuda.get_device_name() if device == "cuda" else "cpu"
        print(f"| {args.flavor} | {name} | {args.precision} | {batch} | {seconds:.2f} | {seconds / batch:.3f} | {memory} "
              f"| `omg bench sample {shlex.join(argv)}` |", flush=True)


CAPTIONS = ["a person walks forward and waves", "a man jumps in place twice",
            "someone turns around slowly, then sits down on a chair", "a person kicks with the right leg"]


def bench_token_padding(module, args, argv: list[str], device: str, context: int = 77) -> None:
    """ms per guided denoiser step (one D_u + D_c pass) with the captions' tokens padded to
    CLIP's 77-token context vs trimmed to the longest caption of the batch."""
    import torch

    batch = args.batch_sizes[0]
    dtype = next(module.controlnet.parameters()).dtype
    trimmed = module.encode_text([CAPTIONS[i % len(CAPTIONS)] for i in range(batch)])
    padded = trimmed.padded(max(context, trimmed.tokens.shape[1]))
    g = torch.Generator().manual_seed(0)
    x = torch.randn(batch, args.frames, module.spec["feature_dim"], generator=g).to(device, dtype)
    t = torch.full((batch,), 500, device=device)
    scale = module.hparams.guidance_scale

    def ms_per_step(text) -> float:
        def step():
            module.controlnet.forward_guided(x, t, text.tokens.to(dtype), text.mask, text.eot, scale)

        with torch.no_grad():
            step()  # warm-up
            if device == "cuda":
                torch.cuda.synchronize()
            start = time.perf_counter()
            for _ in range(args.token_steps):
                step()
            if device == "cuda":
                torch.cuda.synchronize()
        return 1000 * (time.perf_counter() - start) / args.token_steps

    name = torch.cuda.get_device_name() if device == "cuda" else "cpu"
    rows = {f"{padded.tokens.shape[1]} (padded like CLIP)": ms_per_step(padded),
            f"{trimmed.tokens.shape[1]} (trimmed)": ms_per_step(trimmed)}
    print("| flavor | device | precision | batch x frames | text tokens | ms per guided step | command |\n"
          "|---|---|---|---|---|---|---|")
    for tokens, ms in rows.items():
        print(f"| {args.flavor} | {name} | {args.precision} | {batch} x {args.frames} | {tokens} | {ms:.1f} "
              f"| `omg bench sample {shlex.join(argv)}` |")
    padded_ms, trimmed_ms = rows.values()
    print(f"\ntrimming: {padded_ms / trimmed_ms:.2f}x faster per step\n", flush=True)


BENCHMARKS = {"data": bench_data, "train": bench_train, "sample": bench_sample}


def main(argv: list[str]) -> None:
    if not argv or argv[0] in ("-h", "--help"):
        print("usage: omg bench {" + ",".join(BENCHMARKS) + "} [options]\n\n"
              "  data   streaming vs in-memory loader: windows/s and peak memory\n"
              "  train  DiT training step time, frames/s, MFU and peak memory\n"
              "  sample seconds per motion of guided DDIM sampling")
        return
    if argv[0] == "_loader":
        return loader_worker(argv[1:])
    if argv[0] not in BENCHMARKS:
        raise UsageError(f"unknown benchmark {argv[0]!r}; choose from {', '.join(BENCHMARKS)}")
    BENCHMARKS[argv[0]](argv[1:])


def _worker_main(argv: list[str]) -> None:
    """``python -m omg.bench``: bad input ends as one JSON line on stdout and exit code 2, which
    the parent (``_run_measured``) turns back into a UsageError."""
    from omg.data.datamodule import TooManyBadSamples

    try:
        main(argv)
    except UsageError as e:
        message = str(e)
    except TooManyBadSamples as e:  # from a data worker, wrapped in the worker's traceback
        message = last_line(str(e)).removeprefix(f"{TooManyBadSamples.__module__}.TooManyBadSamples: ")
    else:
        return
    print(json.dumps({USAGE_ERROR: message}), flush=True)
    raise SystemExit(2)


if __name__ == "__main__":
    _worker_main(sys.argv[1:])
