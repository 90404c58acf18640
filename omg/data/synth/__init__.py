"""Procedural labelled motion: the embedded mini dataset (humans on smpl22, quadrupeds on smal35).

A clip is built the way an animator keys it: a root path on the floor, a footfall schedule
(stance: the foot tip is planted at a fixed world point; swing: an arc to the next footprint),
body channels (lean, sway, arm swing, spine flex, tail) and analytic two-bone IK that puts each
leg of this individual on its target. Positions are the forward kinematics of the rotations, so
bone lengths are constant and labelled contacts are exact by construction. Everything is
vectorised over frames; one ``numpy.random.Generator`` seeded by (seed, kind, index) drives
each clip, so a clip depends only on its own index.

Modules, from the bottom up: ``curves`` (easing curves), ``rig`` (rotation helpers, rest pose),
``timeline`` (time grid, root path), ``gait`` (footfalls, foot targets, leg IK), ``captions``
(wording), ``human`` and ``animal`` (one function per action, and the species table).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator

import numpy as np
import torch

from omg.data.synth.animal import (
    ANIMAL_ACTION_FUNCTIONS,
    ANIMAL_ACTIONS,
    ANIMALS,
    Animal,
    GaitHabit,
    GaitHabits,
    make_animal_clip,
)
from omg.data.synth.gait import GRAVITY, Gait
from omg.data.synth.human import HUMAN_ACTION_FUNCTIONS, HUMAN_ACTIONS, STYLES, Style, make_human_clip
from omg.errors import UsageError
from omg.motion.base import Clip

__all__ = [
    "ANIMALS", "ANIMAL_ACTIONS", "ANIMAL_ACTION_FUNCTIONS", "GRAVITY", "HUMAN_ACTIONS", "HUMAN_ACTION_FUNCTIONS",
    "STYLES", "Animal", "Gait", "GaitHabit", "GaitHabits", "Style", "synth_clip", "synth_clips",
]  # fmt: skip

# kind -> (the kind's code in the random seed, clip maker)
_KINDS: dict[str, tuple[int, Callable]] = {"human": (0, make_human_clip), "animal": (1, make_animal_clip)}


def synth_clip(kind: str, index: int, seed: int = 0, fps: float = 30.0) -> tuple[Clip, np.ndarray]:
    """Clip ``index`` of a kind ("human" or "animal") and its foot contacts (T, len(skeleton.feet)) bool.

    Actions cycle with the index (animals: categories cycle fastest), so small sets cover them all;
    everything else is drawn from a generator seeded by (seed, kind, index).
    """
    if kind not in _KINDS:
        raise UsageError(f"synth kind must be 'human' or 'animal', got {kind!r}")
    code, make = _KINDS[kind]
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # the tensors here are small: worker threads only add synchronisation
    try:
        return make(np.random.default_rng([seed, code, index]), index, fps)
    finally:
        torch.set_num_threads(threads)


def synth_clips(num_human: int, num_animal: int, seed: int = 0, fps: float = 30.0) -> Iterator[Clip]:
    """``num_human`` smpl22 clips, then ``num_animal`` smal35 clips, deterministic by seed."""
    for kind, count in (("human", num_human), ("animal", num_animal)):
        for index in range(count):
            yield synth_clip(kind, index, seed, fps)[0]
