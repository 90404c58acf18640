"""Generation: motion from a trained checkpoint of any family, the floor between training and tools.

- ``protocol.py``: what a generation is (``GenerationCard``, ``GenerationRequest``, ``GeneratedMotion``) and
  the ``Generator`` every family's adapter implements; ``check_request`` and ``parse_options`` check a
  request against the card before anything is sampled.
- ``registry.py``: the adapter of a module, found by its class (``generator_for``); a plugin family
  registers its own (``register_generator``).
- ``omg.py``, ``omgpt.py``, ``habit.py``: the families' adapters (the card, reading the source motion,
  generating, what ``generation.json`` records).
- ``read.py``: the one reader of a user's source motion; ``write.py``: the one writer of generated motion.

The LightningModules hold training and the tensor-level sampler their evaluation callbacks call
(``omg.lit.sampling.Sampler``); everything that reads a user's file, makes a request or writes one is here.
"""
