"""``omg bench data``: the streaming loader against the in-memory one, windows/s and peak memory,
each loader measured in its own process (``loader_worker``, run as ``python -m omg.tools.bench``)."""

from __future__ import annotations

import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from omg.data.loaders import DEFAULT_CACHE_MB
from omg.errors import UsageError
from omg.tools.args import NonNegativeInt, PositiveFiniteFloat, PositiveInt, number_type
from omg.tools.bench.measure import USAGE_ERROR, run_measured, tree_pss
from omg.tools.common import last_line

MIN_WINDOW = 60  # frames: the shortest window the data benchmark cuts (2 s at 30 fps)
WindowFrames = number_type("WindowFrames", int, [(">=", MIN_WINDOW)],
                           f"an integer >= {MIN_WINDOW} (frames: the shortest window the benchmark cuts)")


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


def loader_worker(argv: list[str]) -> None:
    """Iterate one loader and print {"windows_per_s": ...} (runs in its own process).

    ``argv``: KIND (streaming or in-memory) SHARDS BATCH_SIZE WORKERS BATCHES MAX_LEN CACHE_MB."""
    import os

    kind, shards, batch_size, workers, batches, max_len = argv[0], argv[1], *map(int, argv[2:6])
    cache_mb = float(argv[6])
    # the loaders without Lightning's data module: a data-only process imports no Lightning
    from omg.data.loaders import DEFAULT_TIMEOUT_S, in_memory_loader, stream_loader
    from omg.data.mixture import load_mixture
    from omg.data.windows import Collate, WindowSampler

    baseline = tree_pss(os.getpid())  # the interpreter with torch and omg imported, before any data

    mixture = load_mixture(shards, "--shards")
    spec = mixture.spec()
    collate = Collate(np.asarray(spec.mean, np.float32), np.asarray(spec.std, np.float32))
    windows = WindowSampler(max_len, MIN_WINDOW, "windows")
    if kind == "streaming":  # the training stream as `omg fit` reads it (data.verify_shards, data.timeout)
        loader = stream_loader(mixture, 0, 1, windows, batches + 10, batch_size, collate, num_workers=workers,
                               shuffle_buffer=500, checks=mixture.checks, timeout=DEFAULT_TIMEOUT_S, cache_mb=cache_mb)
    else:
        loader = in_memory_loader(mixture.urls, mixture.manifest["feature_dim"], windows, batch_size, workers,
                                  collate)

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
    sample_interval: PositiveFiniteFloat = 0.05,
    cache_mb: float = DEFAULT_CACHE_MB,
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
        sample_interval: seconds between two samples of the process tree's memory (each sample costs
            about 40 ms of CPU, beside the loader's own: a longer interval leaves the loader more of a small
            machine and may miss a short peak)
        cache_mb: the streaming loader's data.cache_mb: a set whose decoded motion fits is decoded once per worker
            (0: every draw reads and decodes its shard)
        command: the command line, printed with the results

    Returns:
        Per loader: windows per second, peak memory of the process tree and of the loader (MiB).
    """
    _check_data_args(clips, batch_size, shards, cache_mb)
    with tempfile.TemporaryDirectory(prefix="omg-bench-") as tmp:
        if shards is None:
            shards = str(Path(tmp) / "shards")
            t = time.perf_counter()
            write_random_shards(Path(shards), clips, feature_dim)
            print(f"wrote {clips} random clips ({feature_dim}-d) in {time.perf_counter() - t:.1f} s", file=sys.stderr)
        rows = {}
        for kind in ("streaming", "in-memory"):
            cmd = [sys.executable, "-m", "omg.tools.bench", kind, shards, str(batch_size), str(workers), str(batches),
                   str(max_len), str(cache_mb)]
            result, peak = run_measured(cmd, f"the {kind} loader", sample_interval)
            rows[kind] = (result["windows_per_s"], peak / 2**20, (peak - result["baseline"]) / 2**20)
    print("| loader | windows/s | peak PSS, whole process tree (MiB) | of which the loader (MiB) | command |")
    print("|---|---|---|---|---|")
    for kind, (rate, total, loader) in rows.items():
        print(f"| {kind} | {rate:,.0f} | {total:,.0f} | {loader:,.0f} | `{command}` |")
    (s_rate, s_total, s_mem), (m_rate, m_total, m_mem) = rows["streaming"], rows["in-memory"]
    print(f"\nstreaming / in-memory: {s_rate / m_rate:.2f}x the rate, {s_mem / m_mem:.2f}x the loader memory "
          f"({s_total / m_total:.2f}x the whole process tree); target: >= 0.5x the rate, <= 0.25x the memory")
    return rows


def _check_data_args(clips: int, batch_size: int, shards: str | None, cache_mb: float) -> None:
    """Everything the loader workers would refuse, refused before any clip is written."""
    if not cache_mb >= 0:  # also NaN
        raise UsageError(f"--cache_mb must be >= 0 MiB (0: decode every shard at each read), got {cache_mb}")
    if shards is None:
        where = "--clips"
    else:
        from omg.data.loaders import resolve_shards

        try:
            _, manifest, _ = resolve_shards(shards)
        except UsageError as e:  # its messages name the path, not the option
            raise UsageError(f"--shards: {e}" if shards in str(e) else f"--shards {shards}: {e}") from None
        clips, where = manifest["num_clips"], f"--shards {shards} (its manifest)"
    if clips < batch_size:
        raise UsageError(f"{where} gives {clips} clips, fewer than --batch_size {batch_size}: the in-memory "
                         "loader would never fill a batch; lower --batch_size or use more clips")


def worker_main(argv: list[str]) -> None:
    """``python -m omg.tools.bench KIND ...`` (``loader_worker``): bad input ends as one JSON line
    on stdout and exit code 2, which the parent (``run_measured``) turns back into a UsageError."""
    from omg.data.loaders import TooManyBadSamples

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
