"""Khronos' glTF validator (npm's ``gltf-validator``, which ``.ci/run`` installs under ``.ci/node``; elsewhere
``OMG_GLTF_VALIDATOR`` names its ``node_modules``): the tests' one way to run it."""

from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path

import pytest

from helpers import REPO

VALIDATOR = Path(os.environ.get("OMG_GLTF_VALIDATOR", REPO / ".ci/node/node_modules"))

_SCRIPT = ("const v = require('gltf-validator'); const fs = require('fs');"
           "(async () => { for (const f of process.argv.slice(1)) {"
           " const r = await v.validateBytes(new Uint8Array(fs.readFileSync(f)));"
           " console.log(r.issues.numErrors, JSON.stringify(r.issues.messages.filter(m => m.severity == 0))); }"
           "})();")


def validation_errors(files: list[Path | str]) -> dict[str, str]:
    """Each file that has errors -> its error messages (JSON); empty where all pass. Skips the test, with the
    reason, where the validator is not installed."""
    if shutil.which("node") is None or not (VALIDATOR / "gltf-validator").is_dir():
        pytest.skip(f"Khronos' glTF validator is not installed at {VALIDATOR} (.ci/run installs it with npm)")
    run = subprocess.run(["node", "-e", _SCRIPT, *map(str, files)], capture_output=True, text=True, timeout=120,
                         env={**os.environ, "NODE_PATH": str(VALIDATOR)})
    assert run.returncode == 0, run.stderr
    lines = run.stdout.splitlines()
    assert len(lines) == len(files), run.stdout
    return {str(f): line for f, line in zip(files, lines) if line.split()[0] != "0"}
