"""A file a user names is read only when it is a regular file of bounded size (``omg.files.read_file``):
a FIFO, a symbolic link to /dev/zero, a folder or an oversize file is one line through the real
commands, and nothing is written. The FIFO and /dev/zero cases run the CLI in a child process with a
timeout and a memory limit: without the check a FIFO blocks its reader forever and /dev/zero is read
until memory runs out, and a regression must fail this test, not hang the suite or fill the machine.
(The folder, device, oversize, output-folder and YAML-tag cases are rows of tests/test_bad_input.py.)"""

from __future__ import annotations

import json
import os
import resource
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from helpers import BANDAI_RIG, REPO, rig_bvh
from omg.errors import UsageError
from omg.files import MOTION_MAX_BYTES, TEXT_MAX_BYTES, read_file, read_text, read_yaml
from omg.skeleton import SMPL22

TIMEOUT_S = 120  # the commands below end in a few seconds; one that blocks on a FIFO never does
MEMORY_LIMIT = 3 * 2**30  # bytes of heap the child may take: reading /dev/zero hits it within seconds

# runs each argv through omg.cli.main in one process (one start-up for all); prints per command a
# JSON line [exit code, stderr]; an exception that escapes main (a MemoryError) is recorded as such
CHILD = r"""
import contextlib, io, json, sys
from omg.cli import main
for argv in json.loads(sys.argv[1]):
    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        try:
            main(argv)
            code = 0
        except SystemExit as e:
            code = e.code
        except BaseException as e:  # noqa: BLE001 - the test reports it
            code = f"{type(e).__name__}: {str(e)[:200]}"
    print(json.dumps([code, err.getvalue()]), flush=True)
"""


def _limit_memory() -> None:
    resource.setrlimit(resource.RLIMIT_DATA, (MEMORY_LIMIT, MEMORY_LIMIT))


def _listing(root: Path) -> list[str]:
    return sorted(str(p.relative_to(root)) for p in root.rglob("*"))


def test_fifo_and_dev_zero_are_one_line_through_the_cli(tmp_path):
    d = tmp_path
    np.save(d / "still.joints.npy", np.repeat(SMPL22.rest_positions()[None], 10, axis=0).astype(np.float32))
    (d / "human.bvh").write_text(rig_bvh(BANDAI_RIG))
    for name in ("rig.bvh", "map.yaml", "manifest.json"):
        os.mkfifo(d / name)
    (d / "zero.bvh").symlink_to("/dev/zero")
    (d / "motions").mkdir()  # a folder of motions to export, one of them a FIFO
    np.save(d / "motions/a.joints.npy", np.load(d / "still.joints.npy"))
    os.mkfifo(d / "motions/b.joints.npy")
    (d / "plan").mkdir()  # a ControlNet config whose DiT flavor is looked up in the configs beside it
    shutil.copy(REPO / "configs/controlnet_base.yaml", d / "plan/controlnet_base.yaml")
    os.mkfifo(d / "plan/a_fifo.yaml")
    export = ["export", str(d / "still.joints.npy"), "--no_preview"]
    cases = [  # (argv, what the one line says)
        ([*export, "--to_rig", str(d / "rig.bvh")], f"--to_rig {d}/rig.bvh: not a regular file (a FIFO"),
        ([*export, "--to_rig", str(d / "zero.bvh")], f"--to_rig {d}/zero.bvh: not a regular file (a FIFO, socket or "
                                                     "device)"),
        ([*export, "--to_rig", str(d / "human.bvh"), "--joint_map", str(d / "map.yaml")],
         f"joint map {d}/map.yaml: not a regular file (a FIFO"),
        (["export", str(d / "motions"), "--no_preview"], f"{d}/motions/b.joints.npy: not a regular file (a FIFO"),
        (["bench", "sides", "--manifests", f"[{d}/manifest.json]", "--encoders", "[hash]"],
         f"{d}/manifest.json: not a regular file (a FIFO"),
        (["bench", "plan", "--configs", f"[{d}/plan/controlnet_base.yaml]"],
         f"--configs {d}/plan/controlnet_base.yaml: no pretraining config in {d}/plan writes"),
    ]
    before = _listing(d)
    try:
        proc = subprocess.run([sys.executable, "-c", CHILD, json.dumps([argv for argv, _ in cases])],
                              capture_output=True, text=True, timeout=TIMEOUT_S, cwd=d, preexec_fn=_limit_memory,
                              env={**os.environ, "PYTHONPATH": str(REPO)})
    except subprocess.TimeoutExpired as e:
        done = (e.stdout or b"").decode() if isinstance(e.stdout, bytes) else (e.stdout or "")
        pytest.fail(f"blocked after {len(done.splitlines())} of {len(cases)} commands (a FIFO read?): "
                    f"{cases[len(done.splitlines())][0]}")
    results = [json.loads(line) for line in proc.stdout.splitlines()]
    assert len(results) == len(cases), proc.stderr[-3000:]
    for (argv, says), (code, err) in zip(cases, results):
        lines = [line for line in err.splitlines() if line.strip()]
        assert code == 2, (argv, code, err[-2000:])
        assert len(lines) == 1 and lines[0].startswith("omg: error: ") and says in lines[0], (argv, err[-2000:])
    assert _listing(d) == before, "a refused command wrote files"


