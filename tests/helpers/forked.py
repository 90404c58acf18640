"""`omg` commands (and the tests' own scripts) as real processes that start at once: each is forked from one
server process that imported omg, Lightning and the test helpers once (multiprocessing's fork server), instead
of being a fresh interpreter that spends ten seconds of CPU importing them. The child is its own process (its own
pid, signals, exit code, process group when asked, children of its own); what it does not share with a fresh
`python -m omg.cli` is the start-up, which tests/test_cli.py and tests/test_launch.py run for real."""

from __future__ import annotations

import multiprocessing
import os
import runpy
import signal
import subprocess
import sys
from pathlib import Path

from helpers import REPO

# the modules a command's start-up imports: the server imports them once, its children inherit them
PRELOAD = ["torch", "lightning", "omg.cli", "omg.tools.lightning", "omg.lit", "omg.data.datamodule", "omg.callbacks",
           "omg.tools.shards", "omg.tools.serve", "helpers.faults"]
_CONTEXT = multiprocessing.get_context("forkserver")
_CONTEXT.set_forkserver_preload(PRELOAD)


def _run(args: list[str], script: str | None, cwd: str, env: dict[str, str], stdout: str, stderr: str,
         new_session: bool, start_method: str) -> None:
    """In the child: the process state a fresh `python -m omg.cli ARGS` (or `python SCRIPT ARGS`) would have,
    then ``omg.cli.main`` (or the script as ``__main__``). Its SystemExit is the child's exit code
    (multiprocessing's bootstrap)."""
    # a fork server's child inherits "forkserver" as its default; a fresh interpreter has the platform's (the
    # data loader's workers would otherwise start from the server, without this process's state)
    multiprocessing.set_start_method(start_method, force=True)
    if new_session:
        os.setsid()  # as a terminal starts a command: a process group of its own
    os.chdir(cwd)
    os.environ.clear()
    os.environ.update(env)
    for fd, path in ((1, stdout), (2, stderr)):
        if fd == 2 and path == stdout:  # one file for both, as Popen(stderr=STDOUT)
            os.dup2(1, 2)
            continue
        target = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
        os.dup2(target, fd)
        os.close(target)
    sys.stdout = open(1, "w", buffering=1, closefd=False)  # noqa: SIM115 - the process's own streams
    sys.stderr = open(2, "w", buffering=1, closefd=False)  # noqa: SIM115
    signal.signal(signal.SIGINT, signal.default_int_handler)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    import torch

    torch.set_num_threads(int(env.get("OMP_NUM_THREADS", "1")))
    if script is not None:
        sys.argv = [script, *args]
        runpy.run_path(script, run_name="__main__")
        return
    from omg.cli import main

    sys.argv = [str(REPO / "omg" / "cli.py"), *args]
    main(list(args))


class OmgProcess:
    """``subprocess.Popen``'s face (pid, poll, wait, returncode, kill, send_signal) on a forked ``omg ARGS``
    (or ``python SCRIPT ARGS`` with ``script``); ``stdout`` and ``stderr`` are files (the same one for both,
    as ``stderr=STDOUT``)."""

    def __init__(self, args: list[str], *, script: Path | None = None, cwd: Path = REPO,
                 env: dict[str, str] | None = None, stdout: Path | str = os.devnull,
                 stderr: Path | str = os.devnull, new_session: bool = False):
        self.args = [str(script) if script else "omg", *args]
        env = {**os.environ, **(env or {})}
        self._process = _CONTEXT.Process(target=_run, args=(
            list(args), None if script is None else str(script), str(cwd), env, str(stdout), str(stderr),
            new_session, multiprocessing.get_start_method()))
        self._process.start()
        self.pid = self._process.pid

    @property
    def returncode(self) -> int | None:
        """The exit code, or minus the signal that ended it (as Popen's)."""
        return self._process.exitcode

    def poll(self) -> int | None:
        return self._process.exitcode

    def wait(self, timeout: float | None = None) -> int:
        self._process.join(timeout)
        if self._process.exitcode is None:
            raise subprocess.TimeoutExpired(self.args, timeout)
        return self._process.exitcode

    def send_signal(self, signum: int) -> None:
        if self._process.exitcode is None:
            os.kill(self.pid, signum)

    def kill(self) -> None:
        self.send_signal(signal.SIGKILL)


def spawn_ranks(fn, args: tuple, nprocs: int) -> None:
    """``torch.multiprocessing.spawn(fn, args, nprocs)`` with the rank processes forked from the same server:
    each imports only what the server has not (``fn``'s test module), where a spawned rank imports torch and
    Lightning again. A test whose point is what a fresh rank inherits (nothing) spawns its ranks itself."""
    import torch.multiprocessing as mp

    mp.start_processes(fn, args=args, nprocs=nprocs, join=True, start_method="forkserver")
