"""Data sources: registered callables that yield ``Clip``s (or an exception per bad item).

A source is called as ``source(input=..., skeleton=..., fps=..., **options)``; ``input`` is a
path for importers and None for generators. Importing this package registers the built-ins.
"""

from omg.data.sources import synth  # noqa: F401
