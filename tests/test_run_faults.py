"""Faults of a running `omg fit`: SIGTERM, a stalled data worker or read, too many bad samples in a
worker. Each ends with one line on stderr and an exit code a scheduler can act on."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from helpers import REPO, rewrite_member
from helpers.configs import write_config
from helpers.faults import KilledWritingLast
from helpers.forked import OmgProcess
from omg.cli import SIGINT_EXIT, SIGTERM_EXIT, main


def one_error_line(capsys) -> str:
    err = capsys.readouterr().err
    assert "Traceback" not in err
    lines = [ln for ln in err.splitlines() if ln.startswith("omg:")]
    assert len(lines) == 1, err[-2000:]
    return lines[0]


def test_sigterm_saves_a_checkpoint_exits_nonzero_and_resumes_exactly(h263_shards, tmp_path, capsys, caplog):
    shards = h263_shards / "train"
    full = write_config(tmp_path / "full.yaml", shards, tmp_path / "full")
    main(["fit", "--config", full])
    sigterm = {"class_path": "helpers.faults.SigtermAt", "init_args": {"step": 4}}
    stopped = write_config(tmp_path / "stopped.yaml", shards, tmp_path / "stopped", callbacks=[sigterm])
    capsys.readouterr()
    with pytest.raises(SystemExit) as e:
        main(["fit", "--config", stopped])
    assert e.value.code == SIGTERM_EXIT  # not 0: the run did not finish
    line = one_error_line(capsys)
    assert line.startswith("omg: interrupted by SIGTERM at step 5;") and "interrupted.ckpt" in line
    assert (tmp_path / "stopped" / "ckpt" / "interrupted.ckpt").is_file()
    # `--ckpt_path last` takes the newest of last.ckpt (step 4) and interrupted.ckpt (step 5)
    resumed = write_config(tmp_path / "resumed.yaml", shards, tmp_path / "stopped")
    with caplog.at_level("INFO"):
        main(["fit", "--config", resumed, "--ckpt_path", "last"])
    assert ("Restoring states from the checkpoint path at " + str(tmp_path / "stopped" / "ckpt" / "interrupted.ckpt")
            in caplog.text)
    a = torch.load(tmp_path / "full" / "ckpt" / "last.ckpt", weights_only=False)
    b = torch.load(tmp_path / "stopped" / "ckpt" / "last.ckpt", weights_only=False)
    assert a["global_step"] == b["global_step"] == 8
    for key in a["state_dict"]:
        assert torch.equal(a["state_dict"][key], b["state_dict"][key]), key
    assert torch.equal(a["noise_rng"], b["noise_rng"])
    # a run without --ckpt_path starts afresh, even beside another run's checkpoints
    caplog.clear()
    with caplog.at_level("INFO"):
        main(["fit", "--config", resumed])
    assert "Restoring states" not in caplog.text


def _stall(self, rng):
    time.sleep(60)
    yield from ()


def test_a_stalled_data_worker_stops_the_run_with_one_line(h263_shards, tmp_path, capsys, monkeypatch):
    from omg.data.loaders import MotionStream

    monkeypatch.setattr(MotionStream, "_samples", _stall)  # the forked worker inherits it
    config = write_config(tmp_path / "c.yaml", h263_shards / "train", tmp_path / "run", num_workers=1, timeout=2)
    start = time.perf_counter()
    with pytest.raises(SystemExit) as e:
        main(["fit", "--config", config])
    assert e.value.code == 2 and time.perf_counter() - start < 50
    line = one_error_line(capsys)
    assert "data.timeout=2" in line and "stalled" in line


def test_too_many_bad_samples_in_a_worker_is_one_line(h263_shards, tmp_path, capsys):
    import shutil
    import tarfile

    from omg.data.shards import Manifest
    shards = tmp_path / "s"
    shutil.copytree(h263_shards / "train", shards)
    for path in Manifest.load(shards).shard_paths:  # half the samples of every shard
        with tarfile.open(path) as tar:
            keys = sorted({name.split(".")[0] for name in tar.getnames()})
        for key in keys[::2]:
            rewrite_member(path, f"{key}.motion.npy", b"garbage")
    config = write_config(tmp_path / "c.yaml", shards, tmp_path / "run", num_workers=1, verify_shards=False)
    with pytest.raises(SystemExit) as e:
        main(["fit", "--config", config])
    assert e.value.code == 2
    line = one_error_line(capsys)
    assert "samples were bad" in line and "max_bad_fraction" in line and "DataLoader worker" not in line


def test_resume_last_takes_the_newest_whole_checkpoint_and_keeps_the_top_k_policy(h263_shards, tmp_path, caplog):
    """Killed while last.ckpt (step 2) was being replaced at step 4: `--ckpt_path last` takes the
    newer epoch=0-step=4.ckpt, and the resumed run leaves the folder as the run never killed does
    (save_top_k=1: the newest periodic file and last.ckpt), the files of the killed run it does not
    keep deleted, the checkpoint resumed from included, and a user's own files kept."""
    shards = h263_shards / "train"
    main(["fit", "--config", write_config(tmp_path / "full.yaml", shards, tmp_path / "full")])
    kill = {"class_path": "helpers.faults.KillWritingLast", "init_args": {"step": 4}}
    with pytest.raises(KilledWritingLast):
        main(["fit", "--config", write_config(tmp_path / "killed.yaml", shards, tmp_path / "run", callbacks=[kill])])
    ckpt = tmp_path / "run" / "ckpt"
    assert sorted(p.name for p in ckpt.iterdir()) == ["epoch=0-step=4.ckpt", "last.ckpt"]
    assert torch.load(ckpt / "last.ckpt", weights_only=True)["global_step"] == 2
    (ckpt / "epoch=0-step=2.ckpt").write_bytes((ckpt / "last.ckpt").read_bytes())  # killed before its removal
    mine = [ckpt / "mine.ckpt", ckpt / "epoch=0-step=2.ckpt.bak", ckpt / "notes.txt"]
    for path in mine:
        path.write_bytes((ckpt / "last.ckpt").read_bytes())
    with caplog.at_level("INFO"):
        main(["fit", "--config", write_config(tmp_path / "resumed.yaml", shards, tmp_path / "run"), "--ckpt_path",
              "last"])
    assert f"Restoring states from the checkpoint path at {ckpt / 'epoch=0-step=4.ckpt'}" in caplog.text
    full = tmp_path / "full" / "ckpt"
    assert sorted(p.name for p in full.iterdir()) == ["epoch=1-step=8.ckpt", "last.ckpt"]
    kept = ["epoch=1-step=8.ckpt", "last.ckpt", *(m.name for m in mine)]
    assert sorted(p.name for p in ckpt.iterdir()) == sorted(kept)
    a, b = (torch.load(d / "last.ckpt", weights_only=True) for d in (full, ckpt))
    assert a["global_step"] == b["global_step"] == 8
    for key in a["state_dict"]:
        assert torch.equal(a["state_dict"][key], b["state_dict"][key]), key


