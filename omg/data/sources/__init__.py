"""Data sources: registered callables that yield ``Clip``s (or an exception per bad item).

A source is called as ``source(input=..., skeleton=..., fps=..., **options)``; ``input`` is a
path for importers and None for generators. Importing this package registers the built-ins.
A source may return ``omg.data.shards.SourceItems`` instead of a bare iterator, to pass
set-level facts along (a dataset's published mean/std).
"""

from omg.data.sources import aistpp, amass, animalml3d, bvh_dir, humanml3d, motionx, synth  # noqa: F401
