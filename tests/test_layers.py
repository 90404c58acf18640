"""The package's dependencies point one way: every import, lazy ones included, goes to the
importing module's own layer or a lower one (the layer order of docs/architecture.md's layout section).

What counts as an import: every import statement at any depth (``from omg import X`` and relative
imports read as the submodule X where X is one), ``importlib.import_module`` with a literal name,
and the module names omg keeps as data and imports by name (the CLI's command table, the checkpoint
reader's safe globals, the registries' built-in lists). Any other ``import_module`` is an error
unless ``DYNAMIC`` below allows it with its reason.

A registry (``omg.registry.METRICS``) imports its built-in modules on its first lookup, on behalf
of the module that looks a name up: its list is read as imports of every module that imports that
registry (``from omg.registry import METRICS`` imports omg.metrics; ``ALL`` imports every list),
not of omg.registry, which only holds the names. omg.registry is foundation so that any layer can
register into it (the plugin API); a lookup is a dependency of its caller on the registry's
built-ins, and that is where this test checks it.

The packages (``omg.lit``, ``omg.callbacks``, ...) form no cycle, nor do the modules inside one
(an import of ``omg.a.b.c`` runs ``omg/a/b/__init__.py`` first: ``module_edges``); every ``class_path`` of a config
under configs/ imports and its registry names exist; and docs/architecture.md's layout lists every module and
package of omg/ under its layer."""

from __future__ import annotations

import ast
import functools
import importlib
import re
from pathlib import Path

import pytest
import yaml

import omg

PACKAGE = Path(omg.__file__).parent
ROOT = PACKAGE.parent
ARCHITECTURE = ROOT / "docs" / "architecture.md"  # its Layout section lists every module under its layer

# lowest first; a module belongs to the layer of its longest matching prefix
LAYERS: list[tuple[str, tuple[str, ...]]] = [
    ("foundation", ("omg", "omg.errors", "omg.files", "omg.rotations", "omg.skeleton", "omg.kinematics",
                    "omg.registry", "omg.settings")),
    ("formats", ("omg.motion", "omg.text", "omg.io", "omg.retarget", "omg.rig_structure", "omg.export",
                 "omg.joint_maps")),
    ("data", ("omg.data",)),
    ("models", ("omg.models", "omg.diffusion", "omg.samplers", "omg.losses", "omg.metrics")),
    ("training", ("omg.lit", "omg.callbacks", "omg.evaluation")),
    ("generation", ("omg.generation",)),
    ("tools", ("omg.tools",)),
    ("cli", ("omg.cli", "omg.__main__")),
]

# (module, function) -> why its import_module with a computed name is allowed; where the names are
# omg's own data, DATA_TABLES reads them and they are checked as that module's imports
DYNAMIC: dict[tuple[str, str], str] = {
    ("omg.registry", "Registry._load_builtins"):
        "a registry's built-in modules, imported on its first lookup: each Registry(kind, (modules...)) list "
        "is read as imports of the modules that import that registry (REGISTRIES)",
    ("omg.cli", "_run"): "the command table: COMMANDS' module:function entries are omg.cli's imports (DATA_TABLES)",
    ("omg.lit.checkpoint", "_globals"):
        "the classes a weights-only checkpoint read allows: the *_SAFE_GLOBALS tuples are its imports (DATA_TABLES)",
    ("omg.lit.checkpoint", "resolve_class"):
        "a checkpoint's recorded LightningModule class: it imports only omg.lit.* (its own layer), else "
        "modules already imported",
    ("omg.tools.bench.gpu", "_print_config"): "the commands the GPU check resolves in its dry run: _TOOLS' "
                                              "module:function entries are its imports (DATA_TABLES)",
    ("omg.evaluation", "build_evaluator"):
        "a config's evaluator class_path, user input: configs/ are checked by test_every_config_class_path_imports",
    ("omg.tools.lightning", "OmgLightningCLI.check_ckpt_class"):
        "the config's model class_path, which jsonargparse imported already (user input; configs/ are checked "
        "by test_every_config_class_path_imports)",
}


