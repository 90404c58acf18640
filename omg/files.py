"""Files that readers never see half-written: every file omg writes (shards, manifests,
checkpoints, BVH, previews, settings) goes through ``atomic_path``. And the checks made before
reading or writing: ``read_file`` (the one way a user's file is read: a regular file only, at most
a bound of bytes), ``file_problem`` (what a path is when it is no regular file) and
``check_output_dir`` (an output folder that can be created and written, with no folder where an
output file goes)."""

from __future__ import annotations

import fnmatch
import io
import json
import os
import re
import shutil
import stat
import tempfile
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

import numpy as np

from omg.errors import UsageError

# The most bytes read from a user's file of each kind: far above any real one, so that a file that
# never ends (a symbolic link to /dev/zero, a log still being written) is refused, not read until
# memory runs out.
TEXT_MAX_BYTES = 16 * 2**20  # prompts files, configs, joint maps, species files, settings (UTF-8 text)
MOTION_MAX_BYTES = 256 * 2**20  # a motion or rig: BVH, ASF/AMC, DeepMimic, a .npy array (hours of mocap)
MANIFEST_MAX_BYTES = 256 * 2**20  # a clip manifest (JSON, about 1 KiB a clip with its texts)


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


def _size(n: int) -> str:
    return f"{n // 2**20} MiB" if n % 2**20 == 0 else f"{n} bytes"


def read_file(path: str | Path, what: str, max_bytes: int) -> bytes:
    """The bytes of the regular file at ``path`` (symbolic links followed), at most ``max_bytes`` of
    them; a one-line UsageError naming ``what`` (the option, e.g. "--to_rig") otherwise: a folder,
    a FIFO, a device, nothing there, or a larger file. The one way omg reads a file a user names
    (``_open_regular``); the read stops one byte past the bound, as files such as /proc's report no size."""
    path = Path(path)
    where = f"{what} {path}" if what else str(path)
    too_large = f"{where}: larger than the {_size(max_bytes)} omg reads from such a file"
    with _open_regular(path, where) as f:
        if (size := os.fstat(f.fileno()).st_size) > max_bytes:
            raise UsageError(f"{too_large} ({size} bytes)")
        data = _read(f, max_bytes + 1, where)
    if len(data) > max_bytes:  # grew while read, or reports no size
        raise UsageError(too_large)
    return data


def read_head(path: str | Path, n: int, what: str = "") -> bytes:
    """The first ``n`` bytes (fewer in a shorter file) of the regular file at ``path``, checked as
    ``read_file`` checks it: a look at what a file holds reads no more than that."""
    path = Path(path)
    where = f"{what} {path}" if what else str(path)
    with _open_regular(path, where) as f:
        return _read(f, n, where)


@contextmanager
def _open_regular(path: Path, where: str) -> Iterator[io.BufferedReader]:
    """``path`` opened for reading if it is a regular file (symbolic links followed); a one-line
    UsageError led by ``where`` otherwise. Opened non-blocking (a FIFO swapped in after the check
    cannot block the open) and checked again on the open descriptor, which is what is read."""
    if problem := file_problem(path):
        raise UsageError(f"{where}: {problem}")
    try:
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_CLOEXEC", 0))
    except OSError as e:
        raise UsageError(f"{where}: cannot be read ({e.strerror or e})") from None
    with os.fdopen(fd, "rb") as f:
        if not stat.S_ISREG(os.fstat(f.fileno()).st_mode):  # replaced between the check and the open
            raise UsageError(f"{where}: not a regular file (a FIFO, socket or device); a file is expected")
        yield f


def _read(f: io.BufferedReader, n: int, where: str) -> bytes:
    try:
        return f.read(n)
    except OSError as e:
        raise UsageError(f"{where}: cannot be read ({e.strerror or e})") from None


def check_output_dir(path: str | Path, what: str = "--out", files: tuple[str, ...] = ()) -> Path:
    """``path`` can be (or already is) a folder to write in: neither it nor a parent is an existing
    file, the nearest existing one takes new entries, and no entry named like one of ``files`` (glob
    patterns of the files a command writes there) is a folder, which the output file's rename
    (``atomic_path``) cannot replace; a one-line UsageError naming ``what`` otherwise."""
    path = Path(path)
    if files and path.is_dir():
        for entry in sorted(path.iterdir()):
            if (any(fnmatch.fnmatchcase(entry.name, pattern) for pattern in files) and entry.is_dir()
                    and not entry.is_symlink()):  # a rename replaces a link, also one to a folder
                raise UsageError(f"{what} {path}: {entry.name} is a folder, where an output file goes; "
                                 "move it away or choose another folder")
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


def read_text(path: str | Path, what: str, max_bytes: int = TEXT_MAX_BYTES) -> str:
    """A UTF-8 text file's contents (``read_file``); a missing file, a folder, a larger file than
    ``max_bytes`` or another encoding is a UsageError."""
    path = Path(path)
    data = read_file(path, what, max_bytes)
    try:
        return data.decode("utf-8-sig")  # a byte-order mark (Windows editors) is not part of the text
    except UnicodeDecodeError as e:
        raise UsageError(f"{what} {path}: not a UTF-8 text file (byte 0x{data[e.start]:02x} at offset {e.start}); "
                         "save it as UTF-8") from None


def read_array(path: str | Path, what: str, max_bytes: int = MOTION_MAX_BYTES) -> np.ndarray | np.lib.npyio.NpzFile:
    """``np.load`` of the bytes ``read_file`` gives (a FIFO cannot block it, a huge file is refused
    unread): an .npy array, or an .npz as numpy's ``NpzFile`` over those bytes (``with`` closes it).
    Never unpickled; bytes that hold no array raise numpy's own errors (ValueError, OSError,
    EOFError, zipfile.BadZipFile), for the caller to word."""
    return np.load(io.BytesIO(read_file(path, what, max_bytes)), allow_pickle=False)


def read_yaml(path: str | Path, what: str, max_bytes: int = TEXT_MAX_BYTES):
    """A YAML file (``read_text``) read by the safe loader: a tag that would build a Python object
    (``!!python/object/apply:os.system``) or any other unknown tag, and bad syntax, are one UsageError
    naming ``what``, the file and the line."""
    import yaml

    path = Path(path)
    try:
        return yaml.safe_load(read_text(path, what, max_bytes))
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None)
        at = f" at line {mark.line + 1}" if mark is not None else ""
        problem = str(getattr(e, "problem", None) or e).splitlines()[0]
        tag = re.fullmatch(r"could not determine a constructor for the tag '(?:tag:yaml\.org,2002:)?(.*)'", problem)
        if tag:
            name = f"!!{tag.group(1)}" if problem.count("tag:yaml.org,2002:") else tag.group(1)
            raise UsageError(f"{what} {path}: the YAML tag {name}{at} is not allowed; tags that make Python objects "
                             "are never read, give plain values") from None
        raise UsageError(f"{what} {path}: not valid YAML{at} ({problem})") from None


@contextmanager
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
