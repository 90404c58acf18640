"""Helpers the tool commands share: output folders removed again when a command fails (checked
before anything is written by ``omg.files.check_output_dir``); UTF-8 text files are read by
``omg.files.read_text``."""

from __future__ import annotations

import contextlib
import shutil
from pathlib import Path
from typing import Iterator


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
