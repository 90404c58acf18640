"""launch/ scripts: the process layout and accumulation they hand to `omg fit` (launchers faked)."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from helpers import REPO


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
