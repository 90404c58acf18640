"""omg uses jsonargparse, Lightning and torch through their public APIs only (issue #26, 5b; issue
#37, 5): no private attribute (a name starting with ``_``) of theirs is read, called or overridden in
omg/, and no private module or name of theirs is imported (``torch._dynamo``, ``torch.utils._pytree``,
``from torch._C import ...``), except the uses ``ALLOWED`` lists with the reason no public route
exists. What omg computes itself in place of a private hook (Lightning's choice of the SLURM requeue
checkpoint and of the ``last`` checkpoints, the progress bar's epoch) is checked against Lightning's
own.

torch's private names are read from three places: a name bound by an import from torch
(``torch._C``, ``F._canonical_mask``, ``signal_handling._remove_worker_pids``); a method or
attribute on ``self`` that a torch base class defines (``nn.Module._apply``, ``self._modules``);
and an attribute of any other object (``loader_iter._workers``, ``getattr(x, "_workers")``) whose
name torch's sources use and omg itself never defines."""

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
TORCH = "torch"  # scanned as well, its private names read from its sources' text (an AST of 50 MB is slow)

# the scans share the libraries' private names (functools.cache, about 20 s to read): under xdist their
# tests run on one worker, which reads them once
pytestmark = pytest.mark.xdist_group("public_api")

# (omg file, private name) -> why no public route exists. Keep it short: each entry is a hook that
# a new jsonargparse, Lightning or torch may remove without notice.
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
    # torch
    ("omg/models/checkpointing.py", "_composable"):
        "activation checkpointing by forward hooks (torch.distributed._composable.checkpoint, torch 2.14 has it "
        "nowhere public), so that parameter names and checkpoints stay as they are; the public "
        "torch.utils.checkpoint.checkpoint wraps a forward call, which would need a wrapper module (renamed "
        "parameters) or a forward override in every block",
    ("omg/data/loaders.py", "_utils"):
        "stop_workers ends a DataLoader iterator's worker processes with SIGCONT and SIGKILL as well (a stopped "
        "worker never exits on torch's SIGTERM, and Python's exit waits for it forever): torch's SIGCHLD handler "
        "must first forget their pids (torch.utils.data._utils.signal_handling), as torch's own shutdown does",
    ("omg/data/loaders.py", "_remove_worker_pids"):
        "the call that makes torch's SIGCHLD handler forget the workers stop_workers ends (see _utils)",
    ("omg/data/loaders.py", "_worker_pids_set"):
        "whether the iterator's worker pids are registered with torch's SIGCHLD handler, read and cleared as "
        "torch's own shutdown does (see _utils)",
    ("omg/data/loaders.py", "_workers"):
        "a DataLoader iterator's worker processes: torch offers no public handle on them, and stop_workers must "
        "signal each (see _utils)",
}


ATTRIBUTE_CALLS = ("getattr", "hasattr", "setattr", "delattr")  # an attribute named by a string


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


@functools.cache
def torch_private_names() -> frozenset[str]:
    """Every private name torch's sources define or read (``def _name``, ``x._name``), from their text."""
    spec = importlib.util.find_spec(TORCH)
    names: set[str] = set()
    for path in Path(spec.origin).parent.rglob("*.py"):
        for attribute, function in re.findall(r"\.(_[A-Za-z0-9]\w*)|\bdef (_[A-Za-z0-9]\w*)",
                                              path.read_text(encoding="utf-8", errors="replace")):
            names.add(attribute or function)
    return frozenset(names)


@functools.cache
def omg_private_names(root: Path = PACKAGE) -> frozenset[str]:
    """The private names omg defines itself: its functions, classes, variables and ``self`` attributes."""
    names: set[str] = set()
    for path in root.rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
                names.add(node.name)
            elif isinstance(node, ast.Name) and isinstance(node.ctx, ast.Store):
                names.add(node.id)
            elif isinstance(node, ast.Attribute) and isinstance(node.ctx, ast.Store) and _on_self(node.value):
                names.add(node.attr)
    return frozenset(name for name in names if _is_private(name))


def _from_library(module: str | None) -> bool:
    return bool(module) and module.split(".")[0] in (*LIBRARIES, TORCH)


