"""A real 2-node x 1-process job on this machine: the launchers' own scripts, gloo on the CPU,
configs/mini/pretrain.yaml trained a few steps and checkpointed.

``launch/torchrun.sh`` runs twice, as node 0 and node 1, meeting through torchrun's c10d rendezvous
on 127.0.0.1. A node lost mid-run (its training process SIGKILLed) ends the other with one
``omg: error:`` line. The job is then resubmitted as a SLURM job: ``launch/slurm.sbatch`` under a
stand-in ``srun`` that starts the job's tasks as srun does, each with the SLURM_* variables srun would
set (Lightning's SLURMEnvironment reads them); only the scheduler is simulated, the script and the
training are real. The script passes ``--ckpt_path last`` itself, so the resubmitted job resumes from
the newest checkpoint and finishes the run: one job rehearses both launchers and both halves of a node
loss, each training process paying its own start-up (about 11 s of imports) once."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import psutil
import pytest
import torch

from helpers import REPO
from omg.tools.lightning import distributed_failure

# the trainings (marked slow): process start-up and a few steps, about 30-60 s a launch on 2 cores

# a few steps, a checkpoint every 2 (the config's own checkpoint runs every 100), no validation
FAST = ["--trainer.accelerator", "cpu", "--trainer.strategy", "ddp", "--trainer.max_steps", "4",
        "--trainer.limit_val_batches", "0", "--trainer.num_sanity_val_steps", "0", "--trainer.logger", "false",
        "--trainer.enable_progress_bar", "false", "--trainer.enable_model_summary", "false",
        "--data.num_workers", "0", "--trainer.callbacks+=lightning.pytorch.callbacks.ModelCheckpoint",
        "--trainer.callbacks.init_args.every_n_train_steps=2"]

SRUN = """#!/usr/bin/env bash
# srun's task launch: SLURM_NTASKS copies of the command, each with its task's SLURM_* variables
# (srun's own options are for the scheduler)
while [[ $1 == -* ]]; do shift; done
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
    if not (tmp_path / "bin" / "python").exists():
        (tmp_path / "bin" / "python").symlink_to(sys.executable)
    env = {k: v for k, v in os.environ.items() if not k.startswith(("SLURM_", "RANK", "LOCAL_RANK", "WORLD_SIZE"))}
    return {**env, "PATH": f"{tmp_path / 'bin'}:{env['PATH']}", "PYTHONPATH": str(REPO), "GLOBAL_BATCH": "32",
            **extra}


def checkpoints(folder) -> list[str]:
    return sorted(p.name for p in folder.glob("*.ckpt"))


# -- a node lost mid-run ---------------------------------------------------------------------------------
# The process group's timeout in the node-loss test (trainer.strategy.init_args.timeout): short, so that
# a peer that stops without closing its sockets would end the run soon too, yet well above the skew of
# the two ranks' start-up on a busy machine (the process group's rendezvous waits as long).
TIMEOUT = "0:00:30"
EXIT_BOUND_S = 60  # a killed peer is noticed at the next collective (a step); a frozen one after TIMEOUT


def start_two_nodes(tmp_path: Path, env: dict, name: str, args: list[str]) -> list[subprocess.Popen]:
    """``launch/torchrun.sh`` as node 0 and node 1, node 0 first: it hosts the rendezvous store, as the
    node at MASTER_ADDR does on a cluster (here both nodes are 127.0.0.1, and torchrun's store goes
    with the node that hosted it). Each node's console is NAME/node{r}.out; its training process's own
    output is also in NAME/node{r}/ (torchrun's --log-dir and --tee, given as PET_* variables)."""
    port = free_port()
    cmd = ["bash", str(REPO / "launch/torchrun.sh"), "configs/mini/pretrain.yaml", *args]
    (tmp_path / name).mkdir()

    def start(rank: int) -> subprocess.Popen:
        with open(tmp_path / name / f"node{rank}.out", "w") as console:
            return subprocess.Popen(cmd, cwd=REPO, stdout=console, stderr=subprocess.STDOUT,
                                    env={**env, "NODE_RANK": str(rank), "MASTER_PORT": str(port),
                                         "RDZV_ID": f"{name}{os.getpid()}", "PET_TEE": "3",
                                         "PET_LOG_DIR": str(tmp_path / name / f"node{rank}")})

    nodes = [start(0)]
    deadline = time.monotonic() + 120
    while True:
        try:
            socket.create_connection(("127.0.0.1", port), timeout=1).close()
            break
        except OSError:
            assert nodes[0].poll() is None and time.monotonic() < deadline, console(tmp_path, name, 0)
            time.sleep(0.1)
    return [*nodes, start(1)]


def console(tmp_path: Path, name: str, rank: int) -> str:
    return (tmp_path / name / f"node{rank}.out").read_text()


