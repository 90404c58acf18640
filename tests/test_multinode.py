"""A real 2-node x 1-process job on this machine: the launchers' own scripts, gloo on the CPU,
configs/mini/pretrain.yaml trained a few steps and checkpointed.

``launch/torchrun.sh`` runs twice, as node 0 and node 1, meeting through torchrun's c10d rendezvous
on 127.0.0.1. ``launch/slurm.sbatch`` runs under a stand-in ``srun`` that starts the job's tasks
as srun does, each with the SLURM_* variables srun would set (Lightning's SLURMEnvironment reads
them); only the scheduler is simulated, the script and the training are real."""

from __future__ import annotations

import os
import socket
import subprocess
import sys

import pytest

from helpers import REPO

pytestmark = pytest.mark.slow  # two trainings with process start-up: about 30-60 s each on 2 cores

# a few steps, a checkpoint every 2 (the config's own checkpoint runs every 100), no validation
FAST = ["--trainer.accelerator", "cpu", "--trainer.strategy", "ddp", "--trainer.max_steps", "4",
        "--trainer.limit_val_batches", "0", "--trainer.num_sanity_val_steps", "0", "--trainer.logger", "false",
        "--trainer.enable_progress_bar", "false", "--trainer.enable_model_summary", "false",
        "--data.num_workers", "0", "--trainer.callbacks+=lightning.pytorch.callbacks.ModelCheckpoint",
        "--trainer.callbacks.init_args.every_n_train_steps=2"]

SRUN = """#!/usr/bin/env bash
# srun's task launch: SLURM_NTASKS copies of the command, each with its task's SLURM_* variables
pids=()
for ((task = 0; task < SLURM_NTASKS; task++)); do
  SLURM_PROCID=$task SLURM_LOCALID=0 SLURM_NODEID=$task "$@" > "$LOGS/task$task.log" 2>&1 &
  pids+=($!)
done
status=0
for pid in "${pids[@]}"; do wait "$pid" || status=$?; done
exit $status
"""


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def environment(tmp_path, **extra) -> dict:
    (tmp_path / "bin").mkdir(exist_ok=True)
    omg = tmp_path / "bin" / "omg"  # `omg` as installed: this checkout's CLI under this interpreter
    omg.write_text(f'#!/usr/bin/env bash\nexec {sys.executable} -m omg.cli "$@"\n')
    omg.chmod(0o755)
    (tmp_path / "bin" / "python").symlink_to(sys.executable)
    env = {k: v for k, v in os.environ.items() if not k.startswith(("SLURM_", "RANK", "LOCAL_RANK", "WORLD_SIZE"))}
    return {**env, "PATH": f"{tmp_path / 'bin'}:{env['PATH']}", "PYTHONPATH": str(REPO), "GLOBAL_BATCH": "32",
            **extra}


def checkpoints(folder) -> list[str]:
    return sorted(p.name for p in folder.glob("*.ckpt"))


def test_torchrun_two_nodes_train_and_checkpoint(tmp_path):
    env = environment(tmp_path, NODES="2", GPUS="1", MASTER_ADDR="127.0.0.1", MASTER_PORT=str(free_port()),
                      RDZV_ID=f"test{os.getpid()}")
    ckpt = tmp_path / "ckpt"
    cmd = ["bash", str(REPO / "launch/torchrun.sh"), "configs/mini/pretrain.yaml", *FAST,
           f"--trainer.callbacks.init_args.dirpath={ckpt}", "--trainer.default_root_dir", str(tmp_path / "run")]
    nodes = [subprocess.Popen(cmd, env={**env, "NODE_RANK": str(rank)}, cwd=REPO, stdout=subprocess.PIPE,
                              stderr=subprocess.STDOUT, text=True) for rank in (0, 1)]
    logs = [node.communicate(timeout=240)[0] for node in nodes]
    assert [node.returncode for node in nodes] == [0, 0], "\n".join(log[-2000:] for log in logs)
    joined = "\n".join(logs)
    assert "GLOBAL_RANK: 0, MEMBER: 1/2" in joined and "GLOBAL_RANK: 1, MEMBER: 2/2" in joined
    assert "`max_steps=4` reached" in joined
    assert checkpoints(ckpt) == ["epoch=0-step=4.ckpt"]


def test_slurm_sbatch_two_nodes_train_and_checkpoint(tmp_path):
    (tmp_path / "bin").mkdir()
    srun = tmp_path / "bin" / "srun"
    srun.write_text(SRUN)
    srun.chmod(0o755)
    logs = tmp_path / "logs"
    logs.mkdir()
    # what SLURM sets for `sbatch --nodes=2 --ntasks-per-node=1` (one "node" name for both: one machine)
    env = environment(tmp_path, SLURM_JOB_NUM_NODES="2", SLURM_NNODES="2", SLURM_NTASKS="2",
                      SLURM_NTASKS_PER_NODE="1", SLURM_NODELIST="127.0.0.1", SLURM_JOB_NAME="omg-pretrain",
                      SLURM_JOB_ID="4242", MASTER_PORT=str(free_port()), LOGS=str(logs))
    ckpt = tmp_path / "ckpt"
    out = subprocess.run(["bash", str(REPO / "launch/slurm.sbatch"), "configs/mini/pretrain.yaml", *FAST,
                          f"--trainer.callbacks.init_args.dirpath={ckpt}", "--trainer.default_root_dir",
                          str(tmp_path / "run")], env=env, cwd=REPO, capture_output=True, text=True, timeout=240)
    tasks = [(logs / f"task{i}.log").read_text() for i in (0, 1)]
    assert out.returncode == 0, out.stderr[-2000:] + "\n".join(t[-2000:] for t in tasks)
    assert "GLOBAL_RANK: 0, MEMBER: 1/2" in tasks[0] and "GLOBAL_RANK: 1, MEMBER: 2/2" in tasks[1]
    assert checkpoints(ckpt) == ["epoch=0-step=4.ckpt"]
