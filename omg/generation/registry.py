"""Which adapter generates with a trained module: one registry keyed by module class.

Each family registers its adapter (``omg.generation.protocol.Generator``) under the class path of
its LightningModule (``omg.registry.GENERATORS``); a module is served by the adapter of the nearest
class in its method resolution order, so a subclass generates like its family until it registers
its own. A plugin family registers the same way::

    from omg.generation.registry import register_generator

    @register_generator(MyDiffusionModule)
    class MyGenerator(ModuleGenerator): ...
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

from omg.errors import UsageError
from omg.generation.protocol import Generator
from omg.registry import GENERATORS, class_key

module_key = class_key  # the registry key of a module class: its class path


def register_generator(module_class: type | str) -> Callable[[type], type]:
    """A decorator registering an adapter class for ``module_class`` (a class or its class path) and its
    subclasses."""
    key = module_class if isinstance(module_class, str) else module_key(module_class)
    return lambda adapter: GENERATORS.register(key, adapter)


def generator_for(module: Any, what: str | Path = "this checkpoint") -> Generator:
    """``module``'s family adapter, or one line saying that what ``what`` holds generates no motion."""
    if (adapter := GENERATORS.for_class(type(module))) is not None:
        return adapter(module)
    raise UsageError(f"{what} holds a {module_key(type(module))} checkpoint, which generates no motion")
