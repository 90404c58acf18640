"""The ``omg`` tool commands, each a typed function exposed through jsonargparse.

``generate``, ``bench``, ``convert`` (``omg convert-ckpt``), ``shards`` and ``export``; ``lightning``
the LightningCLI of ``omg fit|validate|test|predict``; ``args``
is the argument system they share with ``omg fit`` (parsers made from function signatures,
errors as one line), ``common`` their output-folder and text-file helpers. This package sits
above the library (data, models, Lightning modules) and below ``omg.cli``, which dispatches to
each module's ``main(argv)``; nothing is imported here, so that ``omg --help`` and the
benchmark's worker processes stay fast.
"""
