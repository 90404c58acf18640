"""The suite's time rests on `--dist loadgroup` (pyproject.toml): the tests of one `xdist_group` share
expensive session fixtures (trained checkpoints, multi-rank reference runs) and must run on one worker,
which then builds them once. A pytest and pytest-xdist pair that loses the group runs them anyway,
scattered, each worker training the fixtures again: this checks the pair installed keeps them together."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap


def test_an_xdist_group_runs_on_one_worker(tmp_path):
    (tmp_path / "test_grouped.py").write_text(textwrap.dedent("""
        import os
        import pytest

        pytestmark = pytest.mark.xdist_group("shared")

        @pytest.mark.parametrize("i", range(6))
        def test_worker(i):
            with open(os.path.join(os.environ["RAN"], f"ran-{i}"), "w") as f:
                f.write(os.environ["PYTEST_XDIST_WORKER"])
        """))
    done = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-n", "2", "--dist",
                           "loadgroup", "--basetemp", str(tmp_path / "base"), "-o", "addopts=", str(tmp_path)],
                          cwd=tmp_path, env={**os.environ, "RAN": str(tmp_path)}, capture_output=True, text=True,
                          timeout=120)
    assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-2000:]
    workers = {p.read_text() for p in tmp_path.glob("ran-*")}
    assert len(list(tmp_path.glob("ran-*"))) == 6 and len(workers) == 1, workers
