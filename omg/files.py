"""Files that readers never see half-written: every file omg writes (shards, manifests,
checkpoints, BVH, previews, settings) goes through ``atomic_path``. And the checks made before
reading or writing: ``file_problem`` (what a path is when it is no regular file) and
``check_output_dir`` (an output folder that can be created and written)."""

from __future__ import annotations

import io
import json
import os
import tempfile
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

import numpy as np

from omg.errors import UsageError


@contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """A temporary path beside ``path`` to write to; renamed over ``path`` when the block ends
    without error, so readers see the old file or the whole new one, never a part.

    The temporary name keeps the suffix (writers such as Pillow choose the format by it).
    """
    path = Path(path)
    tmp = path.with_name(f".{path.stem}.{os.getpid()}.tmp{path.suffix}")
    try:
        yield tmp
        with open(tmp, "rb+") as f:
            os.fsync(f.fileno())
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def file_problem(path: str | Path) -> str | None:
    """Why ``path`` is not a regular file to read, in words (a folder, a FIFO or device, nothing);
    None when it is one. Messages say what was found rather than "no such file" for all of them."""
    path = Path(path)
    if path.is_file():
        return None
    if path.is_dir():
        return "is a directory; a file is expected"
    if path.exists():
        return "not a regular file (a FIFO, socket or device); a file is expected"
    if path.is_symlink():
        return "a broken symbolic link; a file is expected"
    return "no such file"


def check_output_dir(path: str | Path, what: str = "--out") -> Path:
    """``path`` can be (or already is) a folder to write in: neither it nor a parent is an existing
    file, and the nearest existing one takes new entries; a one-line UsageError naming ``what`` otherwise."""
    path = Path(path)
    for p in [path, *path.parents]:
        if p.exists() and not p.is_dir():
            where = "" if p == path else f" (its parent {p} is a file)"
            raise UsageError(f"{what} {path}: not a folder{where}; choose a folder path for the output")
        if p.exists():
            if not os.access(p, os.W_OK | os.X_OK):
                raise UsageError(f"{what} {path}: {p} is not writable")
            _probe_writable(path, p, what)
            break
    return path


def _probe_writable(path: Path, existing: Path, what: str) -> None:
    """Create, then remove, a file in ``path`` when it exists, else a folder where its topmost
    missing folder would go: ``os.access`` says yes to root everywhere, also in /proc or on a
    read-only mount. Unique names, so that the ranks of one run can probe at once."""
    try:
        if existing == path:
            with tempfile.TemporaryFile(dir=path):
                pass
        else:
            os.rmdir(tempfile.mkdtemp(dir=existing, prefix=".omg-probe-"))
    except OSError as e:
        raise UsageError(f"{what} {path}: cannot write in {existing} ({e.strerror or e})") from None


def atomic_write(path: Path, data: bytes) -> None:
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


def write_json(path: Path, obj) -> None:
    atomic_write(path, (json.dumps(obj, indent=1) + "\n").encode())


def npy_bytes(array: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, array, allow_pickle=False)
    return buf.getvalue()


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
