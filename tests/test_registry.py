"""Registries: registration, lookup errors that name names and places, builtins, and entry-point plugins."""

from __future__ import annotations

import sys
import textwrap
from types import SimpleNamespace

import pytest

import omg.registry as registry
from helpers import scratch_registries
from omg.errors import UsageError
from omg.registry import ALL, Registry, RegistryError, load_plugins, resolve


def where(obj) -> str:
    return f"{obj.__module__}.{obj.__qualname__}"


# ---------------------------------------------------------------------------------------------
# a fresh registry


def test_register_by_decorator_with_and_without_name():
    widgets = Registry("widget")

    @widgets.register("round")
    class Round:
        def __init__(self, size=1):
            self.size = size

    @widgets.register()
    class Square:
        pass

    @widgets.register()
    def make_triangle(sides=3):
        return ("triangle", sides)

    assert widgets.names() == ["Square", "make_triangle", "round"]
    assert list(widgets) == widgets.names()
    assert widgets.get("round") is Round and widgets.get("Square") is Square
    assert "round" in widgets and "Round" not in widgets and "hexagon" not in widgets
    built = widgets.build("round", size=4)
    assert isinstance(built, Round) and built.size == 4
    assert widgets.build("make_triangle", 5) == ("triangle", 5)


def test_register_uses_a_name_attribute_and_plain_calls():
    widgets = Registry("widget")

    @widgets.register()
    class Gear:
        name = "gear"

    instance = object()
    assert widgets.register("thing", instance) is instance
    assert widgets.names() == ["gear", "thing"]
    assert widgets.get("thing") is instance


def test_describe_is_the_first_docstring_line():
    widgets = Registry("widget")

    @widgets.register("doc")
    class Documented:
        """One line.

        More text."""

    @widgets.register("nodoc")
    def undocumented():
        pass

    assert widgets.describe("doc") == "One line."
    assert widgets.describe("nodoc") == where(undocumented)


def test_duplicate_name_names_both_places():
    widgets = Registry("widget")

    @widgets.register("cog")
    class FirstCog:
        pass

    class SecondCog:
        pass

    with pytest.raises(RegistryError) as e:
        widgets.register("cog", SecondCog)
    message = str(e.value)
    assert "duplicate widget name 'cog'" in message
    assert where(FirstCog) in message and where(SecondCog) in message
    assert "test_registry.test_duplicate_name_names_both_places.<locals>.FirstCog" in message
    assert widgets.get("cog") is FirstCog  # the first one stays


def test_duplicate_instances_are_named_by_their_type():
    widgets = Registry("widget")
    widgets.register("x", SimpleNamespace())
    with pytest.raises(RegistryError, match=r"types\.SimpleNamespace instance"):
        widgets.register("x", SimpleNamespace())


def test_registering_the_same_object_twice_is_fine():
    widgets = Registry("widget")

    class Bolt:
        pass

    widgets.register("bolt", Bolt)
    widgets.register("bolt", Bolt)
    widgets.register("bolt")(Bolt)
    assert widgets.names() == ["bolt"]


def test_unknown_name_lists_the_known_names():
    widgets = Registry("widget")
    widgets.register("beta", object())
    widgets.register("alpha", object())
    with pytest.raises(RegistryError) as e:
        widgets.get("gamma")
    assert str(e.value) == "unknown widget 'gamma'; known widgets: alpha, beta"  # plain, not KeyError-quoted
    with pytest.raises(RegistryError, match="known widgets: alpha, beta"):
        widgets.build("gamma")
    with pytest.raises(RegistryError, match="known gadgets: none"):
        Registry("gadget").get("anything")


def test_registry_error_is_a_usage_error():
    assert issubclass(RegistryError, UsageError)
    assert issubclass(RegistryError, ValueError) and issubclass(RegistryError, KeyError)  # old except clauses work


def test_cli_turns_registry_error_into_exit_code_2(monkeypatch, capsys):
    from omg.cli import main

    def broken():
        raise RegistryError("unknown widget 'gamma'; known widgets: alpha")

    monkeypatch.setattr(registry, "load_plugins", broken)
    with pytest.raises(SystemExit) as e:
        main(["plugins"])
    assert e.value.code == 2
    assert capsys.readouterr().err.strip() == "omg: error: unknown widget 'gamma'; known widgets: alpha"


def test_resolve():
    widgets = Registry("widget")
    thing = object()
    widgets.register("thing", thing)
    assert resolve(widgets, "thing") is thing
    other = object()
    assert resolve(widgets, other) is other
    with pytest.raises(RegistryError, match="unknown widget 'nope'"):
        resolve(widgets, "nope")


# ---------------------------------------------------------------------------------------------
# omg's own registries


def test_all_holds_the_seven_registries():
    # domain components only: Lightning objects (modules, callbacks) are named by class_path
    expected = ["skeletons", "representations", "text_encoders", "data_sources", "metrics", "samplers", "joint_maps"]
    assert list(ALL) == expected
    assert all(isinstance(r, Registry) for r in ALL.values())
    assert len({id(r) for r in ALL.values()}) == 7
    assert ALL["skeletons"] is registry.SKELETONS and ALL["joint_maps"] is registry.JOINT_MAPS
    # a data-file entry is described by its first comment line (`omg plugins`)
    assert registry.JOINT_MAPS.describe("bandai") == "Bandai-Namco Research Motion dataset BVH rig"
    for title in ALL:
        assert title.upper() in registry.__all__ and getattr(registry, title.upper()) is ALL[title]


