"""omg uses jsonargparse and Lightning through their public APIs only (issue #26, 5b): no private
attribute (a name starting with ``_``) of theirs is read, called or overridden in omg/, and no
private module or name of theirs is imported. What omg computes itself in place of a private hook
(Lightning's choice of the SLURM requeue checkpoint and of the ``last`` checkpoints, the progress
bar's epoch) is checked against Lightning's own."""

from __future__ import annotations

import ast
import functools
import importlib
import importlib.util
import inspect
import os
import re
import textwrap
from pathlib import Path
from types import SimpleNamespace

import pytest

from helpers import REPO

PACKAGE = REPO / "omg"
LIBRARIES = ("jsonargparse", "lightning", "lightning_fabric", "pytorch_lightning")

# (omg file, private name) -> why no public route exists. Keep it short: each entry is a hook that
# a new jsonargparse or Lightning may remove without notice.
ALLOWED: dict[tuple[str, str], str] = {
    ("omg/callbacks/run.py", "_signal_connector"):
        "Ctrl-C sets the flag Lightning's own SIGTERM handler sets (trainer.received_sigterm is read-only), so "
        "that the loops stop at a step boundary and raise SIGTERMException as for SIGTERM; the public "
        "trainer.should_stop ends the fit as if it had finished, and the run would not report the interruption",
    ("omg/lit/base.py", "_should_accumulate"):
        "whether this optimizer_step call is a gradient-accumulation micro-step (the EMA updates once per real "
        "step): Lightning offers no public flag, and its fit loop's is private",
    ("omg/lit/checkpoint.py", "_given_hyperparameters"):
        "a module rebuilt from a checkpoint while LightningCLI builds another (HabitPriorModule's VQ-VAE) must record "
        "its own hyper-parameters: LightningCLI hands its config to save_hyperparameters() through this context "
        "variable, and Lightning has no public way to step out of it",
}


def _is_private(name: str) -> bool:
    return name.startswith("_") and not (name.startswith("__") and name.endswith("__"))


@functools.cache
def library_private_names() -> frozenset[str]:
    """Every private attribute name the libraries' sources define or use (``x._name``, ``def _name``)."""
    names: set[str] = set()
    for library in LIBRARIES:
        spec = importlib.util.find_spec(library)
        if spec is None or spec.origin is None:
            continue
        for path in Path(spec.origin).parent.rglob("*.py"):
            try:
                tree = ast.parse(path.read_text(encoding="utf-8"))
            except (SyntaxError, UnicodeDecodeError):
                continue
            for node in ast.walk(tree):
                if isinstance(node, ast.Attribute) and _is_private(node.attr):
                    names.add(node.attr)
                elif isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) and _is_private(node.name):
                    names.add(node.name)
    return frozenset(names)


@functools.cache
def class_private_names(cls: type) -> frozenset[str]:
    """The private names a library class defines or uses on ``self`` (its methods, its attributes)."""
    try:
        tree = ast.parse(textwrap.dedent(inspect.getsource(cls)))
    except (OSError, TypeError, SyntaxError):
        return frozenset()
    names = set()
    for node in ast.walk(tree):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) and _is_private(node.name):
            names.add(node.name)
        elif isinstance(node, ast.Attribute) and _is_private(node.attr):
            names.add(node.attr)
    return frozenset(names)


def _from_library(module: str | None) -> bool:
    return bool(module) and module.split(".")[0] in LIBRARIES


def _on_self(node: ast.expr) -> bool:
    """``self.x`` / ``cls.x`` / ``super().x``: an attribute of the object the method belongs to."""
    if isinstance(node, ast.Name):
        return node.id in ("self", "cls")
    return isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id == "super"


def module_name(path: Path, root: Path) -> str:
    parts = path.relative_to(root).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def private_uses(path: Path, root: Path = REPO) -> list[tuple[int, str, str]]:
    """(line, private name, what) of each use of a library's private name in the file ``path`` (a module
    importable from ``root``, imported to know its classes' bases)."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    module = None
    found: list[tuple[int, str, str]] = []

    def library_bases(class_name: str) -> list[type]:
        nonlocal module
        module = module or importlib.import_module(module_name(path, root))
        cls = getattr(module, class_name, None)
        return [k for k in getattr(cls, "__mro__", ())[1:] if _from_library(k.__module__)]

    def visit(node: ast.AST, bases: list[type]) -> None:
        for child in ast.iter_child_nodes(node):
            inner = bases
            if isinstance(child, ast.ClassDef):
                inner = library_bases(child.name) if node is tree else bases
                own = set().union(*(class_private_names(k) for k in inner)) if inner else set()
                for item in child.body:  # overrides of a library class's private methods
                    if isinstance(item, (ast.FunctionDef, ast.AsyncFunctionDef)) and item.name in own:
                        found.append((item.lineno, item.name, f"overrides {child.name}.{item.name}"))
            elif isinstance(child, ast.ImportFrom) and _from_library(child.module):
                private = [p for p in child.module.split(".") if _is_private(p)]
                private += [a.name for a in child.names if _is_private(a.name)]
                found.extend((child.lineno, name, f"imports from {child.module}") for name in private)
            elif isinstance(child, ast.Import):
                found.extend((child.lineno, p, f"imports {a.name}") for a in child.names if _from_library(a.name)
                             for p in a.name.split(".") if _is_private(p))
            elif isinstance(child, ast.Attribute) and _is_private(child.attr):
                if _on_self(child.value):
                    own = set().union(*(class_private_names(k) for k in bases)) if bases else set()
                    if child.attr in own:
                        found.append((child.lineno, child.attr, f"{ast.unparse(child)} (of a library base class)"))
                elif child.attr in library_private_names():
                    found.append((child.lineno, child.attr, ast.unparse(child)))
            visit(child, inner)

    visit(tree, [])
    return found


def test_the_scan_finds_the_hooks_it_is_for(tmp_path, monkeypatch):
    """The scan itself: the private hooks omg once used are found, omg's own private names are not."""
    (tmp_path / "scanned_probe.py").write_text(textwrap.dedent("""
        from jsonargparse._core import ArgumentParser
        from lightning.pytorch.cli import LightningCLI
        from lightning.pytorch.callbacks import RichProgressBar

        class CLI(LightningCLI):
            def _run_subcommand(self, subcommand):
                super()._prepare_subcommand_kwargs(subcommand)
                return self.trainer._checkpoint_connector._hpc_resume_path

            def _own_helper(self):
                return self._own_value

        class Bar(RichProgressBar):
            def _get_train_description(self, current_epoch):
                return ""

        def watch(action):
            return action._check_type_
    """))
    monkeypatch.syspath_prepend(str(tmp_path))
    names = {name for _, name, _ in private_uses(tmp_path / "scanned_probe.py", tmp_path)}
    assert names == {"_core", "_run_subcommand", "_prepare_subcommand_kwargs", "_checkpoint_connector",
                     "_hpc_resume_path", "_get_train_description", "_check_type_"}


