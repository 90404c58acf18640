"""What the benchmarks share: a worker process run with its process tree's memory sampled
(``run_measured``), and the inputs that need no dataset (``Flavor``, ``unnormalised_spec``)."""

from __future__ import annotations

import json
import subprocess
import threading
import time
from typing import Literal

from omg.errors import UsageError
from omg.models.dit import FLAVORS

USAGE_ERROR = "usage_error"  # the key of a worker's JSON line that reports bad input
Flavor = Literal[tuple(FLAVORS)]  # type: ignore[valid-type]  # mini, base, large, huge, giant


def unnormalised_spec(dim: int, fps: float) -> dict:
    """A humanml3d263 data spec with identity normalisation: the models need no dataset to time."""
    return {"representation": "humanml3d263", "skeleton": "smpl22", "fps": fps, "feature_dim": dim,
            "mean": [0.0] * dim, "std": [1.0] * dim}


def tree_pss(pid: int) -> int:
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


def run_measured(cmd: list[str], what: str = "benchmark worker", interval: float = 0.05) -> tuple[dict, int]:
    """Run a command, sampling its process tree's memory every ``interval`` seconds; (its JSON result, peak
    PSS bytes). A sample reads each process's smaps_rollup, which walks its page tables: about 40 ms of CPU
    for a process that imported torch, taken beside the command's own on a small machine.

    A worker that stops on bad input prints ``{"usage_error": ...}`` and exits with code 2:
    that is a ``UsageError`` here too; any other failure is a bug and a RuntimeError."""
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    peak = 0
    done = threading.Event()

    def sample():
        nonlocal peak
        while not done.is_set():
            peak = max(peak, tree_pss(proc.pid))
            time.sleep(interval)

    sampler = threading.Thread(target=sample, daemon=True)
    sampler.start()
    out, err = proc.communicate()
    done.set()
    sampler.join()
    if proc.returncode != 0:
        if proc.returncode == 2 and (reported := last_json(out)) and USAGE_ERROR in reported:
            raise UsageError(f"{what}: {reported[USAGE_ERROR]}")
        reason = err.strip().splitlines()[-1] if err.strip() else proc.returncode
        raise RuntimeError(f"benchmark worker failed: {reason}")
    return json.loads(out.strip().splitlines()[-1]), peak


def last_json(out: str) -> dict | None:
    """The worker's last stdout line as a JSON object, or None."""
    lines = out.strip().splitlines()
    try:
        value = json.loads(lines[-1]) if lines else None
    except json.JSONDecodeError:
        return None
    return value if isinstance(value, dict) else None
