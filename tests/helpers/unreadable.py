"""Dataset files that must be refused unread: a FIFO named like a clip (an open would wait for a
writer forever) and a sparse file over the read bound; a guard that turns a hang into a failure."""

from __future__ import annotations

import math
import signal
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest

from omg.cli import main
from omg.files import MOTION_MAX_BYTES

FIFO = "not a regular file (a FIFO, socket or device)"
TOO_LARGE = "larger than the 256 MiB omg reads from such a file"


@contextmanager
def no_hang(seconds: int = 120):
    """Fails the test when the block runs longer than ``seconds``: an importer that opens a FIFO waits
    for a writer forever. pytest.fail raises a BaseException, which the importers' ``except Exception``
    (one counted skip per bad file) cannot turn into a skip."""

    def hung(signum, frame):
        pytest.fail(f"still running after {seconds} s: a read blocked (a FIFO opened for reading?)")

    previous = signal.signal(signal.SIGALRM, hung)
    signal.alarm(seconds)
    try:
        yield
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, previous)


def huge_npy(path: Path, row: tuple[int, ...]) -> None:
    """A sparse float32 .npy of (N, *row) with a valid header, one row over MOTION_MAX_BYTES: no disk
    used, but np.load of the path would read (and allocate) all of it."""
    rows = MOTION_MAX_BYTES // (4 * math.prod(row)) + 1
    with open(path, "wb") as f:
        np.lib.format.write_array_header_1_0(f, {"descr": "<f4", "fortran_order": False, "shape": (rows, *row)})
        f.truncate(f.tell() + rows * 4 * math.prod(row))


def one_line_error(capsys, argv: list[str]) -> str:
    """``omg`` with ``argv`` exits 2 with one ``omg: error:`` line (and no hang); that line."""
    with no_hang(), pytest.raises(SystemExit) as exit:
        main(argv)
    err = capsys.readouterr().err.strip()
    assert exit.value.code == 2 and "\n" not in err and err.startswith("omg: error: "), err
    return err
