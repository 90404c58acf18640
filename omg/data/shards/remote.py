"""Where shards and manifests live: local paths, URLs opened through fsspec, and ``pipe:`` commands
(run with their arguments quoted, stopped with their process group after ``PIPE_TIMEOUT_S``, and never
outliving the process that started them: ``pipe_command``)."""

from __future__ import annotations

import os
import signal
import sys
import threading
import time
from pathlib import Path
from typing import Callable

from omg.data.shards.schema import MANIFEST
from omg.errors import UsageError

PIPE_TIMEOUT_S = 600.0  # a pipe: command that prints a manifest (a few MB at most) and has not ended by then hangs
SIGNAL_CHECK_S = 0.5  # how often a wait for a pipe: command returns to Python, to act on a signal it missed

# The shell that runs a pipe: command ($1) in a process group of its own: the command in the background,
# waited for (its exit status is the shell's); on SIGTERM, the parent-death signal it is given, the whole
# group is killed, so the command's own children (a pipeline, a shell's forks, `aws s3 cp`'s) go too.
_GUARD = 'trap "kill -KILL 0" TERM; eval "$1" & wait $!'
PR_SET_PDEATHSIG = 1  # <linux/prctl.h>


def _local_path(url: str) -> Path | None:
    """The local file a shard or set location names, or None for a URL or a ``pipe:`` command."""
    if url.startswith("file://"):
        return Path(url[len("file://"):])
    if "://" in url or url.startswith("pipe:") or url == "-":
        return None
    return Path(url)


def url_file_name(url: str) -> str:
    """The file a path, URL or ``pipe:`` command reads: the last path component of its last word
    that has one (``pipe:aws s3 cp s3://b/set/shard-000001.tar -`` -> ``shard-000001.tar``)."""
    words = [w for w in url.rstrip("/").split() if "." in w.rsplit("/", 1)[-1]] or [url.rstrip("/")]
    return words[-1].rsplit("/", 1)[-1]


def sibling_url(url: str, name: str, new_name: str) -> str:
    """``url`` with its last ``name`` replaced by ``new_name``: a set's manifest URL gives its shards'
    URLs (``pipe:cat /d/manifest.json`` -> ``pipe:cat /d/shard-000000.tar``) and a shard's the manifest's."""
    head, found, tail = url.rpartition(name)
    if not found:
        raise UsageError(f"{url}: cannot tell where {name} is in it; name the set by its directory URL "
                         f"or by its {MANIFEST} URL")
    return head + new_name + tail


def manifest_url(location: str) -> str:
    """The manifest URL of a set given by URL: a URL or command naming ``manifest.json`` is it; a
    directory URL (``s3://bucket/sets/amass``) gets ``/manifest.json`` appended."""
    if MANIFEST in location:
        return location
    if location.startswith("pipe:"):
        raise UsageError(f"{location}: a pipe: set must print its {MANIFEST}, e.g. pipe:cat /data/set/{MANIFEST} "
                         "(its shards are read by the same command with the shard's name in its place)")
    return location.rstrip("/") + "/" + MANIFEST


def _fsspec_opener(url: str):
    """(fsspec's opener for ``url`` or None, what to install when that is None)."""
    protocol = url.split("://", 1)[0]
    try:
        import fsspec
        from fsspec.registry import known_implementations
    except ImportError:
        return None, f"pip install fsspec and its {protocol} backend"
    if protocol not in known_implementations:
        return None, f"fsspec knows no {protocol}:// protocol"
    try:
        fsspec.get_filesystem_class(protocol)
    except ImportError:  # e.g. s3:// without s3fs
        return None, known_implementations[protocol].get("err") or f"install fsspec's {protocol} backend"
    return (lambda: fsspec.open(url, "rb").open()), ""


def open_url(url: str):
    """A binary stream of a local file, a ``pipe:`` command's output, or an object-store URL:
    ``s3://``, ``gs://``, ``hf://``… through fsspec when it and the protocol's backend are installed,
    else whatever ``webdataset.gopen`` knows (``http(s)://`` by curl, ``gs://`` by gsutil)."""
    local = _local_path(url)
    if local is not None:
        return open(local, "rb")
    if url.startswith("pipe:"):
        from webdataset import utils
        from webdataset.gopen import Pipe

        if utils.enforce_security:
            raise ValueError("pipe: URLs are disabled (WDS_SECURE is set)")
        # as webdataset.gopen, but the command in a process group of its own, which a read given up
        # (a stall, a failed check, a reader that stops early) kills whole (see _abandon), as does
        # this process's end, however it ends (pipe_command)
        command = url[len("pipe:"):]
        pipe = Pipe(pipe_command(command), mode="rb", bufsize=8192, ignore_status=[141], start_new_session=True,
                    preexec_fn=dies_with_parent(signal.SIGTERM))
        pipe.args = ((command,), {})  # what webdataset's messages name: the user's command, not the guard
        return pipe
    opener, missing = _fsspec_opener(url)
    if opener is not None:
        return opener()
    from webdataset.gopen import gopen, gopen_schemes

    scheme = url.split("://", 1)[0]
    if scheme not in gopen_schemes:
        raise OSError(f"no reader for {scheme}:// URLs ({missing})")
    return gopen(url)


