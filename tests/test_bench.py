"""``omg bench data`` starts each loader in its own process by a module path
(``python -m omg.tools.bench KIND ...``, the package's ``__main__``): the worker runs by that path,
its figures come back as the table, and its bad input comes back as one line."""

from __future__ import annotations

import subprocess
import sys

import pytest

from helpers import MINI
from omg.cli import main
from omg.errors import UsageError
from omg.tools.bench.measure import run_measured

TRAIN = str(MINI / "human263" / "train")  # the committed mini shards: 90 clips
# the memory sampler's interval (s): at the default 0.05 its reads of /proc take CPU from the worker it samples,
# on the two cores the worker shares; the figures are not what is checked
SAMPLE_S = "0.5"


@pytest.mark.slow  # three worker processes, each importing torch
def test_the_data_benchmark_runs_its_workers_by_module_path(capsys):
    main(["bench", "data", "--shards", TRAIN, "--batch-size", "4", "--batches", "2", "--workers", "0",
          "--max-len", "60", "--sample-interval", SAMPLE_S])
    out = capsys.readouterr().out
    for kind in ("streaming", "in-memory"):
        line = next(line for line in out.splitlines() if line.startswith(f"| {kind} |"))
        rate, total, loader = (float(cell.replace(",", "")) for cell in line.split("|")[2:5])
        assert rate > 0 and total >= loader and total > 0, line  # the tree's peak holds the loader
    assert "streaming / in-memory:" in out
    # bad input the parent cannot see (a batch no pass fills) ends in the worker, and comes back as one line
    worker = [sys.executable, "-m", "omg.tools.bench", "in-memory", TRAIN, "100000", "0", "2", "60", "0"]
    with pytest.raises(UsageError, match=r"^the in-memory loader: a whole pass yields no batch of 100000"):
        run_measured(worker, "the in-memory loader", float(SAMPLE_S))


def test_a_data_only_process_imports_no_lightning():
    """Processes that only read data: the data benchmark's worker (``python -m omg.tools.bench`` runs the package,
    then its ``__main__``), ``omg shards``, and a loader worker started by spawn or forkserver, which unpickles the
    training stream from ``omg.data.loaders``. None imports Lightning, nor what Lightning's start-up pulls in
    (torchmetrics, and through it torchvision and transformers)."""
    heavy = ("lightning", "torchmetrics", "torchvision", "transformers")
    code = ("import sys, omg.tools.bench.__main__, omg.tools.shards, omg.data.loaders; "
            f"print(sorted(m for m in {heavy} if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"