def training_log(tmp_path: Path, name: str, rank: int) -> str:
    """What node ``rank``'s training process itself printed (its stderr: Lightning's and omg's lines)."""
    [log] = (tmp_path / name / f"node{rank}").glob("*/attempt_0/0/stderr.log")
    return log.read_text()


def end(nodes: list[subprocess.Popen]) -> None:
    """Kill what is left of the nodes: torchrun and the training processes it started (in their own sessions)."""
    for node in nodes:
        if node.poll() is None:
            for process in [*psutil.Process(node.pid).children(recursive=True), psutil.Process(node.pid)]:
                process.kill()
            node.wait()


def step_of(name: str) -> int:
    return int(name.removesuffix(".ckpt").rpartition("step=")[2])


@pytest.mark.slow
def test_torchrun_node_lost_mid_run_ends_the_other_in_one_line_and_resumes(tmp_path):
    env = environment(tmp_path, NODES="2", GPUS="1", MASTER_ADDR="127.0.0.1")
    ckpt = tmp_path / "ckpt"
    args = [*FAST, "--trainer.max_steps", "6", "--trainer.callbacks.init_args.save_top_k=-1",  # every checkpoint stays
            f"--trainer.callbacks.init_args.dirpath={ckpt}", "--trainer.default_root_dir", str(tmp_path / "run"),
            "--trainer.strategy", "lightning.pytorch.strategies.DDPStrategy",
            "--trainer.strategy.init_args.timeout", TIMEOUT]
    nodes = start_two_nodes(tmp_path, env, "killed", args)
    try:
        deadline = time.monotonic() + 240
        while not list(ckpt.glob("epoch=*.ckpt")):  # the first checkpoint: mid-run, with something to resume
            assert all(node.poll() is None for node in nodes) and time.monotonic() < deadline, \
                console(tmp_path, "killed", 0)[-3000:] + console(tmp_path, "killed", 1)[-3000:]
            time.sleep(0.1)
        [training] = [p for p in psutil.Process(nodes[1].pid).children(recursive=True) if "omg.cli" in p.cmdline()]
        training.send_signal(signal.SIGKILL)
        killed = time.monotonic()
        try:
            nodes[0].wait(timeout=EXIT_BOUND_S)
        except subprocess.TimeoutExpired:
            raise AssertionError(f"node 0 still runs {EXIT_BOUND_S} s after node 1's training process was killed:\n"
                                 + console(tmp_path, "killed", 0)[-3000:]) from None
        took = time.monotonic() - killed
        nodes[1].wait(timeout=60)
    finally:
        end(nodes)
    print(f"node 0 ended {took:.1f} s after node 1's training process was SIGKILLed")
    assert nodes[0].returncode != 0 and nodes[1].returncode != 0
    log = training_log(tmp_path, "killed", 0)
    errors = [line for line in log.splitlines() if "omg: error:" in line]
    assert len(errors) == 1 and errors[0].startswith("omg: error: ") and "Traceback" not in log, log[-3000:]
    assert "lost a peer process" in errors[0] and "--ckpt_path last" in errors[0], errors[0]
    assert "exitcode: 2" in console(tmp_path, "killed", 0)  # torchrun's summary names the training process's exit

    # the job resubmitted through launch/slurm.sbatch (it adds --ckpt_path last): from the newest checkpoint to
    # max_steps, the same overrides as the torchrun job's
    before = {name: (ckpt / name).stat().st_mtime_ns for name in (p.name for p in ckpt.glob("epoch=*.ckpt"))}
    newest = max(before, key=step_of)
    out, tasks = run_slurm_job(tmp_path, args)
    assert out.returncode == 0, out.stderr[-2000:] + "\n".join(t[-2000:] for t in tasks)
    assert f"Restoring states from the checkpoint path at {ckpt / newest}" in tasks[0]
    # two tasks train together, each the rank srun's SLURM_PROCID gave it: both members of one group
    assert "GLOBAL_RANK: 0, MEMBER: 1/2" in tasks[0] and "GLOBAL_RANK: 1, MEMBER: 2/2" in tasks[1]
    assert "`max_steps=6` reached" in tasks[0]
    # resumed at the newest checkpoint's step, not from 0: the earlier checkpoints are untouched and the
    # resumed run wrote exactly the later ones
    assert {name: (ckpt / name).stat().st_mtime_ns for name in before} == before
    assert checkpoints(ckpt) == sorted([*before, *(f"epoch=0-step={s}.ckpt" for s in range(step_of(newest) + 2, 7, 2))])


