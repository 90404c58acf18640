"""Named registries of components, filled by decorators and by third-party plugins.

A component is registered under a short name (``smpl22``, ``humanml3d263``, ``minilm``) so
that configs can say ``skeleton: smpl22`` instead of a class path. Plugins are packages that
declare an entry point in the ``omg.plugins`` group; loading the entry point imports their
module, whose decorators register the components.
"""

from __future__ import annotations

import importlib
import inspect
from importlib.metadata import entry_points
from pathlib import PurePath
from typing import Any, Iterator, TypeVar

from omg.errors import UsageError

T = TypeVar("T")

PLUGIN_GROUP = "omg.plugins"


class RegistryError(UsageError, KeyError):
    """An unknown or duplicate name; the message says which names exist or where the twin lives."""

    def __str__(self) -> str:  # KeyError quotes its message; we want it plain
        return str(self.args[0])


def _where(obj: Any) -> str:
    try:
        return f"{obj.__module__}.{obj.__qualname__}"
    except AttributeError:
        return f"{type(obj).__module__}.{type(obj).__qualname__} instance"


def class_key(cls: type) -> str:
    """The key of a class in the registries keyed by class (``GENERATORS``, ``MODULE_SAMPLERS``): its class path."""
    return f"{cls.__module__}.{cls.__qualname__}"


class Registry:
    """Maps short names to components (classes, factories or instances) of one kind."""

    def __init__(self, kind: str, builtins: tuple[str, ...] = ()):
        self.kind = kind
        self.builtins = builtins  # modules whose import registers omg's own entries, imported on first lookup
        self._builtins_loaded = False
        self._entries: dict[str, Any] = {}

    def _load_builtins(self) -> None:
        if not self._builtins_loaded:
            self._builtins_loaded = True
            for module in self.builtins:
                importlib.import_module(module)

    def register(self, name: str | None = None, obj: Any = None) -> Any:
        """Register ``obj`` as ``name``; without ``obj``, return a decorator."""
        if obj is None:
            return lambda o: self.register(name, o)
        key = name or getattr(obj, "name", None) or obj.__name__
        if key in self._entries and self._entries[key] is not obj:
            raise RegistryError(
                f"duplicate {self.kind} name {key!r}: registered by {_where(self._entries[key])} "
                f"and again by {_where(obj)}; rename one of them"
            )
        self._entries[key] = obj
        return obj

    def get(self, name: str) -> Any:
        self._load_builtins()
        try:
            return self._entries[name]
        except KeyError:
            known = ", ".join(sorted(self._entries)) or "none"
            raise RegistryError(f"unknown {self.kind} {name!r}; known {self.kind}s: {known}") from None

    def build(self, name: str, *args: Any, **kwargs: Any) -> Any:
        """Instantiate (or call) the component registered as ``name``."""
        return self.get(name)(*args, **kwargs)

    def names(self) -> list[str]:
        self._load_builtins()
        return sorted(self._entries)

    def __contains__(self, name: str) -> bool:
        self._load_builtins()
        return name in self._entries

    def __iter__(self) -> Iterator[str]:
        return iter(self.names())

    def for_class(self, cls: type) -> Any | None:
        """The entry registered for the nearest class of ``cls``'s method resolution order, keyed by class path
        (``class_key``): a subclass takes its family's entry until it registers its own; None if there is none."""
        self._load_builtins()
        for base in cls.__mro__:
            if (key := class_key(base)) in self._entries:
                return self._entries[key]
        return None

    def describe(self, name: str) -> str:
        obj = self.get(name)
        if isinstance(obj, PurePath):  # a data file (joint maps): its first comment line, or its path
            from omg.files import read_text

            try:
                first = read_text(obj, "joint map").splitlines()[0]
            except (UsageError, IndexError):
                first = ""
            return first.lstrip("# ").strip() if first.startswith("#") else str(obj)
        doc = inspect.getdoc(obj) or ""
        return doc.splitlines()[0] if doc else _where(obj)


# Each registry imports its built-in modules lazily, on its first lookup, so that
# `import omg.registry` stays cheap and free of cycles and a skeleton lookup does not
# import torchmetrics.
SKELETONS = Registry("skeleton", ("omg.skeleton",))
REPRESENTATIONS = Registry("representation", ("omg.motion",))
TEXT_ENCODERS = Registry("text encoder", ("omg.text", "omg.text.bge"))
DATA_SOURCES = Registry("data source", ("omg.data.sources",))
METRICS = Registry("metric", ("omg.metrics",))
SAMPLERS = Registry("sampler", ("omg.samplers",))
JOINT_MAPS = Registry("joint map", ("omg.joint_maps",))  # YAML paths or omg.retarget.JointMap objects
# a LightningModule's class path -> the adapter that generates with it (omg.generation.registry); keyed by
# class path as Lightning objects are named, so not among ALL's domain components
GENERATORS = Registry("generator", ("omg.generation.omg", "omg.generation.omgpt", "omg.generation.habit"))
# a LightningModule's class path -> the tensor-level sampler made of it where the module is not one itself
# (omg.lit.sampling.sampler_of): OmniMotionGPT's, which composes the module with its human source
MODULE_SAMPLERS = Registry("module sampler", ("omg.lit.human_source",))

ALL: dict[str, Registry] = {
    "skeletons": SKELETONS,
    "representations": REPRESENTATIONS,
    "text_encoders": TEXT_ENCODERS,
    "data_sources": DATA_SOURCES,
    "metrics": METRICS,
    "samplers": SAMPLERS,
    "joint_maps": JOINT_MAPS,
}

_plugins_loaded: list[str] | None = None


def load_plugins() -> list[str]:
    """Import every ``omg.plugins`` entry point once; return their names.

    An entry point may name a module (importing it registers its components) or a
    callable taking no arguments (called once). A plugin that fails to import is an error
    naming the plugin, not a silent omission.
    """
    global _plugins_loaded
    if _plugins_loaded is not None:
        return _plugins_loaded
    loaded = []
    for ep in entry_points(group=PLUGIN_GROUP):
        try:
            target = ep.load()
            if callable(target) and not inspect.isclass(target) and not inspect.ismodule(target):
                target()
        except Exception as e:  # noqa: BLE001 - re-raised with the plugin's name
            raise UsageError(f"omg plugin {ep.name!r} ({ep.value}) failed to load: {e}") from e
        loaded.append(ep.name)
    _plugins_loaded = loaded
    return loaded


def resolve(registry: Registry, spec: str | T) -> T | Any:
    """A registered name becomes its component; anything else is returned as is."""
    return registry.get(spec) if isinstance(spec, str) else spec


__all__ = ["Registry", "RegistryError", "ALL", "load_plugins", "resolve", "PLUGIN_GROUP"] + [
    name.upper() for name in ALL
]

