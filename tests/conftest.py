"""Shared fixtures: the real-data folder, small shard sets, one torch thread per test process.
Plain helpers (paths, clips, rigs, the tiny DiT) live in the ``helpers`` package."""

from __future__ import annotations

import signal
from pathlib import Path

import pytest


def pytest_collection_modifyitems(config, items):
    """The longest tests and xdist groups first (helpers.schedule): with the xdist workers the long ones start
    at once and the short tests fill the time around them, instead of one long test starting last."""
    from helpers.schedule import longest_first

    longest_first(items)


def pytest_collection_finish(session):
    """Tiny models: thread hand-offs cost more than they gain on a small shared CPU, and one thread keeps
    trained test models bit-reproducible; set before any fixture, for those shared by a whole session.
    Here, not at import: under xdist the controller imports this file too but collects and runs no test,
    so torch (and the helpers, which import omg) load only in the processes that test."""
    import torch

    torch.set_num_threads(1)


@pytest.fixture
def shared_motion() -> Path:
    from helpers import SHARED_MOTION

    if not (SHARED_MOTION / "manifest.json").exists():
        pytest.skip(f"real motion data not found at {SHARED_MOTION} (the shared/ folder beside the checkout)")
    return SHARED_MOTION


@pytest.fixture
def toy_shards(tmp_path) -> Path:
    from helpers import write_toy_shards

    return write_toy_shards(tmp_path / "toy")


@pytest.fixture(autouse=True)
def _quiet_threads():
    import torch

    torch.set_num_threads(1)  # again for each test: a test before may have set another number


@pytest.fixture(autouse=True)
def _ctrl_c_as_python_sets_it():
    """Each test starts with Python's own Ctrl-C handler. pytest started with SIGINT ignored (a script's
    background job, `python -m pytest … &`, which the shell starts so; or a test that left it so: Lightning's
    trainer ignores it for good once it has caught a KeyboardInterrupt) passes the ignore on to every process
    the tests start, and a Python started with SIGINT ignored keeps it so: a test that sends Ctrl-C to an
    `omg` process, as a terminal does (tests/test_run_faults.py), then waited for nothing."""
    if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)


@pytest.fixture(scope="session")
def h263_shards(tmp_path_factory) -> Path:
    """Small humanml3d263 train/val shard sets."""
    from helpers import walking_clip
    from omg.data.shards import ShardWriter
    from omg.motion import get_representation
    from omg.skeleton import SMPL22

    out = tmp_path_factory.mktemp("h263")
    rep = get_representation("humanml3d263", SMPL22)
    ShardWriter(out / "train", rep, 20.0, max_clips=8, log=lambda m: None).write(walking_clip(i) for i in range(32))
    ShardWriter(out / "val", rep, 20.0, max_clips=8, log=lambda m: None).write(walking_clip(100 + i) for i in range(8))
    return out


@pytest.fixture(scope="session")
def omgpt_ckpt(tmp_path_factory) -> Path:
    """`omg fit --config configs/mini/omgpt.yaml`, a few steps of a tiny model; its last checkpoint
    (tests/test_omgpt*.py)."""
    import torch

    from helpers.omgpt import fit_mini

    torch.manual_seed(0)
    return fit_mini(tmp_path_factory.mktemp("omgpt"))
