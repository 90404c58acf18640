"""The ``synth`` source: procedural labeled motion from ``omg.data.synth``."""

from __future__ import annotations

from typing import Iterator

from omg.errors import UsageError
from omg.motion import Clip
from omg.registry import DATA_SOURCES
from omg.skeleton import Skeleton


@DATA_SOURCES.register("synth")
def synth_source(input: str | None, skeleton: Skeleton, fps: float, num_clips: int = 100,
                 seed: int = 0) -> Iterator[Clip]:
    """Procedural humans (smpl22) or quadrupeds (smal35) with template captions, deterministic by seed."""
    from omg.data.synth import synth_clips

    if skeleton.name == "smpl22":
        return synth_clips(num_human=num_clips, num_animal=0, seed=seed, fps=fps)
    if skeleton.name == "smal35":
        return synth_clips(num_human=0, num_animal=num_clips, seed=seed, fps=fps)
    raise UsageError(f"the synth source makes smpl22 humans and smal35 quadrupeds, not {skeleton.name!r}")
