"""Helpers the tool commands share: output folders removed again when a command fails (checked
before anything is written by ``omg.files.check_output_dir``), UTF-8 text files read with one-line errors."""

from __future__ import annotations

import contextlib
import shutil
from pathlib import Path
from typing import Iterator

from omg.errors import UsageError
from omg.files import file_problem


def read_text(path: str | Path, what: str) -> str:
    """A UTF-8 text file's contents; a missing file, a folder or another encoding is a UsageError."""
    path = Path(path)
    if problem := file_problem(path):  # a FIFO would block the read forever
        raise UsageError(f"{what} {path}: {problem}")
    try:
        data = path.read_bytes()
    except OSError as e:
        raise UsageError(f"{what} {path}: cannot be read ({e.strerror or e})") from None
    try:
        return data.decode("utf-8-sig")  # a byte-order mark (Windows editors) is not part of the text
    except UnicodeDecodeError as e:
        raise UsageError(f"{what} {path}: not a UTF-8 text file (byte 0x{data[e.start]:02x} at offset {e.start}); "
                         "save it as UTF-8") from None


def last_line(message: str) -> str:
    """The last non-empty line of a message, e.g. the exception line of a traceback a worker sent."""
    lines = [line for line in message.strip().splitlines() if line.strip()]
    return lines[-1].strip() if lines else message


@contextlib.contextmanager
def removing_created(*dirs: str | Path) -> Iterator[None]:
    """Folders (and their missing parents) this block may create are removed if it fails, with
    everything in them; folders that existed before it, the user's, are never touched."""
    created = []
    for d in map(Path, dirs):
        missing = [p for p in [d, *d.parents] if not p.exists()]
        if missing and missing[-1] not in created:
            created.append(missing[-1])  # the topmost folder the block would create
    try:
        yield
    except Exception:
        for d in created:
            if d.is_dir() and not d.is_symlink():
                shutil.rmtree(d, ignore_errors=True)
        raise