def run_slurm_job(tmp_path: Path, args: list[str]) -> tuple[subprocess.CompletedProcess, list[str]]:
    """``launch/slurm.sbatch configs/mini/pretrain.yaml ARGS`` as SLURM runs the batch script of
    ``sbatch --nodes=2 --ntasks-per-node=1`` (one "node" name for both: one machine), under the stand-in
    ``srun``; its result and each task's output."""
    srun = tmp_path / "bin" / "srun"
    srun.write_text(SRUN)
    srun.chmod(0o755)
    logs = tmp_path / "slurm"
    logs.mkdir()
    env = environment(tmp_path, SLURM_JOB_NUM_NODES="2", SLURM_NNODES="2", SLURM_NTASKS="2",
                      SLURM_NTASKS_PER_NODE="1", SLURM_NODELIST="127.0.0.1", SLURM_JOB_NAME="omg-pretrain",
                      SLURM_JOB_ID="4242", MASTER_PORT=str(free_port()), LOGS=str(logs))
    out = subprocess.run(["bash", str(REPO / "launch/slurm.sbatch"), "configs/mini/pretrain.yaml", *args], env=env,
                         cwd=REPO, capture_output=True, text=True, timeout=240)
    return out, [(logs / f"task{i}.log").read_text() for i in (0, 1)]


# -- what is tested without a cluster: the NCCL setting and the one-line wording ---------------------------------

@pytest.mark.parametrize("preset", [None, "3"])
def test_launch_scripts_turn_on_nccl_async_error_handling(tmp_path, preset):
    """NCCL's watchdog must end a process whose collective failed or outlived the timeout: both launch
    scripts hand TORCH_NCCL_ASYNC_ERROR_HANDLING=1 to the training processes unless it is set (there is
    no NCCL here: what torchrun and srun are given is what is checked), and srun ends the job step when
    a task fails."""
    env = environment(tmp_path, NODES="2", GPUS="1", SLURM_JOB_NUM_NODES="2", SLURM_NTASKS_PER_NODE="1")
    env.pop("TORCH_NCCL_ASYNC_ERROR_HANDLING", None)
    if preset is not None:
        env["TORCH_NCCL_ASYNC_ERROR_HANDLING"] = preset
    for launcher in ("torchrun", "srun"):  # stand-ins that say what they were given
        stub = tmp_path / "bin" / launcher
        stub.write_text('#!/usr/bin/env bash\necho "$TORCH_NCCL_ASYNC_ERROR_HANDLING"\necho "$@"\n')
        stub.chmod(0o755)
    for script, options in (("launch/torchrun.sh", "--nnodes 2"), ("launch/slurm.sbatch", "--kill-on-bad-exit=1")):
        out = subprocess.run(["bash", str(REPO / script), "configs/mini/pretrain.yaml"], env=env, cwd=REPO,
                             capture_output=True, text=True, timeout=60)
        assert out.returncode == 0, out.stderr
        handling, command = out.stdout.splitlines()
        assert handling == (preset or "1") and command.startswith(options), (script, out.stdout)


GLOO = "[/__w/pytorch/pytorch/third_party/gloo/gloo/transport/tcp/"  # how gloo's errors begin


@pytest.mark.parametrize("error, says", [
    (RuntimeError(f"{GLOO}pair.cc:561] Connection closed by peer [127.0.0.1]:7380. This is typically caused by a "
                  "remote worker crashing. Check the logs of the remote worker before reporting an error."),
     "lost a peer process (Connection closed by peer [127.0.0.1]:7380)"),
    (RuntimeError(f"{GLOO}pair.cc:545] Read error [127.0.0.1]:31665: Connection reset by peer"),
     "lost a peer process (Read error [127.0.0.1]:31665: Connection reset by peer)"),
    (RuntimeError(f"{GLOO}unbound_buffer.cc:78] Timed out waiting 10000ms for recv operation to complete"),
     "a collective operation timed out (Timed out waiting 10000ms for recv operation to complete)"),
    (torch.distributed.DistNetworkError("Failed to recv, got 0 bytes. Connection was likely closed. Did the remote "
                                        "server shutdown or crash?"),
     "lost a peer process (Failed to recv, got 0 bytes)"),
    (torch.distributed.DistBackendError("[Rank 0] Watchdog caught collective operation timeout: WorkNCCL(SeqNum=9, "
                                        "OpType=ALLREDUCE) ran for 1800085 milliseconds before timing out."),
     "a collective operation timed out ([Rank 0] Watchdog caught collective operation timeout"),
    (torch.distributed.DistBackendError("NCCL error in: ProcessGroupNCCL.cpp:1970, remote process exited or there "
                                        "was a network error, NCCL version 2.21.5"), "lost a peer process (NCCL error"),
    (RuntimeError("CUDA out of memory. Tried to allocate 2.00 GiB"), None),  # not the run's peers: a traceback
    (torch.distributed.DistBackendError("NCCL error in: ProcessGroupNCCL.cpp:1970, invalid usage"), None),
])
def test_a_lost_peer_or_a_collective_timeout_is_told_in_a_few_words(error, says):
    what = distributed_failure(error)
    if says is None:
        assert what is None
    else:
        assert what.startswith(says), what
        assert "\n" not in what
