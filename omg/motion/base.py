"""A clip of motion, and the interface every feature representation implements."""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np
import torch

from omg.errors import UsageError
from omg.skeleton import Skeleton, get_skeleton


@dataclass
class Clip:
    """One motion on one skeleton, as importers and the synthetic generator produce it.

    ``positions`` are always present. ``rotations`` and ``offsets`` are present when the
    source has them (BVH, synthetic data); representations that need rotations solve them
    by inverse kinematics otherwise. ``features`` are precomputed features of the
    representation named ``features_representation`` (a dataset's published files, e.g.
    HumanML3D's ``new_joint_vecs``); shards of that representation store them verbatim.
    """

    id: str
    skeleton: Skeleton
    fps: float
    positions: np.ndarray  # (T, J, 3) metres, +Y up
    rotations: np.ndarray | None = None  # (T, J, 4) local quaternions (w, x, y, z)
    offsets: np.ndarray | None = None  # (J, 3) this individual's bone offsets
    texts: list[str] = field(default_factory=list)
    labels: dict = field(default_factory=dict)
    category: str | None = None  # e.g. "human", "dog", "horse"
    source: str = ""
    features: np.ndarray | None = None  # (T', D) precomputed features, stored verbatim
    features_representation: str | None = None  # the representation ``features`` belong to

    def __post_init__(self):
        J = self.skeleton.num_joints
        if self.positions.ndim != 3 or self.positions.shape[1:] != (J, 3):
            raise ValueError(
                f"clip {self.id!r}: positions must be (T, {J}, 3) for skeleton "
                f"{self.skeleton.name!r}, got {tuple(self.positions.shape)}"
            )
        if self.rotations is not None and self.rotations.shape != (len(self), J, 4):
            raise ValueError(f"clip {self.id!r}: rotations must be ({len(self)}, {J}, 4), got {self.rotations.shape}")
        if (self.features is None) != (self.features_representation is None):
            raise ValueError(f"clip {self.id!r}: features and features_representation go together")
        if self.features is not None and self.features.ndim != 2:
            raise ValueError(f"clip {self.id!r}: features must be (T', D), got {self.features.shape}")

    def __len__(self) -> int:
        return self.positions.shape[0]

    @property
    def seconds(self) -> float:
        return len(self) / self.fps