@pytest.mark.parametrize(
    "title, name",
    [("skeletons", "smpl22"), ("skeletons", "smal35"), ("representations", "humanml3d263"),
     ("representations", "maa"), ("representations", "quatvel"), ("data_sources", "synth")],
)  # fmt: skip
def test_builtin_components_are_registered(title, name):
    reg = ALL[title]
    assert name in reg
    assert name in reg.names()
    assert reg.get(name) is not None
    assert reg.describe(name)


# ---------------------------------------------------------------------------------------------
# plugins through entry points


class FakeEntryPoint:
    def __init__(self, name: str, value: str, load):
        self.name, self.value, self.load = name, value, load


@pytest.fixture
def plugins(monkeypatch):
    """Install fake ``omg.plugins`` entry points; returns a function taking the list."""
    monkeypatch.setattr(registry, "_plugins_loaded", None)

    def install(*eps):
        def fake_entry_points(*, group):
            assert group == "omg.plugins"
            return list(eps)

        monkeypatch.setattr(registry, "entry_points", fake_entry_points)

    return install


def test_callable_plugin_is_called_once(plugins):
    calls = []
    plugins(FakeEntryPoint("counter", "pkg.mod:setup", lambda: lambda: calls.append(1)))
    assert load_plugins() == ["counter"]
    assert load_plugins() == ["counter"]
    assert calls == [1]


def test_class_plugins_are_not_instantiated(plugins):
    made = []

    class Component:
        def __init__(self):
            made.append(self)

    plugins(FakeEntryPoint("cls", "pkg.mod:Component", lambda: Component))
    assert load_plugins() == ["cls"]
    assert made == []


def test_module_plugin_is_imported_and_registers(plugins, tmp_path, monkeypatch):
    import importlib

    module = "omg_test_plugin_widgets"
    (tmp_path / f"{module}.py").write_text(textwrap.dedent("""
        from omg.registry import TEXT_ENCODERS

        @TEXT_ENCODERS.register("test-plugin-encoder")
        class PluginEncoder:
            '''A text encoder from a plugin.'''
    """))
    monkeypatch.syspath_prepend(str(tmp_path))
    scratch_registries(monkeypatch, registry.TEXT_ENCODERS)
    monkeypatch.delitem(sys.modules, module, raising=False)
    plugins(FakeEntryPoint("widgets", module, lambda: importlib.import_module(module)))

    assert "test-plugin-encoder" not in registry.TEXT_ENCODERS
    assert load_plugins() == ["widgets"]
    assert module in sys.modules
    assert registry.TEXT_ENCODERS.get("test-plugin-encoder").__name__ == "PluginEncoder"
    assert registry.TEXT_ENCODERS.describe("test-plugin-encoder") == "A text encoder from a plugin."
    monkeypatch.delitem(sys.modules, module)


def test_failing_plugin_is_a_usage_error_naming_it(plugins):
    def broken():
        raise ImportError("No module named 'omg_missing'")

    plugins(FakeEntryPoint("good", "pkg:ok", lambda: lambda: None), FakeEntryPoint("bad", "omg_missing:setup", broken))
    with pytest.raises(UsageError) as e:
        load_plugins()
    message = str(e.value)
    assert "'bad'" in message and "omg_missing:setup" in message and "No module named 'omg_missing'" in message
    assert registry._plugins_loaded is None  # a later call tries again


def test_plugin_whose_setup_fails_is_a_usage_error_naming_it(plugins):
    def setup():
        raise RuntimeError("boom")

    plugins(FakeEntryPoint("explodes", "pkg.mod:setup", lambda: setup))
    with pytest.raises(UsageError, match=r"omg plugin 'explodes' \(pkg.mod:setup\).*boom"):
        load_plugins()


def test_no_plugins_installed(plugins):
    plugins()
    assert load_plugins() == []


def test_a_plugin_text_encoder_takes_its_own_arguments_through_options(monkeypatch):
    """text_encoder_args is typed for omg's encoders; a plugin encoder's own keyword arguments travel in its
    ``options`` (as a checkpoint written before the typed groups kept them, at the top level, still loads),
    and an argument the chosen encoder does not take is one line naming it."""
    from omg.text import TextEncoderArgs, build_text_encoder, text_encoder_kwargs
    from omg.text.hashed import HashTextEncoder

    scratch_registries(monkeypatch, registry.TEXT_ENCODERS)

    @registry.TEXT_ENCODERS.register("test-wide-hash")
    class WideHash(HashTextEncoder):
        def __init__(self, width: int = 16, cache_size: int = 100):
            super().__init__(dim=width, cache_size=cache_size)

    typed = text_encoder_kwargs(TextEncoderArgs(options={"width": 8}, cache_size=5))
    earlier = text_encoder_kwargs({"width": 8, "cache_size": 5})  # a checkpoint's mapping from before
    assert typed == earlier == {"width": 8, "cache_size": 5}
    assert build_text_encoder("test-wide-hash", **typed).dim == 8
    with pytest.raises(UsageError, match=r"^text encoder 'test-wide-hash': got an unexpected keyword argument "
                                         r"'side_gain' \(model.init_args.text_encoder_args\)$"):
        build_text_encoder("test-wide-hash", **text_encoder_kwargs({"side_gain": 2.0}))
    with pytest.raises(UsageError, match=r"^text encoder 'hash': got an unexpected keyword argument 'width'"):
        build_text_encoder("hash", **typed)
