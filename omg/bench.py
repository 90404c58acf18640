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

from omg.cli import ToolParser
from omg.errors import UsageError


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


def _run_measured(cmd: list[str]) -> tuple[dict, int]:
    """Run a command, sampling its process tree's memory; (its JSON result, peak PSS bytes)."""
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
        raise RuntimeError(f"benchmark worker failed: {err.strip().splitlines()[-1] if err.strip() else proc.returncode}")
    return json.loads(out.strip().splitlines()[-1]), peak


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
            yield from loader

    it = endless()
    for _ in range(10):  # warm-up: workers started, buffers filled
        next(it)
    start, windows = time.perf_counter(), 0
    for _ in range(batches):
        windows += len(next(it)["id"])
    print(json.dumps({"windows_per_s": windows / (time.perf_counter() - start), "baseline": baseline}))


def bench_data(argv: list[str]) -> None:
    p = ToolParser(prog="omg bench data", description="Streaming vs in-memory loader: windows/s and peak memory.")
    p.add_argument("--clips", type=int, default=10_000)
    p.add_argument("--feature-dim", type=int, default=263)
    p.add_argument("--batch-size", type=int, default=64)
    p.add_argument("--batches", type=int, default=300)
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--max-len", type=int, default=196)
    p.add_argument("--shards", help="an existing shard directory to read instead of a random set")
    args = p.parse_args(argv)
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
            result, peak = _run_measured(cmd)
            rows[kind] = (result["windows_per_s"], peak / 2**20, (peak - result["baseline"]) / 2**20)
    command = "omg bench data " + shlex.join(argv)
    print("| loader | windows/s | peak PSS, whole process tree (MiB) | of which the loader (MiB) | command |")
    print("|---|---|---|---|---|")
    for kind, (rate, total, loader) in rows.items():
        print(f"| {kind} | {rate:,.0f} | {total:,.0f} | {loader:,.0f} | `{command}` |")
    (s_rate, s_total, s_mem), (m_rate, m_total, m_mem) = rows["streaming"], rows["in-memory"]
    print(f"\nstreaming / in-memory: {s_rate / m_rate:.2f}x the rate, {s_mem / m_mem:.2f}x the loader memory "
          f"({s_total / m_total:.2f}x the whole process tree); target: >= 0.5x the rate, <= 0.25x the memory")


# -- train -----------------------------------------------------------------------------------
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

    from omg.lit.pretrain import PretrainModule

    p = ToolParser(prog="omg bench train", description="Training step time, frames/s, MFU and peak memory of a DiT flavor.")
    p.add_argument("--flavor", default="mini")
    p.add_argument("--precision", default="bf16-mixed" if torch.cuda.is_available() else "32-true")
    p.add_argument("--strategy", default="auto", help="auto, ddp, deepspeed_stage_2, ...")
    p.add_argument("--batch-size", type=int, default=8)
    p.add_argument("--frames", type=int, default=300)
    p.add_argument("--steps", type=int, default=20, help="timed steps")
    p.add_argument("--warmup", type=int, default=5)
    p.add_argument("--activation-checkpointing", action="store_true")
    p.add_argument("--peak-tflops", type=float, help="the device's peak, when omg does not know it")
    args = p.parse_args(argv)

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

    trainer = L.Trainer(max_steps=args.warmup + args.steps, precision=args.precision, strategy=args.strategy,
                        devices=1, logger=False, enable_checkpointing=False, enable_progress_bar=False,
                        enable_model_summary=False, callbacks=[Timer()], gradient_clip_val=1.0)
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
def bench_sample(argv: list[str]) -> None:
    import torch

    from omg.lit.controlnet import ControlNetModule

    p = ToolParser(prog="omg bench sample", description="Seconds per motion of guided DDIM sampling (frozen DiT + ControlNet).")
    p.add_argument("--flavor", default="mini")
    p.add_argument("--frames", type=int, default=196)
    p.add_argument("--steps", type=int, default=200)
    p.add_argument("--batch-sizes", default="1,8,32", help="comma-separated batch sizes to try")
    p.add_argument("--text-encoder", default="hash", help="the encoder runs once per batch; hash keeps it out of the timing")
    p.add_argument("--precision", default="bf16" if torch.cuda.is_available() else "fp32", choices=("fp32", "bf16"))
    args = p.parse_args(argv)

    spec = unnormalised_spec(263, fps=20.0)
    device = "cuda" if torch.cuda.is_available() else "cpu"
    module = ControlNetModule(base={"flavor": args.flavor, "dit": None, "spec": spec}, text_encoder=args.text_encoder)
    module = module.to(device, torch.bfloat16 if args.precision == "bf16" else torch.float32).eval()
    print("| flavor | device | precision | batch | s per batch | s per motion | peak memory | command |\n|---|---|---|---|---|---|---|---|")
    for batch in map(int, args.batch_sizes.split(",")):
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


if __name__ == "__main__":
    main(sys.argv[1:])