@pytest.mark.parametrize("init, written, others", [
    ({}, ["epoch=0-step=4.ckpt", "epoch=12-step=5000-v1.ckpt"],
     ["last.ckpt", "last-v1.ckpt", "mine.ckpt", "epoch=0-step=4.ckpt.bak", "best-epoch=0-step=4.ckpt",
      "epoch=0-step=4-val_loss=0.50.ckpt", "interrupted.ckpt"]),
    ({"filename": "{epoch}-{val_loss:.2f}"}, ["epoch=3-val_loss=0.12.ckpt", "epoch=3-val_loss=nan-v2.ckpt"],
     ["epoch=3.ckpt", "epoch=3-val_loss=0.12.ckpt.tmp", "last.ckpt"]),
    ({"filename": "step{step:06d}", "auto_insert_metric_name": False}, ["step000100.ckpt"], ["step=100.ckpt"]),
])
def test_top_k_housekeeping_knows_the_files_a_checkpoint_callback_writes(tmp_path, init, written, others):
    from lightning.pytorch.callbacks import ModelCheckpoint

    from omg.callbacks.checkpoint import written_checkpoints

    for name in written + others:
        (tmp_path / name).write_bytes(b"x")
    callback = ModelCheckpoint(dirpath=tmp_path, **init)
    assert [p.name for p in written_checkpoints(callback)] == sorted(written)


