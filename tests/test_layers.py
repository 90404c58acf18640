"""The package's dependencies point one way: every import, lazy ones included, goes to the
importing module's own layer or a lower one (the layer order of the README's layout section)."""

from __future__ import annotations

import ast
from pathlib import Path

import omg

PACKAGE = Path(omg.__file__).parent

# lowest first; a module belongs to the layer of its longest matching prefix
LAYERS: list[tuple[str, tuple[str, ...]]] = [
    ("foundation", ("omg", "omg.errors", "omg.files", "omg.rotations", "omg.skeleton", "omg.kinematics",
                    "omg.registry")),
    ("formats", ("omg.motion", "omg.text", "omg.io", "omg.retarget", "omg.joint_maps")),
    ("data", ("omg.data",)),
    ("models", ("omg.models", "omg.diffusion", "omg.samplers", "omg.losses", "omg.metrics")),
    ("training", ("omg.lit", "omg.callbacks", "omg.evaluation")),
    ("tools", ("omg.tools",)),
    ("cli", ("omg.cli",)),
]


def layer_of(module: str) -> int:
    best, level = "", None
    for index, (_, prefixes) in enumerate(LAYERS):
        for prefix in prefixes:
            # the bare package name holds only omg/__init__.py, not everything below it
            inside = module == prefix or (prefix != "omg" and module.startswith(prefix + "."))
            if inside and len(prefix) > len(best):
                best, level = prefix, index
    assert level is not None, f"{module} is in no layer: add it to LAYERS and to the README's layout section"
    return level


def module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def imports(source: str, name: str, is_package: bool = False) -> list[tuple[str, int]]:
    """(imported omg module, line) of every import statement in module ``name``'s source, at any
    depth, and of every ``importlib.import_module("omg...")`` with a literal name."""
    package = name if is_package else name.rpartition(".")[0]
    found = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            found += [(alias.name, node.lineno) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")[: len(package.split(".")) - (node.level - 1)]
                base = ".".join([*anchor, *([node.module] if node.module else [])])
            found.append((base, node.lineno))
        elif (isinstance(node, ast.Call) and getattr(node.func, "attr", None) == "import_module" and node.args
              and isinstance(node.args[0], ast.Constant) and isinstance(node.args[0].value, str)):
            found.append((node.args[0].value, node.lineno))
    return [(module, line) for module, line in found if module == "omg" or module.startswith("omg.")]


def test_every_module_is_in_a_layer():
    for path in PACKAGE.rglob("*.py"):
        layer_of(module_name(path))


def test_no_import_points_upward():
    upward = []
    for path in sorted(PACKAGE.rglob("*.py")):
        importer = module_name(path)
        for imported, line in imports(path.read_text(), importer, path.name == "__init__.py"):
            if layer_of(imported) > layer_of(importer):
                upward.append(f"{path.relative_to(PACKAGE.parent)}:{line} {importer} ({LAYERS[layer_of(importer)][0]}) "
                              f"imports {imported} ({LAYERS[layer_of(imported)][0]})")
    assert not upward, "upward imports:\n" + "\n".join(upward)


def test_the_checker_sees_lazy_relative_and_dynamic_imports():
    source = ("from . import windows\n"
              "def f():\n    from ..lit import base\n    import importlib\n    importlib.import_module('omg.cli')\n")
    found = [m for m, _ in imports(source, "omg.data.probe")]
    assert found == ["omg.data", "omg.lit", "omg.cli"]
    assert [layer_of(m) > layer_of("omg.data.probe") for m in found] == [False, True, True]
    assert layer_of("omg") == 0 and layer_of("omg.tools.generate") == 5 and layer_of("omg.data.synth.human") == 2


def test_readme_states_the_same_layer_order():
    readme = (PACKAGE.parent / "README.md").read_text()
    positions = [readme.find(f"**{name}**") for name, _ in LAYERS]
    assert all(p >= 0 for p in positions), "the README's layout section names every layer in bold"
    assert positions == sorted(positions), "the README lists the layers in this order"