def test_read_file_bounds_and_kinds(tmp_path):
    """The one reader: a regular file's bytes up to the bound; anything else a line naming the option."""
    good = tmp_path / "good.txt"
    good.write_bytes(b"x" * 100)
    assert read_file(good, "--x", 100) == b"x" * 100  # exactly the bound is allowed
    (tmp_path / "link.txt").symlink_to(good)  # symbolic links are followed
    assert read_file(tmp_path / "link.txt", "--x", 100) == b"x" * 100
    with pytest.raises(UsageError, match=r"^--x .*good.txt: larger than the 99 bytes omg reads from such a file "
                                         r"\(100 bytes\)$"):
        read_file(good, "--x", 99)
    with pytest.raises(UsageError, match=r"^--x .*: is a directory; a file is expected$"):
        read_file(tmp_path, "--x", 100)
    (tmp_path / "broken.txt").symlink_to(tmp_path / "nothing")
    with pytest.raises(UsageError, match="broken.txt: a broken symbolic link"):
        read_file(tmp_path / "broken.txt", "--x", 100)
    os.mkfifo(tmp_path / "fifo.txt")  # refused before any open: nothing here can block
    with pytest.raises(UsageError, match="fifo.txt: not a regular file"):
        read_file(tmp_path / "fifo.txt", "--x", 100)
    # a file that reports no size (procfs) is still bounded by what is read
    with pytest.raises(UsageError, match=r"^--x /proc/self/status: larger than the 10 bytes omg reads"):
        read_file("/proc/self/status", "--x", 10)
    assert TEXT_MAX_BYTES == 16 * 2**20 and MOTION_MAX_BYTES == 256 * 2**20
    (tmp_path / "latin1.txt").write_bytes("caf\u00e9\n".encode("latin-1"))
    with pytest.raises(UsageError, match=r"^--x .*latin1.txt: not a UTF-8 text file \(byte 0xe9 at offset 3\)"):
        read_text(tmp_path / "latin1.txt", "--x")


@pytest.mark.parametrize("text, says", [
    ("a: 1\nb: !!python/object/apply:os.system ['echo pwned']\n",
     "the YAML tag !!python/object/apply:os.system at line 2 is not allowed"),
    ("a: !!python/name:os.system\n", "the YAML tag !!python/name:os.system at line 1 is not allowed"),
    ("a: !shell ls\n", "the YAML tag !shell at line 1 is not allowed"),
    ("a: [1, 2\n", "not valid YAML at line 2"),
])
def test_read_yaml_refuses_tags_in_one_line(tmp_path, text, says):
    path = tmp_path / "config.yaml"
    path.write_text(text)
    with pytest.raises(UsageError) as e:
        read_yaml(path, "--configs")
    assert str(e.value).startswith(f"--configs {path}: {says}") and "\n" not in str(e.value)