def _mini_fit(root, *args, callbacks: bool = False) -> OmgProcess:
    """`python -m omg.cli fit` on the mini config in its own session (a terminal's process group:
    Ctrl-C reaches the data worker too), writing a checkpoint every 5 steps."""
    command = ["fit", "--config", "configs/mini/pretrain.yaml", f"--trainer.default_root_dir={root}",
               "--trainer.enable_progress_bar=false", "--trainer.callbacks.every_n_train_steps=5", *args]
    if callbacks:
        command.append("--trainer.callbacks+=helpers.faults.SlowAfterCtrlC")
    return omg_process(*command, log=root.parent / f"{root.name}.err", new_session=True)


def _wait_for(condition, process, timeout=120):
    start = time.monotonic()
    while not condition():
        assert process.poll() is None, "the run ended early"
        assert time.monotonic() - start < timeout, "timed out"
        time.sleep(0.1)


@pytest.mark.slow  # an `omg fit` process interrupted, then resumed here: about 20 s on 2 cores
def test_ctrl_c_saves_a_checkpoint_exits_130_and_resumes(tmp_path, caplog, monkeypatch):
    root = tmp_path / "run"
    run = _mini_fit(root, "--trainer.max_steps=300")
    _wait_for(lambda: (root / "checkpoints" / "last.ckpt").exists(), run)
    os.killpg(run.pid, signal.SIGINT)  # Ctrl-C in a terminal: the whole foreground process group
    assert run.wait(timeout=120) == SIGINT_EXIT
    err = (tmp_path / "run.err").read_text()
    assert "Traceback" not in err and "Error" not in err, err[-3000:]
    last = [line for line in err.splitlines() if line.startswith("omg:")][-1]
    interrupted = root / "checkpoints" / "interrupted.ckpt"
    assert last.startswith("omg: interrupted by Ctrl-C at step ") and f"checkpoint {interrupted} " in last, err
    assert "resume with --ckpt_path last" in last
    step = torch.load(interrupted, weights_only=True)["global_step"]
    assert last.startswith(f"omg: interrupted by Ctrl-C at step {step};") and step >= 5

    # the resume in this process (the interrupted run was the real one): the same command with --ckpt_path last
    monkeypatch.chdir(REPO)
    monkeypatch.setattr(sys, "argv", list(sys.argv))  # omg fit sets it for LightningCLI
    with caplog.at_level("INFO"):
        main(["fit", "--config", "configs/mini/pretrain.yaml", f"--trainer.default_root_dir={root}",
              "--trainer.enable_progress_bar=false", "--trainer.callbacks.every_n_train_steps=5",
              f"--trainer.max_steps={step + 2}", "--ckpt_path=last"])
    assert f"Restoring states from the checkpoint path at {interrupted}" in caplog.text
    assert torch.load(root / "checkpoints" / "last.ckpt", weights_only=True)["global_step"] == step + 2


def test_a_second_ctrl_c_aborts_at_once(tmp_path):
    root = tmp_path / "run"
    run = _mini_fit(root, "--trainer.max_steps=300", callbacks=True)
    _wait_for(lambda: (root / "checkpoints" / "last.ckpt").exists(), run)
    os.killpg(run.pid, signal.SIGINT)
    _wait_for(lambda: "Ctrl-C again aborts at once" in (tmp_path / "run.err").read_text(), run)
    start = time.monotonic()
    os.killpg(run.pid, signal.SIGINT)
    assert run.wait(timeout=30) == -signal.SIGINT and time.monotonic() - start < 20