def layer_of(module: str) -> int:
    best, level = "", None
    for index, (_, prefixes) in enumerate(LAYERS):
        for prefix in prefixes:
            # the bare package name holds only omg/__init__.py, not everything below it
            inside = module == prefix or (prefix != "omg" and module.startswith(prefix + "."))
            if inside and len(prefix) > len(best):
                best, level = prefix, index
    assert level is not None, f"{module} is in no layer: add it to LAYERS and to docs/architecture.md's layout section"
    return level


def module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def is_module(name: str) -> bool:
    """Whether the omg module or package ``name`` exists in the tree."""
    path = PACKAGE.parent.joinpath(*name.split("."))
    return path.with_suffix(".py").is_file() or (path / "__init__.py").is_file()


def _scopes(tree: ast.AST) -> dict[ast.AST, str]:
    """Each node's enclosing function or class, dotted (``Class.method``; '' at module level)."""
    scope: dict[ast.AST, str] = {}

    def visit(node: ast.AST, name: str) -> None:
        for child in ast.iter_child_nodes(node):
            inner = name
            if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
                inner = f"{name}.{child.name}" if name else child.name
            scope[child] = inner
            visit(child, inner)

    visit(tree, "")
    return scope


def _strings(node: ast.AST) -> list[str]:
    return [n.value for n in ast.walk(node) if isinstance(n, ast.Constant) and isinstance(n.value, str)]


def registries(source: str) -> dict[str, list[str]]:
    """Registry name -> its built-in modules, of every ``NAME = Registry(kind, (module, ...))`` in
    ``source``; ``ALL`` (the dict of every registry) -> all of them."""
    found: dict[str, list[str]] = {}
    for node in ast.walk(ast.parse(source)):
        if (isinstance(node, ast.Assign) and isinstance(node.value, ast.Call)
                and getattr(node.value.func, "id", None) == "Registry"):
            modules = _strings(node.value.args[1]) if len(node.value.args) > 1 else []
            found.update({target.id: modules for target in node.targets if isinstance(target, ast.Name)})
    found["ALL"] = [module for modules in found.values() for module in modules]
    return found


REGISTRIES = registries((PACKAGE / "registry.py").read_text())


def _command_table(tree: ast.AST) -> list[tuple[str, int]]:
    """The modules of ``COMMANDS = {name: ("module:function", description)}``."""
    return [(entry.elts[0].value.partition(":")[0], entry.lineno) for node in ast.walk(tree)
            if isinstance(node, ast.Assign) and any(getattr(t, "id", None) == "COMMANDS" for t in node.targets)
            for entry in node.value.values
            if isinstance(entry, ast.Tuple) and isinstance(entry.elts[0], ast.Constant)]


def _safe_globals(tree: ast.AST) -> list[tuple[str, int]]:
    """The modules of the classes in the ``*_SAFE_GLOBALS`` tuples."""
    return [(name.rpartition(".")[0], node.lineno) for node in ast.walk(tree)
            if isinstance(node, (ast.Assign, ast.AnnAssign))
            and any(getattr(t, "id", "").endswith("_SAFE_GLOBALS")
                    for t in (node.targets if isinstance(node, ast.Assign) else [node.target]))
            for name in _strings(node.value)]


def _entry_tables(*tables: str):
    """The modules of ``TABLE = {name: "module:attribute"}`` dicts, for each of ``tables``."""
    def read(tree: ast.AST) -> list[tuple[str, int]]:
        return [(value.value.partition(":")[0], value.lineno) for node in ast.walk(tree)
                if isinstance(node, ast.Assign) and any(getattr(t, "id", None) in tables for t in node.targets)
                and isinstance(node.value, ast.Dict) for value in node.value.values
                if isinstance(value, ast.Constant) and isinstance(value.value, str)]
    return read