def test_omg_uses_no_private_jsonargparse_or_lightning_attribute():
    uses = []
    for path in sorted(PACKAGE.rglob("*.py")):
        where = str(path.relative_to(REPO))
        uses += [f"{where}:{line}: {what}" for line, name, what in private_uses(path) if (where, name) not in ALLOWED]
    assert not uses, ("private jsonargparse/Lightning attributes (use a public API, or add an entry to ALLOWED "
                      "with the reason none exists):\n" + "\n".join(uses))


def test_every_allowed_hook_is_still_used():
    used = {(str(path.relative_to(REPO)), name) for path in PACKAGE.rglob("*.py") for _, name, _ in private_uses(path)}
    assert set(ALLOWED) <= used, f"stale ALLOWED entries: {sorted(set(ALLOWED) - used)}"


# -- what omg computes in place of a private hook, against Lightning's own --------------------------
def test_the_hpc_checkpoint_is_lightnings_choice(tmp_path):
    """``hpc_resume_path`` picks the file Lightning's checkpoint connector picks for ckpt_path="hpc"."""
    import lightning as L

    from omg.tools.lightning import hpc_resume_path

    trainer = L.Trainer(default_root_dir=tmp_path, logger=False, enable_checkpointing=False,
                        enable_progress_bar=False, enable_model_summary=False)
    lightning = trainer._checkpoint_connector  # the private answer, read here only to compare
    assert hpc_resume_path(tmp_path) is None and lightning._hpc_resume_path is None
    for name in ("hpc_ckpt_2.ckpt", "hpc_ckpt_10.ckpt", "hpc_ckpt_9.ckpt", "other.ckpt", "last.ckpt"):
        (tmp_path / name).write_bytes(b"")
    assert hpc_resume_path(tmp_path) == lightning._hpc_resume_path == os.path.join(tmp_path, "hpc_ckpt_10.ckpt")
    assert hpc_resume_path(tmp_path / "missing") is None


def test_the_last_checkpoints_are_lightnings(tmp_path):
    """``last_checkpoints`` lists the files ModelCheckpoint looks among for ckpt_path="last"."""
    from lightning.pytorch.callbacks import ModelCheckpoint

    from omg.tools.lightning import last_checkpoints

    callback = ModelCheckpoint(dirpath=tmp_path, save_last=True)
    for name in ("last.ckpt", "last-v1.ckpt", "last-v2.tmp", "epoch=0-step=5.ckpt", "lastly.ckpt", "x-last.ckpt"):
        (tmp_path / name).write_bytes(b"")
    ours = {str(p) for p in last_checkpoints(callback)}
    assert ours == callback._find_last_checkpoints(SimpleNamespace())  # the private answer, to compare
    assert {Path(p).name for p in ours} == {"last.ckpt", "last-v1.ckpt", "lastly.ckpt"}
    assert last_checkpoints(ModelCheckpoint(dirpath=tmp_path / "none")) == []


@pytest.mark.parametrize("max_epochs, expected", [(-1, "Epoch 7"), (None, "Epoch 7"), (10, "Epoch 7/9")])
def test_the_progress_bar_tells_the_epoch_without_a_negative_total(max_epochs, expected):
    """A run bounded by steps (max_epochs -1) reads "Epoch 7", not Lightning's "Epoch 7/-2"."""
    from rich.progress import Progress

    from omg.tools.lightning import StepProgressBar

    bar = StepProgressBar()
    bar.progress = Progress()
    lightning = f"Epoch 7/{max_epochs - 1}" if max_epochs is not None else "Epoch 7"
    bar.train_progress_bar_id = bar.progress.add_task(lightning, total=10)
    bar.retitle(SimpleNamespace(max_epochs=max_epochs, current_epoch=7))
    description = re.sub(r"^\[[^\]]*\]", "", bar.progress.tasks[0].description).strip()
    assert description == expected