def test_slurm_auto_resume_checks_the_requeue_checkpoint(h263_shards, tmp_path, capsys, caplog, monkeypatch):
    """In a SLURM job, Lightning resumes from default_root_dir's hpc_ckpt_N.ckpt on its own: that
    file passes the checks of every checkpoint, and one holding pickled code is one line."""
    import argparse

    for key, value in {"SLURM_NTASKS": "1", "SLURM_JOB_NAME": "omg", "SLURM_JOB_ID": "7", "SLURM_PROCID": "0",
                       "SLURM_LOCALID": "0", "SLURM_NODEID": "0"}.items():
        monkeypatch.setenv(key, value)
    root = tmp_path / "run"
    root.mkdir()
    torch.save({"state_dict": {}, "args": argparse.Namespace(lr=1.0)}, root / "hpc_ckpt_1.ckpt")
    with pytest.raises(SystemExit) as e:
        main(["fit", "--config", write_config(tmp_path / "c.yaml", h263_shards / "train", root)])
    assert e.value.code == 2
    line = one_error_line(capsys)
    assert line.startswith("omg: error: resuming this SLURM job from its requeue checkpoint: ")
    assert "hpc_ckpt_1.ckpt holds pickled Python objects (argparse.Namespace)" in line and "refused" in line
    assert [p.name for p in root.iterdir()] == ["hpc_ckpt_1.ckpt"]  # nothing left behind

    config = write_config(tmp_path / "c.yaml", h263_shards / "train", tmp_path / "first", max_steps=4)
    monkeypatch.delenv("SLURM_NTASKS")  # the first job: not resumed
    main(["fit", "--config", config])
    monkeypatch.setenv("SLURM_NTASKS", "1")
    (root / "hpc_ckpt_2.ckpt").write_bytes((tmp_path / "first" / "ckpt" / "last.ckpt").read_bytes())
    with caplog.at_level("INFO"):
        main(["fit", "--config", write_config(tmp_path / "c.yaml", h263_shards / "train", root, max_steps=6)])
    assert f"Restoring states from the checkpoint path at {root / 'hpc_ckpt_2.ckpt'}" in caplog.text
    assert torch.load(root / "ckpt" / "last.ckpt", weights_only=True)["global_step"] == 6


# -- stalls in real `omg` processes: a stalled read or worker ends the run within about data.timeout,
# with data workers or without, and leaves no process behind

