"""Motion clips and their feature representations (registered by name on import)."""

from omg.motion import humanml3d263, maa, quatvel  # noqa: F401  (registers the representations)
from omg.motion.base import Clip, Representation, length_mask
from omg.motion.spec import DataSpec
from omg.registry import REPRESENTATIONS

__all__ = ["Clip", "DataSpec", "Representation", "get_representation", "length_mask"]


def get_representation(name: str | Representation, skeleton) -> Representation:
    """A representation by registered name for ``skeleton``, or the instance itself."""
    if isinstance(name, Representation):
        return name
    return REPRESENTATIONS.build(name, skeleton)