# module -> reader of the module names it keeps as data and imports by name
DATA_TABLES = {"omg.cli": _command_table, "omg.lit.checkpoint": _safe_globals,
               "omg.tools.bench.gpu": _entry_tables("_TOOLS")}


def imports(source: str, name: str, is_package: bool = False,
            dynamic: list[tuple[str, int]] | None = None, lookups: bool = True) -> list[tuple[str, int]]:
    """(imported omg module, line) of every import statement in module ``name``'s source, at any
    depth, of every ``importlib.import_module("omg...")`` with a literal name and of the names
    ``DATA_TABLES`` reads. ``from P import X`` imports the module P.X where that is a module, else P;
    ``from omg.registry import R`` imports the built-in modules of registry R as well (``REGISTRIES``),
    unless ``lookups`` is false. Each ``import_module`` with a computed name is appended to ``dynamic``
    as (scope, line)."""
    found, computed = _imports(source, name, is_package, lookups)
    if dynamic is not None:
        dynamic.extend(computed)
    return list(found)


@functools.cache  # the tests below read every module's imports; each source is parsed once
def _imports(source: str, name: str, is_package: bool,
             lookups: bool) -> tuple[tuple[tuple[str, int], ...], tuple[tuple[str, int], ...]]:
    """``imports``: (the imports, the computed ``import_module`` calls as (scope, line))."""
    package = name if is_package else name.rpartition(".")[0]
    tree = ast.parse(source)
    scopes = _scopes(tree)
    found, dynamic = [], []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found += [(alias.name, node.lineno) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")[: len(package.split(".")) - (node.level - 1)]
                base = ".".join([*anchor, *([node.module] if node.module else [])])
            for alias in node.names:
                sub = f"{base}.{alias.name}"
                found.append((sub if is_module(sub) else base, node.lineno))
                if lookups and base == "omg.registry":
                    found += [(module, node.lineno) for module in REGISTRIES.get(alias.name, [])]
        elif isinstance(node, ast.Call) and getattr(node.func, "attr", None) == "import_module" and node.args:
            if isinstance(node.args[0], ast.Constant) and isinstance(node.args[0].value, str):
                found.append((node.args[0].value, node.lineno))
            else:
                dynamic.append((scopes.get(node, ""), node.lineno))
    if name in DATA_TABLES:
        found += DATA_TABLES[name](tree)
    return (tuple(dict.fromkeys((module, line) for module, line in found
                                if module == "omg" or module.startswith("omg."))), tuple(dynamic))


def all_imports() -> list[tuple[str, str, int, Path]]:
    """(importer, imported, line, path) over the package."""
    edges = []
    for path in sorted(PACKAGE.rglob("*.py")):
        importer = module_name(path)
        edges += [(importer, imported, line, path)
                  for imported, line in imports(path.read_text(), importer, path.name == "__init__.py")]
    return edges


def where(path: Path, line: int) -> str:
    return f"{path.relative_to(ROOT)}:{line}"


def test_every_module_is_in_a_layer():
    for path in PACKAGE.rglob("*.py"):
        layer_of(module_name(path))


def test_every_import_names_a_module():
    missing = [f"{where(path, line)} {importer} imports {imported}, which is no module of omg"
               for importer, imported, line, path in all_imports() if not is_module(imported)]
    assert not missing, "\n".join(missing)


def test_no_import_points_upward():
    upward = [f"{where(path, line)} {importer} ({LAYERS[layer_of(importer)][0]}) "
              f"imports {imported} ({LAYERS[layer_of(imported)][0]})"
              for importer, imported, line, path in all_imports() if layer_of(imported) > layer_of(importer)]
    assert not upward, "upward imports:\n" + "\n".join(upward)


def test_every_computed_import_is_allowed_with_its_reason():
    found, unknown = set(), []
    for path in sorted(PACKAGE.rglob("*.py")):
        dynamic: list[tuple[str, int]] = []
        module = module_name(path)
        imports(path.read_text(), module, path.name == "__init__.py", dynamic)
        for scope, line in dynamic:
            found.add((module, scope))
            if (module, scope) not in DYNAMIC:
                unknown.append(f"{where(path, line)} {module} ({scope or 'module level'}) imports a computed name: "
                               "import it by name, or keep the names as data that DATA_TABLES reads and add "
                               "(module, function) to DYNAMIC with the reason")
    assert not unknown, "\n".join(unknown)
    stale = sorted(set(DYNAMIC) - found)
    assert not stale, f"DYNAMIC allows computed imports that no longer exist: {stale}"


def package_of(module: str) -> str:
    return ".".join(module.split(".")[:2])


def cycles(edges: dict[tuple[str, str], list[str]]) -> list[list[str]]:
    """The strongly connected components of more than one node (Tarjan), each sorted."""
    graph: dict[str, set[str]] = {}
    for a, b in edges:
        graph.setdefault(a, set()).add(b)
        graph.setdefault(b, set())
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    out = []

    def connect(node: str) -> None:
        index[node] = low[node] = len(index)
        stack.append(node)
        for succ in sorted(graph[node]):
            if succ not in index:
                connect(succ)
                low[node] = min(low[node], low[succ])
            elif succ in stack:
                low[node] = min(low[node], index[succ])
        if low[node] == index[node]:
            component = []
            while True:
                top = stack.pop()
                component.append(top)
                if top == node:
                    break
            if len(component) > 1:
                out.append(sorted(component))

    for node in sorted(graph):
        if node not in index:
            connect(node)
    return out


def package_edges() -> dict[tuple[str, str], list[str]]:
    """(package, package) -> the imports that make that edge, between different packages."""
    edges: dict[tuple[str, str], list[str]] = {}
    for importer, imported, line, path in all_imports():
        a, b = package_of(importer), package_of(imported)
        if a != b:
            edges.setdefault((a, b), []).append(f"{where(path, line)} {importer} imports {imported}")
    return edges


def test_packages_form_no_cycle():
    edges = package_edges()
    found = cycles(edges)
    report = []
    for component in found:
        report.append(f"cycle among {', '.join(component)}:")
        report += [f"  {line}" for (a, b), lines in sorted(edges.items())
                   if a in component and b in component for line in lines]
    assert not found, "\n".join(report)


def module_edges(modules: list[tuple[str, str, str, bool]]) -> dict[tuple[str, str], list[str]]:
    """(module, module) -> the imports that make that edge, between two modules of one package
    (``package_of``: ``omg.tools.bench.gpu`` and ``omg.tools.generate`` are both ``omg.tools``), over
    ``modules``: (name, where it is, source, whether it is a package's ``__init__.py``).

    Every import statement at any depth counts (``imports``). Importing ``omg.a.b.c`` runs
    ``omg/a/b/__init__.py`` first, so it is an edge to each package above the imported module as
    well, except the packages above the importer (Python has loaded them, or is loading them, before
    the importer runs). A registry's built-in list is not read here: the registry imports it on a
    lookup, at call time, and each built-in module imports its registry to register into it
    (``test_no_import_points_upward`` checks those lookups against the layers)."""
    edges: dict[tuple[str, str], list[str]] = {}
    for name, location, source, is_package in modules:
        parts = name.split(".")
        loaded_first = {".".join(parts[:i]) for i in range(1, len(parts) + 1)}
        for imported, line in imports(source, name, is_package, lookups=False):
            pieces = imported.split(".")
            for target in [imported, *(".".join(pieces[:i]) for i in range(len(pieces) - 1, 0, -1))]:
                if target in loaded_first or package_of(target) != package_of(name):
                    continue
                via = "" if target == imported else f" (which runs {target}'s __init__.py first)"
                edges.setdefault((name, target), []).append(f"{location}:{line} {name} imports {imported}{via}")
    return edges


def shortest_cycle(edges: dict[tuple[str, str], list[str]], component: list[str]) -> list[str]:
    """A shortest import chain from the component's first module back to it, inside the component."""
    start, paths = component[0], {component[0]: [component[0]]}
    frontier = [start]
    while frontier:
        nxt = []
        for node in frontier:
            for a, b in sorted(edges):
                if a == node and b in component:
                    if b == start:
                        return [*paths[node], start]
                    if b not in paths:
                        paths[b] = [*paths[node], b]
                        nxt.append(b)
        frontier = nxt
    raise AssertionError(f"{component} is not a cycle")


def cycle_report(edges: dict[tuple[str, str], list[str]]) -> list[str]:
    """One block per cycle: the chain of modules, and the import lines that make each link."""
    report = []
    for component in cycles(edges):
        chain = shortest_cycle(edges, component)
        report.append(f"import cycle {' -> '.join(chain)} (among {', '.join(component)}):")
        report += [f"  {line}" for a, b in zip(chain, chain[1:]) for line in edges[a, b]]
    return report


def test_modules_of_a_package_form_no_cycle():
    modules = [(module_name(path), str(path.relative_to(ROOT)), path.read_text(), path.name == "__init__.py")
               for path in sorted(PACKAGE.rglob("*.py"))]
    report = cycle_report(module_edges(modules))
    assert not report, ("modules that import each other (move what both need into a module that neither "
                        "imports, or one of them into the other's package):\n" + "\n".join(report))


def test_the_cycle_check_sees_function_level_imports_and_packages_run_first():
    # omg bench as one module: bench.py imports gpu.py for its subcommand, gpu.py the device peaks from bench.py
    old = [("omg.tools.bench", "bench.py", "from omg.tools.gpu import bench_gpu\n", False),
           ("omg.tools.gpu", "gpu.py", "def bench_gpu():\n    from omg.tools.bench import PEAK_TFLOPS\n", False)]
    assert cycle_report(module_edges(old)) == [
        "import cycle omg.tools.bench -> omg.tools.gpu -> omg.tools.bench (among omg.tools.bench, omg.tools.gpu):",
        "  bench.py:1 omg.tools.bench imports omg.tools.gpu", "  gpu.py:2 omg.tools.gpu imports omg.tools.bench"]
    # gpu.py left outside the bench package, reading its device module: that import runs bench/__init__.py
    outside = [("omg.tools.bench", "bench/__init__.py", "from omg.tools.gpu import bench_gpu\n", True),
               ("omg.tools.bench.device", "bench/device.py", "import torch\n", False),
               ("omg.tools.gpu", "gpu.py", "from omg.tools.bench.device import device_peak_tflops\n", False)]
    assert cycles(module_edges(outside)) == [["omg.tools.bench", "omg.tools.gpu"]]
    # gpu.py inside the package: its own package is loaded before it runs, and __init__.py imports it
    inside = [("omg.tools.bench", "bench/__init__.py", "from omg.tools.bench import gpu\n", True),
              ("omg.tools.bench.gpu", "bench/gpu.py", "from omg.tools.bench.device import peak_memory\n", False),
              ("omg.tools.bench.device", "bench/device.py", "", False)]
    assert module_edges(inside).keys() == {("omg.tools.bench", "omg.tools.bench.gpu"),
                                           ("omg.tools.bench.gpu", "omg.tools.bench.device")}
    # a registry's built-in list is imported by the registry on a lookup, not by each module registering into it
    registering = [("omg.text", "text/__init__.py", "from omg.text import clip\n", True),
                   ("omg.text.clip", "text/clip.py", "from omg.registry import TEXT_ENCODERS\n", False)]
    assert cycles(module_edges(registering)) == []


def test_the_checker_sees_lazy_relative_and_dynamic_imports():
    source = ("from . import windows\n"
              "def f():\n    from ..lit import base\n    import importlib\n    importlib.import_module('omg.cli')\n"
              "    from omg import kinematics, __version__\n"
              "    importlib.import_module(name)\n")
    dynamic: list[tuple[str, int]] = []
    found = [m for m, _ in imports(source, "omg.data.probe", dynamic=dynamic)]
    assert found == ["omg.data.windows", "omg.lit.base", "omg.kinematics", "omg", "omg.cli"]
    assert dynamic == [("f", 7)]
    assert [layer_of(m) > layer_of("omg.data.probe") for m in found] == [False, True, False, False, True]
    assert layer_of("omg") == 0 and layer_of("omg.tools.generate") == 6 and layer_of("omg.data.synth.human") == 2
    # the names kept as data are imports of the module that keeps them
    table = 'COMMANDS = {"x": ("omg.tools.shards:main", "...")}\n'
    assert [m for m, _ in imports(table, "omg.cli")] == ["omg.tools.shards"]
    # a registry's built-in list is imported by the module that imports the registry
    assert registries('S = Registry("s", ("omg.data.sources",))\nT = Registry("t")\n') == {
        "S": ["omg.data.sources"], "T": [], "ALL": ["omg.data.sources"]}
    assert [m for m, _ in imports("from omg.registry import METRICS\n", "omg.skeleton")] == ["omg.registry",
                                                                                          "omg.metrics"]
    assert cycles({("a", "b"): [], ("b", "c"): [], ("c", "a"): [], ("c", "d"): []}) == [["a", "b", "c"]]


def test_the_data_tables_are_read():
    edges = {(importer, imported) for importer, imported, _, _ in all_imports()}
    assert ("omg.cli", "omg.tools.generate") in edges and ("omg.cli", "omg.tools.habit") in edges
    assert ("omg.callbacks.eval", "omg.metrics") in edges and ("omg.cli", "omg.data.sources") in edges
    assert REGISTRIES["DATA_SOURCES"] == ["omg.data.sources"] and "omg.samplers" in REGISTRIES["ALL"]


# -- configs -------------------------------------------------------------------------------

CONFIGS = sorted((ROOT / "configs").rglob("*.yaml"))
SHORT_NAMES = ("omg.lit", "omg.callbacks")  # the CLI imports these, so jsonargparse resolves their class names


def class_paths(node, key: str = "") -> list[tuple[str, str]]:
    """(class_path, the key it sits under) everywhere in a loaded YAML document."""
    if isinstance(node, dict):
        found = [(str(node["class_path"]), key)] if "class_path" in node else []
        for k, v in node.items():
            found += class_paths(v, str(k) if k != "init_args" else key)
        return found
    if isinstance(node, list):
        return [found for item in node for found in class_paths(item, key)]
    return []


# config keys whose string values are registry names (omg.registry), and the registry that resolves them
REGISTRY_KEYS = {"text_encoder": "TEXT_ENCODERS", "metrics": "METRICS", "sampler": "SAMPLERS",
                 "skeleton": "SKELETONS", "representation": "REPRESENTATIONS", "joint_map": "JOINT_MAPS"}


def registry_names(node) -> list[tuple[str, str]]:
    """(registry, name) of every registry name a loaded YAML document gives under ``REGISTRY_KEYS``
    (a list of metrics holds names or one-key mappings {name: options})."""
    found = []
    if isinstance(node, dict):
        for key, value in node.items():
            if key in REGISTRY_KEYS:
                values = value if isinstance(value, list) else [value]
                names = [next(iter(v)) if isinstance(v, dict) and len(v) == 1 else v for v in values]
                found += [(REGISTRY_KEYS[key], name) for name in names if isinstance(name, str)]
            else:
                found += registry_names(value)
    elif isinstance(node, list):
        found = [item for value in node for item in registry_names(value)]
    return found


def resolve(path: str) -> type:
    if "." not in path:
        for package in SHORT_NAMES:
            module = importlib.import_module(package)
            if path in getattr(module, "__all__", ()):
                return getattr(module, path)
        raise AssertionError(f"short class name {path} is not exported by {', '.join(SHORT_NAMES)}")
    module, _, name = path.rpartition(".")
    return getattr(importlib.import_module(module), name)


@pytest.mark.parametrize("config", CONFIGS, ids=lambda p: str(p.relative_to(ROOT / "configs")))
def test_every_config_class_path_imports(config):
    """A config is an importer that may name any layer's class, but each name must resolve to a
    public class; an evaluator (read by omg.evaluation) must be one that omg.evaluation may import;
    a registry name (``text_encoder: minilm``, ``metrics: [fid]``) must be one its registry holds."""
    problems = []
    for path, key in class_paths(yaml.safe_load(config.read_text())):
        try:
            cls = resolve(path)
        except (ImportError, AttributeError, AssertionError) as e:
            problems.append(f"{path}: does not resolve ({e})")
            continue
        if not isinstance(cls, type):
            problems.append(f"{path}: not a class")
        qualified = f"{cls.__module__}.{cls.__qualname__}"
        if any(part.startswith("_") for part in qualified.split(".")):
            problems.append(f"{path}: a private name ({qualified})")
        if key == "evaluator" and cls.__module__.startswith("omg") and layer_of(cls.__module__) > layer_of(
                "omg.evaluation"):
            problems.append(f"{path}: an evaluator from {cls.__module__}, above omg.evaluation's layer")
    registry = importlib.import_module("omg.registry")
    for name, short in registry_names(yaml.safe_load(config.read_text())):
        if short not in getattr(registry, name):
            known = ", ".join(getattr(registry, name).names())
            problems.append(f"{short}: not a name of omg.registry.{name} ({known})")
    assert not problems, f"{config.relative_to(ROOT)}:\n" + "\n".join(problems)


# -- docs/architecture.md ------------------------------------------------------------------

def architecture_layout() -> dict[str, list[str]]:
    """Layer name -> the top-level entries (``errors.py``, ``motion/``) its layout line lists,
    outside parentheses."""
    doc = ARCHITECTURE.read_text()
    section = doc.split("\n## Layout\n", 1)[1].split("\n## ", 1)[0]
    items = re.findall(r"^\d+\. \*\*(\w+)\*\*:(.*?)(?=^\d+\. |^\s*$)", section, re.S | re.M)
    layout = {}
    for name, text in items:
        while re.search(r"\([^()]*\)", text):
            text = re.sub(r"\([^()]*\)", "", text)
        layout[name] = re.findall(r"`([\w]+(?:\.py|/))`", text)
    return layout


def test_architecture_states_the_same_layer_order():
    doc = ARCHITECTURE.read_text()
    positions = [doc.find(f"**{name}**") for name, _ in LAYERS]
    assert all(p >= 0 for p in positions), "docs/architecture.md's layout section names every layer in bold"
    assert positions == sorted(positions), "docs/architecture.md lists the layers in this order"
    assert list(architecture_layout()) == [name for name, _ in LAYERS], "one numbered layout line per layer, in order"


def test_architecture_lists_every_module_under_its_layer():
    layout = architecture_layout()
    tree = {f"{p.stem}.py" for p in PACKAGE.glob("*.py") if p.name != "__init__.py"}
    tree |= {f"{p.name}/" for p in PACKAGE.iterdir() if (p / "__init__.py").is_file()}
    listed = {entry: layer for layer, entries in layout.items() for entry in entries}
    problems = [f"{entry} is in omg/ but not in docs/architecture.md's layout list"
                for entry in sorted(tree - set(listed))]
    problems += [f"{entry} is listed under {listed[entry]} but is not in omg/" for entry in sorted(set(listed) - tree)]
    for entry in sorted(tree & set(listed)):
        layer = LAYERS[layer_of(f"omg.{entry.removesuffix('.py').removesuffix('/')}")][0]
        if listed[entry] != layer:
            problems.append(f"{entry} is listed under {listed[entry]}, but its layer is {layer}")
    for _, prefixes in LAYERS:
        problems += [f"LAYERS names {prefix}, which is not in omg/" for prefix in prefixes if not is_module(prefix)]
    assert not problems, "\n".join(problems)