def processes(where: str | None = None, parent: int | None = None) -> list[int]:
    """Live (not zombie) processes whose command line names ``where``, or whose parent is ``parent``."""
    found = []
    for entry in Path("/proc").iterdir():
        try:
            stat = (entry / "stat").read_text().rsplit(")", 1)[1].split()
            command = (entry / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
        except (OSError, IndexError):  # not a process, or gone
            continue
        named = where is not None and where in command
        if stat[0] != "Z" and (named or (parent is not None and int(stat[1]) == parent)):
            found.append(int(entry.name))
    return found


def omg_process(*args: str, log: Path, new_session: bool = False) -> OmgProcess:
    """`omg ARGS` as its own process (forked from the preloaded server: tests/helpers/forked.py), run from the
    repository, stderr to ``log``; ``new_session``: in a process group of its own, as a terminal starts it."""
    return OmgProcess(list(args), env={"OMP_NUM_THREADS": "1"}, stderr=log, new_session=new_session)


def finish(process: OmgProcess, log: Path, within: float, leftovers: str | None = None) -> str:
    """Wait ``within`` seconds for ``process`` to end (killing it and what it left when it does not), then
    assert it ended with exit code 2 and one error line, and left no process naming ``leftovers``."""
    try:
        process.wait(within)
    except subprocess.TimeoutExpired:
        process.kill()
        process.wait()
    finally:
        left = processes(leftovers) if leftovers else []
        for pid in left:
            os.kill(pid, signal.SIGKILL)
    err = log.read_text()
    assert process.returncode == 2, f"exit code {process.returncode} after {within} s: {err[-2000:]}"
    assert "Traceback" not in err
    lines = [ln for ln in err.splitlines() if ln.startswith("omg:")]
    assert len(lines) == 1, err[-2000:]
    assert not left, f"left behind: {left}"
    return lines[0]


def stalling_set(shards: Path, out: Path) -> str:
    """A `pipe:` URL of ``shards``' set whose every shard is a FIFO that no one writes: `cat` blocks on it."""
    out.mkdir()
    shutil.copy(shards / "manifest.json", out / "manifest.json")
    for shard in shards.glob("*.tar"):
        os.mkfifo(out / shard.name)
    return f"pipe:cat {out}/manifest.json"


def test_a_stopped_data_worker_ends_the_run_within_data_timeout(h263_shards, tmp_path):
    """SIGSTOP on a worker that has batches in flight: the main process blocked fetching a batch's
    shared-memory descriptor from it (multiprocessing.resource_sharer), which DataLoader(timeout) does not bound."""
    root = tmp_path / "run"
    config = write_config(tmp_path / "c.yaml", h263_shards / "train", root, max_steps=100_000, num_workers=1,
                          batches_per_epoch=100_000, timeout=3)
    log = tmp_path / "err.txt"
    process = omg_process("fit", "--config", config, log=log)
    deadline = time.monotonic() + 240
    while not (root / "ckpt" / "last.ckpt").exists() and process.poll() is None and time.monotonic() < deadline:
        time.sleep(0.2)  # a checkpoint every 2 steps: training runs, the worker keeps batches queued
    workers = processes(parent=process.pid)
    assert len(workers) == 1, log.read_text()[-2000:]
    os.kill(workers[0], signal.SIGSTOP)
    start = time.monotonic()
    try:
        line = finish(process, log, within=60)
    finally:
        if processes(parent=process.pid) or workers[0] in processes(str(config)):
            os.kill(workers[0], signal.SIGKILL)
    assert time.monotonic() - start < 3 + 20
    assert "data.timeout=3" in line and "stalled" in line
    assert workers[0] not in processes(str(config))  # killed: a stopped process never acts on SIGTERM


@pytest.mark.parametrize("num_workers", [0, 1])
def test_a_stalled_read_ends_the_run(h263_shards, tmp_path, num_workers):
    """num_workers 0 (configs/mini/omgpt.yaml): the shard is read in the main process, which
    DataLoader(timeout) never bounded. Either way the `pipe:` command is killed with the run."""
    train = stalling_set(h263_shards / "train", tmp_path / "fifo")
    config = write_config(tmp_path / "c.yaml", train, tmp_path / "run", num_workers=num_workers, timeout=2)
    log = tmp_path / "err.txt"
    line = finish(omg_process("fit", "--config", config, log=log), log, within=90, leftovers=str(tmp_path / "fifo"))
    assert "data.timeout=2" in line and "stalled" in line


def test_a_stalled_validation_read_ends_the_run(h263_shards, tmp_path):
    val = stalling_set(h263_shards / "val", tmp_path / "fifo")
    config = write_config(tmp_path / "c.yaml", h263_shards / "train", tmp_path / "run", timeout=2, val=val)
    log = tmp_path / "err.txt"
    process = omg_process("validate", "--config", config, "--trainer.limit_val_batches", "1", log=log)
    line = finish(process, log, within=90, leftovers=str(tmp_path / "fifo"))
    assert "data.timeout=2" in line and "shard-000000.tar was not read" in line


def test_a_stalled_read_ends_shards_inspect(h263_shards, tmp_path):
    url = stalling_set(h263_shards / "train", tmp_path / "fifo")
    log = tmp_path / "err.txt"
    line = finish(omg_process("shards", "inspect", url, "--timeout", "2", log=log), log, within=60,
                  leftovers=str(tmp_path / "fifo"))
    assert "--timeout=2" in line and "stalled" in line


def test_a_stalled_manifest_fetch_ends_the_run_within_data_timeout(tmp_path):
    """The manifest of a `pipe:` set is read before training: a command that never ends is bounded by
    data.timeout like a shard's read (it was stopped only after 600 s), and is killed."""
    fifo = tmp_path / "fifo"
    fifo.mkdir()
    os.mkfifo(fifo / "manifest.json")
    config = write_config(tmp_path / "c.yaml", f"pipe:cat {fifo}/manifest.json", tmp_path / "run", timeout=2)
    log = tmp_path / "err.txt"
    line = finish(omg_process("fit", "--config", config, log=log), log, within=90, leftovers=str(fifo))
    assert line.startswith("omg: error: the manifests of data.train were not read in data.timeout=2 s"), line
    assert not (tmp_path / "run").exists()


def test_ctrl_c_during_a_stalled_manifest_fetch_is_one_line(tmp_path):
    """Before training starts no handler of the run's is set: Ctrl-C is Python's KeyboardInterrupt, which
    ends the fetch at once; its command is killed and the CLI says so in one line (not a traceback).
    Python's handler is there only when omg starts with SIGINT not ignored, as a terminal starts it
    (conftest's ``_ctrl_c_as_python_sets_it``: a suite started as a script's background job hung here)."""
    assert signal.getsignal(signal.SIGINT) is not signal.SIG_IGN
    fifo = tmp_path / "fifo"
    fifo.mkdir()
    os.mkfifo(fifo / "manifest.json")
    config = write_config(tmp_path / "c.yaml", f"pipe:cat {fifo}/manifest.json", tmp_path / "run")
    log = tmp_path / "err.txt"
    process = omg_process("fit", "--config", config, log=log, new_session=True)
    _wait_for(lambda: processes(f"cat {fifo}/manifest.json"), process, timeout=240)
    os.killpg(process.pid, signal.SIGINT)
    try:
        process.wait(60)
    except subprocess.TimeoutExpired:
        pass
    left = processes(str(fifo))
    kill_all([process.pid, *left])
    process.wait()
    err = log.read_text()
    assert process.returncode == SIGINT_EXIT and "Traceback" not in err, err[-2000:]
    assert [ln for ln in err.splitlines() if ln.startswith("omg:")] == ["omg: interrupted by Ctrl-C"], err[-2000:]
    assert not left, f"left behind: {left}"


# -- the end of a stalled run: a stop signal ends it at once, and nothing it started outlives it, SIGKILL
# included. data.timeout is left at its default (600 s): the stall itself would hold the run for 10 minutes.

def stalled_fit(h263_shards, tmp_path, num_workers: int) -> tuple[OmgProcess, Path, str]:
    """`omg fit` (as a terminal starts it) on a set whose shards never arrive, once it reads one:
    (the process, its stderr, the stalled set's folder)."""
    train = stalling_set(h263_shards / "train", tmp_path / "fifo")
    config = write_config(tmp_path / "c.yaml", train, tmp_path / "run", num_workers=num_workers)
    log = tmp_path / "err.txt"
    process = omg_process("fit", "--config", config, log=log, new_session=True)
    _wait_for(lambda: processes(f"cat {tmp_path / 'fifo'}/shard-"), process, timeout=240)
    time.sleep(0.5)  # the main process is waiting for the batch
    return process, log, str(tmp_path / "fifo")


def kill_all(pids: list[int]) -> None:
    for pid in pids:
        try:
            os.kill(pid, signal.SIGKILL)
        except ProcessLookupError:
            pass


@pytest.mark.slow  # an `omg fit` process stalled, then stopped: about 30 s on 2 cores
@pytest.mark.parametrize("stop, num_workers", [(signal.SIGTERM, 0), (signal.SIGINT, 1)],
                         ids=["sigterm-no-workers", "ctrl-c-one-worker"])
def test_a_stop_signal_ends_a_stalled_run_with_its_usual_line(h263_shards, tmp_path, stop, num_workers):
    """SIGTERM (to omg, as `kill` and schedulers send it) or Ctrl-C (to the terminal's process group) while
    the batch read is stalled: Lightning's handlers only set a flag for the end of the step, which a stalled
    read never reaches. The run ends within a few seconds (omg.data.deadline.STOP_GRACE_S) as at a step's
    end, with its exit code and line, and its `pipe:` commands and data workers end with it."""
    process, log, fifo = stalled_fit(h263_shards, tmp_path, num_workers)
    start = time.monotonic()
    if stop == signal.SIGINT:
        os.killpg(process.pid, signal.SIGINT)
    else:
        process.send_signal(signal.SIGTERM)
    try:
        process.wait(90)
    except subprocess.TimeoutExpired:
        pass
    took = time.monotonic() - start
    left = processes(fifo) + processes(str(tmp_path / "c.yaml"))
    kill_all([process.pid, *left])
    process.wait()
    err = log.read_text()
    print(f"{stop.name} with {num_workers} workers: ended {took:.1f} s after the signal")
    assert process.returncode == {signal.SIGTERM: SIGTERM_EXIT, signal.SIGINT: SIGINT_EXIT}[stop], err[-2000:]
    assert took < 45  # STOP_GRACE_S and the interpreter's exit, on a busy machine
    assert "Traceback" not in err
    lines = [ln for ln in err.splitlines() if ln.startswith("omg:") and "interrupted" in ln]
    said = "SIGTERM" if stop == signal.SIGTERM else "Ctrl-C"
    assert lines == [f"omg: interrupted by {said} at step 0; no checkpoint was written"], err[-2000:]
    assert not left, f"left behind: {left}"


@pytest.mark.parametrize("num_workers", [0, 1])
def test_no_pipe_command_outlives_a_killed_run(h263_shards, tmp_path, num_workers):
    """omg SIGKILLed while its `pipe:` command (started by the main process, or by a data worker) is stalled:
    the command, the shell around it and the worker end with it (Linux's parent-death signal), where they
    used to run on for good."""
    process, log, fifo = stalled_fit(h263_shards, tmp_path, num_workers)
    readers = processes(fifo)
    assert readers
    process.kill()
    process.wait()
    deadline = time.monotonic() + 20
    while (left := processes(fifo) + processes(str(tmp_path / "c.yaml"))) and time.monotonic() < deadline:
        time.sleep(0.1)
    kill_all(left)
    assert not left, f"still running after omg was SIGKILLed: {left}"


def test_a_stalled_read_of_the_second_streams_validation_set_ends(h263_shards, tmp_path):
    """OmniMotionGPT's data.human.val goes through the same bound (in-process: SIGALRM in this main thread)."""
    import threading

    from omg.data.paired import PairedDataModule
    from omg.errors import UsageError

    fifo = str(tmp_path / "fifo")
    data = PairedDataModule(val=str(h263_shards / "val"),
                            human={"val": stalling_set(h263_shards / "val", tmp_path / "fifo"), "timeout": 1})
    # without the bound the read never ends: kill `cat` after a while, so the test fails instead of hanging
    rescue = threading.Timer(30, lambda: [os.kill(pid, signal.SIGKILL) for pid in processes(fifo)])
    rescue.start()
    start = time.monotonic()
    try:
        with pytest.raises(UsageError, match=r"shard-000000.tar was not read in data.timeout=1 s"):
            data.human_val_samples()
    finally:
        rescue.cancel()
    assert time.monotonic() - start < 10
    assert not processes(fifo)


def test_a_non_finite_loss_names_the_batch_clips_in_one_line(h263_shards, tmp_path, capsys):
    """Values that overflow the loss (1e30: finite, so every sample decodes) in a set read without
    checksums: one line with the step and the batch's clips, not a FloatingPointError traceback."""
    import io
    import re
    import shutil
    import tarfile

    import numpy as np

    from omg.data.shards import Manifest
    shards = tmp_path / "s"
    shutil.copytree(h263_shards / "train", shards)
    huge = io.BytesIO()
    np.save(huge, np.full((40, 263), 1e30, np.float32))
    for path in Manifest.load(shards).shard_paths:
        with tarfile.open(path) as tar:
            keys = sorted({name.split(".")[0] for name in tar.getnames()})
        for key in keys:
            rewrite_member(path, f"{key}.motion.npy", huge.getvalue())
    config = write_config(tmp_path / "c.yaml", shards, tmp_path / "run", max_steps=2, verify_shards=False)
    pressed = []
    ctrl_c = signal.signal(signal.SIGINT, lambda *_: pressed.append("Ctrl-C"))  # as a notebook's
    try:
        with pytest.raises(SystemExit) as e:
            main(["fit", "--config", config])
        assert e.value.code == 2
        # after a fit that raised, Ctrl-C does what it did before it (Lightning's teardown put omg's handler
        # back after on_exception had given the previous one back)
        signal.raise_signal(signal.SIGINT)
        assert pressed == ["Ctrl-C"]
    finally:
        signal.signal(signal.SIGINT, ctrl_c)
    line = one_error_line(capsys)
    assert "non-finite loss" in line and "at step 0" in line
    assert re.search(r"on the batch of clips walk\d+, walk\d+, walk\d+, walk\d+;", line), line  # batch_size 4