def read_url(url: str, timeout: float = PIPE_TIMEOUT_S) -> bytes:
    """All the bytes ``open_url`` gives; a ``pipe:`` command that fails, or runs longer than
    ``timeout`` seconds, raises ``OSError`` (with the last line it printed to stderr)."""
    if url.startswith("pipe:"):
        import subprocess

        # its own process group: on a timeout the shell and everything it started are stopped
        ends = time.monotonic() + timeout
        with subprocess.Popen(pipe_command(url[len("pipe:"):]), stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                              start_new_session=True, preexec_fn=dies_with_parent(signal.SIGTERM)) as process:
            try:
                while True:
                    # in slices: a Ctrl-C whose handler ran just before the wait began (or on another thread)
                    # interrupts nothing, and Python acts on it only when the wait returns
                    try:
                        out, err = process.communicate(timeout=min(SIGNAL_CHECK_S, max(0.0, ends - time.monotonic())))
                        break
                    except subprocess.TimeoutExpired:  # nothing is lost: communicate goes on where it stopped
                        if time.monotonic() >= ends:
                            raise
            except subprocess.TimeoutExpired:
                _kill_group(process)
                raise OSError(f"the command did not end within {timeout:g} s and was stopped") from None
            except BaseException:  # data.timeout's alarm, a stop signal, Ctrl-C: the command is not waited for
                _kill_group(process)
                raise
        if process.returncode != 0:
            said = err.decode(errors="replace").strip().splitlines()
            raise OSError(f"the command exited with {process.returncode}" + (f": {said[-1]}" if said else ""))
        return out
    with open_url(url) as stream:
        return stream.read()


def pipe_command(command: str) -> list[str]:
    """The argv that runs a ``pipe:`` command through ``/bin/sh`` (as ``shell=True`` would) under the
    guard that kills its whole process group on SIGTERM: start it with ``start_new_session=True``
    and ``preexec_fn=dies_with_parent(signal.SIGTERM)``."""
    return ["/bin/sh", "-c", _GUARD, "sh", command]


def dies_with_parent(signum: int) -> Callable[[], None] | None:
    """A ``preexec_fn`` that has Linux send the child ``signum`` when this process ends, SIGKILL
    included (``prctl(PR_SET_PDEATHSIG)``); None elsewhere. The signal comes when the *thread* that
    started the child ends, so only the main thread gets one (where omg and its data workers read);
    a child started from another thread is ended by its reader only."""
    if not sys.platform.startswith("linux") or threading.current_thread() is not threading.main_thread():
        return None
    import ctypes

    prctl = ctypes.CDLL(None, use_errno=True).prctl  # looked up before the fork: the child only calls it
    parent = os.getpid()
    return lambda: _set_parent_death_signal(prctl, signum, parent)


def end_with_parent(signum: int, parent: int) -> None:
    """Have Linux send this process ``signum`` when its parent process ``parent`` ends, SIGKILL
    included (a forked data worker; see ``dies_with_parent``); nothing elsewhere."""
    if sys.platform.startswith("linux"):
        import ctypes

        _set_parent_death_signal(ctypes.CDLL(None, use_errno=True).prctl, signum, parent)


def _set_parent_death_signal(prctl, signum: int, parent: int) -> None:
    prctl(PR_SET_PDEATHSIG, int(signum), 0, 0, 0)
    if os.getppid() != parent:  # the parent ended before the signal was set: it will never come
        os.kill(os.getpid(), signal.SIGKILL)


def _kill_group(process) -> None:
    """Kill a command started in a process group of its own, with everything it started, and reap it."""
    try:
        os.killpg(process.pid, signal.SIGKILL)
    except ProcessLookupError:  # it ended meanwhile
        pass
    process.wait()


def _abandon(stream) -> None:
    """Close a stream that will not be read to its end. A ``pipe:`` command is killed with its process
    group, not waited for: webdataset's close waits up to two hours for a command that is stalled, and
    killing only the shell would leave its commands running."""
    process = getattr(stream, "proc", None)
    if process is not None and process.poll() is None:
        _kill_group(process)
    try:
        stream.close()
    except OSError:  # the killed command's exit status: not news
        pass
