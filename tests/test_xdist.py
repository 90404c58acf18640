"""The suite's time rests on `--dist loadgroup` (pyproject.toml): the tests of one `xdist_group` share
expensive session fixtures (trained checkpoints, multi-rank reference runs) and must run on one worker,
which then builds them once. A pytest and pytest-xdist pair that loses the group runs them anyway,
scattered, each worker training the fixtures again: this checks the pair installed keeps them together,
and that the longest tests and groups are handed out first (tests/helpers/schedule.py)."""

from __future__ import annotations

import ast
import os
import re
import subprocess
import sys
import textwrap
from pathlib import Path

from helpers.schedule import LONGEST, unit_of, unit_seconds


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


def test_the_longest_units_start_first(request):
    """conftest.py hands the workers the longest tests and groups first (helpers.schedule): over this
    session's tests, no unit (a test, or an xdist group's tests together) takes longer than the one before."""
    items = request.session.items
    seconds = unit_seconds(items)
    units = [unit_of(item) for item in items]
    late = [(units[k], seconds[units[k]]) for k in range(1, len(units)) if seconds[units[k]] > seconds[units[k - 1]]]
    assert not late, late[:5]
    split = {u for k, u in enumerate(units) if u in units[:k] and units[k - 1] != u}
    assert not split, split  # a group's tests follow each other


def test_the_schedule_names_tests_and_groups_that_exist():
    """A renamed test, parameter case or group would drop out of LONGEST silently, and start late."""
    tests = Path(__file__).parent
    groups = {g for path in tests.glob("test_*.py") for g in re.findall(r'xdist_group\("(\w+)"\)', path.read_text())}
    for key in LONGEST:
        if "::" not in key:
            assert key in groups, f"{key}: no xdist_group of that name"
            continue
        file, test = key.split("::")
        name, _, case = test.partition("[")
        defined = {node.name: node for node in ast.parse((tests / file).read_text()).body
                   if isinstance(node, ast.FunctionDef)}
        assert name in defined, f"{key}: no such test"
        if case:
            cases = parameter_ids(defined[name])
            assert cases is None or case.removesuffix("]") in cases, f"{key}: no such case of {name} ({cases})"


def parameter_ids(test: ast.FunctionDef) -> set[str] | None:
    """The ids pytest gives the cases of ``test``'s one ``parametrize`` of literal values (ints, strings,
    booleans; a tuple's joined by "-"), or None where they cannot be read from the source."""
    marks = [d for d in test.decorator_list if isinstance(d, ast.Call) and ast.unparse(d.func).endswith("parametrize")]
    if len(marks) != 1 or len(marks[0].args) != 2 or marks[0].keywords:
        return None
    try:
        values = ast.literal_eval(marks[0].args[1])
    except ValueError:
        return None
    return {"-".join(map(str, v)) if isinstance(v, tuple) else str(v) for v in values}
