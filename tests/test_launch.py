"""launch/ scripts: the process layout and accumulation they hand to `omg fit` (launchers faked); and
`omg fit --trainer.devices 2` on one machine, which starts its second rank itself (Lightning's subprocess
launcher runs the same command again), for real on two gloo processes."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from helpers import REPO
from helpers.configs import write_config


@pytest.fixture
def fake_bin(tmp_path):
    """`torchrun`, `srun` and `python` stand-ins; the launchers' own logic runs for real."""
    for name in ("torchrun", "srun"):
        path = tmp_path / name
        path.write_text('#!/usr/bin/env bash\necho "$(basename "$0") $*"\n')
        path.chmod(0o755)
    (tmp_path / "python").symlink_to(sys.executable)
    return tmp_path


def launch(script, config, fake_bin, **env):
    full_env = {**os.environ, "PATH": f"{fake_bin}:{os.environ['PATH']}", **env}
    return subprocess.run(["bash", str(REPO / "launch" / script), str(REPO / config)], capture_output=True, text=True,
                          env=full_env, cwd=REPO)


def test_torchrun_multi_node_keeps_the_global_batch(fake_bin):
    out = launch("torchrun.sh", "configs/pretrain_giant.yaml", fake_bin, NODES="2", GPUS="4", NODE_RANK="1",
                 MASTER_ADDR="10.1.2.3")
    assert out.returncode == 0, out.stderr
    line = out.stdout.strip()
    assert line.startswith("torchrun --nnodes 2 --nproc-per-node 4 --node-rank 1 --rdzv-backend c10d "
                           "--rdzv-endpoint 10.1.2.3:29500 --rdzv-id omg")
    assert "-m omg.cli fit --config" in line and "pretrain_giant.yaml" in line
    assert "--trainer.num_nodes 2 --trainer.devices 4 --data.batch_size 8 --trainer.accumulate_grad_batches 4" in line


def test_slurm_reads_the_allocation(fake_bin):
    out = launch("slurm.sbatch", "configs/pretrain_base.yaml", fake_bin, SLURM_JOB_NUM_NODES="4",
                 SLURM_NTASKS_PER_NODE="2")
    assert out.returncode == 0, out.stderr
    # --kill-on-bad-exit: one lost task ends the step instead of leaving the others in a collective
    assert "srun --kill-on-bad-exit=1 omg fit --config" in out.stdout
    assert ("--trainer.num_nodes 4 --trainer.devices 2 --data.batch_size 32 "
            "--trainer.accumulate_grad_batches 1" in out.stdout)
    assert "--ckpt_path last" in out.stdout


def test_an_impossible_global_batch_is_refused(fake_bin):
    out = launch("torchrun.sh", "configs/pretrain_base.yaml", fake_bin, NODES="3", GPUS="8")
    assert out.returncode == 2 and "not a multiple" in out.stderr


# -- one machine, two ranks: `omg fit --trainer.devices 2` --------------------------------------------

def console_script() -> Path:
    """The ``omg`` console script of this interpreter's environment (``pip install -e .`` writes it)."""
    script = Path(sys.executable).parent / "omg"
    assert script.is_file(), f"no omg console script beside {sys.executable}: install omg (pip install -e .)"
    return script


@pytest.mark.slow  # two training processes start up: about 40 s each way on 2 cores
@pytest.mark.parametrize("how", ["console script", "python -m omg"])
def test_devices_2_on_one_machine_starts_both_ranks_from_any_folder(h263_shards, tmp_path, how):
    """docs/guide/scale.md's "one node, all its GPUs" command on the CPU: rank 0 runs the command again for rank 1.
    From a folder that is not the checkout, with a config and an output folder given relative to it: rank
    1 must run the same program (not ``python $PWD/omg``) with the same arguments in the same folder."""
    write_config(tmp_path / "fit.yaml", h263_shards / "train", Path("run"), max_steps=2)
    program = [str(console_script())] if how == "console script" else [sys.executable, "-m", "omg"]
    env = {k: v for k, v in os.environ.items()
           if not k.startswith(("SLURM_", "RANK", "LOCAL_RANK", "WORLD_SIZE", "MASTER_", "NODE_RANK", "PYTHONPATH"))}
    out = subprocess.run([*program, "fit", "--config", "fit.yaml", "--trainer.devices", "2",
                          "--trainer.strategy", "ddp", "--trainer.logger", "false"],
                         cwd=tmp_path, env={**env, "OMP_NUM_THREADS": "1"}, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-3000:]
    # each rank says so itself (Lightning's line, printed by the process that joins as that rank)
    assert "GLOBAL_RANK: 0, MEMBER: 1/2" in out.stderr and "GLOBAL_RANK: 1, MEMBER: 2/2" in out.stderr, out.stderr
    assert "`max_steps=2` reached" in out.stderr
    last = torch.load(tmp_path / "run" / "ckpt" / "last.ckpt", weights_only=True)  # the relative folder, in cwd
    assert last["global_step"] == 2