def _bound_modules(tree: ast.AST) -> dict[str, str]:
    """Each name an import binds in the file (at any depth) -> the module it comes from."""
    bound = {}
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            bound.update({(a.asname or a.name.split(".")[0]): (a.name if a.asname else a.name.split(".")[0])
                          for a in node.names})
        elif isinstance(node, ast.ImportFrom) and node.module and not node.level:
            bound.update({(a.asname or a.name): node.module for a in node.names})
    return bound


def _root(node: ast.expr) -> str | None:
    """The name an attribute chain starts from (``torch`` of ``torch.utils._pytree``), if a name."""
    while isinstance(node, ast.Attribute):
        node = node.value
    return node.id if isinstance(node, ast.Name) else None


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
    bound = _bound_modules(tree)

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
                attribute(child.value, child.attr, child.lineno, ast.unparse(child), bases)
            elif (isinstance(child, ast.Call) and getattr(child.func, "id", None) in ATTRIBUTE_CALLS
                  and len(child.args) > 1 and isinstance(child.args[1], ast.Constant)
                  and isinstance(child.args[1].value, str) and _is_private(child.args[1].value)):
                attribute(child.args[0], child.args[1].value, child.lineno, ast.unparse(child), bases)
            visit(child, inner)

    def attribute(owner: ast.expr, name: str, line: int, text: str, bases: list[type]) -> None:
        """``owner.name`` (or ``getattr(owner, "name")``), ``name`` private."""
        root = _root(owner)
        if _on_self(owner):
            own = set().union(*(class_private_names(k) for k in bases)) if bases else set()
            if name in own:
                found.append((line, name, f"{text} (of a library base class)"))
        elif name in library_private_names():
            found.append((line, name, text))
        elif root in bound:  # read from an imported module or a name imported from one
            if bound[root].split(".")[0] == TORCH:
                found.append((line, name, f"{text} (read from {bound[root]})"))
        elif name in torch_private_names() and name not in omg_private_names():
            found.append((line, name, f"{text} (a private attribute of torch's)"))

    visit(tree, [])
    return found


def test_the_scan_finds_torchs_private_names(tmp_path, monkeypatch):
    """The scan covers torch: private modules imported, private names read from torch's modules and
    objects, nn.Module's private methods overridden; omg's own private names and another library's
    (``os._exit``) are not torch's."""
    (tmp_path / "torch_probe.py").write_text(textwrap.dedent("""
        import os
        import torch
        import torch._C
        import torch.nn.functional as F
        from torch import nn
        from torch.utils import _pytree
        from torch.utils.data._utils import signal_handling

        class Net(nn.Module):
            def _apply(self, fn, recurse=True):
                return super()._apply(fn, recurse)

            def own(self):
                self._helper = 1
                return self._modules, self._helper

        def probe(loader_iter, tensor):
            torch._dynamo.reset()
            F._canonical_mask
            signal_handling._remove_worker_pids(1)
            getattr(loader_iter, "_workers", [])
            loader_iter._worker_pids_set = False
            tensor._own_probe_value
            os._exit(0)
    """))
    monkeypatch.syspath_prepend(str(tmp_path))
    found = private_uses(tmp_path / "torch_probe.py", tmp_path)
    assert {name for _, name, _ in found} == {"_C", "_pytree", "_utils", "_apply", "_modules", "_dynamo",
                                             "_canonical_mask", "_remove_worker_pids", "_workers",
                                             "_worker_pids_set"}
    assert (11, "_apply", "overrides Net._apply") in found


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


@pytest.fixture(scope="session")
def omg_uses() -> dict[str, list[tuple[int, str, str]]]:
    """private_uses of each of omg's files, by its path in the repository (scanned once)."""
    return {str(path.relative_to(REPO)): private_uses(path) for path in sorted(PACKAGE.rglob("*.py"))}


def test_omg_uses_no_private_jsonargparse_lightning_or_torch_attribute(omg_uses):
    uses = [f"{where}:{line}: {what}" for where, found in omg_uses.items() for line, name, what in found
            if (where, name) not in ALLOWED]
    assert not uses, ("private jsonargparse/Lightning/torch attributes (use a public API, or add an entry to ALLOWED "
                      "with the reason none exists):\n" + "\n".join(uses))


def test_every_allowed_hook_is_still_used(omg_uses):
    used = {(where, name) for where, found in omg_uses.items() for _, name, _ in found}
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