class Representation(ABC):
    """Maps clips to per-frame feature vectors (T', D) and features back to joint positions.

    ``encode`` runs on numpy in data pipelines; ``decode`` is batched, differentiable torch,
    because training losses (velocity, foot contact) are computed on decoded positions.
    Per-clip quantities that do not change over time (bone offsets) travel beside the
    features in the sample's metadata and come back to ``decode`` as ``offsets``.
    """

    name: ClassVar[str]
    frames_dropped: ClassVar[int] = 0  # T' = T - frames_dropped (velocities need a next frame)
    stance_root: ClassVar[bool] = False  # whether ``root_from_stance`` is defined

    def __init__(self, skeleton: Skeleton | str):
        self.skeleton = get_skeleton(skeleton)

    @property
    @abstractmethod
    def dim(self) -> int:
        """Features per frame."""

    @abstractmethod
    def encode(self, clip: Clip) -> tuple[np.ndarray, dict]:
        """(T', D) float32 features and metadata to store beside them (JSON-serialisable)."""

    @abstractmethod
    def decode(self, features: torch.Tensor, offsets: torch.Tensor | None = None) -> torch.Tensor:
        """(..., T', D) features -> (..., T', J, 3) joint positions."""

    def mirror_map(self) -> tuple[np.ndarray, np.ndarray]:
        """(D,) source feature and (D,) sign of each feature of the mirror image: the features of
        a motion seen in a mirror across the body's sagittal plane (x -> -x, left <-> right) are a
        signed permutation of its own (``mirror``). Representations that cannot say raise."""
        raise UsageError(f"representation {self.name!r} does not define its mirror image (mirror_map)")

    def mirror(self, features, offsets=None):
        """(..., T', D) features (numpy or torch) and the clip's (J, 3) offsets (or None) -> those of
        the motion's mirror image, exactly: applying it twice gives the input back."""
        index, sign = self.mirror_map()
        if isinstance(features, torch.Tensor):
            sign = torch.as_tensor(sign, dtype=features.dtype, device=features.device)
        mirrored = features[..., index] * (sign if isinstance(features, torch.Tensor) else sign.astype(features.dtype))
        return mirrored, (None if offsets is None else self.skeleton.mirror(offsets))

    def channel_joints(self) -> np.ndarray:
        """(D,) the joint each feature belongs to (0: the root, whose features carry the trajectory): what
        body-part composition takes from each part's text (``omg.lit.timeline``). Representations that cannot
        say raise."""
        raise UsageError(f"representation {self.name!r} does not map its features to joints (channel_joints): "
                         "body-part composition needs that, as humanml3d263 has")

    def foot_contacts(self, features: torch.Tensor) -> torch.Tensor | None:
        """(..., T', F) contact labels in [0, 1] for ``skeleton.feet``, if the features carry them."""
        return None

    def contact_features(self) -> tuple[int, ...]:
        """The feature channels that are flags, not quantities (foot contacts): sampling's ``smoothing`` keeps
        them as they are (``omg.lit.control.smoothed``)."""
        return ()

    def integrated_features(self) -> tuple[int, ...]:
        """The feature channels whose running sum ``decode`` takes (a root velocity, a yaw rate): row t moves
        frame t to t + 1. Spatial control changes them by differences of a change per frame (``omg.lit.control``),
        so that a target at frame t asks a change of its own frame, not of every frame before it."""
        return ()

    def heading_features(self) -> tuple[int, ...]:
        """The channels that turn the whole body (a yaw rate): spatial control changes them only for a facing."""
        return ()

    def inpaint(self, features: torch.Tensor, targets: torch.Tensor, stated: torch.Tensor) -> torch.Tensor:
        """(..., T', D) features with the values that joint targets (..., T', J, 3) state outright written in
        where ``stated`` (..., T', J, 3) says a target gives that axis (spatial control's inpainting,
        ``omg.lit.control``); a representation whose features state no joint position returns them as they are."""
        return features

    def root_from_stance(self, features: torch.Tensor, strength: float = 1.0) -> torch.Tensor:
        """(..., T', D) features with the root's horizontal motion taken from the stance foot: where a
        foot is planted, the root steps so that the foot stays still (sampling's ``stance_root``).
        Representations without foot contacts and a root velocity raise."""
        raise UsageError(f"representation {self.name!r} cannot step its root by the stance foot (stance_root): "
                         "that needs foot contacts and a root velocity in the features, as humanml3d263 has")

    def finalize_stats(self, mean: np.ndarray, std: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Turn per-feature mean/std over a dataset into the normalisation to store.

        The default floors the std so that constant features do not blow up.
        """
        return mean.astype(np.float32), np.maximum(std, 1e-4).astype(np.float32)


def mirror_block(symmetry: Sequence[int], start: int, joints: Sequence[int], signs: Sequence[float]
                 ) -> tuple[list[int], list[float]]:
    """The mirror map of a block of per-joint values at ``start``, one slot of len(signs) values
    for each of ``joints`` in order: each slot reads its mirror joint's slot (``symmetry``) with
    ``signs`` (``rotations.REFLECT_X`` for vectors, ``rotations.SIXD_REFLECT_X`` for 6D rotations)."""
    width, slot = len(signs), {j: k for k, j in enumerate(joints)}
    index, sign = [], []
    for j in joints:
        source = start + slot[symmetry[j]] * width
        index.extend(range(source, source + width))
        sign.extend(signs)
    return index, sign


def check_mirrorable(rep: Representation) -> Sequence[int]:
    """The skeleton's symmetry, or a UsageError for a skeleton that has none."""
    if not rep.skeleton.symmetry:
        raise UsageError(f"skeleton {rep.skeleton.name!r} has no symmetry: {rep.name} features cannot be mirrored")
    return rep.skeleton.symmetry


def length_mask(lengths, frames: int | None = None, device: torch.device | str | None = None) -> torch.Tensor:
    """(B,) frame counts -> (B, frames) bool, True on each row's first lengths[b] frames;
    ``frames`` defaults to the longest."""
    lengths = torch.as_tensor(lengths, device=device)
    frames = int(lengths.max()) if frames is None else frames
    return torch.arange(frames, device=lengths.device)[None, :] < lengths[:, None]
